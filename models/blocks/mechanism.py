"""The 3-RPR mechanism as blocks, at three fidelities (DESIGN "Fidelity levels").

Shared interface of the dynamic fidelities (``rigid``, ``multibody``):

- inputs ``leg[i].f`` [N]: actuator force along leg i, positive when it extends the leg (thesis.md §4);
- outputs ``platform.x``, ``platform.y`` [m], ``platform.phi`` [rad], ``platform.vx``,
  ``platform.vy`` [m/s], ``platform.omega`` [rad/s] (global frame), ``leg[i].s`` [m] (leg length
  ``|B_i - A_i|``) and ``leg[i].v`` [m/s] (its rate);
- flanges ``leg[i]``: effort ``leg[i].f`` in, flow ``leg[i].v`` out, so ``f * v`` is the power
  the actuator puts into the mechanism;
- parameters: the geometry (``A1x .. A3y``, ``Lmp``, ``a1 .. a3``) and mass properties
  (``e1, e2, m_cyl, I_cyl, m_rod, I_rod, m_p, I_p``) with defaults from the ``config`` preset,
  the start pose ``x0, y0, phi0`` and start rates ``vx0, vy0, omega0`` (global frame; the
  multibody fidelity derives its bodies' velocities from them), and per leg a lumped actuator mass ``leg[i].m_act`` [kg] and
  viscous damping ``leg[i].b_act`` [N s/m] acting on the leg's extension (DESIGN option (b):
  a rotor of inertia ``J`` behind a rack of ratio ``r`` adds ``J / r**2``; see
  :mod:`models.blocks.motor`).  With both at 0 the mechanism is the thesis's.

All equations come from :mod:`models.kinematics` and :mod:`models.virtual_work`; the multibody
fidelity builds its own body equations (Newton–Euler, penalty joints) but places its bodies with
the same kinematics and the same mass-centre conventions (thesis.md §3).
"""
from __future__ import annotations

import casadi as ca

from ..block import Block, Flange, Var
from ..kinematics import inverse_jacobian, inverse_kinematics, joint_offsets, leg_motion
from ..virtual_work import actuator_forces, mass_matrix_and_bias
from ._common import ParamSet, geometry_params, inertia_params, solver_params, stroke_ratings

LEGS = (1, 2, 3)
POSE_OUTPUTS = [
    Var("platform.x", "m", "platform centre C, x"),
    Var("platform.y", "m", "platform centre C, y"),
    Var("platform.phi", "rad", "platform orientation"),
    Var("platform.vx", "m/s", "velocity of C, x (global frame)"),
    Var("platform.vy", "m/s", "velocity of C, y (global frame)"),
    Var("platform.omega", "rad/s", "platform angular rate"),
]
LEG_OUTPUTS = ([Var(f"leg[{i}].s", "m", f"length of leg {i}, |B{i} - A{i}|") for i in LEGS]
               + [Var(f"leg[{i}].v", "m/s", f"extension rate of leg {i}") for i in LEGS])
FORCE_INPUTS = [Var(f"leg[{i}].f", "N", f"actuator force along leg {i}, positive extending") for i in LEGS]
FLANGES = [Flange(f"leg[{i}]", effort=f"leg[{i}].f", flow=f"leg[{i}].v", causality="flow_out") for i in LEGS]


def _actuator_params(ps: ParamSet) -> tuple[ca.SX, ca.SX]:
    m_act = ca.vertcat(*[ps.add(f"leg[{i}].m_act", 0.0, "kg", f"mass lumped on the extension of leg {i} "
                                "(reflected rotor inertia J/r^2)", lower=0.0) for i in LEGS])
    b_act = ca.vertcat(*[ps.add(f"leg[{i}].b_act", 0.0, "N.s/m", f"viscous damping on the extension of leg {i} "
                                "(reflected b/r^2)", lower=0.0) for i in LEGS])
    return m_act, b_act


def _start_pose(ps: ParamSet) -> tuple[ca.SX, ca.SX]:
    """Start pose ``q0 = (x0, y0, phi0)`` and start rates ``qd0 = (vx0, vy0, omega0)`` (global
    frame) as parameters."""
    q0 = ca.vertcat(ps.add("x0", -0.15, "m", "start pose: x of C (Table 6.8)"),
                    ps.add("y0", -0.15, "m", "start pose: y of C (Table 6.8)"),
                    ps.add("phi0", 0.0, "rad", "start pose: orientation (Table 6.8)"))
    qd0 = ca.vertcat(ps.add("vx0", 0.0, "m/s", "start rate: velocity of C, x (global frame)"),
                     ps.add("vy0", 0.0, "m/s", "start rate: velocity of C, y (global frame)"),
                     ps.add("omega0", 0.0, "rad/s", "start rate: platform angular rate"))
    return q0, qd0


def rigid_dynamics(q, qd, f, g, m, m_act, b_act) -> ca.SX:
    """Platform acceleration ``qdd`` for leg forces ``f``: the virtual-work model
    ``M qdd + h = J^T tau`` (:func:`models.virtual_work.mass_matrix_and_bias`) with, per leg, a
    lumped mass ``m_act`` and damper ``b_act`` on the extension ``L``:
    ``tau = f - b_act Ld - m_act Ldd`` and ``Ldd = J qdd + (Jdot qd)``, so
    ``(M + J^T diag(m_act) J) qdd = J^T (f - b_act Ld - m_act Jdot qd) - h``.  With
    ``m_act = b_act = 0`` this is :func:`models.virtual_work.forward_dynamics`."""
    M, h = mass_matrix_and_bias(q, qd, g, m)
    J = inverse_jacobian(q, g)
    Ld = J @ qd
    conv = leg_motion(q, qd, ca.DM.zeros(3), g, m[0], m[1]).Ldd  # Jdot qd
    Mt = M + J.T @ ca.diag(m_act) @ J
    return ca.solve(Mt, J.T @ (f - b_act * Ld - m_act * conv) - h)


def rigid(config: str, integrator: str = "rk4", substeps: int = 1) -> Block:
    """3-DOF reduced dynamics by virtual work; states ``(x, y, phi, vx, vy, omega)``."""
    ps = ParamSet()
    g = geometry_params(ps, config)
    m = inertia_params(ps, config)
    m_act, b_act = _actuator_params(ps)
    q0, qd0 = _start_pose(ps)
    xs = ca.SX.sym("xs", 6)
    f = ca.SX.sym("f", 3)
    q, qd = xs[0:3], xs[3:6]
    qdd = rigid_dynamics(q, qd, f, g, m, m_act, b_act)
    L, _ = inverse_kinematics(q, g)
    Ld = inverse_jacobian(q, g) @ qd
    states = [Var(n, u, d) for n, u, d in (
        ("q.x", "m", "x of C"), ("q.y", "m", "y of C"), ("q.phi", "rad", "orientation"),
        ("q.vx", "m/s", "velocity of C, x"), ("q.vy", "m/s", "velocity of C, y"), ("q.omega", "rad/s", "angular rate"))]
    solver_params(ps, integrator)
    return Block.build(
        "mechanism", description="3-RPR mechanism, rigid 3-DOF dynamics by virtual work (thesis.md §4)",
        params=ps.params, inputs=FORCE_INPUTS, outputs=POSE_OUTPUTS + LEG_OUTPUTS, states=states,
        p=ps.vector(), u=f, x=xs, ode=ca.vertcat(qd, qdd), out=ca.vertcat(q, qd, L, Ld),
        start=ca.vertcat(q0, qd0), integrator=integrator, substeps=substeps,
        flanges=list(FLANGES), fidelity="rigid", ratings=stroke_ratings(config))


def kinematic(config: str) -> Block:
    """Prescribed platform motion in, leg kinematics and the actuator forces that produce it out
    (the virtual-work reference, :func:`models.virtual_work.actuator_forces`, plus the lumped
    actuator terms ``m_act Ldd + b_act Ld``).  No states."""
    ps = ParamSet()
    g = geometry_params(ps, config)
    m = inertia_params(ps, config)
    m_act, b_act = _actuator_params(ps)
    names = [("platform.x", "m"), ("platform.y", "m"), ("platform.phi", "rad"),
             ("platform.vx", "m/s"), ("platform.vy", "m/s"), ("platform.omega", "rad/s"),
             ("platform.ax", "m/s2"), ("platform.ay", "m/s2"), ("platform.alpha", "rad/s2")]
    inputs = [Var(n, u, "prescribed platform motion (global frame)") for n, u in names]
    u = ca.SX.sym("pose", 9)
    q, qd, qdd = u[0:3], u[3:6], u[6:9]
    mot = leg_motion(q, qd, qdd, g, m[0], m[1])
    tau = actuator_forces(q, qd, qdd, g, m) + m_act * mot.Ldd + b_act * mot.Ld
    outputs = (LEG_OUTPUTS + [Var(f"leg[{i}].a", "m/s2", f"extension acceleration of leg {i}") for i in LEGS]
               + [Var(f"leg[{i}].f", "N", f"actuator force needed along leg {i}, positive extending") for i in LEGS])
    return Block.build(
        "mechanism", description="3-RPR mechanism, prescribed motion: leg kinematics and virtual-work forces",
        params=ps.params, inputs=inputs, outputs=outputs, states=[], p=ps.vector(), u=u, x=ca.SX(0, 1),
        ode=ca.SX(0, 1), out=ca.vertcat(mot.L, mot.Ld, mot.Ldd, tau), start=ca.SX(0, 1), integrator="none",
        fidelity="kinematic", ratings=stroke_ratings(config))


def _rot(th) -> ca.SX:
    c, s = ca.cos(th), ca.sin(th)
    return ca.vertcat(ca.horzcat(c, -s), ca.horzcat(s, c))


def multibody(config: str, integrator: str = "radau", substeps: int = 1) -> Block:
    """Seven rigid bodies in body-fixed coordinates joined by parasitic spring-dampers (the thesis's
    bond graph, Section 6.3).

    Bodies: cylinder i (mass centre at ``A_i - e1 s_i``, its joint point A at body coordinates
    ``(e1, 0)``), rod i (mass centre at ``B_i - e2 s_i``, joint point B at ``(e2, 0)``), and the
    platform (centre C, joint points ``b_i = -r (cos a_i, sin a_i)``); a body's x axis points
    along its leg, from A to B.  Each body has the states ``position (x, y)`` [m] and angle
    ``theta`` [rad] (global), and velocity ``(vx_b, vy_b)`` [m/s] in its own frame and
    ``omega`` [rad/s]: ``m (dv_b/dt + omega x v_b) = R^T F``, ``I domega/dt = tau``.

    Joints are penalty elements ``F = -(k gap + c dgap/dt) dgap/dq`` (the forces of a potential and
    a Rayleigh dissipation, so energy is exact up to the dampers):

    - revolute at ``A_i`` (ground-cylinder) and ``B_i`` (rod-platform): the 2-vector between the
      two joint points, stiffness ``k_joint`` [N/m], damping ``c_joint`` [N s/m];
    - prismatic cylinder-rod: the rod's mass centre's distance from the cylinder's axis
      (``k_joint``, ``c_joint``) and the angle between rod and cylinder (``k_rot`` [N m/rad],
      ``c_rot`` [N m s/rad]).  The thesis gives every parasitic element 1e8 and 2000.

    The actuator force ``leg[i].f`` acts between the cylinder's joint point A and the rod's joint
    point B, along the line joining them, whose length is the output ``leg[i].s``; so ``f * v``
    is exactly the power it delivers.  A lumped actuator mass ``m_act`` adds
    ``m_act/2 * (ds/dt)**2`` of kinetic energy (a rank-one term of the mass matrix per leg,
    inverted by Sherman–Morrison since legs share no body) and ``b_act`` a damper on ``s``.

    Start: every body placed by the leg kinematics (:func:`models.kinematics.leg_motion`) at the
    start pose ``(x0, y0, phi0)`` with the velocities that the platform's start rates
    ``(vx0, vy0, omega0)`` impose on it (body frame), so every joint starts relaxed and unstretched.
    """
    ps = ParamSet()
    g = geometry_params(ps, config)
    m = inertia_params(ps, config)
    m_act, b_act = _actuator_params(ps)
    q0, qd0 = _start_pose(ps)
    k = ps.add("k_joint", 1e8, "N/m", "parasitic joint stiffness (revolute joints, prismatic transverse)", lower=0.0)
    c = ps.add("c_joint", 2000.0, "N.s/m", "parasitic joint damping (revolute joints, prismatic transverse)",
               lower=0.0)
    k_rot = ps.add("k_rot", 1e8, "N.m/rad", "parasitic stiffness keeping each rod aligned with its cylinder",
                   lower=0.0)
    c_rot = ps.add("c_rot", 2000.0, "N.m.s/rad", "parasitic damping keeping each rod aligned with its cylinder",
                   lower=0.0)
    e1, e2, m_cyl, I_cyl, m_rod, I_rod, m_p, I_p = (m[j] for j in range(8))

    bodies = [(f"cylinder[{i}]", m_cyl, I_cyl) for i in LEGS] + [(f"rod[{i}]", m_rod, I_rod) for i in LEGS] \
        + [("platform", m_p, I_p)]
    nb = len(bodies)
    xs = ca.SX.sym("xs", 6 * nb)
    st = [xs[6 * j:6 * j + 6] for j in range(nb)]
    pos = [s[0:2] for s in st]
    th = [s[2] for s in st]
    vb = [s[3:5] for s in st]
    om = [s[5] for s in st]
    R = [_rot(t) for t in th]
    qg = ca.vertcat(*[s[0:3] for s in st])  # generalized positions (global)
    qgd = ca.vertcat(*[ca.vertcat(R[j] @ vb[j], om[j]) for j in range(nb)])  # their rates
    cyl, rod, plat = (lambda i: i - 1), (lambda i: i + 2), 6

    def point(j, local):
        return pos[j] + R[j] @ local

    A = [ca.vertcat(g[2 * (i - 1)], g[2 * (i - 1) + 1]) for i in LEGS]
    b_local = joint_offsets(0.0, g)  # platform joints in the platform's frame
    Q = ca.SX.zeros(3 * nb)

    def penalty(gap, kk, cc):
        Jg = ca.jacobian(gap, qg)
        return -Jg.T @ (kk * gap + cc * (Jg @ qgd))

    f = ca.SX.sym("f", 3)
    lengths, rates = [], []
    for i in LEGS:
        Pc = point(cyl(i), ca.vertcat(e1, 0))  # joint A on the cylinder
        Pr = point(rod(i), ca.vertcat(e2, 0))  # joint B on the rod
        Pb = point(plat, b_local[i - 1])  # joint B on the platform
        axis_n = R[cyl(i)] @ ca.DM([0, 1])
        Q += penalty(Pc - A[i - 1], k, c)
        Q += penalty(Pb - Pr, k, c)
        Q += penalty(ca.dot(pos[rod(i)] - pos[cyl(i)], axis_n), k, c)
        Q += penalty(th[rod(i)] - th[cyl(i)], k_rot, c_rot)
        ell = ca.norm_2(Pr - Pc)
        grad = ca.gradient(ell, qg)
        ld = ca.dot(grad, qgd)
        Q += grad * (f[i - 1] - b_act[i - 1] * ld)
        lengths.append(ell)
        rates.append(ld)
    # accelerations in the global frame: block-diagonal mass matrix D plus, per leg, m_act grad grad^T
    dinv = ca.vertcat(*[ca.vertcat(1 / mass, 1 / mass, 1 / inertia) for _, mass, inertia in bodies])
    rhs = Q
    grads = []
    for i in LEGS:
        ell = lengths[i - 1]
        grad = ca.gradient(ell, qg)
        hess, _ = ca.hessian(ell, qg)
        conv = ca.dot(qgd, hess @ qgd)  # the part of d2(ell)/dt2 that is not grad . qdd
        rhs = rhs - m_act[i - 1] * conv * grad
        grads.append(grad)
    acc = dinv * rhs
    for i in LEGS:
        a = grads[i - 1]
        Da = dinv * a
        acc = acc - Da * (m_act[i - 1] * ca.dot(a, dinv * rhs)) / (1 + m_act[i - 1] * ca.dot(a, Da))
    ode = []
    for j in range(nb):
        aj = acc[3 * j:3 * j + 3]
        dvb = R[j].T @ aj[0:2] + om[j] * ca.vertcat(vb[j][1], -vb[j][0])
        ode += [R[j] @ vb[j], om[j], dvb, aj[2]]
    # start: bodies placed, and given the velocities of, the rigid mechanism's motion at the start
    # pose and rates (the leg kinematics of models.kinematics), so every joint starts relaxed
    mot = leg_motion(q0, qd0, ca.DM.zeros(3), g, e1, e2)
    start = []
    for body in range(nb):
        if body < 6:
            i = body % 3
            pc, vc = (mot.p_cyl, mot.v_cyl) if body < 3 else (mot.p_rod, mot.v_rod)
            start += [pc[:, i], mot.theta[i], _rot(mot.theta[i]).T @ vc[:, i], mot.w[i]]
        else:
            start += [q0, _rot(q0[2]).T @ qd0[0:2], qd0[2]]
    states = []
    for name, _, _ in bodies:
        states += [Var(f"body.{name}.x", "m", "mass centre x"), Var(f"body.{name}.y", "m", "mass centre y"),
                   Var(f"body.{name}.theta", "rad", "body angle"),
                   Var(f"body.{name}.vx_b", "m/s", "mass-centre velocity along the body's x axis"),
                   Var(f"body.{name}.vy_b", "m/s", "mass-centre velocity along the body's y axis"),
                   Var(f"body.{name}.omega", "rad/s", "angular rate")]
    out = ca.vertcat(pos[plat], th[plat], R[plat] @ vb[plat], om[plat], *lengths, *rates)
    solver_params(ps, integrator)
    return Block.build(
        "mechanism", description="3-RPR mechanism, seven bodies with parasitic spring-damper joints "
                                 "(thesis bond graph, Section 6.3)",
        params=ps.params, inputs=FORCE_INPUTS, outputs=POSE_OUTPUTS + LEG_OUTPUTS, states=states,
        p=ps.vector(), u=f, x=xs, ode=ca.vertcat(*ode), out=out, start=ca.vertcat(*start),
        integrator=integrator, substeps=substeps, flanges=list(FLANGES), fidelity="multibody",
        ratings=stroke_ratings(config))
