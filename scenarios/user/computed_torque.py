"""A computed-torque controller of the 3-RPR written as a user block (models.user.BlockBuilder).

The controller inverts the virtual-work model of the rigid mechanism (docs/explanation/thesis.md §4,
models.virtual_work.actuator_forces): with the platform pose error ``e = q_ref - q`` it commands
the acceleration ``a = qdd_ref + Kd (qd_ref - qd) + Kp e`` and returns the leg forces that
produce it, ``tau = J^-T (M(q) a + h(q, qd))``.  Where its model equals the plant, the closed
loop is three decoupled error equations ``e'' + Kd e' + Kp e = 0`` (critically damped for
``Kd = 2 sqrt(Kp)``): what tests/test_user_blocks.py checks against the analytic solution.

The geometry and the inertias are those of a preset (option ``config``); the platform's mass and
inertia are parameters, so a scene can give the controller a wrong model (a robustness study).
"""
import math

import casadi as ca

from models.geometry import INERTIA_FIELDS, preset
from models.user import BlockBuilder
from models.virtual_work import actuator_forces

AXES = (("x", "m", "m/s", "m/s2"), ("y", "m", "m/s", "m/s2"), ("phi", "rad", "rad/s", "rad/s2"))


def computed_torque(config: str = "cross_leg"):
    """Computed-torque pose controller of the ``config`` preset (no states: a static law)."""
    mp = preset(config)
    b = BlockBuilder("computed_torque", f"computed-torque pose control by the virtual-work model ({config})")
    Kp = b.param("Kp", 400.0, "1/s2", "stiffness of the error dynamics e'' + Kd e' + Kp e = 0", lower=0.0)
    Kd = b.param("Kd", 40.0, "1/s", "damping of the error dynamics (critical: 2 sqrt(Kp))", lower=0.0)
    masses = {f: getattr(mp.inertia, f) for f in INERTIA_FIELDS}
    masses["m_p"] = b.param("m_p", masses["m_p"], "kg", "platform mass the controller assumes", lower=0.0)
    masses["I_p"] = b.param("I_p", masses["I_p"], "kg.m2", "platform inertia the controller assumes", lower=0.0)
    ref = [b.input(f"ref.{n}", u, f"setpoint: {n}") for n, u, _, _ in AXES]
    ref_d = [b.input(f"ref.v{n}" if n != "phi" else "ref.omega", u, f"setpoint rate: {n}") for n, _, u, _ in AXES]
    ref_dd = [b.input(f"ref.a{n}" if n != "phi" else "ref.alpha", u, f"setpoint acceleration: {n}")
              for n, _, _, u in AXES]
    q = [b.input(f"q.{n}", u, f"measured pose: {n}") for n, u, _, _ in AXES]
    qd = [b.input(f"q.v{n}" if n != "phi" else "q.omega", u, f"measured rate: {n}") for n, _, u, _ in AXES]
    q, qd = ca.vertcat(*q), ca.vertcat(*qd)
    a = ca.vertcat(*ref_dd) + Kd * (ca.vertcat(*ref_d) - qd) + Kp * (ca.vertcat(*ref) - q)
    tau = actuator_forces(q, qd, a, ca.DM(mp.geometry_vector()), ca.vertcat(*[masses[f] for f in INERTIA_FIELDS]))
    for i in range(3):
        b.output(f"leg[{i + 1}].f", tau[i], "N", f"force command of leg {i + 1}, positive extending")
        b.rating(f"leg[{i + 1}].f", -200.0, 200.0, "rated", "a bound on the commanded force (no motor here)")
    return b.build()


BLOCKS = {"computed_torque": computed_torque}
