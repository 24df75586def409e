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
    ``signals[(block, name)]`` is every input and output of every block as an expression of ``x``.
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

    def signal_function(self, names: Sequence[tuple[str, str]]) -> ca.Function:
        """``x -> [signals...]`` (``(x, z) -> ...`` with an algebraic loop) for the given
        ``(block, name)`` pairs."""
        args = [self.x, self.z] if self.z.numel() else [self.x]
        return ca.Function("signals", args, [ca.vertcat(*[self.signals[n] for n in names])])


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
    fns = {n: b.functions() for n, b in blocks.items()}
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
            outs[n] = fns[n]["out"](xs[n], input_vector(n, False), params[n])
            pending.remove(n)
    signals: dict[tuple[str, str], ca.SX] = {}
    odes, x0, slices, k = [], [], {}, 0
    for n, b in blocks.items():
        u = input_vector(n, True)
        y = fns[n]["out"](xs[n], u, params[n])
        signals.update({(n, v.name): u[j] for j, v in enumerate(b.inputs)})
        signals.update({(n, v.name): y[j] for j, v in enumerate(b.outputs)})
        nx = b.x.numel()
        slices[n] = slice(k, k + nx)
        k += nx
        if nx:
            odes.append(fns[n]["ode"](xs[n], u, params[n]))
            s0 = fns[n]["start"](params[n])
            s0 = s0 if isinstance(s0, ca.SX) else np.array(s0).ravel()  # symbolic parameters: a symbolic start
            for state, value in starts.get(n, {}).items():
                s0[b.index("states", state)] = value
            x0.append(s0)
    X = ca.vertcat(*xs.values())
    keys = tuple(cut)
    z = ca.vertcat(*[cut[k] for k in keys]) if keys else ca.SX(0, 1)
    alg = ca.vertcat(*[cut[k] - signals[feeds[k]] for k in keys]) if keys else ca.SX(0, 1)
    z0 = np.array([float(inputs.get(b, {}).get(i, 0.0)) for b, i in keys])
    symbolic = any(isinstance(s, ca.SX) for s in x0)
    start = (ca.vertcat(*x0) if symbolic else np.concatenate(x0)) if x0 else np.zeros(0)
    return Composite(X, ca.vertcat(*odes) if odes else ca.SX(0, 1), start, signals, slices, z, alg, z0, keys)


def _direct_inputs(block: Block) -> set[str]:
    """Inputs that some output of ``block`` depends on directly."""
    return {i for deps in block.feedthrough().values() for i in deps}


def _available(source: tuple[str, str] | None, outs: Mapping[str, ca.SX]) -> bool:
    """An input is available when no wire feeds it (constant) or its source block is evaluated."""
    return source is None or source[0] in outs


__all__ = ["Composite", "Wire", "compose"]
