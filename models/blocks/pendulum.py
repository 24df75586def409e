"""A pendulum against a stop: the acceptance test of located events (issue 30).

A point mass on a massless rod of length ``L`` [m] under gravity ``g`` [m/s2], angle ``theta``
[rad] from the downward vertical, angular rate ``omega`` [rad/s]:

    dtheta/dt = omega,    domega/dt = -(g / L) sin(theta)

A stop at ``theta_stop`` (default 0: the lowest point) is hit from above (``theta`` falling
through ``theta_stop``); the impact reverses the rate with restitution ``e``:
``omega+ = -e omega-``.  Modes count the impacts (``impacts``) and keep the last impact's time
(``t_impact`` [s]), both also outputs, so a trace or a test reads the event times directly.

Released from rest at ``theta0`` with the stop at 0, the impact times are analytic: the first
after a quarter period ``K(k0^2) / w0`` (``w0 = sqrt(g / L)``, ``k = sin(amplitude / 2)``, ``K``
the complete elliptic integral of the first kind), each next after a half period
``2 K(k_n^2) / w0`` of the amplitude the previous impact left, ``1 - cos(a_n) = e^2 (1 - cos(a_{n-1}))``
(energy: the impact keeps ``e^2`` of the kinetic energy).
"""
from __future__ import annotations

import casadi as ca

from ..block import FALLING, Block, Var
from ._common import ParamSet


def stop(integrator: str = "rk4", substeps: int = 10) -> Block:
    """The pendulum against a stop (module docstring)."""
    ps = ParamSet()
    L = ps.add("L", 0.5, "m", "rod length", lower=1e-9)
    g = ps.add("g", 9.81, "m/s2", "gravity", lower=0.0)
    e = ps.add("e", 0.7, "1", "coefficient of restitution of the stop", lower=0.0, upper=1.0)
    theta0 = ps.add("theta0", 1.0, "rad", "start angle (released from rest)")
    stop_at = ps.add("theta_stop", 0.0, "rad", "angle of the stop (hit when theta falls through it)")
    th, w = ca.SX.sym("theta"), ca.SX.sym("omega")
    impacts, t_impact, t = ca.SX.sym("impacts"), ca.SX.sym("t_impact"), ca.SX.sym("t")
    return Block.build(
        "pendulum", description="pendulum against a stop (impact with restitution)", params=ps.params,
        inputs=[], outputs=[Var("theta", "rad", "angle from the downward vertical"), Var("omega", "rad/s", "angular rate"),
                            Var("impacts", "1", "impacts so far"), Var("t_impact", "s", "time of the last impact")],
        states=[Var("state.theta", "rad", "angle"), Var("state.omega", "rad/s", "angular rate")],
        p=ps.vector(), u=ca.SX(0, 1), x=ca.vertcat(th, w), ode=ca.vertcat(w, -g / L * ca.sin(th)),
        out=ca.vertcat(th, w, impacts, t_impact), start=ca.vertcat(theta0, 0.0),
        modes=[Var("mode.impacts", "1", "impacts so far"), Var("mode.t_impact", "s", "time of the last impact")],
        m=ca.vertcat(impacts, t_impact), mode_start=[0.0, 0.0], t=t,
        indicators=th - stop_at, directions=[FALLING], event_names=["stop"],
        updates=[ca.vertcat(th, -e * w, impacts + 1, t)],
        integrator=integrator, substeps=substeps, fidelity="stop")
