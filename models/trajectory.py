"""Platform trajectories through task-space waypoints, planned by toppra and ruckig.

A trajectory is a piecewise cubic in time, :class:`PiecewiseCubic`: on segment k, with
``tau = t - breaks[k]``, the pose ``q = (x, y, phi)`` [m, m, rad] is
``P_k + V_k tau + A_k tau^2 / 2 + J_k tau^3 / 6``.  Every planner's result has that form exactly:
ruckig's jerk-limited profiles are constant-jerk phases, toppra's time-optimal parametrisation
comes back as a cubic spline in time, and waypoints with given times are joined by a clamped
cubic spline.  The same coefficients serve numpy here and CasADi in the trajectory block
(:mod:`models.blocks.task`), so the FMU evaluates the planned motion itself, not a resampling.

Methods:

- ``"ruckig"``: one jerk-limited point-to-point move per pair of waypoints, stopping at each
  (ruckig's community version; never its cloud API), under per-coordinate limits of pose
  velocity, acceleration and jerk (``Limits.pose_speed``, ``pose_accel``, ``pose_jerk``);
- ``"toppra"``: a cubic spline path through the waypoints, time-scaled as fast as the limits in
  the legs' space allow: leg speed and acceleration through the inverse kinematics and its
  derivatives, and the drive's voltage through the virtual-work inverse dynamics (below);
- ``"spline"``: the waypoints at the given ``times``, joined by a clamped cubic spline (rest at
  both ends).

The drive (:class:`Drive`) is a straight force-speed line ``u = alpha F + beta v`` [V] per leg,
``|u| <= U``: for the Table 6.7 DC motor with its rack, quasi-static (the 0.44 ms electrical
time constant neglected) ``alpha = R rack / kt``, ``beta = kt / rack + R b / (kt rack)`` (back-EMF
and rotor friction); for the Firgelli FA-200, the datasheet's line.  toppra's constraints are
affine in ``(s_ddot, s_dot^2)``, which the back-EMF term ``beta v`` (linear in ``s_dot``) is
not, so the planner bounds it conservatively: ``|F| <= (u_max - beta v_max) / alpha`` with the
leg speed limit ``v_max``.  The exact voltage is then checked on the result, and the result is
slowed uniformly (``t -> k t``) by the smallest factor that brings every checked quantity within
its limit (velocities scale by ``1/k``, accelerations and the in-plane inverse dynamics, which
has no gravity term, by ``1/k^2``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

import casadi as ca
import numpy as np

from .drives import DRIVES, Drive
from .geometry import Manipulator
from .kinematics import NG, leg_motion, numpy_map
from .numeric import vectorize
from .virtual_work import NI, inverse_dynamics_fn

METHODS = ("ruckig", "toppra", "spline")


class TrajectoryError(ValueError):
    """A task that cannot be planned (the message names the field or the waypoint)."""


# --- limits ---------------------------------------------------------------------------------------
def _triple(name: str, v) -> tuple[float, float, float]:
    try:
        vals = (float(v),) * 3 if np.isscalar(v) else tuple(float(x) for x in v)
    except (TypeError, ValueError):
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(x) and 1e-6 <= x <= 1e6 for x in vals):
        raise TrajectoryError(f"limits.{name}: expected one number or three (x, y, phi) in 1e-6 .. 1e6, got {v!r}")
    return vals  # type: ignore[return-value]


@dataclass(frozen=True)
class Limits:
    """Limits of a motion.  Legs: ``leg_speed`` [m/s], ``leg_accel`` [m/s2]; the drive and the
    planning voltage ``u_max`` [V] (<= ``drive.U``, the rest left to the feedback loop);
    ``m_act`` [kg] the actuator mass lumped on each leg's extension.  Pose (ruckig):
    ``pose_speed`` [m/s, m/s, rad/s], ``pose_accel``, ``pose_jerk`` per coordinate."""

    leg_speed: float = 0.5
    leg_accel: float = 5.0
    drive: Drive = field(default_factory=lambda: DRIVES["table67"])
    u_max: float = 12.0
    m_act: float = 0.0
    pose_speed: tuple[float, float, float] = (0.1, 0.1, 0.5)
    pose_accel: tuple[float, float, float] = (1.0, 1.0, 5.0)
    pose_jerk: tuple[float, float, float] = (10.0, 10.0, 50.0)

    def planning_force(self) -> float:
        """Force bound [N] the planner uses: the drive's current limit, and the voltage left at
        full leg speed once the back-EMF is paid (the conservative bound of the module docstring)."""
        spare = (self.u_max - self.drive.beta * self.leg_speed) / self.drive.alpha
        if spare <= 0:
            raise TrajectoryError(f"limits: the back-EMF at leg_speed {self.leg_speed} m/s "
                                  f"({self.drive.beta * self.leg_speed:.3g} V) exceeds u_max {self.u_max} V")
        return min(self.drive.F_max, spare)


def limits_from(spec: dict | None) -> Limits:
    """:class:`Limits` from a mapping (a task file's or a scene's ``limits``); unknown keys and bad
    values raise :class:`TrajectoryError` naming the key."""
    spec = dict(spec or {})
    base = Limits()
    known = {f for f in Limits.__dataclass_fields__}
    bad = sorted(set(spec) - known)
    if bad:
        raise TrajectoryError(f"limits: unknown key {bad[0]!r} (expected one of {', '.join(sorted(known))})")
    out = {}
    for key, value in spec.items():
        if key == "drive":
            if not isinstance(value, str) or value not in DRIVES:
                raise TrajectoryError(f"limits.drive: {value!r} is not a drive (expected one of {', '.join(DRIVES)})")
            out[key] = DRIVES[value]
        elif key.startswith("pose_"):
            out[key] = _triple(key, value)
        else:
            try:
                x = float(value)
            except (TypeError, ValueError):
                x = math.nan
            if not (math.isfinite(x) and x <= 1e6 and (x >= 1e-6 or (key == "m_act" and x >= 0))):
                raise TrajectoryError(f"limits.{key}: expected a number in 1e-6 .. 1e6"
                                      + (" (or 0)" if key == "m_act" else "") + f", got {value!r}")
            out[key] = x
    lim = replace(base, **out)
    if lim.u_max > lim.drive.U:
        raise TrajectoryError(f"limits.u_max {lim.u_max} V exceeds the drive's rated {lim.drive.U} V")
    return lim


# --- the piecewise cubic ----------------------------------------------------------------------------
@dataclass(frozen=True)
class PiecewiseCubic:
    """Pose trajectory (module docstring): ``breaks`` (n+1,) [s] and per segment the pose ``P``,
    rate ``V``, acceleration ``A`` and jerk ``J`` at its start, each (n, 3).  Before ``breaks[0]``
    the start pose holds and after ``breaks[-1]`` the end pose (rates zero there by construction:
    every planner starts and ends at rest)."""

    breaks: np.ndarray
    P: np.ndarray
    V: np.ndarray
    A: np.ndarray
    J: np.ndarray
    waypoint_times: tuple[float, ...] = ()

    @property
    def duration(self) -> float:
        return float(self.breaks[-1] - self.breaks[0])

    @property
    def end(self) -> np.ndarray:
        """Pose at the end of the last segment."""
        return self.evaluate(np.array([self.breaks[-1]]))[0][:, 0]

    def evaluate(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pose, rate and acceleration at the times ``t`` (any shape): three arrays (3, *t.shape)."""
        t = np.asarray(t, dtype=float)
        flat = t.ravel()
        tc = np.clip(flat, self.breaks[0], self.breaks[-1])
        k = np.clip(np.searchsorted(self.breaks, tc, side="right") - 1, 0, len(self.P) - 1)
        tau = (tc - self.breaks[k])[:, None]
        P, V, A, J = self.P[k], self.V[k], self.A[k], self.J[k]
        q = P + tau * (V + tau * (A / 2 + tau * J / 6))
        qd = V + tau * (A + tau * J / 2)
        qdd = A + tau * J
        moving = ((flat >= self.breaks[0]) & (flat <= self.breaks[-1]))[:, None]
        qd, qdd = np.where(moving, qd, 0.0), np.where(moving, qdd, 0.0)
        shape = (3,) + t.shape
        return q.T.reshape(shape), qd.T.reshape(shape), qdd.T.reshape(shape)

    def scaled(self, k: float) -> "PiecewiseCubic":
        """The same path slowed uniformly: ``q_new(t) = q(t / k)``."""
        b0 = self.breaks[0]
        return PiecewiseCubic(b0 + k * (self.breaks - b0), self.P, self.V / k, self.A / k ** 2, self.J / k ** 3,
                              tuple(b0 + k * (w - b0) for w in self.waypoint_times))

    def shifted(self, t0: float) -> "PiecewiseCubic":
        """The same motion starting at ``t0`` [s]."""
        d = t0 - self.breaks[0]
        return replace(self, breaks=self.breaks + d, waypoint_times=tuple(w + d for w in self.waypoint_times))

    def table(self) -> np.ndarray:
        """One row per segment: ``t_k, P(3), V(3), A(3), J(3)`` (13 columns), the block's data."""
        return np.column_stack([self.breaks[:-1], self.P, self.V, self.A, self.J])


def from_ppoly(breaks: np.ndarray, c: np.ndarray, waypoint_times=()) -> PiecewiseCubic:
    """From scipy's ``PPoly`` coefficients ``c`` (4, n, 3), highest power first."""
    if c.shape[0] < 4:
        c = np.concatenate([np.zeros((4 - c.shape[0],) + c.shape[1:]), c])
    return PiecewiseCubic(np.asarray(breaks, float), c[3].copy(), c[2].copy(), 2 * c[1], 6 * c[0], tuple(waypoint_times))


# --- planners ----------------------------------------------------------------------------------------
def check_waypoints(waypoints) -> np.ndarray:
    """Waypoints as an (n, 3) array of finite poses, n >= 2 (error names the bad one)."""
    try:
        w = np.asarray(waypoints, dtype=float)
    except (TypeError, ValueError) as exc:
        raise TrajectoryError(f"waypoints: expected a list of [x, y, phi] poses ({exc})") from None
    if w.ndim != 2 or w.shape[1] != 3:
        raise TrajectoryError(f"waypoints: expected a list of [x, y, phi] poses, got shape {w.shape}")
    if len(w) < 2:
        raise TrajectoryError("waypoints: at least two poses are needed")
    bad = np.nonzero(~np.all(np.isfinite(w), axis=1))[0]
    if bad.size:
        raise TrajectoryError(f"waypoints[{bad[0]}]: not a finite pose: {w[bad[0]].tolist()}")
    far = np.nonzero(np.any(np.abs(w) > 100.0, axis=1))[0]
    if far.size:
        raise TrajectoryError(f"waypoints[{far[0]}]: {w[far[0]].tolist()} is not a pose of a planar robot "
                              "(expected metres and radians, |value| <= 100)")
    same = np.nonzero(np.all(np.diff(w, axis=0) == 0, axis=1))[0]
    if same.size:
        raise TrajectoryError(f"waypoints[{same[0] + 1}] repeats waypoints[{same[0]}]")
    return w


def plan_ruckig(waypoints, limits: Limits) -> PiecewiseCubic:
    """Jerk-limited point-to-point moves through the waypoints, at rest at each (module docstring)."""
    from ruckig import InputParameter, Result, Ruckig, Trajectory

    w = check_waypoints(waypoints)
    segs: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    t0, times = 0.0, [0.0]
    for k in range(len(w) - 1):
        inp = InputParameter(3)
        inp.current_position, inp.target_position = list(w[k]), list(w[k + 1])
        inp.current_velocity = inp.current_acceleration = [0.0] * 3
        inp.target_velocity = inp.target_acceleration = [0.0] * 3
        inp.max_velocity, inp.max_acceleration = list(limits.pose_speed), list(limits.pose_accel)
        inp.max_jerk = list(limits.pose_jerk)
        traj = Trajectory(3)
        result = Ruckig(3).calculate(inp, traj)
        if result not in (Result.Working, Result.Finished):
            raise TrajectoryError(f"waypoints[{k}] -> waypoints[{k + 1}]: ruckig found no motion ({result})")
        segs += _ruckig_segments(traj, t0)
        t0 += traj.duration
        times.append(t0)
    breaks = np.array([s[0] for s in segs] + [t0])
    return PiecewiseCubic(breaks, *(np.array([s[i] for s in segs]) for i in range(1, 5)), tuple(times))


def _ruckig_segments(traj, t0: float):
    """Constant-jerk segments of one ruckig trajectory on the union of its coordinates' phase times."""
    phases = []  # per coordinate: (start times, p, v, a, j) of its non-empty phases
    for prof in (traj.profiles[0][d] for d in range(3)):
        start, rows = 0.0, []
        for i in range(7):
            if prof.t[i] > 0:
                rows.append((start, prof.p[i], prof.v[i], prof.a[i], prof.j[i]))
            start += prof.t[i]
        phases.append(rows)
    cuts: list[float] = []
    for c in sorted({r[0] for rows in phases for r in rows} | {0.0}):
        if c < traj.duration - 1e-12 and (not cuts or c - cuts[-1] > 1e-12):  # one cut per instant
            cuts.append(c)
    out = []
    for c in cuts:
        P, V, A, J = (np.zeros(3) for _ in range(4))
        for d, rows in enumerate(phases):
            if rows:  # the phase holding c (merged cuts: a phase may start up to 1e-12 s after c)
                s, p, v, a, j = max((r for r in rows if r[0] <= c + 1e-12), key=lambda r: r[0])
            else:  # a coordinate that does not move
                s, p, v, a, j = 0.0, traj.at_time(0.0)[0][d], 0.0, 0.0, 0.0
            tau = c - s
            P[d] = p + tau * (v + tau * (a / 2 + tau * j / 6))
            V[d] = v + tau * (a + tau * j / 2)
            A[d] = a + tau * j
            J[d] = j
        out.append((t0 + c, P, V, A, J))
    return out


def plan_spline(waypoints, times) -> PiecewiseCubic:
    """Clamped cubic spline through the waypoints at the given strictly increasing ``times`` [s]."""
    from scipy.interpolate import CubicSpline

    w = check_waypoints(waypoints)
    try:
        t = np.asarray(times, dtype=float)
    except (TypeError, ValueError):
        raise TrajectoryError(f"times: expected {len(w)} times in s, one per waypoint, got {times!r}") from None
    if t.shape != (len(w),) or not np.all(np.isfinite(t)):
        raise TrajectoryError(f"times: expected {len(w)} finite times, one per waypoint, got {list(np.ravel(t))}")
    if np.any(np.diff(t) <= 0):
        k = int(np.nonzero(np.diff(t) <= 0)[0][0])
        raise TrajectoryError(f"times[{k + 1}] = {t[k + 1]} s is not after times[{k}] = {t[k]} s")
    cs = CubicSpline(t, w, bc_type="clamped", axis=0)
    return from_ppoly(cs.x, cs.c, tuple(t))


def path_parameter(w: np.ndarray, r: float) -> np.ndarray:
    """Path parameter at the waypoints: cumulative distance [m] with the orientation counted as
    the arc ``r dphi`` of the platform joints' circle (radius r)."""
    d = np.diff(w, axis=0) * np.array([1.0, 1.0, r])
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(d, axis=1))])


@lru_cache(maxsize=None)
def _leg_rates_np():
    return numpy_map("leg_motion")


@lru_cache(maxsize=None)
def leg_dynamics_fn() -> ca.Function:
    """``(q, qd, qdd, g, m, m_act) -> (L, Ld, Ldd, F)``: leg lengths, rates, accelerations and the
    forces of the motion (virtual-work inverse dynamics plus ``m_act Ldd``) in one function, its
    common subexpressions shared (one numpy replay evaluates all four)."""
    q, qd, qdd, g, mi, ma = (ca.SX.sym(n, k) for n, k in (("q", 3), ("qd", 3), ("qdd", 3), ("g", NG), ("m", NI),
                                                          ("m_act", 1)))
    mot = leg_motion(q, qd, qdd, g, mi[0], mi[1])
    F = inverse_dynamics_fn()(q, qd, qdd, g, mi) + ma * mot.Ldd
    return ca.Function("leg_dynamics", [q, qd, qdd, g, mi, ma], [mot.L, mot.Ld, mot.Ldd, F],
                       ["q", "qd", "qdd", "g", "m", "m_act"], ["L", "Ld", "Ldd", "F"], {"cse": True})


@lru_cache(maxsize=None)
def _leg_dynamics_np():
    return vectorize(leg_dynamics_fn())


def leg_dynamics(m: Manipulator, q, qd, qdd, m_act: float = 0.0) -> tuple[np.ndarray, ...]:
    """``L, Ld, Ldd, F`` (each (3, ...)) of :func:`leg_dynamics_fn` over poses (3, ...)."""
    L, Ld, Ldd, F = _leg_dynamics_np()(q, qd, qdd, m.geometry_vector(), m.inertia.vector(), [float(m_act)])
    return L, Ld, Ldd, F


def leg_state(m: Manipulator, q, qd, qdd) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leg lengths, rates and accelerations (3, ...) for poses and their derivatives (3, ...)."""
    out = _leg_rates_np()(q, qd, qdd, m.geometry_vector(), [m.inertia.e1, m.inertia.e2])
    return out[0], out[1], out[2]


def leg_forces(m: Manipulator, q, qd, qdd, m_act: float = 0.0) -> np.ndarray:
    """Leg forces [N] (3, ...) for the motion: virtual-work inverse dynamics plus ``m_act Ldd``."""
    return leg_dynamics(m, q, qd, qdd, m_act)[3]


def plan_toppra(m: Manipulator, waypoints, limits: Limits, gridpoints: int = 100) -> PiecewiseCubic:
    """Time-optimal motion along a cubic spline through the waypoints (module docstring)."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint

    w = check_waypoints(waypoints)
    ss = path_parameter(w, m.r)
    path = ta.SplineInterpolator(ss, w, bc_type="clamped")
    grid = np.unique(np.concatenate([np.linspace(0.0, ss[-1], gridpoints), ss]))
    F = limits.planning_force()
    _check_path(m, path, ss)
    cons = [leg_speed_constraint(m, limits.leg_speed), leg_dynamics_constraint(m, limits, F)]
    inst = algo.TOPPRA(cons, path, gridpoints=grid, parametrizer="ParametrizeSpline")
    traj = inst.compute_trajectory(0.0, 0.0)
    if traj is None:
        raise TrajectoryError("toppra found no feasible parametrisation: a waypoint or the path between them "
                              "needs more than the limits allow (check it with `rpr-cosim task check`)")
    cs = traj.cspl
    if len(cs.x) != len(grid):
        raise TrajectoryError(f"toppra returned {len(cs.x)} knots for {len(grid)} gridpoints")
    # the gridpoints include the waypoints' path parameters, and the spline's knots are their times
    wt = tuple(float(cs.x[int(np.searchsorted(grid, s))]) for s in ss)
    return from_ppoly(cs.x, cs.c, wt)


def _check_path(m: Manipulator, path, ss: np.ndarray, n: int = 2000) -> None:
    """Refuse a geometric path that leaves the stroke or crosses det J = 0: no timing makes it
    feasible (the forces grow without bound at a singularity), so toppra is not asked to."""
    s = np.linspace(0.0, ss[-1], n)
    q = path(s).T
    L = numpy_map("ik")(q, m.geometry_vector())[0]
    det = np.ravel(numpy_map("det")(q, m.geometry_vector())[0])
    bad = np.nonzero(np.any((L < m.Lmin) | (L > m.Lmax), axis=0) | (np.sign(det) != np.sign(det[0])))[0]
    if bad.size:
        k = int(bad[0])
        after = int(np.searchsorted(ss, s[k], side="right")) - 1
        what = "leaves the stroke" if np.any((L[:, k] < m.Lmin) | (L[:, k] > m.Lmax)) else "crosses det J = 0"
        raise TrajectoryError(f"the path through the waypoints {what} at pose ({q[0, k]:.6f}, {q[1, k]:.6f}, "
                              f"{q[2, k]:.6f}) after waypoints[{after}]: toppra cannot time it")


def leg_dynamics_constraint(m: Manipulator, limits: Limits, F_max: float):
    """toppra constraint on every leg's acceleration ``|Ldd| <= leg_accel`` and force
    ``|F| <= F_max``, both ``a(s) s_ddot + b(s) s_dot^2 + c(s)`` (toppra's second-order form),
    evaluated over all gridpoints at once (toppra's own class calls them point by point)."""
    # toppra is imported here, not with the module: only planning needs it
    from toppra.constraint import DiscretizationType, SecondOrderConstraint
    from toppra.constraint.linear_constraint import canlinear_colloc_to_interpolate

    def both(q, v, a):  # (6, n): leg accelerations, then forces
        _, _, Ldd, F = leg_dynamics(m, q, v, a, limits.m_act)
        return np.concatenate([Ldd, F])

    eye = np.vstack([np.eye(6), -np.eye(6)])
    bound = np.concatenate([[limits.leg_accel] * 3, [F_max] * 3] * 2)

    class _LegDynamics(SecondOrderConstraint):
        def compute_constraint_params(self, path, gridpoints):
            p, ps, pss = (path(gridpoints, k).T for k in (0, 1, 2))
            zero = np.zeros_like(p)
            c = both(p, zero, zero).T
            a = both(p, zero, ps).T - c
            b = both(p, ps, pss).T - c
            n = len(gridpoints)
            F, g = np.repeat(eye[None], n, axis=0), np.repeat(bound[None], n, axis=0)
            return canlinear_colloc_to_interpolate(a, b, c, F, g, None, None, gridpoints)

    return _LegDynamics(both, lambda _q: eye, lambda _q: bound, dof=3,
                        discretization_scheme=DiscretizationType.Interpolation)


def leg_speed_constraint(m: Manipulator, v_max: float):
    """toppra constraint ``|L_i'(s)| s_dot <= v_max`` on every leg: a bound on ``s_dot^2``."""
    # toppra is imported here, not with the module: only planning needs it
    from toppra.constraint import ConstraintType, DiscretizationType, LinearConstraint

    class _LegSpeed(LinearConstraint):
        def __init__(self):
            super().__init__()
            self.constraint_type = ConstraintType.CanonicalLinear
            self.discretization_type = DiscretizationType.Collocation
            self.identical = True
            self.dof = 3
            self._format_string = f"    Leg speed limit {v_max} m/s\n"

        def compute_constraint_params(self, path, gridpoints):
            q, qs = path(gridpoints).T, path(gridpoints, 1).T
            Ls = leg_state(m, q, qs, np.zeros_like(q))[1]
            peak = np.max(np.abs(Ls), axis=0)
            with np.errstate(divide="ignore"):
                xmax = np.where(peak > 0, (v_max / peak) ** 2, 1e12)
            xbound = np.column_stack([np.zeros_like(xmax), xmax])
            return None, None, None, None, None, None, xbound

    return _LegSpeed()


# --- the checked result -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Peaks:
    """Largest magnitudes along a trajectory: leg speed [m/s], acceleration [m/s2], force [N],
    power [W], drive voltage [V]; pose rate, acceleration and jerk per coordinate (3,)."""

    leg_speed: float
    leg_accel: float
    force: float
    power: float
    voltage: float
    pose_speed: np.ndarray
    pose_accel: np.ndarray
    pose_jerk: np.ndarray


def sample_times(traj: PiecewiseCubic, per_segment: int = 16, dt: float = 1e-3) -> np.ndarray:
    """Every break, ``per_segment`` points inside each segment, and a ``dt`` grid [s] (coarser
    for a motion longer than :data:`MAX_SAMPLES` ``dt``)."""
    dt = max(dt, traj.duration / MAX_SAMPLES)
    inner = (traj.breaks[:-1, None] + np.diff(traj.breaks)[:, None] * np.linspace(0, 1, per_segment + 1)[None, :])
    uniform = np.arange(traj.breaks[0], traj.breaks[-1], dt)
    return np.unique(np.concatenate([inner.ravel(), uniform, [traj.breaks[-1]]]))


def leg_profile(m: Manipulator, traj: PiecewiseCubic, t: np.ndarray, limits: Limits) -> dict[str, np.ndarray]:
    """Leg length, speed, acceleration, force, power and voltage (each (3, len t)) at times ``t``."""
    q, qd, qdd = traj.evaluate(t)
    L, Ld, Ldd, F = leg_dynamics(m, q, qd, qdd, limits.m_act)
    return {"L": L, "Ld": Ld, "Ldd": Ldd, "F": F, "P": F * Ld, "u": limits.drive.voltage(F, Ld)}


def _refined_peak(f, t: np.ndarray, values: np.ndarray, rounds: int = 4, points: int = 65) -> float:
    """The largest of ``values`` (sampled at ``t``) refined by zooming in on the best sample:
    each round evaluates ``f`` (vectorised over times) on ``points`` times between the best
    sample's neighbours, so the bracket shrinks by ``points / 2`` per round."""
    k = int(np.argmax(values))
    a, b, best = t[max(k - 1, 0)], t[min(k + 1, len(t) - 1)], float(values[k])
    for _ in range(rounds):
        if b <= a:
            break
        s = np.linspace(a, b, points)
        v = f(s)
        j = int(np.argmax(v))
        best = max(best, float(v[j]))
        a, b = s[max(j - 1, 0)], s[min(j + 1, points - 1)]
    return best


def peaks(m: Manipulator, traj: PiecewiseCubic, limits: Limits) -> Peaks:
    """:class:`Peaks` measured on the trajectory itself (dense samples, each peak refined)."""
    t = sample_times(traj)
    prof = leg_profile(m, traj, t, limits)
    def peak(key: str) -> float:
        vals = np.max(np.abs(prof[key]), axis=0)
        return _refined_peak(lambda s: np.max(np.abs(leg_profile(m, traj, s, limits)[key]), axis=0), t, vals)

    _, qd, qdd = traj.evaluate(t)
    # pose rate is quadratic and acceleration linear on a segment: their peaks are at breaks or
    # at a rate's stationary point tau = -A/J, added here exactly
    stat = []
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(traj.J != 0, -traj.A / traj.J, np.nan)
    seg = np.diff(traj.breaks)[:, None]
    ok = (tau > 0) & (tau < seg)
    for d in range(3):
        stat += list((traj.breaks[:-1] + np.where(ok[:, d], tau[:, d], 0.0)))
    _, qd_s, _ = traj.evaluate(np.array(stat))
    speed = np.maximum(np.max(np.abs(qd), axis=1), np.max(np.abs(qd_s), axis=1))
    return Peaks(peak("Ld"), peak("Ldd"), peak("F"), peak("P"), peak("u"), speed,
                 np.max(np.abs(qdd), axis=1), np.max(np.abs(traj.J), axis=0))


def leg_ratios(pk: Peaks, limits: Limits) -> dict[str, float]:
    """Each leg-space peak over its limit (the drive's voltage over ``u_max``)."""
    return {"leg speed": pk.leg_speed / limits.leg_speed, "leg acceleration": pk.leg_accel / limits.leg_accel,
            "leg force": pk.force / limits.drive.F_max, "drive voltage": pk.voltage / limits.u_max}


def fit_to_limits(m: Manipulator, traj: PiecewiseCubic, limits: Limits, margin: float = 1e-12,
                  max_rounds: int = 20) -> tuple[PiecewiseCubic, float]:
    """Slow ``traj`` uniformly until every leg-space peak is within its limit (module docstring);
    returns the result and the factor ``k >= 1`` applied."""
    k_total = 1.0
    for _ in range(max_rounds):
        if traj.duration > MAX_DURATION:
            break
        r = leg_ratios(peaks(m, traj, limits), limits)
        k = max(r["leg speed"], math.sqrt(r["leg acceleration"]), math.sqrt(r["leg force"]), r["drive voltage"] ** 0.5)
        if k <= 1.0:
            return traj, k_total
        k *= 1.0 + margin
        traj, k_total = traj.scaled(k), k_total * k
    raise TrajectoryError("the motion could not be brought within the limits by slowing it down")


def plan(m: Manipulator, waypoints, method: str = "ruckig", limits: Limits | None = None, times=None) -> PiecewiseCubic:
    """Plan a motion through ``waypoints`` (module docstring); toppra's result is slowed onto the
    limits exactly (:func:`fit_to_limits`)."""
    limits = limits or Limits()
    if method not in METHODS:
        raise TrajectoryError(f"method {method!r}: expected one of {', '.join(METHODS)}")
    if method == "spline" or times is not None:
        if times is None:
            raise TrajectoryError("method spline: give one time per waypoint (times: [...])")
        return _within_duration(plan_spline(waypoints, times))
    if method == "ruckig":
        traj = plan_ruckig(waypoints, limits)
    else:
        traj = fit_to_limits(m, _within_duration(plan_toppra(m, waypoints, limits)), limits)[0]
    return _within_duration(traj)


#: Most samples of a motion's uniform grid (memory: a few hundred bytes per sample).
MAX_SAMPLES = 1_000_000
#: Longest motion [s] a plan may take (a day: beyond it the limits are mistaken, and sampling it
#: every millisecond would not fit in memory).
MAX_DURATION = 86400.0


def _within_duration(traj: PiecewiseCubic) -> PiecewiseCubic:
    if not (math.isfinite(traj.duration) and traj.duration <= MAX_DURATION):
        raise TrajectoryError(f"the motion would last {traj.duration:.4g} s (at most {MAX_DURATION:g} s): "
                              "are the limits in m/s, m/s2 and V?")
    return traj
