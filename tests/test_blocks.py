"""The model catalog (models.blocks) against independent sources: the thesis's tables (SPEC §5, §6),
analytic solutions, SPEC §1 formulas written again in numpy, finite differences, and a second
formulation of the same physics (rigid vs multibody, forward vs inverse dynamics).

Blocks are simulated directly in CasADi (CVODES at tight tolerances), not through an FMU."""
from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

import models.blocks as B
from models import geometry as G
from models import kinematics as K
from models import virtual_work as V
from models.block import BlockError

CROSS = G.preset("cross_leg")
LEGS = (1, 2, 3)


# --- helpers ---------------------------------------------------------------------------------
def simulate(blk, ts, *, u=None, p=None, x0=None, tol=1e-10):
    """Outputs (len(ts), ny) and states of ``blk`` over ``ts`` with inputs ``u``: a constant
    vector, or a function of the CasADi time symbol returning the input vector."""
    p = blk.param_defaults if p is None else np.asarray(p, float)
    F = blk.functions()
    x0 = np.array(F["start"](p)).ravel() if x0 is None else np.asarray(x0, float)
    t = ca.SX.sym("t")
    uu = ca.DM(np.zeros(blk.u.numel())) if u is None else (u(t) if callable(u) else ca.DM(np.asarray(u, float)))
    ode = F["ode"](blk.x, uu, p)
    I = ca.integrator("I", "cvodes", {"x": blk.x, "t": t, "ode": ode}, ts[0], ts,
                      {"abstol": tol, "reltol": tol, "max_num_steps": 10 ** 6})
    xs = np.array(I(x0=x0)["xf"]).reshape(len(x0), len(ts))
    out = ca.Function("o", [blk.x, t], [F["out"](blk.x, uu, p)])
    ys = np.array([np.array(out(xs[:, k], ts[k])).ravel() for k in range(len(ts))])
    return ys, xs.T


def col(blk, name):
    return blk.index("outputs", name)


def ik_numpy(q):
    """SPEC §1 leg lengths, written again: A_i of the 0.3 m base, B_i = C - (Lmp/sqrt3)(cos, sin)(phi + a_i)."""
    o = 0.3 / math.sqrt(3)
    A = np.array([[-o * math.cos(math.pi / 6), o * math.sin(math.pi / 6)],
                  [o * math.cos(math.pi / 6), o * math.sin(math.pi / 6)], [0.0, -o]])
    a = np.array([math.pi / 6, 5 * math.pi / 6, 3 * math.pi / 2])
    x, y, phi = q
    Bx = x - 0.2 / math.sqrt(3) * np.cos(phi + a)
    By = y - 0.2 / math.sqrt(3) * np.sin(phi + a)
    return np.hypot(Bx - A[:, 0], By - A[:, 1])


def random_states(n, seed):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        q = np.array([rng.uniform(-0.3, 0.0), rng.uniform(-0.3, 0.0), rng.uniform(-0.4, 0.4)])
        L = ik_numpy(q)
        if np.all((L > 0.12) & (L < 0.55)) and abs(np.linalg.det(K.jacobian(CROSS, q))) > 0.05:
            out.append((q, rng.normal(0, 0.5, 3), rng.normal(0, 3.0, 3)))
    return out


STATES = random_states(6, seed=3)


# --- mechanism: rigid --------------------------------------------------------------------------
@pytest.mark.parametrize("k", range(len(STATES)))
@pytest.mark.parametrize("lumped", [False, True], ids=["bare", "m_act"])
def test_rigid_inverts_virtual_work_inverse_dynamics(k, lumped):
    """tau from virtual-work inverse dynamics (plus the lumped actuator terms m Ldd + b Ld, with
    Ldd from the Chapter 5 kinematics) -> the rigid block returns the same qdd."""
    q, qd, qdd = STATES[k]
    m_act, b_act = (np.array([0.058, 0.03, 0.1]), np.array([3.0, 0.5, 14.0])) if lumped else (np.zeros(3), np.zeros(3))
    tau = V.inverse_dynamics(CROSS, q, qd, qdd)
    mot = K.leg_motion_fn()(q, qd, qdd, CROSS.geometry_vector(), [0.3, 0.3])
    Ld, Ldd = np.array(mot[1]).ravel(), np.array(mot[2]).ravel()
    tau = tau + m_act * Ldd + b_act * Ld
    blk = B.make("mechanism", "rigid", **{f"leg[{i}].m_act": m_act[i - 1] for i in LEGS},
                 **{f"leg[{i}].b_act": b_act[i - 1] for i in LEGS})
    xdot = np.array(blk.functions()["ode"](np.r_[q, qd], tau, blk.param_defaults)).ravel()
    np.testing.assert_allclose(xdot[:3], qd, rtol=0, atol=0)
    np.testing.assert_allclose(xdot[3:], qdd, rtol=0, atol=1e-10 * max(1.0, np.abs(qdd).max()))


@pytest.mark.parametrize("k", range(3))
@pytest.mark.parametrize("m_act", [0.0, 0.058])
def test_rigid_conserves_energy_without_input(k, m_act):
    """No input and no damping: T = virtual_work.kinetic_energy (+ m_act Ld^2 / 2) stays constant."""
    q, qd, _ = STATES[k]
    blk = B.make("mechanism", "rigid", **{f"leg[{i}].m_act": m_act for i in LEGS})
    ts = np.linspace(0.0, 0.5, 11)
    ys, xs = simulate(blk, ts, x0=np.r_[q, qd], tol=1e-12)
    g, m = CROSS.geometry_vector(), CROSS.inertia.vector()
    Ld = ys[:, [col(blk, f"leg[{i}].v") for i in LEGS]]
    qs, qds = ca.SX.sym("q", 3), ca.SX.sym("qd", 3)
    T = ca.Function("T", [qs, qds], [V.kinetic_energy(qs, qds, g, m)])
    E = np.array([float(T(xs[j, :3], xs[j, 3:])) for j in range(len(ts))]) \
        + 0.5 * m_act * np.sum(Ld ** 2, axis=1)
    assert np.ptp(xs[:, 2]) > 0.05  # it really moved
    assert np.max(np.abs(E - E[0])) < 1e-9 * E[0]


def test_rigid_outputs_and_start_pose():
    blk = B.make("mechanism", "rigid", x0=-0.2, y0=-0.15, phi0=0.2)
    F = blk.functions()
    x0 = np.array(F["start"](blk.param_defaults)).ravel()
    y = np.array(F["out"](x0, np.zeros(3), blk.param_defaults)).ravel()
    np.testing.assert_allclose(y[:3], [-0.2, -0.15, 0.2])
    # Table 6.12 target lengths (SPEC §6: four places, +-6e-5 m)
    np.testing.assert_allclose(y[[col(blk, f"leg[{i}].s") for i in LEGS]], [0.3415, 0.3641, 0.2613], atol=6e-5)
    assert [fl.name for fl in blk.flanges] == ["leg[1]", "leg[2]", "leg[3]"]


def test_rigid_leg_rate_is_derivative_of_leg_length():
    q, qd, _ = STATES[0]
    blk = B.make("mechanism", "rigid")
    out = blk.functions()["out"]
    h = 1e-6
    s = lambda qq: np.array(out(np.r_[qq, qd], np.zeros(3), blk.param_defaults)).ravel()[6:9]
    fd = (s(q + h * qd) - s(q - h * qd)) / (2 * h)
    np.testing.assert_allclose(s(q) , ik_numpy(q), atol=1e-14)
    np.testing.assert_allclose(np.array(out(np.r_[q, qd], np.zeros(3), blk.param_defaults)).ravel()[9:12], fd,
                               atol=1e-8)


# --- mechanism: rigid against Lagrange's equations (a formulation it was not built from) -----------
def lagrange_rigid_ode(m_act, b_act) -> ca.Function:
    """``(q, qd, f) -> qdd`` of the rigid mechanism with lumped actuators, from the Lagrange
    formulation of tests/test_virtual_work.py (positions written from the joint coordinates,
    energies differentiated by CasADi; no virtual work, no Chapter 5 kinematics): the leg force
    ``f = tau_L(q, qd, qdd) + m_act Ldd + b_act Ld`` is affine in ``qdd``, solved for it."""
    from test_virtual_work import lagrange_forces

    q, qd, qdd, f = (ca.SX.sym(n, 3) for n in ("q", "qd", "qdd", "f"))
    tau, _, L = lagrange_forces()(q, qd, qdd, CROSS.geometry_vector(), CROSS.inertia.vector())
    Ld = ca.jtimes(L, q, qd)
    Ldd = ca.jtimes(Ld, q, qd) + ca.jtimes(Ld, qd, qdd)
    need = tau + ca.DM(m_act) * Ldd + ca.DM(b_act) * Ld
    A = ca.jacobian(need, qdd)
    rest = ca.substitute(need, qdd, ca.DM.zeros(3))
    return ca.Function("lagrange_qdd", [q, qd, f], [ca.solve(A, f - rest)])


LUMPED = {"bare": (np.zeros(3), np.zeros(3)), "m_act": (np.array([0.058, 0.03, 0.1]), np.array([3.0, 0.5, 14.0]))}


@pytest.mark.parametrize("k", range(len(STATES)))
@pytest.mark.parametrize("lumped", sorted(LUMPED))
def test_rigid_forward_dynamics_equals_lagrange(k, lumped):
    """The rigid block's accelerations under random leg forces equal Lagrange's."""
    q, qd, _ = STATES[k]
    m_act, b_act = LUMPED[lumped]
    f = np.random.default_rng(k).normal(0.0, 5.0, 3)
    blk = B.make("mechanism", "rigid", **{f"leg[{i}].m_act": m_act[i - 1] for i in LEGS},
                 **{f"leg[{i}].b_act": b_act[i - 1] for i in LEGS})
    xdot = np.array(blk.functions()["ode"](np.r_[q, qd], f, blk.param_defaults)).ravel()
    want = np.array(lagrange_rigid_ode(m_act, b_act)(q, qd, f)).ravel()
    np.testing.assert_allclose(xdot[3:], want, rtol=0, atol=1e-10 * max(1.0, np.abs(want).max()))


@pytest.fixture(scope="module")
def lagrange_trajectory():
    """0.5 s of the bare rigid mechanism under constant leg forces, from the scene's start pose,
    integrated from Lagrange's equations by CVODES at 1e-12."""
    ts = np.linspace(0.0, 0.5, 501)
    x, f = ca.SX.sym("x", 6), ca.DM(FORCE)
    ode = ca.vertcat(x[3:], lagrange_rigid_ode(np.zeros(3), np.zeros(3))(x[:3], x[3:], f))
    I = ca.integrator("I", "cvodes", {"x": x, "ode": ode}, 0.0, ts, {"abstol": 1e-12, "reltol": 1e-12})
    return ts, np.array(I(x0=[-0.15, -0.15, 0.0, 0.0, 0.0, 0.0])["xf"]).T


def test_rigid_block_trajectory_equals_lagrange(lagrange_trajectory):
    ts, want = lagrange_trajectory
    _, xs = simulate(B.make("mechanism", "rigid"), ts, u=FORCE, tol=1e-12)
    assert np.ptp(want[:, 2]) > 0.05  # it turned
    np.testing.assert_allclose(xs, want, rtol=0, atol=5e-12)  # both CVODES at 1e-12: measured 1.5e-13


def test_rigid_fmu_trajectory_equals_lagrange(lagrange_trajectory, tmp_path_factory):
    """The exported rigid FMU (RK4 at 1 ms) run by FMPy's own master follows Lagrange's solution
    to RK4's accuracy (measured: 9e-12 m in x, 1.3e-11 m in y, 3.6e-11 rad; bound 1e-10)."""
    import fmpy

    import fmus

    ts, want = lagrange_trajectory
    path = fmus.build_fmu(B.make("mechanism", "rigid"), cache_dir=tmp_path_factory.getbasetemp() / "fmu-cache")
    res = fmpy.simulate_fmu(str(path), stop_time=0.5, step_size=1e-3, output_interval=1e-3,
                            start_values={f"leg[{i}].f": FORCE[i - 1] for i in LEGS},
                            output=["platform.x", "platform.y", "platform.phi"])
    got = np.column_stack([res["platform.x"], res["platform.y"], res["platform.phi"]])
    np.testing.assert_allclose(res["time"], ts, atol=1e-12)
    np.testing.assert_allclose(got, want[:, :3], rtol=0, atol=1e-10)


# --- mechanism: multibody ---------------------------------------------------------------------------
FORCE = [2.0, -1.0, 1.5]


@pytest.fixture(scope="module")
def rigid_reference():
    """Rigid response to a constant force, with and without lumped actuator terms."""
    res = {}
    ts = np.linspace(0.0, 0.2, 21)
    for lumped in (False, True):
        over = ({**{f"leg[{i}].m_act": 0.058 for i in LEGS}, **{f"leg[{i}].b_act": 3.0 for i in LEGS}}
                if lumped else {})
        res[lumped] = simulate(B.make("mechanism", "rigid", **over), ts, u=FORCE)[0], over
    return ts, res


@pytest.mark.parametrize("lumped", [False, True], ids=["bare", "m_act"])
def test_multibody_converges_to_rigid_as_joints_stiffen(rigid_reference, lumped):
    """Parasitic joints of stiffness 1e6, 1e7, 1e8: the pose and leg-length errors against the
    rigid model fall by about a decade per decade (measured: pose 2.9e-5, 2.3e-6, 2.3e-7 m)."""
    ts, res = rigid_reference
    y_rigid, over = res[lumped]
    errs = []
    for k in (1e6, 1e7, 1e8):
        blk = B.make("mechanism", "multibody", k_joint=k, k_rot=k, **over)
        ys, _ = simulate(blk, ts, u=FORCE, tol=1e-10)
        errs.append((np.abs(ys[:, :3] - y_rigid[:, :3]).max(), np.abs(ys[:, 6:9] - y_rigid[:, 6:9]).max()))
    errs = np.array(errs)
    print("multibody vs rigid (pose, legs) at k = 1e6, 1e7, 1e8:", errs.tolist())
    assert np.all(errs[1:] < errs[:-1] / 5)  # at least 5x better per decade
    assert errs[-1, 0] < 1e-6 and errs[-1, 1] < 1e-6
    assert np.abs(y_rigid[-1, :3] - y_rigid[0, :3]).max() > 0.02  # and the platform moved cm


def _multibody_energy(x, m_act, k, k_rot):
    """Kinetic + spring energy of the seven bodies, written from the state layout (per body: x, y,
    theta, body-frame vx, vy, omega; cylinders 1-3, rods 1-3, platform) and SPEC §1/§3 geometry."""
    A = np.array(CROSS.base)
    e1 = e2 = 0.3
    mass = [1.0] * 6 + [1.69935]
    inertia = [0.03003800838] * 6 + [0.01145826355]
    b = x.reshape(7, 6)
    rot = lambda th: np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    E = sum(0.5 * mass[j] * (b[j, 3] ** 2 + b[j, 4] ** 2) + 0.5 * inertia[j] * b[j, 5] ** 2 for j in range(7))
    r = 0.2 / math.sqrt(3)
    for i in range(3):
        c, d, p = b[i], b[i + 3], b[6]
        Pc = c[:2] + rot(c[2]) @ [e1, 0.0]
        Pr = d[:2] + rot(d[2]) @ [e2, 0.0]
        ang = G.CROSS_ANGLES[i]
        Pb = p[:2] + rot(p[2]) @ [-r * math.cos(ang), -r * math.sin(ang)]
        n = rot(c[2]) @ [0.0, 1.0]
        E += 0.5 * k * (np.sum((Pc - A[i]) ** 2) + np.sum((Pb - Pr) ** 2) + np.dot(d[:2] - c[:2], n) ** 2)
        E += 0.5 * k_rot * (d[2] - c[2]) ** 2
        # lumped actuator mass: rate of |Pr - Pc| from the points' velocities
        vel = lambda body, local: rot(body[2]) @ body[3:5] + body[5] * (rot(body[2]) @ np.array([-local[1], local[0]]))
        u = (Pr - Pc) / np.linalg.norm(Pr - Pc)
        E += 0.5 * m_act * np.dot(u, vel(d, [e2, 0.0]) - vel(c, [e1, 0.0])) ** 2
    return E


@pytest.mark.parametrize("m_act", [0.0, 0.058])
def test_multibody_conserves_energy_without_damping(m_act):
    """Undamped joints, no input, random body velocities: kinetic energy plus the penalty springs'
    energy (written again here from the state layout) stays constant while the joints ring."""
    k = 1e6
    blk = B.make("mechanism", "multibody", k_joint=k, k_rot=k, c_joint=0.0, c_rot=0.0,
                 **{f"leg[{i}].m_act": m_act for i in LEGS})
    x0 = np.array(blk.functions()["start"](blk.param_defaults)).ravel()
    rng = np.random.default_rng(5)
    x0 = x0 + np.concatenate([np.r_[0, 0, 0, rng.normal(0, 0.1, 3)] for _ in range(7)])
    ts = np.linspace(0, 0.05, 6)
    _, xs = simulate(blk, ts, x0=x0, tol=1e-12)
    E = np.array([_multibody_energy(x, m_act, k, k) for x in xs])
    springs = E - np.array([_multibody_energy(x, m_act, 0.0, 0.0) for x in xs])
    assert springs.max() > 1e-3 * E[0]  # the joints really are loaded
    assert np.max(np.abs(E - E[0])) < 1e-7 * E[0]


def test_multibody_starts_relaxed_at_the_start_pose():
    rigid = B.make("mechanism", "rigid", x0=-0.2, y0=-0.12, phi0=0.15)
    mb = B.make("mechanism", "multibody", x0=-0.2, y0=-0.12, phi0=0.15)
    ys = [np.array(b.functions()["out"](b.functions()["start"](b.param_defaults), np.zeros(3),
                                        b.param_defaults)).ravel() for b in (rigid, mb)]
    np.testing.assert_allclose(ys[1], ys[0], atol=1e-14)
    xdot = np.array(mb.functions()["ode"](mb.functions()["start"](mb.param_defaults), np.zeros(3),
                                          mb.param_defaults)).ravel()
    assert np.abs(xdot).max() < 1e-6  # relaxed springs: no force, no motion
    assert [o.name for o in mb.outputs] == [o.name for o in rigid.outputs]
    assert [i.name for i in mb.inputs] == [i.name for i in rigid.inputs]


# --- mechanism: kinematic ---------------------------------------------------------------------------
def _path(t):
    s, c = math.sin(math.pi * t), math.cos(math.pi * t)
    w = math.pi
    return [-0.25 + 0.05 * s, -0.15 + 0.05 * s, 0.0, 0.05 * w * c, 0.05 * w * c, 0.0,
            -0.05 * w * w * s, -0.05 * w * w * s, 0.0]


@pytest.mark.parametrize("leg,force,accel", [(1, 2.610272368, 0.678478249), (2, 1.440588406, 0.696504281),
                                             (3, 0.693698204, 0.019889875)])
def test_kinematic_mechanism_reproduces_tables_7_7_and_7_9(leg, force, accel):
    """SPEC §5: at t = 0.5 s the virtual-work forces (Table 7.9, <= 1 %) and leg accelerations
    (Table 7.7, 0.2 %; leg 3: SPEC says "2 %", the exact instant -- the path's acceleration
    peak -- gives 2.19 %, so the bound is 2.2 %, the one-digit "2 %" to its next digit)."""
    blk = B.make("mechanism", "kinematic")
    y = np.array(blk.functions()["out"](ca.DM(0, 1), _path(0.5), blk.param_defaults)).ravel()
    assert y[col(blk, f"leg[{leg}].f")] == pytest.approx(force, rel=0.01)
    assert y[col(blk, f"leg[{leg}].a")] == pytest.approx(accel, rel=0.002 if leg < 3 else 0.022)


def test_kinematic_forces_drive_the_rigid_block_along_the_path():
    """Second formulation: the kinematic block's forces (inverse dynamics, with lumped actuator
    terms) fed to the rigid block (forward dynamics) reproduce the path's accelerations."""
    over = {**{f"leg[{i}].m_act": 0.058 for i in LEGS}, **{f"leg[{i}].b_act": 3.0 for i in LEGS}}
    kin, rig = B.make("mechanism", "kinematic", **over), B.make("mechanism", "rigid", **over)
    for t in (0.1, 0.5, 1.3):
        u = _path(t)
        f = np.array(kin.functions()["out"](ca.DM(0, 1), u, kin.param_defaults)).ravel()[9:12]
        qdd = np.array(rig.functions()["ode"](u[:6], f, rig.param_defaults)).ravel()[3:]
        np.testing.assert_allclose(qdd, u[6:], atol=1e-10)


# --- DC motor ---------------------------------------------------------------------------------------
KT = 60 / (2 * math.pi * 145)  # 145 rpm/V
R_, L_, J_, b_, r_ = 0.574, 0.251e-3, 1.45e-4, 86e-6, 0.05


@pytest.mark.parametrize("fidelity,rotor", [("full", "lumped"), ("full", "state"), ("quasistatic", "lumped"),
                                            ("quasistatic", "state")])
def test_motor_steady_state_against_viscous_load(fidelity, rotor):
    """Motor on a mass m with viscous load c (m dv/dt = f - c v), 6 V.  By hand, at steady state
    ``kt i = b w + r c v``, ``i = (u - kt w) / R``, ``v = r w``, so
    ``v = kt u / (R r) / (c + kt^2/(R r^2) + b/r^2)`` and ``i = (u - kt v / r) / R``."""
    u0, m, c = 6.0, 1.0, 5.0
    blk = B.make("dc_motor", fidelity, rotor=rotor)
    F = blk.functions()
    p = blk.param_defaults
    mass = m + (J_ / r_ ** 2 if rotor == "lumped" else 0.0)  # option (b): lump the rotor into the leg
    xm, vleg = ca.SX.sym("xm", blk.x.numel()), ca.SX.sym("vleg")
    y = F["out"](xm, ca.vertcat(u0, vleg), p)
    ode = ca.vertcat(F["ode"](xm, ca.vertcat(u0, vleg), p), (y[0] - c * vleg) / mass) if blk.x.numel() \
        else (y[0] - c * vleg) / mass
    X = ca.vertcat(xm, vleg)
    I = ca.integrator("I", "cvodes", {"x": X, "ode": ode}, 0, 4.0, {"abstol": 1e-12, "reltol": 1e-12})
    xf = np.array(I(x0=np.r_[np.array(F["start"](p)).ravel(), 0.0])["xf"]).ravel()
    yf = np.array(ca.Function("o", [X], [y])(xf)).ravel()
    v = KT * u0 / (R_ * r_) / (c + KT ** 2 / (R_ * r_ ** 2) + b_ / r_ ** 2)
    i = (u0 - KT * v / r_) / R_
    assert xf[-1] == pytest.approx(v, rel=1e-8)
    assert yf[col(blk, "i")] == pytest.approx(i, rel=1e-8)
    assert yf[col(blk, "w")] == pytest.approx(v / r_, rel=1e-8)
    assert yf[col(blk, "torque")] == pytest.approx(KT * i, rel=1e-8)
    assert yf[col(blk, "flange.f")] == pytest.approx(c * v, rel=1e-8)


def test_motor_current_rise_with_blocked_shaft():
    """Full motor, leg held (v = 0): ``i(t) = u/R (1 - exp(-R t / L))`` (pole -R/L = -2287 1/s)."""
    blk = B.make("dc_motor", "full")
    ts = np.linspace(0, 2e-3, 21)
    ys, _ = simulate(blk, ts, u=[12.0, 0.0], tol=1e-12)
    np.testing.assert_allclose(ys[:, col(blk, "i")], 12.0 / R_ * (1 - np.exp(-R_ * ts / L_)), rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(ys[:, col(blk, "flange.f")], KT * ys[:, col(blk, "i")] / r_, rtol=1e-12)


def test_motor_reports_reflected_rotor_mass_and_ideal_gain():
    blk = B.make("dc_motor", "full")
    y = np.array(blk.functions()["out"]([0.0], [0.0, 0.0], blk.param_defaults)).ravel()
    assert y[col(blk, "m_reflected")] == pytest.approx(1450e-3 * 1e-4 / 0.05 ** 2)  # 1450 g cm2 / (0.05 m)^2
    ideal = B.make("dc_motor", "ideal")
    y = np.array(ideal.functions()["out"](ca.DM(0, 1), [2.0, 0.1], ideal.param_defaults)).ravel()
    assert y[col(ideal, "flange.f")] == pytest.approx(2.0 * KT / (R_ * r_))
    assert y[col(ideal, "w")] == pytest.approx(0.1 / r_)


# --- PID ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("form", ["parallel", "standard"])
def test_pid_step_response_is_ramp_plus_filtered_kick(form):
    """Constant error e from t = 0, filter state at 0, no limit: ``y = Kp e + ki e t + kd e/Tf
    exp(-t/Tf)`` with (ki, kd, Tf) = (Ki, Kd, Tf) or (Kp/Ti, Kp Td, beta Td)."""
    e = 0.03
    if form == "parallel":
        gains = dict(Kp=30.0, Ki=80.0, Kd=2.0, Tf=0.05)
        ki, kd, Tf = 80.0, 2.0, 0.05
    else:
        gains = dict(Kp=30.0, Ti=0.5, Td=0.4, beta=0.1)
        ki, kd, Tf = 60.0, 12.0, 0.04
    blk = B.make("pid", "continuous", form=form, u_max=1e6, **gains)
    ts = np.linspace(0, 0.5, 26)
    ys, _ = simulate(blk, ts, u=[0.33 + e, 0.33], tol=1e-12)
    np.testing.assert_allclose(ys[:, col(blk, "y")], 30.0 * e + ki * e * ts + kd * e / Tf * np.exp(-ts / Tf),
                               rtol=1e-8)
    np.testing.assert_allclose(ys[:, col(blk, "e")], e, rtol=1e-12)


def test_pid_derivative_on_measurement_of_a_ramp():
    """Measurement ``a t`` (setpoint = measurement, so e = 0), w0 = 0: ``y = -Kd a (1 - exp(-t/Tf))``."""
    a, Kd, Tf = 0.2, 20.0, 0.01
    blk = B.make("pid", "continuous", derivative="measurement", Kd=Kd, Tf=Tf)
    ts = np.linspace(0, 0.1, 21)
    ys, _ = simulate(blk, ts, u=lambda t: ca.vertcat(a * t, a * t), tol=1e-12)
    np.testing.assert_allclose(ys[:, col(blk, "y")], -Kd * a * (1 - np.exp(-ts / Tf)), rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize("anti_windup", ["none", "clamp", "backcalc"])
def test_pid_limit_and_anti_windup(anti_windup):
    """Saturated PI (Kd = 0) on a constant error e: the output is u_max; the integral part grows as
    ``Ki e t`` (none), stays at 0 (clamp), or tends to ``u_max - Kp e + Ki e Tt`` as
    ``1 - exp(-t/Tt)`` (back calculation, dI/dt = Ki e + (y - v)/Tt)."""
    e, Kp, Ki, Tt = 1.0, 30.0, 80.0, 0.2
    over = dict(Tt=Tt) if anti_windup == "backcalc" else {}
    blk = B.make("pid", "continuous", anti_windup=anti_windup, Kp=Kp, Ki=Ki, Kd=0.0, **over)
    ts = np.linspace(0, 1.0, 11)
    ys, xs = simulate(blk, ts, u=[e, 0.0], tol=1e-12)
    np.testing.assert_allclose(ys[:, col(blk, "y")], 12.0)
    expected = {"none": Ki * e * ts, "clamp": 0 * ts,
                "backcalc": (12.0 - Kp * e + Ki * e * Tt) * (1 - np.exp(-ts / Tt))}[anti_windup]
    np.testing.assert_allclose(xs[:, 0], expected, rtol=1e-8, atol=1e-9)


def _discrete_run(T, horizon=0.5):
    blk = B.make("pid", "discrete", sample_period=T, Kp=3.0, Ki=8.0, Kd=0.5, Tf=0.05, u_max=1e3)
    F = blk.functions()
    p = blk.param_defaults
    x = np.array(F["start"](p)).ravel()
    n = int(round(horizon / T))
    ys = []
    for k in range(n + 1):
        u = [math.sin(4 * k * T), 0.0]
        ys.append(float(F["out"](x, u, p)[0]))
        x = np.array(F["ode"](x, u, p)).ravel()
    return np.array(ys)[:: n // 10]


def test_discrete_pid_tends_to_the_continuous_one():
    """Error ``sin(4 t)``: the sampled controller's output at t = 0, 0.05, ... 0.5 s approaches the
    continuous one linearly in the sample period (forward-Euler integral)."""
    cont = B.make("pid", "continuous", Kp=3.0, Ki=8.0, Kd=0.5, Tf=0.05, u_max=1e3)
    ts = np.linspace(0, 0.5, 11)
    y_ref = simulate(cont, ts, u=lambda t: ca.vertcat(ca.sin(4 * t), 0.0), tol=1e-12)[0][:, 0]
    errs = [np.abs(_discrete_run(T) - y_ref).max() for T in (1e-2, 1e-3, 1e-4)]
    print("discrete vs continuous PID, T = 1e-2, 1e-3, 1e-4:", errs)
    assert errs[0] > 1e-3  # the coarse one is visibly different
    for a, b in zip(errs, errs[1:]):
        assert 5 < a / b < 20  # first order
    assert errs[-1] < 2e-3


# --- pose setpoint ---------------------------------------------------------------------------------
@pytest.mark.parametrize("t", [0.0, 0.2335, 0.5, 1.7, 3.25])
def test_sine_setpoint_legs_equal_ik_of_the_path(t):
    blk = B.make("pose_setpoint", profile="sine")
    out = blk.functions()["out"]
    y = lambda tt: np.array(out([tt], ca.DM(0, 1), blk.param_defaults)).ravel()
    path = _path(t)
    np.testing.assert_allclose(y(t)[:9], path, atol=1e-15)
    np.testing.assert_allclose(y(t)[[col(blk, f"leg[{i}].s") for i in LEGS]], ik_numpy(path[:3]), atol=1e-15)
    h = 1e-5
    fd = (ik_numpy(_path(t + h)[:3]) - ik_numpy(_path(t - h)[:3])) / (2 * h)
    np.testing.assert_allclose(y(t)[[col(blk, f"leg[{i}].v") for i in LEGS]], fd, atol=1e-9)
    fdd = (ik_numpy(_path(t + 1e-4)[:3]) - 2 * ik_numpy(path[:3]) + ik_numpy(_path(t - 1e-4)[:3])) / 1e-8
    np.testing.assert_allclose(y(t)[[col(blk, f"leg[{i}].a") for i in LEGS]], fdd, atol=1e-5)


def test_sine_setpoint_matches_table_7_3_lengths():
    """SPEC §5: Table 7.3 matches the path at t = 0.2335 s to 0.2 %."""
    blk = B.make("pose_setpoint", profile="sine")
    y = np.array(blk.functions()["out"]([0.2335], ca.DM(0, 1), blk.param_defaults)).ravel()
    np.testing.assert_allclose(y[[col(blk, f"leg[{i}].s") for i in LEGS]],
                               [0.309994594, 0.372398991, 0.276864985], rtol=2e-3)


@pytest.mark.parametrize("profile", ["step", "ramp"])
def test_step_and_ramp_setpoints_give_table_6_12_lengths(profile):
    """Start and target leg lengths of Table 6.12 (SPEC §6: 0.3109, 0.3559, 0.2043 -> 0.3415, 0.3641,
    0.2613, four places, +-6e-5 m); the ramp is halfway in pose at mid-time with the constant rate."""
    blk = B.make("pose_setpoint", profile=profile, t_step=1.0, **({"duration": 2.0} if profile == "ramp" else {}))
    y = lambda t: np.array(blk.functions()["out"]([t], ca.DM(0, 1), blk.param_defaults)).ravel()
    legs = [col(blk, f"leg[{i}].s") for i in LEGS]
    np.testing.assert_allclose(y(0.5)[legs], [0.3109, 0.3559, 0.2043], atol=6e-5)
    np.testing.assert_allclose(y(3.5)[legs], [0.3415, 0.3641, 0.2613], atol=6e-5)
    if profile == "ramp":
        np.testing.assert_allclose(y(2.0)[:6], [-0.175, -0.15, 0.1, -0.025, 0.0, 0.1], atol=1e-15)
        np.testing.assert_allclose(y(2.0)[legs], ik_numpy([-0.175, -0.15, 0.1]), atol=1e-15)


def test_setpoint_clock_runs_at_unit_rate_from_t0():
    blk = B.make("pose_setpoint", profile="sine", t0=2.0)
    ys, xs = simulate(blk, np.linspace(0, 1.0, 5))
    np.testing.assert_allclose(xs[:, 0], 2.0 + np.linspace(0, 1.0, 5), atol=1e-9)
    np.testing.assert_allclose(ys[-1, :3], _path(3.0)[:3], atol=1e-9)


# --- make() errors ------------------------------------------------------------------------------------
@pytest.mark.parametrize("args,kwargs,needle", [
    (("mechansim",), {}, "did you mean 'mechanism'"),
    (("mechanism", "rigd"), {}, "did you mean 'rigid'"),
    (("mechanism", "rigid"), {"confg": "cross_leg"}, "did you mean 'config'"),
    (("mechanism", "rigid"), {"config": "cross-leg"}, "did you mean 'cross_leg'"),
    (("mechanism", "multibody"), {"k_joints": 1e6}, "did you mean 'k_joint'"),
    (("pid", "continuous"), {"Kpp": 3.0}, "did you mean 'Kp'"),
    (("pid", "continuous"), {"form": "paralel"}, "did you mean 'parallel'"),
    (("pid", "discrete"), {"anti_windup": "clmp"}, "did you mean 'clamp'"),
    (("pid", "discrete"), {"sample_period": 0}, "sample_period=0 must be a positive number"),
    (("dc_motor", "full"), {"rotor": "lumpd"}, "did you mean 'lumped'"),
    (("dc_motor", "full"), {"substeps": 0}, "substeps=0 must be a whole number"),
    (("mechanism", "rigid"), {"m_p": -1.0}, "m_p=-1.0 is outside"),
    (("pose_setpoint",), {"profile": "sinus"}, "did you mean 'sine'"),
])
def test_make_errors_name_the_bad_name_with_a_suggestion(args, kwargs, needle):
    with pytest.raises(BlockError) as exc:
        B.make(*args, **kwargs)
    msg = str(exc.value)
    assert needle in msg
    assert "\n" not in msg
    assert args[0] in msg


@pytest.mark.parametrize("model,fidelity", [(m, f) for m, fs in B.catalog().items() for f in fs])
def test_catalog_blocks_declare_documented_parameters(model, fidelity):
    blk = B.make(model, fidelity)
    assert blk.fidelity == fidelity
    for prm in blk.params:
        assert prm.description, prm.name
        assert prm.lower <= prm.default <= prm.upper
