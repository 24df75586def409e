"""Platform trajectory source with inverse kinematics: the setpoints of a scene.

Outputs: the pose ``platform.x``, ``platform.y`` [m], ``platform.phi`` [rad], its rates
``platform.vx``, ``platform.vy`` [m/s], ``platform.omega`` [rad/s] and accelerations
``platform.ax``, ``platform.ay`` [m/s2], ``platform.alpha`` [rad/s2] (the inputs of the
kinematic mechanism), and per leg the length ``leg[i].s`` [m], rate ``leg[i].v`` [m/s] and
acceleration ``leg[i].a`` [m/s2] by :func:`models.kinematics.leg_motion` (the PID setpoints).
No inputs.

Blocks are autonomous, so the block keeps its own clock: a state ``clock.t`` with
``dt/dt = 1`` starting at the parameter ``t0`` (set it to the scene's start time).  RK4 integrates
it exactly (to round-off), whatever the step.

Profiles (construction option ``profile``):

- ``"step"``: start pose ``(x0, y0, phi0)`` before ``t_step``, goal ``(x1, y1, phi1)`` from
  ``t_step`` on (defaults: Table 6.8, start (-0.15, -0.15, 0) -> target (-0.2, -0.15, 0.2),
  ``t_step = 0``: the goal from the first instant, as in the thesis); rates are zero;
- ``"ramp"``: linear from start to goal over ``duration`` seconds from ``t_step``;
- ``"sine"``: Chapter 7's path (thesis.md §5), ``pose = centre + amplitude sin(2 pi freq t + phase)``
  with centre ``(xc, yc, phic)`` = (-0.25, -0.15, 0), amplitudes ``(amp_x, amp_y, amp_phi)``
  = (0.05, 0.05, 0) and ``freq`` = 0.5 Hz, i.e. ``x = -0.25 + 0.05 sin(pi t)``.
"""
from __future__ import annotations

import math

import casadi as ca

from ..block import Block, Var
from ..kinematics import leg_motion
from ._common import ParamSet, geometry_params, stroke_ratings

PROFILES = ("step", "ramp", "sine")
LEGS = (1, 2, 3)


def _endpoints(ps: ParamSet) -> tuple[ca.SX, ca.SX]:
    start = ca.vertcat(ps.add("x0", -0.15, "m", "start pose: x (Table 6.8)"),
                       ps.add("y0", -0.15, "m", "start pose: y (Table 6.8)"),
                       ps.add("phi0", 0.0, "rad", "start pose: orientation (Table 6.8)"))
    goal = ca.vertcat(ps.add("x1", -0.2, "m", "goal pose: x (Table 6.8 target)"),
                      ps.add("y1", -0.15, "m", "goal pose: y (Table 6.8 target)"),
                      ps.add("phi1", 0.2, "rad", "goal pose: orientation (Table 6.8 target)"))
    return start, goal


def pose_setpoint(config: str = "cross_leg", profile: str = "step") -> Block:
    """The trajectory source (module docstring)."""
    ps = ParamSet()
    g = geometry_params(ps, config)
    t0 = ps.add("t0", 0.0, "s", "start value of the block's clock (the scene's start time)")
    clock = ca.SX.sym("clock")
    zero = ca.DM.zeros(3)
    if profile == "step":
        start, goal = _endpoints(ps)
        t_step = ps.add("t_step", 0.0, "s", "time of the step from start to goal")
        q, qd, qdd = ca.if_else(clock >= t_step, goal, start), zero, zero
    elif profile == "ramp":
        start, goal = _endpoints(ps)
        t_step = ps.add("t_step", 0.0, "s", "time the ramp starts")
        duration = ps.add("duration", 1.0, "s", "duration of the ramp", lower=1e-12)
        frac = ca.fmin(ca.fmax((clock - t_step) / duration, 0.0), 1.0)
        moving = ca.logic_and(clock >= t_step, clock < t_step + duration)
        q = start + frac * (goal - start)
        qd = ca.if_else(moving, (goal - start) / duration, zero)
        qdd = zero
    else:
        centre = ca.vertcat(ps.add("xc", -0.25, "m", "path centre: x (thesis.md §5)"),
                            ps.add("yc", -0.15, "m", "path centre: y (thesis.md §5)"),
                            ps.add("phic", 0.0, "rad", "path centre: orientation (thesis.md §5)"))
        amp = ca.vertcat(ps.add("amp_x", 0.05, "m", "amplitude in x (thesis.md §5)"),
                         ps.add("amp_y", 0.05, "m", "amplitude in y (thesis.md §5)"),
                         ps.add("amp_phi", 0.0, "rad", "amplitude in orientation (thesis.md §5)"))
        freq = ps.add("freq", 0.5, "Hz", "frequency (thesis.md §5: sin(pi t), 0.5 Hz)")
        phase = ps.add("phase", 0.0, "rad", "phase at t = 0")
        wt = 2 * math.pi * freq
        arg = wt * clock + phase
        q = centre + amp * ca.sin(arg)
        qd = amp * wt * ca.cos(arg)
        qdd = -amp * wt ** 2 * ca.sin(arg)
    mot = leg_motion(q, qd, qdd, g)
    names = [("x", "m"), ("y", "m"), ("phi", "rad"), ("vx", "m/s"), ("vy", "m/s"), ("omega", "rad/s"),
             ("ax", "m/s2"), ("ay", "m/s2"), ("alpha", "rad/s2")]
    outputs = ([Var(f"platform.{n}", u, "platform setpoint (global frame)") for n, u in names]
               + [Var(f"leg[{i}].s", "m", f"leg {i} length setpoint (inverse kinematics)") for i in LEGS]
               + [Var(f"leg[{i}].v", "m/s", f"leg {i} rate setpoint") for i in LEGS]
               + [Var(f"leg[{i}].a", "m/s2", f"leg {i} acceleration setpoint") for i in LEGS])
    return Block.build(
        "pose_setpoint", description=f"platform trajectory ({profile}) with inverse kinematics",
        params=ps.params, inputs=[], outputs=outputs, states=[Var("clock.t", "s", "the block's clock")],
        p=ps.vector(), u=ca.SX(0, 1), x=clock, ode=ca.SX(1), out=ca.vertcat(q, qd, qdd, mot.L, mot.Ld, mot.Ldd),
        start=t0, integrator="rk4", fidelity="default", ratings=stroke_ratings(config))
