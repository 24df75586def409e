"""The component contract: a small declarative block built from CasADi expressions.

A :class:`Block` declares parameters (unit, default, bounds), inputs, outputs and states, and
gives the maths as CasADi SX expressions of the symbols it owns:

- ``ode``: ``dx/dt = f(x, u, p)`` for a continuous block, or the update ``x[k+1] = f(x[k], u, p)``
  applied every ``sample_period`` seconds for a discrete block;
- ``out``: ``y = h(x, u, p)``;
- ``start``: state start values ``x0 = s(p)`` (may depend on parameters).

A block may also have *events* (docs/explanation/events.md): discrete states ``m`` (``modes``,
start values ``mode_start(p)``) that ``ode`` and ``out`` may read, event ``indicators``
``z(t, x, u, p, m)`` whose sign change in the declared ``directions`` fires the matching entry
of ``updates`` (the new ``(x, m)`` from the left limits), and time events (``sample_times``: a
:class:`Sample` fires its update at ``offset + k period``).  ``t`` is the symbol of time that
indicators and updates may use (``ode``/``out`` stay autonomous).

Inputs are held constant over a communication step (zero-order hold).  Direct feedthrough is
derived from the Jacobian sparsity of ``out`` with respect to ``u``.  Flanges name an
effort/flow pair of variables that form a power bond with another block's flange.

``models/`` is maths only: a block knows nothing of files or FMI; :mod:`fmus` turns it into one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import casadi as ca
import numpy as np

from .interface import BlockError, Flange, Param, Rating, Var  # noqa: F401  (re-exported: the contract's parts)

Integrator = Literal["rk4", "radau", "exact", "discrete", "none"]
#: Event directions: an indicator fires rising (``z`` from ``< 0`` to ``>= 0``), falling (from
#: ``> 0`` to ``<= 0``) or either.
RISING, FALLING, EITHER = 1, -1, 0
#: Integrators that can locate a crossing (they have a dense output in the FMU's core).
EVENT_INTEGRATORS = ("rk4", "radau", "exact", "none")


@dataclass
class Sample:
    """A time event: fires at ``offset + k period`` [s] (``k = 0, 1, ...``) and applies ``update``,
    an SX column of the new ``(x, m)`` (``nx + nm`` rows) in ``t, x, u, p, m`` (None: the
    identity, e.g. a pure sample instant)."""

    period: float
    offset: float = 0.0
    update: ca.SX | None = None
    name: str = ""

    def next_after(self, t: float, tol: float = 0.0) -> float:
        """The first instant of this sample at or after ``t - tol`` [s]."""
        k = max(0, math.ceil((t - tol - self.offset) / self.period))
        return self.offset + k * self.period


def _column(expr, label: str = "") -> ca.SX:
    if expr is None:
        return ca.SX(0, 1)
    if isinstance(expr, (list, tuple)):
        return ca.vertcat(*[ca.SX(e) if not isinstance(e, ca.SX) else e for e in expr]) if expr else ca.SX(0, 1)
    return expr if isinstance(expr, ca.SX) else ca.SX(expr)


@dataclass
class Block:
    """A component: symbols, equations and metadata.  Build with :meth:`Block.build`."""

    name: str
    description: str
    params: list[Param]
    inputs: list[Var]
    outputs: list[Var]
    states: list[Var]
    p: ca.SX
    u: ca.SX
    x: ca.SX
    ode: ca.SX
    out: ca.SX
    start: ca.SX
    integrator: Integrator = "rk4"
    substeps: int = 1
    sample_period: float | None = None
    flanges: list[Flange] = field(default_factory=list)
    fidelity: str = ""
    ratings: dict[str, Rating] = field(default_factory=dict)
    # -- events (all empty for a continuous block) ----------------------------------------------
    modes: list[Var] = field(default_factory=list)
    m: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    mode_start: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    t: ca.SX | None = None
    indicators: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    directions: list[int] = field(default_factory=list)
    updates: list[ca.SX | None] = field(default_factory=list)
    event_names: list[str] = field(default_factory=list)
    sample_times: list[Sample] = field(default_factory=list)

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def build(cls, name: str, *, description: str = "", params: list[Param], inputs: list[Var],
              outputs: list[Var], states: list[Var], p: ca.SX, u: ca.SX, x: ca.SX, ode, out, start,
              **kw) -> "Block":
        """Check shapes and names, then return the block.  Raises :class:`BlockError`."""
        blk = cls(name=name, description=description, params=list(params), inputs=list(inputs),
                  outputs=list(outputs), states=list(states), p=p, u=u, x=x,
                  ode=ca.SX(ode) if not isinstance(ode, ca.SX) else ode,
                  out=ca.SX(out) if not isinstance(out, ca.SX) else out,
                  start=ca.SX(start) if not isinstance(start, ca.SX) else start, **kw)
        blk.m, blk.mode_start, blk.indicators = _column(blk.m), _column(blk.mode_start), _column(blk.indicators)
        blk.modes, blk.directions, blk.sample_times = list(blk.modes), list(blk.directions), list(blk.sample_times)
        nz = blk.indicators.numel()
        if not blk.directions and nz:
            blk.directions = [EITHER] * nz
        if not blk.updates and nz:
            blk.updates = [None] * nz
        blk.updates = [None if g is None else _column(g) for g in blk.updates]
        for smp in blk.sample_times:
            if smp.update is not None:
                smp.update = _column(smp.update)
        if not blk.event_names:
            blk.event_names = [f"z[{i}]" for i in range(nz)]
        blk.check()
        return blk

    def check(self) -> None:
        """Validate the declaration before any code is generated."""
        n = self.name
        for what, sym, decl in (("parameter", self.p, self.params), ("input", self.u, self.inputs),
                                ("state", self.x, self.states)):
            if not sym.is_column() or sym.numel() != len(decl):
                raise BlockError(f"block {n}: {len(decl)} {what}s declared but the {what} symbol has shape "
                                 f"{sym.shape}")
            if sym.numel() and not sym.is_valid_input():
                raise BlockError(f"block {n}: the {what} vector must be made of pure symbols")
        names = [v.name for v in self.params + self.inputs + self.outputs + self.states]
        dup = sorted({v for v in names if names.count(v) > 1})
        if dup:
            raise BlockError(f"block {n}: variable {dup[0]!r} is declared more than once")
        for label, expr, rows in (("ode", self.ode, len(self.states)), ("out", self.out, len(self.outputs)),
                                  ("start", self.start, len(self.states))):
            if expr.shape != (rows, 1) and not (rows == 0 and expr.numel() == 0):
                var = (self.states if label != "out" else self.outputs)
                hint = f" (variables: {', '.join(v.name for v in var)})" if var else ""
                raise BlockError(f"block {n}: {label} has shape {expr.shape}, expected ({rows}, 1){hint}")
        allowed = {"ode": [self.x, self.u, self.p, self.m], "out": [self.x, self.u, self.p, self.m],
                   "start": [self.p]}
        for label, expr in (("ode", self.ode), ("out", self.out), ("start", self.start)):
            free = ca.symvar(expr)
            known = {s.name() for sym in allowed[label] for s in ca.symvar(sym)}
            stray = [s.name() for s in free if s.name() not in known]
            if stray:
                what = "parameter" if label == "start" else "state, input, parameter or mode"
                hint = " (time appears in indicators and updates only: blocks are autonomous)" \
                    if self.t is not None and stray[0] == self.t.name() else ""
                raise BlockError(f"block {n}: {label} uses symbol {stray[0]!r}, which is not a declared {what}{hint}")
        for prm in self.params:
            if not (prm.lower <= prm.default <= prm.upper):
                raise BlockError(f"block {n}: parameter {prm.name!r} default {prm.default} is outside "
                                 f"[{prm.lower}, {prm.upper}]")
            if not math.isfinite(prm.default):
                raise BlockError(f"block {n}: parameter {prm.name!r} needs a finite default (start) value")
        if self.integrator not in ("rk4", "radau", "exact", "discrete", "none"):
            raise BlockError(f"block {n}: unknown integrator {self.integrator!r}")
        if self.integrator == "discrete" and not (self.sample_period and self.sample_period > 0):
            raise BlockError(f"block {n}: a discrete block needs a positive sample_period")
        if self.substeps < 1:
            raise BlockError(f"block {n}: substeps must be >= 1, got {self.substeps}")
        vars_ = {v.name for v in self.inputs + self.outputs}
        for var, r in self.ratings.items():
            if var not in vars_:
                raise BlockError(f"block {n}: rating for {var!r}, which is not an input or output")
            if not (r.low < r.high):
                raise BlockError(f"block {n}: rating of {var!r} needs low < high, got [{r.low}, {r.high}]")
        for fl in self.flanges:
            for v in (fl.effort, fl.flow):
                if v not in vars_:
                    raise BlockError(f"block {n}: flange {fl.name!r} names {v!r}, which is not an input or output")
        self._check_events()

    def _check_events(self) -> None:
        """The event declaration: modes, indicators with directions and updates, samples."""
        n = self.name
        if not self.has_events:
            return
        if not self.m.is_column() or self.m.numel() != len(self.modes):
            raise BlockError(f"block {n}: {len(self.modes)} modes declared but the mode symbol has shape {self.m.shape}")
        if self.m.numel() and not self.m.is_valid_input():
            raise BlockError(f"block {n}: the mode vector must be made of pure symbols")
        if self.t is not None and not (self.t.numel() == 1 and self.t.is_valid_input()):
            raise BlockError(f"block {n}: the time symbol t must be one pure scalar symbol")
        names = [v.name for v in self.params + self.inputs + self.outputs + self.states + self.modes]
        dup = sorted({v for v in names if names.count(v) > 1})
        if dup:
            raise BlockError(f"block {n}: variable {dup[0]!r} is declared more than once (modes included)")
        if self.mode_start.shape != (len(self.modes), 1) and not (not self.modes and self.mode_start.numel() == 0):
            raise BlockError(f"block {n}: mode_start has shape {self.mode_start.shape}, expected ({len(self.modes)}, 1)")
        nz = self.indicators.numel()
        if not self.indicators.is_column() and nz:
            raise BlockError(f"block {n}: indicators must be a column, got shape {self.indicators.shape}")
        for what, seq in (("directions", self.directions), ("updates", self.updates), ("event_names", self.event_names)):
            if len(seq) != nz:
                raise BlockError(f"block {n}: {len(seq)} {what} for {nz} indicators (one each)")
        for i, d in enumerate(self.directions):
            if d not in (RISING, FALLING, EITHER):
                raise BlockError(f"block {n}: direction of indicator {self.event_names[i]!r} is {d!r}; expected "
                                 f"1 (rising), -1 (falling) or 0 (either)")
        if self.integrator not in EVENT_INTEGRATORS:
            raise BlockError(f"block {n}: events need one of the integrators {', '.join(EVENT_INTEGRATORS)} "
                             f"(a dense output to locate crossings); got {self.integrator!r}")
        known = {s.name() for sym in (self.x, self.u, self.p, self.m) for s in ca.symvar(sym)}
        if self.t is not None:
            known.add(self.t.name())
        rows = self.x.numel() + self.m.numel()
        exprs = [("mode_start", self.mode_start, {s.name() for s in ca.symvar(self.p)})]
        exprs.append(("indicators", self.indicators, known))
        for i, g in enumerate(self.updates):
            if g is not None:
                exprs.append((f"update of {self.event_names[i]!r}", g, known))
        for j, smp in enumerate(self.sample_times):
            label = f"sample {smp.name or j}"
            if not (math.isfinite(smp.period) and smp.period > 0 and math.isfinite(smp.offset) and smp.offset >= 0):
                raise BlockError(f"block {n}: {label} needs a finite period > 0 and offset >= 0, got "
                                 f"period {smp.period}, offset {smp.offset}")
            if smp.update is not None:
                exprs.append((f"update of {label}", smp.update, known))
        for label, expr, allowed in exprs:
            if label.startswith("update") and expr.shape != (rows, 1):
                raise BlockError(f"block {n}: {label} has shape {expr.shape}, expected ({rows}, 1): the new "
                                 f"states then the new modes")
            stray = [s.name() for s in ca.symvar(expr) if s.name() not in allowed]
            if stray:
                raise BlockError(f"block {n}: {label} uses symbol {stray[0]!r}, which is not a declared "
                                 f"{'parameter' if label == 'mode_start' else 'time, state, input, parameter or mode'}")

    # -- events -------------------------------------------------------------------------------
    @property
    def has_events(self) -> bool:
        """Whether the block declares modes, indicators or time events."""
        return bool(self.modes or self.indicators.numel() or self.sample_times)

    @property
    def time_symbol(self) -> ca.SX:
        """The block's symbol of time (a fresh one when it declares none)."""
        if self.t is None:
            self.__dict__["t"] = ca.SX.sym("t")
        return self.t

    def event_functions(self) -> dict[str, ca.Function]:
        """CasADi functions of the events: ``indicators(t, x, u, p, m) -> z``,
        ``update(k, t, x, u, p, m) -> (x_new, m_new)`` (``k``: the indicator's index, then
        ``nz + j`` for sample ``j``; the identity for an update given as None) and
        ``mode_start(p) -> m0``."""
        t = self.time_symbol
        args, names = [t, self.x, self.u, self.p, self.m], ["t", "x", "u", "p", "m"]
        nx = self.x.numel()
        ident = ca.vertcat(self.x, self.m)
        cases = []
        for k, g in enumerate(list(self.updates) + [s.update for s in self.sample_times]):
            g = ident if g is None else g
            cases.append(ca.Function(f"{self.name}_update{k}", args, [g[:nx, :], g[nx:, :]], names, ["x_new", "m_new"]))
        keep = ca.Function(f"{self.name}_update_none", args, [self.x, self.m], names, ["x_new", "m_new"])
        return {
            "indicators": ca.Function(f"{self.name}_indicators", args, [self.indicators], names, ["z"]),
            "update": ca.Function.conditional(f"{self.name}_update", cases, keep),
            "mode_start": ca.Function(f"{self.name}_mode_start", [self.p], [self.mode_start], ["p"], ["m0"]),
        }

    def continuous_view(self) -> "Block":
        """The same block between events: modes become trailing parameters (``p' = [p; m]``,
        defaults from ``mode_start`` at the parameter defaults) and there are no events; one
        substep (the FMU's core takes the substeps itself, so that it can stop inside one)."""
        if not self.has_events:
            return self
        m0 = np.asarray(ca.Function("m0", [self.p], [self.mode_start])(self.param_defaults), dtype=float).reshape(-1)
        extra = [Param(v.name, float(m0[i]), v.unit, description=v.description or "mode")
                 for i, v in enumerate(self.modes)]
        return Block(name=self.name, description=self.description, params=self.params + extra,
                     inputs=self.inputs, outputs=self.outputs, states=self.states, p=ca.vertcat(self.p, self.m),
                     u=self.u, x=self.x, ode=self.ode, out=self.out, start=self.start, integrator=self.integrator,
                     substeps=1, flanges=self.flanges, fidelity=self.fidelity, ratings=self.ratings)

    # -- derived structure --------------------------------------------------------------------
    @property
    def memoryless(self) -> bool:
        """No state, no sampling: every output is a function of the inputs and parameters now."""
        return not self.states and self.integrator == "none" and not self.sample_period and not self.has_events

    @property
    def param_defaults(self) -> np.ndarray:
        return np.array([p.default for p in self.params], dtype=float)

    def param_vector(self, **values: float) -> np.ndarray:
        """Parameter vector from defaults overridden by ``values`` (unknown names refused)."""
        vec = self.param_defaults.copy()
        index = {p.name: i for i, p in enumerate(self.params)}
        for k, v in values.items():
            if k not in index:
                raise BlockError(f"block {self.name}: unknown parameter {k!r}; expected one of "
                                 f"{', '.join(index)}")
            prm = self.params[index[k]]
            if not (prm.lower <= float(v) <= prm.upper):
                raise BlockError(f"block {self.name}: parameter {k!r} = {v} is outside [{prm.lower}, {prm.upper}]")
            vec[index[k]] = float(v)
        return vec

    def feedthrough(self) -> dict[str, list[str]]:
        """For each output, the inputs it depends on directly (from the Jacobian sparsity;
        remembered while ``out`` and ``u`` are the same expressions: a batch asks once per scene)."""
        memo = self.__dict__.get("_feedthrough")
        if memo is None or memo[0] is not self.out or memo[1] is not self.u:
            memo = (self.out, self.u, self._feedthrough())
            self.__dict__["_feedthrough"] = memo
        return {y: list(u) for y, u in memo[2].items()}

    def _feedthrough(self) -> dict[str, list[str]]:
        if self.u.numel() == 0:
            return {y.name: [] for y in self.outputs}
        sp = ca.jacobian_sparsity(self.out, self.u) if self.out.numel() else None
        res: dict[str, list[str]] = {}
        for i, y in enumerate(self.outputs):
            res[y.name] = [self.inputs[j].name for j in range(len(self.inputs)) if sp is not None and sp.has_nz(i, j)]
        return res

    def functions(self) -> dict[str, ca.Function]:
        """CasADi functions ``ode(x, u, p)``, ``out(x, u, p)``, ``start(p)``; for a block with
        modes, ``ode(x, u, p, m)`` and ``out(x, u, p, m)``."""
        if self.m.numel():
            args, names = [self.x, self.u, self.p, self.m], ["x", "u", "p", "m"]
            return {
                "ode": ca.Function(f"{self.name}_ode", args, [self.ode], names, ["xdot"]),
                "out": ca.Function(f"{self.name}_out", args, [self.out], names, ["y"]),
                "start": ca.Function(f"{self.name}_start", [self.p], [self.start], ["p"], ["x0"]),
            }
        return {
            "ode": ca.Function(f"{self.name}_ode", [self.x, self.u, self.p], [self.ode], ["x", "u", "p"], ["xdot"]),
            "out": ca.Function(f"{self.name}_out", [self.x, self.u, self.p], [self.out], ["x", "u", "p"], ["y"]),
            "start": ca.Function(f"{self.name}_start", [self.p], [self.start], ["p"], ["x0"]),
        }

    def index(self, kind: str, name: str) -> int:
        """Position of variable ``name`` among ``kind`` (``inputs``, ``outputs``, ``states``, ``params``)."""
        seq = getattr(self, kind)
        for i, v in enumerate(seq):
            if v.name == name:
                return i
        raise BlockError(f"block {self.name}: no {kind[:-1]} named {name!r}")
