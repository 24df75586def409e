"""Users' own components: the :class:`BlockBuilder` that writes a :class:`~models.block.Block` in
a few lines, and the documentation rule every user block must satisfy.

A user block is exactly what the catalog's blocks are (:mod:`models.block`): parameters with SI
units, defaults, bounds and descriptions; inputs, outputs and states with units and
descriptions; flanges (effort/flow pairs); CasADi SX equations ``dx/dt = ode(x, u, p)``,
``y = out(x, u, p)``, ``x0 = start(p)``; ratings for the run-time guards; the embedded
integrator.  Direct feedthrough is derived from the equations, as for the catalog.

    from models.user import BlockBuilder

    def damper(integrator="rk4"):
        b = BlockBuilder("damper", "mass with viscous friction driven by a force")
        m = b.param("m", 1.0, "kg", "mass", lower=0.0)
        c = b.param("c", 0.5, "N.s/m", "viscous friction coefficient", lower=0.0)
        f = b.input("f", "N", "applied force")
        v = b.state("v", 0.0, "m/s", "velocity")
        b.der(v, (f - c * v) / m)
        b.output("v_out", v, "m/s", "velocity")
        return b.build(integrator=integrator)

:func:`require_documented` is the rule a user block meets before it is used: every parameter,
input, output and state has a unit (``"1"`` when dimensionless) and a description.  The
catalog's blocks meet it too (``tests/test_user_blocks.py`` checks that).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import casadi as ca

from .block import Block, BlockError, Flange, Param, Rating, Var
from .interface import suggest


def require_documented(block: Block, where: str = "", *, units: bool = True) -> None:
    """Raise :class:`BlockError` (one line, naming the block and the variable) when a parameter,
    input, output or state of ``block`` lacks a unit (unless ``units`` is False) or a description."""
    label = where or f"block {block.name}"
    for kind, seq in (("parameter", block.params), ("input", block.inputs), ("output", block.outputs),
                      ("state", block.states), ("mode", block.modes)):
        for v in seq:
            if units and not str(v.unit).strip():
                raise BlockError(f"{label}: {kind} {v.name!r} has no unit (give its SI unit, \"1\" when "
                                 f"dimensionless)")
            if not str(v.description).strip():
                raise BlockError(f"{label}: {kind} {v.name!r} has no description")
    if not block.description.strip():
        raise BlockError(f"{label}: the block has no description")


class BlockBuilder:
    """Collects a block's declarations and equations; :meth:`build` checks and returns the
    :class:`~models.block.Block`.  Every declaring method returns the CasADi symbol to write
    equations with."""

    def __init__(self, name: str, description: str, *, fidelity: str = "") -> None:
        self.name, self.description, self.fidelity = name, description, fidelity
        self._params: list[tuple[Param, ca.SX]] = []
        self._inputs: list[tuple[Var, ca.SX]] = []
        self._states: list[tuple[Var, ca.SX, object]] = []
        self._ders: dict[str, ca.SX] = {}
        self._outputs: list[tuple[Var, ca.SX]] = []
        self._flanges: list[Flange] = []
        self._ratings: dict[str, Rating] = {}
        self._modes: list[tuple[Var, ca.SX, object]] = []
        self._events: list[tuple[str, ca.SX, int, dict]] = []
        self._samples: list[tuple[str, float, float, dict]] = []
        self._t: ca.SX | None = None

    # declarations ----------------------------------------------------------------------------
    def param(self, name: str, default: float, unit: str, description: str, *, lower: float = -math.inf,
              upper: float = math.inf) -> ca.SX:
        """A tunable real parameter (its value is the FMU's start value, settable in a scene)."""
        sym = ca.SX.sym(name)
        self._params.append((Param(name, float(default), unit, lower, upper, description), sym))
        return sym

    def input(self, name: str, unit: str, description: str) -> ca.SX:
        """A real input, held constant over a communication step."""
        sym = ca.SX.sym(name)
        self._inputs.append((Var(name, unit, description), sym))
        return sym

    def state(self, name: str, start, unit: str, description: str) -> ca.SX:
        """A continuous state; ``start`` is a number or an expression of parameters.  Give its
        derivative with :meth:`der`."""
        sym = ca.SX.sym(name)
        self._states.append((Var(name, unit, description), sym, start))
        return sym

    def der(self, state: ca.SX, rhs) -> None:
        """``d state / dt = rhs`` (an expression of states, inputs and parameters)."""
        name = state.name() if isinstance(state, ca.SX) and state.is_symbolic() else str(state)
        if name not in {v.name for v, _, _ in self._states}:
            raise BlockError(f"block {self.name}: der() of {name!r}, which is not a declared state")
        if name in self._ders:
            raise BlockError(f"block {self.name}: the derivative of state {name!r} is given twice")
        self._ders[name] = ca.SX(rhs)

    def output(self, name: str, expr, unit: str, description: str, *, local: bool = False) -> None:
        """An output ``name = expr`` (an expression of states, inputs and parameters); ``local``:
        an internal variable, exported as an FMI local (recordable, not connectable)."""
        self._outputs.append((Var(name, unit, description, local), ca.SX(expr)))

    def flange(self, name: str, effort: str, flow: str, causality: str, why: str = "") -> None:
        """A power port made of an input and an output of this block: ``effort`` (force [N] or
        torque [N.m]) and ``flow`` (velocity [m/s] or angular velocity [rad/s]); ``causality``
        ``"effort_out"`` (flow in, effort out) or ``"flow_out"`` (effort in, flow out); ``why``:
        why the block cannot take the other causality (one line), if it cannot."""
        if causality not in ("effort_out", "flow_out"):
            raise BlockError(f"block {self.name}: flange {name!r} causality {causality!r}; expected effort_out "
                             f"or flow_out")
        self._flanges.append(Flange(name, effort, flow, causality, why))  # type: ignore[arg-type]

    def rating(self, variable: str, low: float, high: float, kind: str = "rated", source: str = "") -> None:
        """Operating limits of an input or output, enforced by the run-time guards."""
        self._ratings[variable] = Rating(float(low), float(high), kind, source)  # type: ignore[arg-type]

    # events (docs/explanation/events.md) ----------------------------------------------------------
    def mode(self, name: str, start, unit: str, description: str) -> ca.SX:
        """A discrete state (a mode: constant between events, changed by :meth:`when` and
        :meth:`sample`); ``start`` is a number or an expression of parameters."""
        sym = ca.SX.sym(name)
        self._modes.append((Var(name, unit, description), sym, start))
        return sym

    def time(self) -> ca.SX:
        """The symbol of time [s], for indicators and resets (equations stay autonomous)."""
        if self._t is None:
            self._t = ca.SX.sym("t")
        return self._t

    def when(self, indicator, reset: Mapping, *, direction: int = 0, name: str = "") -> None:
        """An event where ``indicator`` crosses zero (``direction`` +1 rising, -1 falling, 0
        either), applying ``reset`` (state or mode symbol -> new value, from the values just
        before; the others keep theirs): Modelica's ``when z < 0 then reinit(v, -e*pre(v))``
        is ``when(z, {v: -e * v}, direction=-1)``."""
        self._events.append((name or f"event{len(self._events)}", ca.SX(indicator), int(direction), dict(reset)))

    def sample(self, period: float, reset: Mapping, *, offset: float = 0.0, name: str = "") -> None:
        """A time event at ``offset + k period`` [s] applying ``reset`` (as :meth:`when`)."""
        self._samples.append((name or f"sample{len(self._samples)}", float(period), float(offset), dict(reset)))

    def _event_kw(self, x: ca.SX) -> dict:
        from .block import Sample

        if not (self._modes or self._events or self._samples):
            return {}
        syms = [x[i] for i in range(x.numel())] + [s for _, s, _ in self._modes]
        names = {s.name() for s in syms}

        def update(reset: Mapping, label: str) -> ca.SX:
            new = {}
            for k, v in reset.items():
                key = k.name() if isinstance(k, ca.SX) and k.is_symbolic() else str(k)
                if key not in names:
                    raise BlockError(f"block {self.name}: {label} resets {key!r}, which is not a state or mode")
                new[key] = ca.SX(v)
            return ca.vertcat(*[new.get(s.name(), s) for s in syms])

        return dict(modes=[v for v, _, _ in self._modes], m=_column([s for _, s, _ in self._modes]),
                    mode_start=_column([ca.SX(s) for _, _, s in self._modes]), t=self._t,
                    indicators=_column([z for _, z, _, _ in self._events]),
                    directions=[d for _, _, d, _ in self._events], event_names=[n for n, _, _, _ in self._events],
                    updates=[update(r, f"event {n!r}") for n, _, _, r in self._events],
                    sample_times=[Sample(T, off, update(r, f"sample {n!r}"), n) for n, T, off, r in self._samples])

    # the block -------------------------------------------------------------------------------
    def build(self, *, integrator: str = "rk4", substeps: int = 1, sample_period: float | None = None,
              units_required: bool = True, events: dict | None = None) -> Block:
        """The checked block (:meth:`models.block.Block.build` and :func:`require_documented`;
        ``units_required=False`` lets a variable's unit be empty, i.e. unknown, as a Modelica
        model may leave it; ``events``: the block's event fields, ``modes``, ``m``,
        ``mode_start``, ``t``, ``indicators``, ``directions``, ``updates``, ``event_names``,
        ``sample_times``, as :class:`~models.block.Block` has them)."""
        missing = [v.name for v, _, _ in self._states if v.name not in self._ders]
        if missing:
            raise BlockError(f"block {self.name}: state {missing[0]!r} has no derivative (call der())")
        if integrator == "radau" and self._states:
            from .integrators import RADAU_ATOL, RADAU_RTOL, SOLVER_ATOL, SOLVER_RTOL
            if SOLVER_RTOL not in {p.name for p, _ in self._params}:
                self.param(SOLVER_RTOL, RADAU_RTOL, "1", "relative tolerance of the Radau Newton iteration",
                           lower=1e-15, upper=1e-2)
                self.param(SOLVER_ATOL, RADAU_ATOL, "1", "absolute tolerance of the Radau Newton iteration",
                           lower=1e-20, upper=1.0)
        col = _column
        x = col([s for _, s, _ in self._states])
        blk = Block.build(
            self.name, description=self.description, params=[p for p, _ in self._params],
            inputs=[v for v, _ in self._inputs], outputs=[v for v, _ in self._outputs],
            states=[v for v, _, _ in self._states], p=col([s for _, s in self._params]),
            u=col([s for _, s in self._inputs]), x=col([s for _, s, _ in self._states]),
            ode=col([self._ders[v.name] for v, _, _ in self._states]), out=col([e for _, e in self._outputs]),
            start=col([ca.SX(s) for _, _, s in self._states]),
            integrator=integrator if self._states else ("none" if integrator != "discrete" else integrator),
            substeps=substeps, sample_period=sample_period, flanges=list(self._flanges), fidelity=self.fidelity,
            ratings=dict(self._ratings), **(events if events is not None else self._event_kw(x)))
        require_documented(blk, units=units_required)
        return blk


def with_defaults(blk: Block, where: str, overrides: Mapping[str, object], options: list[str]) -> Block:
    """``blk`` with parameter defaults (the FMU's start values) replaced by ``overrides``
    (names checked against the parameters, values against the bounds); ``options`` are the
    construction options' names, for the message about an unknown name."""
    index = {p.name: i for i, p in enumerate(blk.params)}
    params = list(blk.params)
    for name, value in overrides.items():
        if name not in index:
            valid = list(options) + list(index)
            raise BlockError(f"{where}: unknown option or parameter {name!r}{suggest(name, valid)} "
                             f"(options: {', '.join(options) or 'none'}; parameters: {', '.join(index)})")
        prm = params[index[name]]
        try:
            v = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise BlockError(f"{where}: parameter {name}={value!r} must be a number [{prm.unit or '1'}]") from None
        if isinstance(value, bool) or not math.isfinite(v) or not (prm.lower <= v <= prm.upper):
            raise BlockError(f"{where}: parameter {name}={value!r} is outside [{prm.lower}, {prm.upper}] "
                             f"[{prm.unit or '1'}]")
        params[index[name]] = dataclasses.replace(prm, default=v)
    blk = dataclasses.replace(blk, params=params)
    blk.check()
    return blk


def _column(items: list) -> ca.SX:
    return ca.vertcat(*items) if items else ca.SX(0, 1)


def check_factory_result(obj, where: str) -> Block:
    """``obj`` (what a user's factory returned) as a documented :class:`Block`, else
    :class:`BlockError` naming ``where``."""
    if not isinstance(obj, Block):
        raise BlockError(f"{where}: the factory returned {type(obj).__name__}, not a models.block.Block "
                         f"(build it with models.user.BlockBuilder or models.block.Block.build)")
    obj.check()
    require_documented(obj, where)
    return obj


def blocks_of(module_blocks: Mapping, where: str) -> dict[str, dict[str, object]]:
    """A user module's ``BLOCKS`` table normalised to ``model -> fidelity -> factory``:
    ``BLOCKS = {"gear": factory}`` (one fidelity, ``"default"``) or
    ``{"gear": {"stiff": f1, "rigid": f2}}`` (the first is the default)."""
    if not isinstance(module_blocks, Mapping):
        raise BlockError(f"{where}: BLOCKS must be a mapping model name -> factory (or fidelity -> factory)")
    out: dict[str, dict[str, object]] = {}
    for model, entry in module_blocks.items():
        fids = dict(entry) if isinstance(entry, Mapping) else {"default": entry}
        if not fids:
            raise BlockError(f"{where}: model {model!r} has no fidelity")
        for fid, factory in fids.items():
            if not callable(factory):
                raise BlockError(f"{where}: {model}/{fid} is {type(factory).__name__}, not a callable factory")
        out[str(model)] = {str(k): v for k, v in fids.items()}
    return out


__all__ = ["BlockBuilder", "require_documented", "check_factory_result", "blocks_of", "with_defaults"]
