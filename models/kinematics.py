"""3-RPR kinematics, written once in CasADi symbols (thesis.md §1–§3, thesis Chapters 4–5).

Symbolic inputs are ``q = (x, y, phi)`` [m, m, rad] and the flat geometry vector ``g`` (see
:data:`models.geometry.GEOMETRY_FIELDS`).  Every equation here is a CasADi expression; the
``*_fn`` functions wrap them as :class:`casadi.Function`, and :func:`numpy_map` replays them over
numpy grids (see :mod:`models.numeric`).

Vectors in the plane are 2-element columns; the scalar cross product ``a x b = a_x b_y - a_y b_x``
and ``w x b = w (-b_y, b_x)`` for an angular rate ``w`` about z.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from .geometry import Manipulator
from .numeric import NumpyFunction, vectorize

NG = 10  # length of the geometry vector


# --- the equations --------------------------------------------------------------------------
def fixed_joints(g):
    """A_i as a list of three 2-vectors."""
    return [ca.vertcat(g[2 * i], g[2 * i + 1]) for i in range(3)]


def joint_offsets(phi, g):
    """``b_i = B_i - C = -r (cos(phi + a_i), sin(phi + a_i))`` for i = 1..3."""
    r = g[6]
    return [-r * ca.vertcat(ca.cos(phi + g[7 + i]), ca.sin(phi + g[7 + i])) for i in range(3)]


def cross(a, b):
    """Scalar (z) cross product of two plane vectors."""
    return a[0] * b[1] - a[1] * b[0]


def perp(v, w=1.0):
    """``w x v``: the plane vector v turned by +90° and scaled by the z-rate w."""
    return w * ca.vertcat(-v[1], v[0])


def leg_vectors(q, g):
    """Leg vectors ``d_i = B_i - A_i`` [m]."""
    c = q[0:2]
    return [c + b - a for a, b in zip(fixed_joints(g), joint_offsets(q[2], g))]


def inverse_kinematics(q, g):
    """Leg lengths ``L`` [m] and leg angles ``theta`` [rad] (3-vectors)."""
    d = leg_vectors(q, g)
    L = ca.vertcat(*[ca.norm_2(v) for v in d])
    theta = ca.vertcat(*[ca.atan2(v[1], v[0]) for v in d])
    return L, theta


def inverse_jacobian(q, g):
    """``J`` with ``Ldot = J q_dot`` (eq. 4.14): row i = [cos th_i, sin th_i, r sin(phi + a_i - th_i)].

    Written as ``[s_i, b_i x s_i]`` with the unit leg vector ``s_i = d_i / L_i`` (the same numbers,
    since ``r sin(phi + a_i - th_i) = b_i x s_i``), which avoids an atan2 and a sin/cos per leg.
    """
    rows = []
    for b, d in zip(joint_offsets(q[2], g), leg_vectors(q, g)):
        s = d / ca.norm_2(d)
        rows.append(ca.horzcat(s[0], s[1], cross(b, s)))
    return ca.vertcat(*rows)


def dexterity(q, g, length_scale=1.0):
    """det J and the DSI ``(mu, mu_x, mu_y, mu_phi)``; ``length_scale`` converts the length unit of
    the rotational column (100 for the centimetre maps of Chapter 4)."""
    J = inverse_jacobian(q, g)
    J = ca.horzcat(J[:, 0:2], length_scale * J[:, 2])
    det = ca.det(J)
    cols = [ca.norm_2(J[:, k]) for k in range(3)]
    return det, ca.vertcat(ca.fabs(det), *cols)


@dataclass
class LegMotion:
    """Chapter 5 leg kinematics (all 3-vectors or 2x3 matrices, columns per leg).

    ``L, Ld, Ldd``: length [m], rate [m/s], acceleration [m/s²];
    ``theta, w, alpha``: leg angle [rad], angular rate [rad/s], angular acceleration [rad/s²];
    ``p_cyl, v_cyl, a_cyl`` / ``p_rod, v_rod, a_rod``: mass-centre position, velocity and
    acceleration of the cylinder (at ``A_i - e1 s_i``) and the rod (at ``A_i + (L_i - e2) s_i``);
    ``v_p, a_p``: platform centre velocity and acceleration; ``w_p, alpha_p``: platform rates.
    """

    L: ca.SX
    Ld: ca.SX
    Ldd: ca.SX
    theta: ca.SX
    w: ca.SX
    alpha: ca.SX
    p_cyl: ca.SX
    v_cyl: ca.SX
    a_cyl: ca.SX
    p_rod: ca.SX
    v_rod: ca.SX
    a_rod: ca.SX


def leg_motion(q, qd, qdd, g, e1=0.3, e2=0.3) -> LegMotion:
    """Velocity and acceleration kinematics by the matrix approach of Chapter 5 (thesis.md §3)."""
    wp, alp = qd[2], qdd[2]
    vp, ap = qd[0:2], qdd[0:2]
    A = fixed_joints(g)
    b = joint_offsets(q[2], g)
    out = {k: [] for k in ("L", "Ld", "Ldd", "theta", "w", "alpha", "p_cyl", "v_cyl", "a_cyl",
                           "p_rod", "v_rod", "a_rod")}
    for i in range(3):
        d = q[0:2] + b[i] - A[i]
        L = ca.norm_2(d)
        s = d / L
        vB = vp + perp(b[i], wp)
        aB = ap + perp(b[i], alp) + perp(perp(b[i], wp), wp)
        Ld = ca.dot(s, vB)
        w = cross(s, vB) / L
        Ldd = ca.dot(s, aB) + L * w ** 2
        alpha = (cross(s, aB) - 2 * Ld * w) / L
        n = perp(s)  # unit normal of the leg
        out["L"].append(L)
        out["Ld"].append(Ld)
        out["Ldd"].append(Ldd)
        out["theta"].append(ca.atan2(d[1], d[0]))
        out["w"].append(w)
        out["alpha"].append(alpha)
        out["p_cyl"].append(A[i] - e1 * s)
        out["v_cyl"].append(-e1 * w * n)
        out["a_cyl"].append(-e1 * (alpha * n - w ** 2 * s))
        out["p_rod"].append(A[i] + (L - e2) * s)
        out["v_rod"].append(Ld * s + (L - e2) * w * n)
        out["a_rod"].append(Ldd * s + 2 * Ld * w * n + (L - e2) * (alpha * n - w ** 2 * s))
    return LegMotion(**{k: (ca.vertcat(*v) if k in ("L", "Ld", "Ldd", "theta", "w", "alpha")
                            else ca.horzcat(*v)) for k, v in out.items()})


def forward_kinematics_polynomial(phi, L, g):
    """Residual ``f(phi)`` whose real roots are the assembly modes for leg lengths ``L``.

    With ``P_i(phi) = A_i - b_i(phi)`` every mode satisfies ``|C - P_i|² = L_i²``.  Subtracting
    the first circle from the others gives ``M(phi) C = rhs(phi)``; with ``C = adj(M) rhs / det M``
    the first circle becomes ``|adj(M) rhs - det(M) P_1|² - det(M)² L_1² = 0``, a trigonometric
    polynomial in ``phi``.  Returns that residual and ``(adj(M) rhs, det M)``.
    """
    P = [a - b for a, b in zip(fixed_joints(g), joint_offsets(phi, g))]
    rows = [2 * (P[i] - P[0]) for i in (1, 2)]
    rhs = [ca.sumsqr(P[i]) - ca.sumsqr(P[0]) - L[i] ** 2 + L[0] ** 2 for i in (1, 2)]
    det = rows[0][0] * rows[1][1] - rows[0][1] * rows[1][0]
    num = ca.vertcat(rows[1][1] * rhs[0] - rows[0][1] * rhs[1], -rows[1][0] * rhs[0] + rows[0][0] * rhs[1])
    return ca.sumsqr(num - det * P[0]) - det ** 2 * L[0] ** 2, num, det


# --- CasADi functions (built once) ------------------------------------------------------------
def _sym(name, n):
    return ca.SX.sym(name, n)


@lru_cache(maxsize=None)
def ik_fn() -> ca.Function:
    """``(q, g) -> (L, theta)``."""
    q, g = _sym("q", 3), _sym("g", NG)
    L, th = inverse_kinematics(q, g)
    return ca.Function("ik", [q, g], [L, th], ["q", "g"], ["L", "theta"])


@lru_cache(maxsize=None)
def jacobian_fn() -> ca.Function:
    """``(q, g) -> J`` (3x3)."""
    q, g = _sym("q", 3), _sym("g", NG)
    return ca.Function("inverse_jacobian", [q, g], [inverse_jacobian(q, g)], ["q", "g"], ["J"])


@lru_cache(maxsize=None)
def dexterity_fn(length_scale: float = 1.0) -> ca.Function:
    """``(q, g) -> (detJ, dsi)`` with ``dsi = (mu, mu_x, mu_y, mu_phi)``."""
    q, g = _sym("q", 3), _sym("g", NG)
    det, dsi = dexterity(q, g, length_scale)
    L, _ = inverse_kinematics(q, g)
    return ca.Function("dexterity", [q, g], [det, dsi, L], ["q", "g"], ["detJ", "dsi", "L"])


@lru_cache(maxsize=None)
def det_fn() -> ca.Function:
    """``(q, g) -> detJ`` [m]: the determinant of :func:`dexterity` alone (SI units), cheaper to
    evaluate along a trajectory than the whole DSI."""
    q, g = _sym("q", 3), _sym("g", NG)
    return ca.Function("det_j", [q, g], [dexterity(q, g)[0]], ["q", "g"], ["detJ"])


@lru_cache(maxsize=None)
def leg_motion_fn() -> ca.Function:
    """``(q, qd, qdd, g, e) -> Chapter 5 quantities`` with ``e = (e1, e2)``; names as in :class:`LegMotion`."""
    q, qd, qdd, g, e = _sym("q", 3), _sym("qd", 3), _sym("qdd", 3), _sym("g", NG), _sym("e", 2)
    m = leg_motion(q, qd, qdd, g, e[0], e[1])
    names = list(LegMotion.__dataclass_fields__)
    return ca.Function("leg_motion", [q, qd, qdd, g, e], [getattr(m, k) for k in names],
                       ["q", "qd", "qdd", "g", "e"], names)


@lru_cache(maxsize=None)
def fk_polynomial_fn() -> ca.Function:
    """``(phi, L, g) -> (f, num, det)`` of :func:`forward_kinematics_polynomial`."""
    phi, L, g = _sym("phi", 1), _sym("L", 3), _sym("g", NG)
    f, num, det = forward_kinematics_polynomial(phi, L, g)
    return ca.Function("fk_poly", [phi, L, g], [f, num, det], ["phi", "L", "g"], ["f", "num", "det"])


@lru_cache(maxsize=None)
def numpy_map(name: str, length_scale: float = 1.0) -> NumpyFunction:
    """Numpy replay of one of the functions above: ``"ik"``, ``"jacobian"``, ``"dexterity"``,
    ``"det"``, ``"leg_motion"``, ``"fk_polynomial"``."""
    builders = {"ik": ik_fn, "jacobian": jacobian_fn, "leg_motion": leg_motion_fn, "det": det_fn,
                "fk_polynomial": fk_polynomial_fn, "dexterity": lambda: dexterity_fn(length_scale)}
    if name not in builders:
        raise KeyError(f"unknown kinematic map {name!r}; expected one of {', '.join(builders)}")
    return vectorize(builders[name]())


# --- numeric convenience (numpy in, numpy out) ---------------------------------------------------
def ik(m: Manipulator, q) -> tuple[np.ndarray, np.ndarray]:
    """Leg lengths and angles for pose(s) ``q`` of shape (3,) or (3, ...)."""
    q = np.asarray(q, dtype=float)
    L, th = numpy_map("ik")(q, _g(m, q))
    return L, th


def jacobian(m: Manipulator, q) -> np.ndarray:
    """Inverse Jacobian ``J`` (3x3) at a single pose."""
    return np.array(jacobian_fn()(np.asarray(q, float), m.geometry_vector()))


def _g(m: Manipulator, q: np.ndarray) -> np.ndarray:
    g = m.geometry_vector()
    return g.reshape((NG,) + (1,) * (q.ndim - 1))


def forward_kinematics(m: Manipulator, L, *, within_stroke: bool = True, tol: float = 1e-10) -> np.ndarray:
    """All real assembly modes ``(x, y, phi)`` for leg lengths ``L`` [m], shape (n, 3), n <= 6.

    The residual of :func:`forward_kinematics_polynomial` is a trigonometric polynomial in phi;
    it is sampled at 64 angles, turned into Fourier coefficients by an FFT and solved as a
    polynomial in ``z = exp(i phi)`` (companion matrix), so no mode is missed.  Each root is then
    polished by Newton's method on the three loop equations.  With ``within_stroke`` only modes
    whose legs lie in ``[Lmin, Lmax]`` are kept (they do by construction, since L is given; the
    check rejects ``L`` outside the stroke).
    """
    L = np.asarray(L, dtype=float).reshape(3)
    if within_stroke and (np.any(L < m.Lmin - 1e-12) or np.any(L > m.Lmax + 1e-12)):
        return np.zeros((0, 3))
    g = m.geometry_vector()
    n = 64
    phis = 2 * np.pi * np.arange(n) / n
    f, _, _ = numpy_map("fk_polynomial")(phis[None, :], L[:, None], g[:, None])
    c = np.fft.fft(f[0]) / n  # f(phi) = sum_k c_k e^{i k phi}
    K = n // 2 - 1
    coef = np.concatenate([c[-K:], c[:K + 1]])  # k = -K..K
    scale = np.max(np.abs(coef))
    if scale == 0:
        raise ValueError(f"{m.name}: forward kinematics is degenerate for L={L.tolist()}")
    keep = np.nonzero(np.abs(coef) > 1e-11 * scale)[0]
    coef = coef[keep[0]:keep[-1] + 1]
    roots = np.roots(coef[::-1])  # highest power first
    cands = [float(np.angle(z)) for z in roots if abs(abs(z) - 1.0) < 1e-3]
    sols: list[np.ndarray] = []
    for phi in cands:
        q = _pose_from_phi(m, L, phi)
        if q is None:
            continue
        q = _newton_polish(m, L, q)
        if q is None:
            continue
        if any(np.allclose(q[:2], s[:2], atol=1e-8) and abs(_wrap(q[2] - s[2])) < 1e-8 for s in sols):
            continue
        sols.append(q)
    return np.array(sorted(sols, key=lambda s: s[2])) if sols else np.zeros((0, 3))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _pose_from_phi(m: Manipulator, L: np.ndarray, phi: float):
    _, num, det = fk_polynomial_fn()(phi, L, m.geometry_vector())
    det = float(det)
    if abs(det) < 1e-14:
        return None
    c = np.array(num).ravel() / det
    return np.array([c[0], c[1], _wrap(phi)])


def _newton_polish(m: Manipulator, L: np.ndarray, q: np.ndarray, iters: int = 20):
    g = m.geometry_vector()
    for _ in range(iters):
        Lq, _ = ik_fn()(q, g)
        res = np.array(Lq).ravel() - L
        if np.max(np.abs(res)) < 1e-13:
            break
        J = np.array(jacobian_fn()(q, g))
        try:
            q = q - np.linalg.solve(J, res)
        except np.linalg.LinAlgError:
            return None
    Lq, _ = ik_fn()(q, g)
    if np.max(np.abs(np.array(Lq).ravel() - L)) > 1e-9:
        return None
    q[2] = _wrap(q[2])
    return q
