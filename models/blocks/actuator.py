"""Electric linear actuator with a lead screw, voltage in (the rig of thesis Chapter 8, thesis.md §7).

Per leg: the driver applies ``u`` [V], clamped to the rated ``+-v_rated``.  The screw is not
back-drivable and the motor's force-speed line is straight: the speed the motor settles at is

    v_free = v_nl (u / v_rated) - v_nl f_load / f_stall

(``v_nl`` the no-load speed at ``v_rated``, ``f_stall`` the force that stops it, ``f_load`` the
force opposing extension), reached with a first-order lag ``tau dv/dt = v_free - v`` (motor and
gear inertia).  The stroke ``x`` integrates ``v`` and stays within ``0 .. stroke_max`` (end stops);
the leg length is ``s = s_offset + x``.

Actuator presets (construction option ``actuator``):

- ``"fa200"``: Firgelli FA-200-L-12 (thesis.md §7): 12 V, 0.8 in/s = 20.32 mm/s top speed, 200 lbf =
  890 N dynamic force (used as the stall force of the line: the datasheet gives no other); the
  time constant is not published: ``tau`` = 20 ms is an assumption (a geared DC motor), set it from
  a step response of the rig.
- ``"x"``: the thesis's high-performance "X" actuator (Section 8.1.7).  Only its 15 g
  (147 m/s2) peak acceleration is published; the defaults ``v_nl`` = 0.5 m/s and
  ``tau = v_nl / 147 m/s2`` = 3.4 ms reproduce that acceleration from rest at the rated voltage,
  ``f_stall`` = 100 N is an assumption.  Set the parameters once the actuator is measured.

Stroke: legs of 0.1 .. 0.6 m (thesis.md §1): ``s_offset`` = 0.1 m, ``stroke_max`` = 0.5 m.

End stops (construction option ``end_stops``), both located inside the FMU's step as events
(:mod:`._stops`):

- ``"clamp"`` (the default): the stop holds the rod, not the motor.  The rod's arrival at ``0``
  or ``stroke_max`` is an event (``x+`` on the stop, mode ``hold = +-1``); while it rests there
  its rate is zero (``dx/dt = 0``) and the motor speed ``v`` runs on (``tau dv/dt = v_free - v``:
  it winds up to ``v_free``); it leaves, an event too, where ``v`` turns away from the stop
  (changes sign).  Modes per leg: ``hold``, ``impacts`` (arrivals), ``t_arrival``, ``t_release``.
- ``"impact"``: an impact with restitution ``e`` (default 0: a lead screw does not bounce),
  ``v+ = -e v-``; with ``e`` = 0 the speed is reset to 0 and held there while the rod rests on
  the stop, until the drive pulls it away (``v_free`` changes sign).  Modes per leg: ``hold``,
  ``impacts``, ``v_impact``.

While a leg rests, both give the same stroke and rod rate; they differ in the motor speed and
so in the release (the clamp's wound-up ``v`` must first decay to zero).  Per leg both add the
output ``leg[i].impacts`` (``impacts`` for ``"single"``): arrivals at a stop so far.

Fidelities: ``"rig"``, the three legs of the rig in one block (inputs ``leg[i].u``, outputs
``leg[i].s``, ``leg[i].stroke``, ``leg[i].v``: the interface of the hardware FMU, so a scene swaps
one for the other); ``"single"``, one actuator with a load-force input ``f_load``.  The
virtual board's plant integrates the ``"single"`` block (:mod:`hardware.virtual`).
"""
from __future__ import annotations

import casadi as ca

from ..block import Block, Var
from ._common import INF, ParamSet
from ._stops import StopEvents, clamp_stops, end_stops

ACTUATORS = {
    "fa200": {"v_rated": 12.0, "v_nl": 0.02032, "f_stall": 890.0, "tau": 0.02},
    "x": {"v_rated": 12.0, "v_nl": 0.5, "f_stall": 100.0, "tau": 0.5 / 147.15},
}
STROKE = 0.5
S_OFFSET = 0.1
END_STOPS = ("clamp", "impact")


def _common(ps: ParamSet, actuator: str) -> dict[str, ca.SX]:
    d = ACTUATORS[actuator]
    return {
        "v_rated": ps.add("v_rated", d["v_rated"], "V", "rated (driver supply) voltage: commands are clamped to +-v_rated",
                          lower=1e-6),
        "v_nl": ps.add("v_nl", d["v_nl"], "m/s", "no-load speed at the rated voltage", lower=0.0),
        "f_stall": ps.add("f_stall", d["f_stall"], "N", "force that stalls the actuator at the rated voltage",
                          lower=1e-6),
        "tau": ps.add("tau", d["tau"], "s", "time constant of the speed (motor and gear inertia)", lower=1e-6),
        "stroke_max": ps.add("stroke_max", STROKE, "m", "usable stroke (end stops at 0 and stroke_max)", lower=1e-6),
        "s_offset": ps.add("s_offset", S_OFFSET, "m", "leg length at zero stroke", lower=0.0),
    }


def _stop_params(ps: ParamSet) -> dict[str, ca.SX]:
    return {"e": ps.add("e", 0.0, "1", "coefficient of restitution of the end stops", lower=0.0, upper=1.0),
            "v_rest": ps.add("v_rest", 1e-6, "m/s", "rebound speed below which the rod rests on a stop", lower=0.0)}


def _leg(p: dict, u, f_load, x, v, x0, ev: StopEvents, clamp: bool, t: ca.SX, prefix: str = ""):
    """(dx/dt, dv/dt, v at the rod, impacts) of one actuator starting at the stroke ``x0``, its
    end stops located events (:mod:`._stops`): clamped (``clamp``) or impacts."""
    u_sat = ca.fmin(p["v_rated"], ca.fmax(-p["v_rated"], u))
    v_free = p["v_nl"] * u_sat / p["v_rated"] - p["v_nl"] * f_load / p["f_stall"]
    if clamp:
        dx, modes = clamp_stops(ev, prefix, x, v, 0.0, p["stroke_max"], t, x0=x0)
        return dx, (v_free - v) / p["tau"], dx, modes["impacts"]
    dx, dv, modes = end_stops(ev, prefix, x, v, (v_free - v) / p["tau"], 0.0, p["stroke_max"], p["e"], p["v_rest"],
                              x0=x0)
    return dx, dv, dx, modes["impacts"]


def _stroke_start(p: dict, s0) -> ca.SX:
    """The stroke at the start [m]: the leg length ``s0`` within the stroke."""
    return ca.fmin(p["stroke_max"], ca.fmax(0, s0 - p["s_offset"]))


def rig(actuator: str = "fa200", integrator: str = "rk4", substeps: int = 1, end_stops: str = "clamp") -> Block:
    """Three actuators, one per leg (module docstring)."""
    ps = ParamSet()
    p = _common(ps, actuator)
    ev, clamp, t = StopEvents(), end_stops == "clamp", ca.SX.sym("t")
    if not clamp:
        p.update(_stop_params(ps))
    counts = []
    s0 = [ps.add(f"leg[{i}].s0", S_OFFSET + STROKE / 2, "m", f"leg {i} length at the start", lower=0.0) for i in (1, 2, 3)]
    u = ca.SX.sym("u", 3)
    xs = ca.SX.sym("x", 6)  # stroke, speed per leg
    ode, out, states, inputs, outputs, start = [], [], [], [], [], []
    for k, i in enumerate((1, 2, 3)):
        x, v = xs[2 * k], xs[2 * k + 1]
        dx, dv, v_rod, n = _leg(p, u[k], 0.0, x, v, _stroke_start(p, s0[k]), ev, clamp, t, f"leg[{i}].")
        counts.append(n)
        ode += [dx, dv]
        out += [p["s_offset"] + x, x, v_rod]
        inputs.append(Var(f"leg[{i}].u", "V", f"leg {i} driver voltage"))
        states += [Var(f"state.leg[{i}].stroke", "m", f"leg {i} stroke"), Var(f"state.leg[{i}].v", "m/s", f"leg {i} speed")]
        outputs += [Var(f"leg[{i}].s", "m", f"leg {i} length"), Var(f"leg[{i}].stroke", "m", f"leg {i} stroke"),
                    Var(f"leg[{i}].v", "m/s", f"leg {i} extension rate")]
        start += [_stroke_start(p, s0[k]), ca.SX(0)]
    out += counts
    outputs += [Var(f"leg[{i}].impacts", "1", f"leg {i}: arrivals at an end stop so far") for i in (1, 2, 3)]
    return Block.build("linear_actuator", description=f"three {actuator} linear actuators (the rig, thesis.md §7)",
                       params=ps.params, inputs=inputs, outputs=outputs, states=states, p=ps.vector(), u=u, x=xs,
                       ode=ca.vertcat(*ode), out=ca.vertcat(*out), start=ca.vertcat(*start), integrator=integrator,
                       substeps=substeps, fidelity="rig", **ev.block_kw(xs))


def single(actuator: str = "fa200", integrator: str = "rk4", substeps: int = 1, end_stops: str = "clamp") -> Block:
    """One actuator with a load force input (module docstring)."""
    ps = ParamSet()
    p = _common(ps, actuator)
    s0 = ps.add("s0", S_OFFSET + STROKE / 2, "m", "leg length at the start", lower=0.0)
    ev, clamp = StopEvents(), end_stops == "clamp"
    if not clamp:
        p.update(_stop_params(ps))
    u = ca.SX.sym("u", 2)
    xs = ca.SX.sym("x", 2)
    dx, dv, v_rod, n = _leg(p, u[0], u[1], xs[0], xs[1], _stroke_start(p, s0), ev, clamp, ca.SX.sym("t"))
    outputs = [Var("s", "m", "leg length"), Var("stroke", "m", "stroke"), Var("v", "m/s", "extension rate"),
               Var("impacts", "1", "arrivals at an end stop so far")]
    out = [p["s_offset"] + xs[0], xs[0], v_rod, n]
    return Block.build(
        "linear_actuator", description=f"{actuator} linear actuator (thesis.md §7)", params=ps.params,
        inputs=[Var("u", "V", "driver voltage"), Var("f_load", "N", "load force opposing extension")],
        outputs=outputs, states=[Var("state.stroke", "m", "stroke"), Var("state.v", "m/s", "speed")], p=ps.vector(),
        u=u, x=xs, ode=ca.vertcat(dx, dv), out=ca.vertcat(*out),
        start=ca.vertcat(_stroke_start(p, s0), 0), integrator=integrator,
        substeps=substeps, fidelity="single", **ev.block_kw(xs))


#: The "motor" fidelity's defaults: a small 12 V DC motor behind the FA-200's gear and lead screw,
#: chosen to match what thesis.md §7 publishes (12 V, 20.32 mm/s no-load) and the "rig" fidelity's
#: assumed 20 ms speed lag; the motor's own constants are not published (assumptions, to be
#: calibrated on the rig with ``rpr-cosim fit``).  No-load speed 12 k / (k^2 + b R) = 923 rad/s,
#: times ``lead`` = 20.3 mm/s; time constant J R / (k^2 + b R) = 20 ms; stall current 3 A.
MOTOR = {"R": 4.0, "k": 0.01, "b": 7.5e-6, "J": 6.5e-7, "lead": 2.2e-5}
#: The pots' nominal calibration (hardware.convert: an ideal 10 kOhm, 25-inch pot behind 1 kOhm on
#: a 12-bit ADC): counts at zero stroke and at ``pot_length``.
POT_LENGTH = 0.635
RAW_FULL = 4096 * 10e3 / 11e3


def motor_rig(integrator: str = "rk4", substeps: int = 4) -> Block:
    """The rig's three legs, each a DC motor (armature resistance ``R``, torque and back-EMF constant
    ``k``, viscous friction ``b``, inertia ``J`` at the motor) turning a lead screw of ``lead`` m/rad
    that the platform cannot back-drive (no load force), read by a potentiometer on a 12-bit ADC:

        i = (u - k w) / R,  J dw/dt = k i - b w,  dx/dt = lead w (0 at an end stop),
        raw = raw_zero + (raw_full - raw_zero) (x - latency v) / pot_length

    (inductance neglected: its 0.1 ms pole is far below the 1 ms loop).  ``raw`` is the ADC's
    level before rounding, ``latency`` [s] the sensor's delay to first order (``x(t - latency)``
    as ``x - latency v``).  The motor constants are the three actuators' (one type); each leg has
    its own start ``leg[i].s0`` and pot calibration ``leg[i].raw_zero``, ``leg[i].raw_full``.
    Interface: the "rig" fidelity's plus ``leg[i].i`` [A] and ``leg[i].raw`` [counts]."""
    ps = ParamSet()
    v_rated = ps.add("v_rated", 12.0, "V", "rated (driver supply) voltage: commands are clamped to +-v_rated",
                     lower=1e-6)
    R = ps.add("R", MOTOR["R"], "Ohm", "armature resistance (assumed)", lower=1e-3, upper=1e3)
    k = ps.add("k", MOTOR["k"], "N.m/A", "torque constant = back-EMF constant [V s/rad] (assumed)", lower=1e-5,
               upper=10.0)
    b = ps.add("b", MOTOR["b"], "N.m.s/rad", "viscous friction at the motor (assumed)", lower=0.0, upper=1.0)
    J = ps.add("J", MOTOR["J"], "kg.m2", "inertia at the motor: rotor, gear and screw (assumed)", lower=1e-12,
               upper=1.0)
    lead = ps.add("lead", MOTOR["lead"], "m/rad", "rod travel per motor radian (gear and lead screw)", lower=1e-9,
                  upper=1.0)
    stroke_max = ps.add("stroke_max", STROKE, "m", "usable stroke (end stops at 0 and stroke_max)", lower=1e-6)
    s_offset = ps.add("s_offset", S_OFFSET, "m", "leg length at zero stroke", lower=0.0)
    pot = ps.add("pot_length", POT_LENGTH, "m", "stroke at which raw_full is read", lower=1e-6)
    latency = ps.add("latency", 0.0, "s", "sensor latency (first order: x(t - latency) = x - latency v)",
                     lower=0.0, upper=0.1)
    s0 = [ps.add(f"leg[{i}].s0", S_OFFSET + STROKE / 2, "m", f"leg {i} length at the start", lower=0.0)
          for i in (1, 2, 3)]
    rz = [ps.add(f"leg[{i}].raw_zero", 0.0, "1", f"leg {i} pot: ADC counts at zero stroke", lower=-4096.0,
                 upper=4096.0) for i in (1, 2, 3)]
    rf = [ps.add(f"leg[{i}].raw_full", RAW_FULL, "1", f"leg {i} pot: ADC counts at pot_length", lower=1.0,
                 upper=1e5) for i in (1, 2, 3)]
    u = ca.SX.sym("u", 3)
    xs = ca.SX.sym("x", 6)  # stroke, shaft speed per leg
    ode, out, states, inputs, outputs, start = [], [], [], [], [], []
    for j, i in enumerate((1, 2, 3)):
        x, w = xs[2 * j], xs[2 * j + 1]
        u_sat = ca.fmin(v_rated, ca.fmax(-v_rated, u[j]))
        cur = (u_sat - k * w) / R
        at_end = ca.logic_or(ca.logic_and(x >= stroke_max, w > 0), ca.logic_and(x <= 0, w < 0))
        v_rod = ca.if_else(at_end, 0, lead * w)
        ode += [v_rod, (k * cur - b * w) / J]
        raw = rz[j] + (rf[j] - rz[j]) * (x - latency * v_rod) / pot
        out += [s_offset + x, x, v_rod, cur, raw]
        inputs.append(Var(f"leg[{i}].u", "V", f"leg {i} driver voltage"))
        states += [Var(f"state.leg[{i}].stroke", "m", f"leg {i} stroke"),
                   Var(f"state.leg[{i}].w", "rad/s", f"leg {i} motor speed")]
        outputs += [Var(f"leg[{i}].s", "m", f"leg {i} length"), Var(f"leg[{i}].stroke", "m", f"leg {i} stroke"),
                    Var(f"leg[{i}].v", "m/s", f"leg {i} extension rate"), Var(f"leg[{i}].i", "A", f"leg {i} current"),
                    Var(f"leg[{i}].raw", "1", f"leg {i} pot reading [ADC counts, before rounding]")]
        start += [ca.fmin(stroke_max, ca.fmax(0, s0[j] - s_offset)), ca.SX(0)]
    return Block.build("linear_actuator", description="three lead-screw actuators, each a DC motor, read by "
                                                      "potentiometers (the rig, thesis.md §7)",
                       params=ps.params, inputs=inputs, outputs=outputs, states=states, p=ps.vector(), u=u, x=xs,
                       ode=ca.vertcat(*ode), out=ca.vertcat(*out), start=ca.vertcat(*start), integrator=integrator,
                       substeps=substeps, fidelity="motor")
