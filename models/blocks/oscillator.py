"""A linear mass-spring-damper, the building block of the two-mass coupling test of master
algorithms (the classic co-simulation benchmark: two oscillators joined by a spring, cut at the
spring).

Mass ``m`` on a spring ``k`` and a damper ``d`` to the ground, position ``x`` [m] from the
spring's rest point, velocity ``v`` [m/s]:

- option ``coupling="none"``: input ``f`` [N], an external force on the mass:
  ``m dv/dt = -k x - d v + f``;
- option ``coupling="spring"``: the mass also carries the coupling spring ``kc`` towards the
  other mass, and its position is kept relative to the other mass: state ``s = x - x_other`` [m]
  (the coupling spring's elongation) and ``v`` [m/s].  Inputs ``x_in`` and ``v_in``, the other
  mass's position and velocity: ``ds/dt = v - v_in``,
  ``m dv/dt = -k (x_in + s) - d v - kc s``.  Outputs ``f`` [N] ``= kc s``, the spring's pull on the
  other mass (positive along +x), ``v`` and ``s``.  (Keeping ``s`` rather than ``x`` as the state
  avoids a redundant state: with both, ``s - (x - x_other)`` would be a conserved, neutral mode.)

Option ``stop="impact"`` (coupling ``none`` only) puts the mass between end stops at ``x_min``
and ``x_max`` [m]: impacts located inside the FMU's step with Newton's restitution ``e``
(``v+ = -e v-``), rest on a stop once the rebound is below ``v_rest`` [m/s], release when the
force pushing into it falls to zero (:mod:`._stops`); outputs ``impacts`` and ``v_impact``.

Neither variant has direct feedthrough (``f`` is a state output), so two of them close a loop
without an algebraic loop, and every output at a communication point depends only on states.
Both are linear time-invariant, so a master algorithm's macro step is a linear map whose spectral
radius decides stability (:mod:`models.coupling`).  The embedded integrator is RK4 with
``substeps`` (default 40): the slaves' own error stays far below the coupling error studied.
"""
from __future__ import annotations

import casadi as ca

from ..block import Block, BlockError, Var
from ._common import ParamSet
from ._stops import StopEvents, end_stops

COUPLING = ("none", "spring")
STOPS = ("none", "impact")


def oscillator(coupling: str = "none", integrator: str = "rk4", substeps: int = 40, stop: str = "none") -> Block:
    """The mass-spring-damper (module docstring); ``coupling`` picks the interface."""
    ps = ParamSet()
    m = ps.add("m", 1.0, "kg", "mass", lower=1e-12)
    k = ps.add("k", 1.0, "N/m", "spring to the ground", lower=0.0)
    d = ps.add("d", 0.1, "N.s/m", "damper to the ground", lower=0.0)
    x0 = ps.add("x0", 0.0, "m", "start position (coupling 'spring': start elongation x - x_other)")
    v0 = ps.add("v0", 0.0, "m/s", "start velocity")
    x, v = ca.SX.sym("x"), ca.SX.sym("v")
    states = [Var("state.x", "m", "position"), Var("state.v", "m/s", "velocity")]
    outputs = [Var("x", "m", "position"), Var("v", "m/s", "velocity")]
    events: dict = {}
    if stop != "none" and coupling != "none":
        raise BlockError(f"oscillator: option stop={stop!r} needs coupling 'none' (a force input)")
    if coupling == "none":
        f = ca.SX.sym("f")
        inputs = [Var("f", "N", "external force on the mass")]
        xs, u = ca.vertcat(x, v), f
        ode = ca.vertcat(v, (-k * x - d * v + f) / m)
        out = ca.vertcat(x, v)
        start = ca.vertcat(x0, v0)
        if stop == "impact":
            lo = ps.add("x_min", -1.0, "m", "lower end stop")
            hi = ps.add("x_max", 1.0, "m", "upper end stop")
            e = ps.add("e", 0.5, "1", "coefficient of restitution of the stops", lower=0.0, upper=1.0)
            v_rest = ps.add("v_rest", 1e-6, "m/s", "rebound speed below which the mass comes to rest on a stop",
                            lower=0.0)
            ev = StopEvents()
            dx, dv, modes = end_stops(ev, "", x, v, ode[1], lo, hi, e, v_rest)
            ode = ca.vertcat(dx, dv)
            out = ca.vertcat(out, modes["impacts"], modes["v_impact"])
            outputs = outputs + [Var("impacts", "1", "impacts on the stops so far"),
                                 Var("v_impact", "m/s", "velocity of the last impact")]
            events = ev.block_kw(xs)
    else:
        kc = ps.add("kc", 100.0, "N/m", "coupling spring to the other mass", lower=0.0)
        s_, x_in, v_in = ca.SX.sym("s"), ca.SX.sym("x_in"), ca.SX.sym("v_in")
        inputs = [Var("x_in", "m", "position of the other mass"), Var("v_in", "m/s", "velocity of the other mass")]
        states = [Var("state.s", "m", "coupling spring elongation x - x_other"), Var("state.v", "m/s", "velocity")]
        outputs = [Var("f", "N", "coupling spring force on the other mass, kc s"), Var("v", "m/s", "velocity"),
                   Var("s", "m", "coupling spring elongation x - x_other")]
        xs, u = ca.vertcat(s_, v), ca.vertcat(x_in, v_in)
        ode = ca.vertcat(v - v_in, (-k * (x_in + s_) - d * v - kc * s_) / m)
        out = ca.vertcat(kc * s_, v, s_)
        start = ca.vertcat(x0, v0)
    return Block.build(
        "oscillator", description=f"linear mass-spring-damper (coupling {coupling})", params=ps.params,
        inputs=inputs, outputs=outputs, states=states, p=ps.vector(), u=u, x=xs, ode=ode, out=out, start=start,
        integrator=integrator, substeps=substeps, fidelity="linear", **events)
