"""A mass on a surface with Coulomb friction and stiction: the stick-slip part of issue 30.

Mass ``m`` [kg] at ``x`` [m], velocity ``v`` [m/s], driven by the force ``f`` [N] (an input: the
drive comes from another component), friction from the surface:

``stiction`` (located events; modes ``stuck`` = 1 or 0 and ``dir`` = +1/-1 while sliding)
    stuck: ``dx/dt = dv/dt = 0`` (the surface balances ``f``: friction ``-f``) while
    ``|f| < Fs``; it breaks away where ``f`` rises through ``Fs`` (sliding +1) or falls through
    ``-Fs`` (sliding -1).  Sliding in direction ``d``: ``m dv/dt = f - d Fc - b v``; where ``v``
    reaches 0 the mass sticks (``v+ = 0``) if ``|f| <= Fs``, else slides on in the direction of
    ``f``.  ``Fs >= Fc`` is the breakaway (static) force, ``Fc`` the Coulomb (kinetic) force,
    ``b`` viscous [N s/m].  Indicators: ``f - Fs``, ``-f - Fs`` (rising) while stuck, ``d v``
    (falling) while sliding.  While its mode is not active a breakaway indicator sits at -1 (so
    sticking where ``|f| > Fs`` fires it at once) and the stop indicator at 0, which never fires:
    at a breakaway ``v`` is 0 and the stop must wait until it returns there.
``smooth`` (no events, the tanh law)
    ``m dv/dt = f - F(v) - b v`` with ``F(v) = (Fc + (Fs - Fc) exp(-(v/v_s)^2)) tanh(v / v_eps)``:
    a Stribeck curve through ``Fs`` near rest, smoothed over ``v_eps`` [m/s]; a stiff law for
    small ``v_eps`` (Radau by default).  It cannot stick: a mass under ``|f| < Fs`` creeps at
    about ``v_eps f / Fs``.

Outputs: ``x``, ``v``, ``friction`` (the force of the surface on the mass), and for ``stiction``
``stuck`` (1 while stuck), ``sticks`` (stick events so far), ``t_stick`` and ``t_slip`` (the
times of the last stick and the last breakaway: a trace on any grid holds every event time).
"""
from __future__ import annotations

import casadi as ca

from ..block import FALLING, RISING, Block, Var
from ._common import ParamSet

FIDELITIES = ("stiction", "smooth")


def _params(ps: ParamSet) -> dict[str, ca.SX]:
    return {"m": ps.add("m", 1.0, "kg", "mass", lower=1e-12),
            "Fc": ps.add("Fc", 2.0, "N", "Coulomb (kinetic) friction force", lower=0.0),
            "Fs": ps.add("Fs", 3.0, "N", "breakaway (static) friction force, >= Fc", lower=0.0),
            "b": ps.add("b", 0.5, "N.s/m", "viscous friction", lower=0.0),
            "x0": ps.add("x0", 0.0, "m", "start position (at rest)")}


_INPUTS = [Var("f", "N", "drive force on the mass")]
_OUTPUTS = [Var("x", "m", "position"), Var("v", "m/s", "velocity"),
            Var("friction", "N", "force of the surface on the mass")]
_STATES = [Var("state.x", "m", "position"), Var("state.v", "m/s", "velocity")]


def stiction(integrator: str = "rk4", substeps: int = 10) -> Block:
    """Coulomb friction with stick and slip modes (module docstring)."""
    ps = ParamSet()
    p = _params(ps)
    x, v, f, t = ca.SX.sym("x"), ca.SX.sym("v"), ca.SX.sym("f"), ca.SX.sym("t")
    stuck, d, sticks = ca.SX.sym("stuck"), ca.SX.sym("dir"), ca.SX.sym("sticks")
    t_stick, t_slip = ca.SX.sym("t_stick"), ca.SX.sym("t_slip")
    sliding = stuck == 0
    friction = ca.if_else(sliding, -d * p["Fc"] - p["b"] * v, -f)
    ode = ca.vertcat(ca.if_else(sliding, v, 0.0), ca.if_else(sliding, (f + friction) / p["m"], 0.0))
    # at v = 0 while sliding: stick if the drive cannot overcome stiction, else slide its way
    holds = ca.fabs(f) <= p["Fs"]
    stop = ca.vertcat(x, 0.0, ca.if_else(holds, 1.0, 0.0), ca.if_else(holds, d, ca.sign(f)),
                      ca.if_else(holds, sticks + 1, sticks), ca.if_else(holds, t, t_stick), ca.if_else(holds, t_slip, t))
    return Block.build(
        "sliding_mass", description="mass with Coulomb friction and stiction (stick and slip modes)",
        params=ps.params, inputs=_INPUTS, outputs=_OUTPUTS + [Var("stuck", "1", "1 while stuck, 0 while sliding"),
                                                              Var("sticks", "1", "stick events so far"),
                                                              Var("t_stick", "s", "time the mass last stuck"),
                                                              Var("t_slip", "s", "time the mass last broke away "
                                                                                 "(or reversed)")],
        states=_STATES, p=ps.vector(), u=f, x=ca.vertcat(x, v), ode=ode,
        out=ca.vertcat(x, v, friction, stuck, sticks, t_stick, t_slip), start=ca.vertcat(p["x0"], 0.0),
        modes=[Var("mode.stuck", "1", "1 while stuck"), Var("mode.dir", "1", "sliding direction, +1 or -1"),
               Var("mode.sticks", "1", "stick events so far"), Var("mode.t_stick", "s", "time of the last stick"),
               Var("mode.t_slip", "s", "time of the last breakaway")],
        m=ca.vertcat(stuck, d, sticks, t_stick, t_slip), mode_start=[1.0, 1.0, 0.0, 0.0, 0.0], t=t,
        indicators=ca.vertcat(ca.if_else(sliding, -1.0, f - p["Fs"]), ca.if_else(sliding, -1.0, -f - p["Fs"]),
                              ca.if_else(sliding, d * v, 0.0)),
        directions=[RISING, RISING, FALLING], event_names=["breakaway+", "breakaway-", "stop"],
        updates=[ca.vertcat(x, v, 0.0, 1.0, sticks, t_stick, t), ca.vertcat(x, v, 0.0, -1.0, sticks, t_stick, t), stop],
        integrator=integrator, substeps=substeps, fidelity="stiction")


def smooth(integrator: str = "radau", substeps: int = 10) -> Block:
    """The smooth (tanh, Stribeck) law of the module docstring."""
    ps = ParamSet()
    p = _params(ps)
    v_eps = ps.add("v_eps", 1e-3, "m/s", "velocity over which the friction's sign is smoothed", lower=1e-12)
    v_s = ps.add("v_s", 1e-2, "m/s", "Stribeck velocity: friction falls from Fs to Fc over it", lower=1e-12)
    from ._common import solver_params
    solver_params(ps, integrator)
    x, v, f = ca.SX.sym("x"), ca.SX.sym("v"), ca.SX.sym("f")
    level = p["Fc"] + (p["Fs"] - p["Fc"]) * ca.exp(-(v / v_s) ** 2)
    friction = -level * ca.tanh(v / v_eps) - p["b"] * v
    return Block.build(
        "sliding_mass", description="mass with smoothed Coulomb friction and a Stribeck curve (tanh law)",
        params=ps.params, inputs=_INPUTS, outputs=_OUTPUTS, states=_STATES, p=ps.vector(), u=f,
        x=ca.vertcat(x, v), ode=ca.vertcat(v, (f + friction) / p["m"]), out=ca.vertcat(x, v, friction),
        start=ca.vertcat(p["x0"], 0.0), integrator=integrator, substeps=substeps, fidelity="smooth")
