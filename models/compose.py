"""Blocks wired together as one ODE: the monolithic counterpart of a co-simulation.

A co-simulation holds each input constant over a communication step; the composite here feeds
every input its source's output at every instant, so integrating it with a tight variable-step
solver gives the reference the master algorithms converge to as the step shrinks.  The blocks'
own ``ode``/``out``/``start`` functions are used unchanged: no equation is written twice.

Conventions: ``wires`` are ``(source block, output, destination block, input)``; an input that
no wire feeds keeps a constant value (``inputs`` or 0).  Outputs are evaluated in the order of
the blocks' declared direct feedthrough.  A wiring with an algebraic loop (a cycle of direct
feedthrough) is refused unless ``loops=True``: then the loop is cut at the inputs of one block
per cycle, each cut input becomes an algebraic variable ``z`` and the composite is the
semi-explicit index-1 DAE ``dx/dt = ode(x, z)``, ``0 = alg(x, z) = z - (source output)``, for a
DAE solver (IDAS) that keeps the loop consistent at every instant.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .block import Block, BlockError

Wire = tuple[str, str, str, str]


@dataclass
class Composite:
    """``dx/dt = ode(x)`` with ``x`` the blocks' states stacked in block order from ``x0``;
    ``signals[(block, name)]`` is every input, output, state and mode of every block as an expression of ``x``
    (and ``m``).
    With an algebraic loop (``compose(..., loops=True)``), ``z`` are the cut inputs (start guess
    ``z0``), ``0 = alg`` closes the loop, and ``ode`` and ``signals`` depend on ``z`` too."""

    x: ca.SX
    ode: ca.SX
    x0: np.ndarray
    signals: dict[tuple[str, str], ca.SX]
    slices: dict[str, slice]  # each block's states within x
    z: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    alg: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    z0: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cuts: tuple[tuple[str, str], ...] = ()  # (block, input) of each algebraic variable
    #: blocks with events: their modes stacked (``m``, start ``m0``) and every event of every block
    #: as an expression of ``(t, x, m)`` (:class:`CompositeEvent`); ``ode`` and ``signals`` then
    #: depend on ``m`` too
    m: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    m0: np.ndarray = field(default_factory=lambda: np.zeros(0))
    t: ca.SX = field(default_factory=lambda: ca.SX.sym("t"))
    events: list["CompositeEvent"] = field(default_factory=list)

    @property
    def has_events(self) -> bool:
        return bool(self.events) or self.m.numel() > 0

    def signal_function(self, names: Sequence[tuple[str, str]]) -> ca.Function:
        """``x -> [signals...]`` (``(x, z) -> ...`` with an algebraic loop, ``(x, m) -> ...`` with
        events, ``m`` empty where no block has modes) for the given ``(block, name)`` pairs."""
        args = [self.x, self.z] if self.z.numel() else [self.x]
        if self.has_events:
            args.append(self.m)
        return ca.Function("signals", args, [ca.vertcat(*[self.signals[n] for n in names])])


@dataclass
class CompositeEvent:
    """One event of one block in the composite: an indicator (``indicator`` with ``direction``)
    or a sample (``period``, ``offset``), and its update of the whole ``(x, m)``; all expressions
    of the composite's ``(t, x, m)``."""

    name: str  # "<block>.<event>"
    block: str
    indicator: ca.SX | None
    direction: int
    new_x: ca.SX
    new_m: ca.SX
    period: float | None = None
    offset: float = 0.0


def compose(blocks: Mapping[str, Block], params: Mapping[str, np.ndarray | ca.SX], wires: Sequence[Wire], *,
            starts: Mapping[str, Mapping[str, float]] | None = None,
            inputs: Mapping[str, Mapping[str, float]] | None = None, loops: bool = False) -> Composite:
    """One ODE from ``blocks`` with numeric parameter vectors ``params`` (a DAE when ``loops``
    allows an algebraic loop and the wiring has one: module docstring).  A parameter vector may be
    CasADi SX (some entries symbols, e.g. the parameters a fit estimates): ``ode`` and ``signals``
    then depend on those symbols, and ``x0`` is SX as well.

    ``starts[block][state]`` overrides a state's start value; ``inputs[block][input]`` is the
    constant value of an input no wire feeds.  Raises :class:`BlockError` for a sampled
    (``discrete``) block, an unknown variable in a wire, or an algebraic loop (without ``loops``)."""
    starts, inputs = starts or {}, inputs or {}
    for name, b in blocks.items():
        if b.integrator == "discrete":
            raise BlockError(f"block {name} ({b.name}) is sampled (discrete); a monolithic ODE needs "
                             f"continuous blocks (use its continuous fidelity)")
    feeds: dict[tuple[str, str], tuple[str, str]] = {}
    for src, out, dst, inp in wires:
        for blk, var, kind in ((src, out, "outputs"), (dst, inp, "inputs")):
            if blk not in blocks:
                raise BlockError(f"wire {src}.{out} -> {dst}.{inp}: no block {blk!r}")
            blocks[blk].index(kind, var)  # raises BlockError naming the variable
        feeds[(dst, inp)] = (src, out)

    xs = {n: ca.SX.sym(f"x_{n}", b.x.numel()) for n, b in blocks.items()}
    ms = {n: ca.SX.sym(f"m_{n}", b.m.numel()) for n, b in blocks.items()}
    fns = {n: b.functions() for n, b in blocks.items()}

    def call(n: str, what: str, u: ca.SX):
        args = (xs[n], u, params[n], ms[n]) if blocks[n].m.numel() else (xs[n], u, params[n])
        return fns[n][what](*args)
    outs: dict[str, ca.SX] = {}
    cut: dict[tuple[str, str], ca.SX] = {}  # (block, input) -> its algebraic variable

    def input_vector(n: str, ready: bool) -> ca.SX:
        """Inputs of ``n``; with ``ready`` False, inputs whose source is not evaluated yet are 0
        (allowed only where ``n``'s outputs do not depend on them directly)."""
        b, vals = blocks[n], []
        for v in b.inputs:
            src = feeds.get((n, v.name))
            if src is None:
                vals.append(ca.SX(float(inputs.get(n, {}).get(v.name, 0.0))))
            elif (n, v.name) in cut:
                vals.append(cut[(n, v.name)])
            elif src[0] in outs:
                vals.append(outs[src[0]][blocks[src[0]].index("outputs", src[1])])
            elif ready:
                raise AssertionError("unreachable: every block's outputs exist in the second pass")
            else:
                vals.append(ca.SX(0.0))
        return ca.vertcat(*vals) if vals else ca.SX(0, 1)

    pending = list(blocks)
    while pending:
        ready = [n for n in pending if all(_available(feeds.get((n, i)), outs) or (n, i) in cut
                                           for i in _direct_inputs(blocks[n]))]
        if not ready and not loops:
            raise BlockError(f"algebraic loop through blocks {', '.join(pending)}: their outputs depend "
                             f"directly on each other's")
        if not ready:  # cut the loop at the direct inputs of the first pending block
            n = pending[0]
            for i in sorted(_direct_inputs(blocks[n])):
                if not _available(feeds.get((n, i)), outs):
                    cut[(n, i)] = ca.SX.sym(f"z_{n}_{i}")
            ready = [n]
        for n in ready:
            outs[n] = call(n, "out", input_vector(n, False))
            pending.remove(n)
    signals: dict[tuple[str, str], ca.SX] = {}
    inputs_now: dict[str, ca.SX] = {}
    odes, x0, slices, k = [], [], {}, 0
    for n, b in blocks.items():
        u = input_vector(n, True)
        y = call(n, "out", u)
        inputs_now[n] = u
        signals.update({(n, v.name): u[j] for j, v in enumerate(b.inputs)})
        signals.update({(n, v.name): y[j] for j, v in enumerate(b.outputs)})
        signals.update({(n, v.name): xs[n][j] for j, v in enumerate(b.states)})  # recordable as in the FMU
        signals.update({(n, v.name): ms[n][j] for j, v in enumerate(b.modes)})
        nx = b.x.numel()
        slices[n] = slice(k, k + nx)
        k += nx
        if nx:
            odes.append(call(n, "ode", u))
            s0 = fns[n]["start"](params[n])
            s0 = s0 if isinstance(s0, ca.SX) else np.array(s0).ravel()  # symbolic parameters: a symbolic start
            for state, value in starts.get(n, {}).items():
                s0[b.index("states", state)] = value
            x0.append(s0)
    X = ca.vertcat(*xs.values())
    M = ca.vertcat(*ms.values())
    t = ca.SX.sym("t")
    events = _events(blocks, params, xs, ms, inputs_now, X, M, t)
    if (events or M.numel()) and cut:
        # a loop of blocks whose outputs do not feed each other through: substitute it away
        odes, signals, events = _unloop(cut, feeds, signals, odes, events)
        cut = {}
    m0 = np.concatenate([np.array(b.event_functions()["mode_start"](params[n])).ravel()
                         for n, b in blocks.items() if b.m.numel()]) if M.numel() else np.zeros(0)
    keys = tuple(cut)
    z = ca.vertcat(*[cut[k] for k in keys]) if keys else ca.SX(0, 1)
    alg = ca.vertcat(*[cut[k] - signals[feeds[k]] for k in keys]) if keys else ca.SX(0, 1)
    z0 = np.array([float(inputs.get(b, {}).get(i, 0.0)) for b, i in keys])
    symbolic = any(isinstance(s, ca.SX) for s in x0)
    start = (ca.vertcat(*x0) if symbolic else np.concatenate(x0)) if x0 else np.zeros(0)
    return Composite(X, ca.vertcat(*odes) if odes else ca.SX(0, 1), start, signals, slices, z, alg, z0, keys,
                     M, m0, t, events)


def _unloop(cut, feeds, signals, odes, events):
    """Replace the cut inputs by their sources' expressions where the loop is false (no output
    depends on itself through the cut: per output, not per block); a true algebraic loop with
    events is refused (the event reference integrates ODEs)."""
    keys = list(cut)
    z = ca.vertcat(*[cut[k] for k in keys])
    src = ca.vertcat(*[signals[feeds[k]] for k in keys])
    for _ in range(len(keys) + 1):
        if not ca.depends_on(src, z):
            break
        src = ca.substitute(src, z, src)
    else:
        raise BlockError(f"blocks with events in an algebraic loop through {', '.join(f'{b}.{i}' for b, i in keys)}: "
                         f"the monolithic reference with events needs an ODE")

    def sub(e):
        return ca.substitute(e, z, src)

    signals = {k: sub(v) for k, v in signals.items()}
    odes = [sub(o) for o in odes]
    for e in events:
        e.new_x, e.new_m = sub(e.new_x), sub(e.new_m)
        if e.indicator is not None:
            e.indicator = sub(e.indicator)
    return odes, signals, events


def _events(blocks, params, xs, ms, inputs_now, X, M, t) -> list[CompositeEvent]:
    """Every block's indicators and samples with their updates, on the composite's ``(t, X, M)``
    (each block's own event functions, its inputs as the composite's signals)."""
    out: list[CompositeEvent] = []
    for n, b in blocks.items():
        if not b.has_events:
            continue
        ef = b.event_functions()
        u, p = inputs_now[n], params[n]
        z = ef["indicators"](t, xs[n], u, p, ms[n])
        own = ca.vertcat(xs[n], ms[n])
        for k in range(b.indicators.numel() + len(b.sample_times)):
            xn, mn = ef["update"](k, t, xs[n], u, p, ms[n])
            new_x = ca.substitute(X, own, ca.vertcat(xn, mn))
            new_m = ca.substitute(M, own, ca.vertcat(xn, mn))
            if k < b.indicators.numel():
                out.append(CompositeEvent(f"{n}.{b.event_names[k]}", n, z[k], int(b.directions[k]), new_x, new_m))
            else:
                smp = b.sample_times[k - b.indicators.numel()]
                out.append(CompositeEvent(f"{n}.{smp.name or 'sample'}", n, None, 0, new_x, new_m, float(smp.period),
                                          float(smp.offset)))
    return out


def _direct_inputs(block: Block) -> set[str]:
    """Inputs that some output of ``block`` depends on directly."""
    return {i for deps in block.feedthrough().values() for i in deps}


def _available(source: tuple[str, str] | None, outs: Mapping[str, ca.SX]) -> bool:
    """An input is available when no wire feeds it (constant) or its source block is evaluated."""
    return source is None or source[0] in outs


__all__ = ["Composite", "Wire", "compose"]
