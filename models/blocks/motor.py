"""DC motor driving a leg through a rack and pinion (thesis Table 6.7, thesis.md §6).

Interface: input ``u`` [V] (armature voltage) and the flange ``flange``: flow ``flange.v`` [m/s]
in (the leg's extension rate), effort ``flange.f`` [N] out (force along the leg, positive
extending).  The rack turns shaft speed into leg speed, ``v = rack * w`` with ``rack`` = 0.05 m/rad,
and shaft torque into leg force, ``f = torque / rack``.

Electrical part ("full"): ``L di/dt = u - R i - kt w``; torque ``kt i``; the back-EMF constant
equals the torque constant.  "quasistatic" sets ``L = 0``: ``i = (u - kt w) / R``.  "ideal" is a
force source ``f = gain * u``.

Rotor inertia ``J`` and viscous friction ``b`` (construction option ``rotor``):

- ``"lumped"`` (default, DESIGN option (b)): the motor is inertia-free.  Its friction is a
  function of the input speed, so it stays inside: ``f = (kt i - b w) / rack``.  The rotor's
  inertia cannot (that would need ``dv/dt``, a derivative of an input): the motor reports it as the
  output ``m_reflected = J / rack**2`` [kg] (0.058 kg with Table 6.7), to be lumped into the
  mechanism's ``leg[i].m_act``.  No stiffness at the interface.
- ``"state"`` (option (a)): the rotor keeps its speed ``w`` as a state and the bond to the leg is a
  stiff spring-damper, ``f = k_bond * d + c_bond * (rack w - v)`` with ``dd/dt = rack w - v``,
  ``J dw/dt = kt i - b w - rack f`` (defaults: the thesis's parasitic 1e8 N/m and 2000 N s/m).
  Stiff at the interface: the case where co-simulation master algorithms differ.

Rotor friction (construction option ``friction``, with ``rotor="state"`` only: a rotor whose speed
is the leg's cannot stick):

- ``"viscous"`` (default): ``b w`` only, the equations above.
- ``"stiction"``: Coulomb friction with stiction, stick and slip as modes whose switches are located
  events inside the FMU's step (docs/explanation/events.md).  The net drive torque on the rotor is
  ``T = kt i - rack f`` (electromagnetic torque minus the load through the bond).  Stuck
  (mode ``stuck`` = 1): ``w = 0``, ``dw/dt = 0`` while ``|T| <= Ts`` (the friction holds ``-T``);
  it breaks away where ``T`` rises through ``Ts`` (slipping +1) or falls through ``-Ts``
  (slipping -1).  Slipping in direction ``s`` (mode ``dir``): ``J dw/dt = T - s Tc - b w``; where
  ``w`` reaches 0 the rotor sticks (``w+ = 0``) if ``|T| <= Ts``, else slips on in the direction
  of ``T``.  Indicators: ``T - Ts``, ``-T - Ts`` (rising) while stuck, ``s w`` (falling) while
  slipping (the law of ``sliding_mass``'s ``stiction``, :mod:`.friction`).  ``Ts >= Tc``.  The
  defaults are assumptions (Table 6.7 gives the viscous ``b`` only): ``Tc`` = 0.02 N m, the torque
  of a ~0.3 A no-load current (``kt`` 0.3 A), typical of a motor of this size and close to the
  viscous torque at its 182 rad/s no-load speed (0.016 N m); ``Ts = 1.5 Tc`` = 0.03 N m, a usual
  static-to-kinetic ratio.  The rotor then breaks away from rest at ``Ts R / kt`` = 0.26 V.
  Extra outputs: ``friction`` (the friction torque on the rotor [N m]), ``stuck``, ``sticks``
  (stick events so far), ``t_stick`` and ``t_slip`` (times of the last stick and breakaway).

Torque constant.  Table 6.7 prints the gyrator as "145" without a unit.  Read as a speed constant
of 145 rpm/V it gives ``kt = 60 / (2 pi 145) = 0.0659 N m/A``; 0.145 N m/A is the other
candidate (thesis.md §6).  Both were run in the closed-loop scene of Table 6.10 (monolithic CasADi/CVODES
at 1e-9: rigid mechanism with ``leg[i].m_act = J/rack**2``, three full motors, parallel PID
Kp = 30, Ki = 80, Kd = 20 with a 1 ms derivative filter on the error, +/-12 V, step from
(-0.15, -0.15, 0) to (-0.2, -0.15, 0.2)); Table 6.10 shows phi peaking at ~0.30 rad near 1.3 s,
x dipping to ~-0.22 m and L1 peaking at ~0.355 m:

=============  ===============  ========  =======  ==============================  ====================
kt [N m/A]     phi peak [rad]   x min     L1 peak  pose at 5 s                     torque after 50 ms
=============  ===============  ========  =======  ==============================  ====================
0.0659         0.3027 @ 1.31 s  -0.2225   0.3556   (-0.2023, -0.1499, 0.2080)      -0.025 .. 0.092 N m
0.145          0.2967 @ 1.38 s  -0.2191   0.3541   (-0.2022, -0.1500, 0.2097)      -0.029 .. 0.035 N m
=============  ===============  ========  =======  ==============================  ====================

(The first milliseconds saturate at 12 V, the derivative kick of the setpoint step.)  The default
is ``kt = 0.0659`` N m/A: it matches all three figures of Table 6.10 (0.145 peaks later, lower and
shallower), and its torques after the kick are nearer Table 6.11's -0.13 .. 0.20 N m (0.145 needs
about a third of the torque for the same motion).  A 10 ms derivative filter would instead
cut the phi peak to 0.267 rad for either constant, which is why the PID's default ``Tf`` is 1 ms.
"""
from __future__ import annotations

import math

import casadi as ca

from ..block import FALLING, RISING, Block, BlockError, Flange, Rating, Var
from ._common import INF, ParamSet, solver_params

ROTOR = ("lumped", "state")
FRICTION = ("viscous", "stiction")
#: Default Coulomb and breakaway torques [N m] of ``friction="stiction"`` (assumptions: docstring).
TC_DEFAULT, TS_DEFAULT = 0.02, 0.03
KT_RPM_PER_V = 60.0 / (2 * math.pi * 145.0)  # 145 rpm/V as N m/A (= V s/rad)

#: Default torque constant [N m/A]: 145 rpm/V (module docstring: the closed-loop study).
KT_DEFAULT = KT_RPM_PER_V

#: Rated armature voltage [V]: the FA-200-L-12 is a 12 V actuator and Table 6.7 limits the PID
#: output to +-12 V (thesis.md §6-7).
U_RATED = 12.0
#: Peak current [A] of the motor driver: the thesis's Cytron "13 A" driver (thesis.md §7) carries
#: 13 A continuously and 30 A at peak (its datasheet).  The Table 6.7 motor stalls at
#: 12 V / 0.574 Ohm = 20.9 A, which the setpoint kick of pid_step reaches for a few milliseconds.
I_PEAK = 30.0
RATINGS = {
    "u": Rating(-U_RATED, U_RATED, "rated", "12 V actuator, Table 6.7 output limit (thesis.md §6-7)"),
    "i": Rating(-I_PEAK, I_PEAK, "rated", "peak current of the 13 A motor driver (thesis.md §7; 30 A peak)"),
}

FLANGE = Flange("flange", effort="flange.f", flow="flange.v", causality="effort_out")
INPUTS = [Var("u", "V", "armature voltage"), Var("flange.v", "m/s", "leg extension rate (rack speed)")]


def _params(ps: ParamSet, electrical: bool, rotor: str) -> dict[str, ca.SX]:
    p = {}
    if electrical:
        p["R"] = ps.add("R", 0.574, "Ohm", "armature resistance (Table 6.7)", lower=0.0)
        p["kt"] = ps.add("kt", KT_DEFAULT, "N.m/A", "torque constant = back-EMF constant [V s/rad]", lower=0.0)
    p["J"] = ps.add("J", 1.45e-4, "kg.m2", "rotor inertia (Table 6.7: 1450 g cm2)", lower=0.0)
    p["b"] = ps.add("b", 86e-6, "N.m.s/rad", "rotor viscous friction (Table 6.7: 86 uN m s/rad)", lower=0.0)
    p["rack"] = ps.add("rack", 0.05, "m/rad", "rack-and-pinion ratio: leg speed per shaft speed", lower=0.0)
    if rotor == "state":
        p["k_bond"] = ps.add("k_bond", 1e8, "N/m", "stiffness of the rack-leg bond (option (a))", lower=0.0)
        p["c_bond"] = ps.add("c_bond", 2000.0, "N.s/m", "damping of the rack-leg bond (option (a))", lower=0.0)
    return p


def _stiction(ps: ParamSet, p: dict, w: ca.SX, net: ca.SX) -> tuple[ca.SX, list[Var], list[ca.SX], dict]:
    """The stick and slip law of the module docstring on the rotor state ``w`` under the net drive
    torque ``net``: ``(J dw/dt, outputs, output expressions, Block.build event keywords)``."""
    tc = ps.add("Tc", TC_DEFAULT, "N.m", "Coulomb (kinetic) friction torque (assumed: module docstring)", lower=0.0)
    ts = ps.add("Ts", TS_DEFAULT, "N.m", "breakaway (static) friction torque, >= Tc (assumed: module docstring)",
                lower=0.0)
    t = ca.SX.sym("t")
    stuck, d, sticks = ca.SX.sym("stuck"), ca.SX.sym("dir"), ca.SX.sym("sticks")
    t_stick, t_slip = ca.SX.sym("t_stick"), ca.SX.sym("t_slip")
    slipping = stuck == 0
    friction = ca.if_else(slipping, -d * tc - p["b"] * w, -net)
    holds = ca.fabs(net) <= ts  # at w = 0 while slipping: stick, else slip on the way T drives
    stop = (ca.if_else(holds, 0.0, w), [ca.if_else(holds, 1.0, 0.0), ca.if_else(holds, d, ca.sign(net)),
                                        ca.if_else(holds, sticks + 1, sticks), ca.if_else(holds, t, t_stick),
                                        ca.if_else(holds, t_slip, t)])
    outputs = [Var("friction", "N.m", "friction torque on the rotor"), Var("stuck", "1", "1 while stuck, 0 slipping"),
               Var("sticks", "1", "stick events so far"), Var("t_stick", "s", "time the rotor last stuck"),
               Var("t_slip", "s", "time the rotor last broke away (or reversed)")]
    events = dict(
        modes=[Var("mode.stuck", "1", "1 while stuck"), Var("mode.dir", "1", "slipping direction, +1 or -1"),
               Var("mode.sticks", "1", "stick events so far"), Var("mode.t_stick", "s", "time of the last stick"),
               Var("mode.t_slip", "s", "time of the last breakaway")],
        m=ca.vertcat(stuck, d, sticks, t_stick, t_slip), mode_start=[1.0, 1.0, 0.0, 0.0, 0.0], t=t,
        indicators=ca.vertcat(ca.if_else(slipping, -1.0, net - ts), ca.if_else(slipping, -1.0, -net - ts),
                              ca.if_else(slipping, d * w, 0.0)),
        directions=[RISING, RISING, FALLING], event_names=["breakaway+", "breakaway-", "stick"],
        updates=[(ca.SX(0.0), [0.0, 1.0, sticks, t_stick, t]), (ca.SX(0.0), [0.0, -1.0, sticks, t_stick, t]), stop])
    return ca.if_else(slipping, net + friction, 0.0), outputs, [friction, stuck, sticks, t_stick, t_slip], events


def _event_updates(events: dict, xs: list[ca.SX], w: ca.SX) -> dict:
    """Full ``(x, m)`` updates from the stiction law's ``(w+, m+)`` pairs: the other states kept."""
    events["updates"] = [ca.vertcat(*[new_w if ca.is_equal(s, w) else s for s in xs], *[ca.SX(v) for v in modes])
                         for new_w, modes in events["updates"]]
    return events


def _build(fidelity: str, rotor: str, integrator: str, substeps: int, friction: str = "viscous") -> Block:
    if friction == "stiction" and rotor != "state":
        raise BlockError(f"dc_motor ({fidelity}): friction 'stiction' needs rotor 'state' (set that option too: "
                         f"the rotor speed is the state that sticks; with rotor 'lumped' it is the leg's)")
    ps = ParamSet()
    electrical = fidelity in ("full", "quasistatic")
    p = _params(ps, electrical, rotor)
    if fidelity == "full":
        p["L"] = ps.add("L", 0.251e-3, "H", "armature inductance (Table 6.7: 0.251 mH)", lower=0.0)
    u = ca.SX.sym("uin", 2)
    volt, v = u[0], u[1]
    xs_list, ode, states, start = [], [], [], []
    if fidelity == "full":
        i_sym = ca.SX.sym("i_state")
        xs_list.append(i_sym)
        states.append(Var("state.i", "A", "armature current"))
        start.append(0.0)
    if rotor == "state":
        w_sym, d_sym = ca.SX.sym("w_state"), ca.SX.sym("d_state")
        xs_list += [w_sym, d_sym]
        states += [Var("state.w", "rad/s", "shaft speed"), Var("state.d", "m", "deflection of the rack-leg bond")]
        start += [0.0, 0.0]
        w = w_sym
    else:
        w = v / p["rack"]
    if fidelity == "full":
        i = i_sym
        di = (volt - p["R"] * i - p["kt"] * w) / p["L"]
    else:
        i = (volt - p["kt"] * w) / p["R"]
    torque = p["kt"] * i
    extra_out, extra, events = [], [], {}
    if rotor == "state":
        f = p["k_bond"] * d_sym + p["c_bond"] * (p["rack"] * w - v)
        if friction == "stiction":
            jdw, extra_out, extra, events = _stiction(ps, p, w_sym, torque - p["rack"] * f)
        else:
            jdw = torque - p["b"] * w - p["rack"] * f
        dw = jdw / p["J"]
        dd = p["rack"] * w - v
    else:
        f = (torque - p["b"] * w) / p["rack"]
    if fidelity == "full":
        ode.append(di)
    if rotor == "state":
        ode += [dw, dd]
    outputs = [Var("flange.f", "N", "force on the leg, positive extending"),
               Var("i", "A", "armature current"), Var("torque", "N.m", "electromagnetic torque kt i"),
               Var("w", "rad/s", "shaft speed")]
    out = [f, i, torque, w]
    if rotor == "lumped":
        outputs.append(Var("m_reflected", "kg", "rotor inertia seen at the leg, J/rack^2: lump into the "
                                                "mechanism's leg[i].m_act"))
        out.append(p["J"] / p["rack"] ** 2)
    xs = ca.vertcat(*xs_list) if xs_list else ca.SX(0, 1)
    if events:
        events = _event_updates(events, xs_list, w_sym)
    solver_params(ps, integrator if xs_list else "none")
    law = ", Coulomb friction with stiction" if friction == "stiction" else ""
    return Block.build(
        "dc_motor", description=f"DC motor with rack and pinion ({fidelity}, rotor {rotor}{law}; thesis Table 6.7)",
        params=ps.params, inputs=list(INPUTS), outputs=outputs + extra_out, states=states, p=ps.vector(), u=u, x=xs,
        ode=ca.vertcat(*ode) if ode else ca.SX(0, 1), out=ca.vertcat(*out, *extra),
        start=ca.vertcat(*[ca.SX(s) for s in start]) if start else ca.SX(0, 1),
        integrator=integrator if xs_list else "none", substeps=substeps, flanges=[FLANGE], fidelity=fidelity,
        ratings=dict(RATINGS), **events)


def full(rotor: str = "lumped", integrator: str = "exact", substeps: int = 1, friction: str = "viscous") -> Block:
    """Armature current state (pole ``-R/L`` ~ -2290 1/s: stiff).  The equations are linear, so
    the default integrator is ``exact`` (:func:`models.integrators.exact_kernel`): exact and
    stable at any step, cheaper than a Radau step (no Newton iteration)."""
    return _build("full", rotor, integrator, substeps, friction)


def quasistatic(rotor: str = "lumped", integrator: str = "exact", substeps: int = 1,
                friction: str = "viscous") -> Block:
    """``L = 0``: the current follows the voltage at once.  No state with ``rotor="lumped"``."""
    return _build("quasistatic", rotor, integrator, substeps, friction)


def ideal() -> Block:
    """Force source ``flange.f = gain * u``; ``gain`` defaults to the stall force per volt of the
    full motor, ``kt / (R rack)`` [N/V]."""
    ps = ParamSet()
    gain = ps.add("gain", KT_DEFAULT / (0.574 * 0.05), "N/V", "force per volt (default: stall force per volt "
                                                           "kt/(R rack) of the Table 6.7 motor)", lower=-INF)
    rack = ps.add("rack", 0.05, "m/rad", "rack-and-pinion ratio (for the shaft-speed output)", lower=0.0)
    u = ca.SX.sym("uin", 2)
    return Block.build(
        "dc_motor", description="ideal force source f = gain u", params=ps.params, inputs=list(INPUTS),
        outputs=[Var("flange.f", "N", "force on the leg, positive extending"), Var("w", "rad/s", "shaft speed")],
        states=[], p=ps.vector(), u=u, x=ca.SX(0, 1), ode=ca.SX(0, 1), out=ca.vertcat(gain * u[0], u[1] / rack),
        start=ca.SX(0, 1), integrator="none", flanges=[FLANGE], fidelity="ideal",
        ratings={"u": RATINGS["u"]})
