"""Virtual-work inverse dynamics against the thesis (SPEC §5) and a second, independently written
formulation (Lagrange's equations with CasADi automatic differentiation)."""
from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np
import pytest

from models import geometry as G
from models import kinematics as K
from models import virtual_work as V

CROSS = G.preset("cross_leg")
RNG = np.random.default_rng(7)


@lru_cache(maxsize=None)
def lagrange_forces() -> ca.Function:
    """tau from Lagrange's equations; positions written directly from the joint coordinates.

    Bodies: platform at C (angle phi); per leg a cylinder at ``A - e1 d/|d|`` and a rod at
    ``A + (|d| - e2) d/|d|``, both turned by ``atan2(d)``, with ``d = B - A`` and
    ``B = C - r (cos(phi + a), sin(phi + a))``.  ``J^T tau = d/dt dT/dqd - dT/dq`` with ``J = dL/dq``.
    Outputs ``(tau, T, L)``: forces, kinetic energy and the leg lengths ``|B - A|``.
    """
    q, qd, qdd = ca.SX.sym("q", 3), ca.SX.sym("qd", 3), ca.SX.sym("qdd", 3)
    g, m = ca.SX.sym("g", 10), ca.SX.sym("m", 8)
    e1, e2, mc, Ic, mr, Ir, mp, Ip = (m[k] for k in range(8))
    T = 0.5 * mp * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * Ip * qd[2] ** 2
    lengths = []
    for i in range(3):
        A = ca.vertcat(g[2 * i], g[2 * i + 1])
        B = q[:2] - g[6] * ca.vertcat(ca.cos(q[2] + g[7 + i]), ca.sin(q[2] + g[7 + i]))
        d = B - A
        n = ca.sqrt(d[0] ** 2 + d[1] ** 2)
        lengths.append(n)
        theta = ca.atan2(d[1], d[0])
        for pos, mass, inertia in ((A - e1 * d / n, mc, Ic), (A + (n - e2) * d / n, mr, Ir)):
            v = ca.jtimes(pos, q, qd)
            T += 0.5 * mass * ca.dot(v, v) + 0.5 * inertia * ca.jtimes(theta, q, qd) ** 2
    dT_dqd = ca.gradient(T, qd)
    Q = ca.jtimes(dT_dqd, q, qd) + ca.jtimes(dT_dqd, qd, qdd) - ca.gradient(T, q)
    J = ca.jacobian(ca.vertcat(*lengths), q)
    return ca.Function("lagrange", [q, qd, qdd, g, m], [ca.solve(J.T, Q), T, ca.vertcat(*lengths)])


def random_state():
    while True:
        q = np.array([RNG.uniform(-0.35, 0.1), RNG.uniform(-0.35, 0.1), RNG.uniform(-0.5, 0.5)])
        L, _ = K.ik(CROSS, q)
        if np.all((L > 0.12) & (L < 0.58)) and abs(np.linalg.det(K.jacobian(CROSS, q))) > 0.05:
            return q, RNG.normal(0, 0.5, 3), RNG.normal(0, 3.0, 3)


STATES = [random_state() for _ in range(8)]


@pytest.mark.parametrize("k", range(len(STATES)))
def test_virtual_work_equals_lagrange(k):
    q, qd, qdd = STATES[k]
    tau = V.inverse_dynamics(CROSS, q, qd, qdd)
    ref = lagrange_forces()(q, qd, qdd, CROSS.geometry_vector(), CROSS.inertia.vector())[0]
    ref = np.array(ref).ravel()
    assert np.max(np.abs(tau - ref)) <= 1e-10 * np.max(np.abs(ref))


@pytest.mark.parametrize("k", range(len(STATES)))
def test_power_balance(k):
    """tau . Ldot = dT/dt, with T from the Lagrange formulation differentiated along the motion."""
    q, qd, qdd = STATES[k]
    tau = V.inverse_dynamics(CROSS, q, qd, qdd)
    Ld = K.jacobian(CROSS, q) @ qd
    f = lagrange_forces()
    g, m = CROSS.geometry_vector(), CROSS.inertia.vector()

    def T(t):
        return float(f(q + qd * t + 0.5 * qdd * t * t, qd + qdd * t, qdd, g, m)[1])

    h = 1e-4
    dT = (T(-2 * h) - 8 * T(-h) + 8 * T(h) - T(2 * h)) / (12 * h)
    assert float(tau @ Ld) == pytest.approx(dT, rel=1e-8, abs=1e-10)


@pytest.mark.parametrize("k", range(4))
def test_mass_matrix_and_bias_reproduce_inverse_dynamics(k):
    q, qd, qdd = STATES[k]
    g, m = CROSS.geometry_vector(), CROSS.inertia.vector()
    M, h = (np.array(v) for v in V.mass_matrix_fn()(q, qd, g, m))
    assert np.allclose(M, M.T, atol=1e-14) and np.all(np.linalg.eigvalsh(M) > 0)
    tau = np.linalg.solve(K.jacobian(CROSS, q).T, M @ qdd + h.ravel())
    np.testing.assert_allclose(tau, V.inverse_dynamics(CROSS, q, qd, qdd), rtol=1e-12, atol=1e-12)


def test_kinetic_energy_equals_lagrange():
    q, qd, qdd = STATES[0]
    g, m = CROSS.geometry_vector(), CROSS.inertia.vector()
    qs, qds = ca.SX.sym("q", 3), ca.SX.sym("qd", 3)
    ke = ca.Function("ke", [qs, qds], [V.kinetic_energy(qs, qds, g, m)])
    assert float(ke(q, qd)) == pytest.approx(float(lagrange_forces()(q, qd, qdd, g, m)[1]), rel=1e-12)


def test_table_7_9_actuator_forces():
    """SPEC §5: the virtual-work forces of Table 7.9 at t = 0.5 s, within 1 %."""
    t = 0.5
    s, c, w = np.sin(np.pi * t), np.cos(np.pi * t), np.pi
    q = [-0.25 + 0.05 * s, -0.15 + 0.05 * s, 0.0]
    qd = [0.05 * w * c, 0.05 * w * c, 0.0]
    qdd = [-0.05 * w * w * s, -0.05 * w * w * s, 0.0]
    tau = V.inverse_dynamics(CROSS, q, qd, qdd)
    np.testing.assert_allclose(tau, [2.610272368, 1.440588406, 0.693698204], rtol=1e-2)
