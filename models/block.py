"""The component contract: a small declarative block built from CasADi expressions.

A :class:`Block` declares parameters (unit, default, bounds), inputs, outputs and states, and
gives the maths as CasADi SX expressions of the symbols it owns:

- ``ode``: ``dx/dt = f(x, u, p)`` for a continuous block, or the update ``x[k+1] = f(x[k], u, p)``
  applied every ``sample_period`` seconds for a discrete block;
- ``out``: ``y = h(x, u, p)``;
- ``start``: state start values ``x0 = s(p)`` (may depend on parameters).

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
        allowed = {"ode": [self.x, self.u, self.p], "out": [self.x, self.u, self.p], "start": [self.p]}
        for label, expr in (("ode", self.ode), ("out", self.out), ("start", self.start)):
            free = ca.symvar(expr)
            known = {s.name() for sym in allowed[label] for s in ca.symvar(sym)}
            stray = [s.name() for s in free if s.name() not in known]
            if stray:
                raise BlockError(f"block {n}: {label} uses symbol {stray[0]!r}, which is not a declared "
                                 f"{'parameter' if label == 'start' else 'state, input or parameter'}")
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

    # -- derived structure --------------------------------------------------------------------
    @property
    def memoryless(self) -> bool:
        """No state, no sampling: every output is a function of the inputs and parameters now."""
        return not self.states and self.integrator == "none" and not self.sample_period

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
        """CasADi functions ``ode(x, u, p)``, ``out(x, u, p)``, ``start(p)``."""
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
