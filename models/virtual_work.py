"""Inverse dynamics of the 3-RPR by the principle of virtual work (thesis.md §4, thesis §6.7, App. B).

``J^T tau + F_p + sum_i (J_ci^T F_ci + J_ri^T F_ri) = 0`` where ``F = (-m a_x, -m a_y, -I alpha)``
are the inertial wrenches of the platform, the cylinders and the rods, and each ``J_*`` maps the
platform rates ``q_dot`` to the body's (v_x, v_y, omega).  ``tau_i`` [N] is the actuator force
along leg i, positive when it extends the leg.  Gravity is along -z and does no in-plane work.

The same expressions give the joint-space form used by forward dynamics:
``J^T tau = M(q) q_ddot + h(q, q_dot)`` with the platform-space mass matrix
``M = sum J_b^T diag(m, m, I) J_b`` and bias ``h`` (the inertial terms at ``q_ddot = 0``).

Inertia vector ``m`` in the order of :data:`models.geometry.INERTIA_FIELDS`:
``(e1, e2, m_cyl, I_cyl, m_rod, I_rod, m_p, I_p)``.
"""
from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np

from .geometry import Manipulator
from .kinematics import NG, inverse_jacobian, leg_motion

NI = 8  # length of the inertia vector


def generalized_inertial_force(q, qd, qdd, g, m):
    """``Q = -sum_b J_b^T F_b`` (3-vector [N, N, N m]): the platform-space force that the
    actuators must supply, ``J^T tau = Q``."""
    e1, e2, mc, Ic, mr, Ir, mp, Ip = (m[k] for k in range(NI))
    mot = leg_motion(q, qd, qdd, g, e1, e2)
    Q = ca.vertcat(mp * qdd[0], mp * qdd[1], Ip * qdd[2])  # platform: J_p = I
    for i in range(3):
        for v, a, mass, inertia in ((mot.v_cyl[:, i], mot.a_cyl[:, i], mc, Ic),
                                    (mot.v_rod[:, i], mot.a_rod[:, i], mr, Ir)):
            Jb = ca.jacobian(ca.vertcat(v, mot.w[i]), qd)  # body rates are linear in q_dot
            Q += Jb.T @ ca.vertcat(mass * a, inertia * mot.alpha[i])
    return Q


def actuator_forces(q, qd, qdd, g, m):
    """Leg forces ``tau`` [N] that produce the motion ``(q, qd, qdd)``: ``tau = J^-T Q``."""
    J = inverse_jacobian(q, g)
    return ca.solve(J.T, generalized_inertial_force(q, qd, qdd, g, m))


def mass_matrix_and_bias(q, qd, g, m):
    """``M(q)`` (3x3, symmetric positive definite) and ``h(q, qd)`` with ``Q = M qdd + h``."""
    qdd = ca.SX.sym("qdd_", 3)
    Q = generalized_inertial_force(q, qd, qdd, g, m)
    M = ca.jacobian(Q, qdd)
    h = ca.substitute(Q, qdd, ca.DM.zeros(3))
    return ca.substitute(M, qdd, ca.DM.zeros(3)), h


def forward_dynamics(q, qd, tau, g, m, f_ext=None):
    """Platform acceleration from leg forces: ``qdd = M^-1 (J^T tau + f_ext - h)``."""
    M, h = mass_matrix_and_bias(q, qd, g, m)
    rhs = inverse_jacobian(q, g).T @ tau - h
    if f_ext is not None:
        rhs = rhs + f_ext
    return ca.solve(M, rhs)


def kinetic_energy(q, qd, g, m):
    """Kinetic energy [J] of the platform and the six leg bodies."""
    M, _ = mass_matrix_and_bias(q, qd, g, m)
    return 0.5 * ca.dot(qd, M @ qd)


# --- CasADi functions ----------------------------------------------------------------------
@lru_cache(maxsize=None)
def inverse_dynamics_fn() -> ca.Function:
    """``(q, qd, qdd, g, m) -> tau``."""
    q, qd, qdd, g, m = (ca.SX.sym(n, k) for n, k in (("q", 3), ("qd", 3), ("qdd", 3), ("g", NG), ("m", NI)))
    return ca.Function("inverse_dynamics", [q, qd, qdd, g, m], [actuator_forces(q, qd, qdd, g, m)],
                       ["q", "qd", "qdd", "g", "m"], ["tau"])


@lru_cache(maxsize=None)
def mass_matrix_fn() -> ca.Function:
    """``(q, qd, g, m) -> (M, h)``."""
    q, qd, g, m = (ca.SX.sym(n, k) for n, k in (("q", 3), ("qd", 3), ("g", NG), ("m", NI)))
    M, h = mass_matrix_and_bias(q, qd, g, m)
    return ca.Function("mass_matrix", [q, qd, g, m], [M, h], ["q", "qd", "g", "m"], ["M", "h"])


def inverse_dynamics(mp: Manipulator, q, qd, qdd) -> np.ndarray:
    """Numeric leg forces [N] for one state (numpy 3-vectors in, 3-vector out)."""
    return np.array(inverse_dynamics_fn()(q, qd, qdd, mp.geometry_vector(), mp.inertia.vector())).ravel()
