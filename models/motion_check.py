"""A motion checked before it runs: workspace, stroke, singularity, dexterity and actuator limits.

The motion is any vectorised function ``motion(t) -> (q, qd, qdd)`` (each (3, len t); pose
``(x, y, phi)`` [m, m, rad] and its time derivatives), e.g. :meth:`PiecewiseCubic.evaluate`.  It
is sampled on a uniform grid (``dt``, default 1 ms); every checked quantity is written as a
margin ``g(t) >= 0`` and the first sample where a margin turns negative brackets the crossing,
which is then located by vectorised multisection (each round evaluates 256 times in the bracket
at once, only the margin's group: kinematic or dynamic) to :data:`TIME_TOL`.

Checked, per leg where it applies:

- stroke: ``L - Lmin >= 0`` and ``Lmax - L >= 0`` (the workspace at the pose's orientation);
- singularity: ``det J`` keeps the sign it has at the start; a change of sign is a crossing of
  ``det J = 0`` and, since det J changes sign exactly where two assembly modes meet, the start of
  another assembly mode: the path is refused there whatever the other margins say;
- dexterity: ``|det J| >= margins.det`` and the DSI column norms ``mu_x, mu_y >= margins.dsi``,
  ``mu_phi >= margins.dsi_phi`` (thesis units: det J, mu_phi in cm, length scale 100);
- the actuators, through the virtual-work inverse dynamics plus the lumped ``m_act Ldd``: leg
  speed, acceleration, force, power ``|F Ld|`` against the drive's line power, and the drive's
  voltage ``alpha F + beta Ld`` against ``u_max``.

The result's one-line refusal names the time, the pose and the limit.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .analysis import THESIS_LENGTH_SCALE
from .geometry import Manipulator
from .kinematics import numpy_map
from .trajectory import MAX_SAMPLES, Limits, TrajectoryError, leg_dynamics

#: Tolerance [s] to which a crossing's time is located.
TIME_TOL = 1e-12
Motion = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Margins:
    """Smallest acceptable dexterity along a motion (thesis units, length scale 100):
    ``det`` = |det J| [cm], ``dsi`` = mu_x, mu_y [-], ``dsi_phi`` = mu_phi [cm]."""

    det: float = 1.0
    dsi: float = 0.1
    dsi_phi: float = 1.0


@dataclass(frozen=True)
class Violation:
    """The first time ``t`` [s] a limit is broken, the pose there, and what was broken."""

    t: float
    pose: tuple[float, float, float]
    limit: str
    detail: str

    def line(self) -> str:
        """The one-line refusal."""
        x, y, phi = self.pose
        return (f"refused at t = {self.t:.9f} s, pose (x, y, phi) = ({x:.6f} m, {y:.6f} m, {phi:.6f} rad): "
                f"{self.limit} ({self.detail})")


@dataclass
class CheckResult:
    """Every limit's first violation (``violations``, by time), the sampled times and margins
    (``t``; ``margins[name]`` is ``g(t)`` per sample, min over legs) and the start's assembly
    mode sign (``det_sign``)."""

    t: np.ndarray
    margins: dict[str, np.ndarray]
    violations: list[Violation] = field(default_factory=list)
    det_sign: float = 1.0

    @property
    def ok(self) -> bool:
        return not self.violations

    @property
    def refusal(self) -> Violation | None:
        """The violation that refuses the motion: a singularity crossing when there is one,
        else the earliest violation."""
        if not self.violations:
            return None
        crossing = [v for v in self.violations if v.limit.startswith("det J = 0")]
        return crossing[0] if crossing else self.violations[0]


# --- the margins ---------------------------------------------------------------------------------
def _margin_functions(m: Manipulator, limits: Limits, margins: Margins, motion: Motion, det_sign: float):
    """``names`` and two functions ``g(t) -> (rows, len t)``: the kinematic margins (stroke, det J,
    DSI: cheap) and the dynamic ones (leg speed, acceleration, force, power, voltage), so that a
    root search evaluates only the group of the margin it locates."""
    geo = m.geometry_vector()
    dex = numpy_map("dexterity", THESIS_LENGTH_SCALE)
    kin_names = ([f"leg {i} stroke min" for i in (1, 2, 3)] + [f"leg {i} stroke max" for i in (1, 2, 3)]
                 + ["det J = 0", "|det J| margin", "mu_x margin", "mu_y margin", "mu_phi margin"])
    dyn_names = [f"leg {i} {what}" for what in ("speed", "acceleration", "force", "power", "drive voltage")
                 for i in (1, 2, 3)]
    drive = limits.drive

    def stack(rows, n):
        return np.concatenate([np.broadcast_to(np.asarray(r, float), (len(r), n)) for r in rows])

    def g_kin(t: np.ndarray) -> np.ndarray:
        q, _, _ = motion(t)
        det, dsi, L = dex(q, geo)
        det = np.broadcast_to(det[0], t.shape)
        return stack([L - m.Lmin, m.Lmax - L, [det_sign * det], [np.abs(det) - margins.det],
                      [dsi[1] - margins.dsi], [dsi[2] - margins.dsi], [dsi[3] - margins.dsi_phi]], t.size)

    def g_dyn(t: np.ndarray) -> np.ndarray:
        q, qd, qdd = motion(t)
        _, Ld, Ldd, F = leg_dynamics(m, q, qd, qdd, limits.m_act)
        u = drive.voltage(F, Ld)
        return stack([limits.leg_speed - np.abs(Ld), limits.leg_accel - np.abs(Ldd), drive.F_max - np.abs(F),
                      drive.power - np.abs(F * Ld), limits.u_max - np.abs(u)], t.size)

    return [(kin_names, g_kin), (dyn_names, g_dyn)]


def _limit_text(name: str, m: Manipulator, limits: Limits, margins: Margins) -> str:
    if "stroke min" in name:
        return f"{name}: L >= Lmin = {m.Lmin} m"
    if "stroke max" in name:
        return f"{name}: L <= Lmax = {m.Lmax} m"
    if name == "|det J| margin":
        return f"|det J| >= {margins.det} cm"
    if name in ("mu_x margin", "mu_y margin"):
        return f"{name.split()[0]} >= {margins.dsi}"
    if name == "mu_phi margin":
        return f"mu_phi >= {margins.dsi_phi} cm"
    bounds = {"speed": f"{limits.leg_speed} m/s", "acceleration": f"{limits.leg_accel} m/s2",
              "force": f"{limits.drive.F_max:.4g} N ({limits.drive.name})",
              "power": f"{limits.drive.power:.4g} W ({limits.drive.name})",
              "drive voltage": f"{limits.u_max} V ({limits.drive.name})"}
    what = name.split(" ", 2)[2]
    return f"{name} within {bounds[what]}"


# --- root finding --------------------------------------------------------------------------------------
def locate(g_row: Callable[[np.ndarray], np.ndarray], a: float, b: float, tol: float = TIME_TOL,
           points: int = 256) -> float:
    """The first time in ``[a, b]`` where ``g_row`` turns negative, given ``g_row(a) >= 0 > g_row(b)``:
    vectorised multisection down to ``tol``, then one secant step inside the last bracket."""
    ends = g_row(np.array([a, b]))
    ga, gb = float(ends[0]), float(ends[1])
    while b - a > tol:
        s = np.linspace(a, b, points)
        v = g_row(s)
        k = int(np.argmax(v < 0))
        if k == 0 or not v[k] < 0:  # no sign change seen (round-off): keep the bracket's right end
            break
        a, b, ga, gb = s[k - 1], s[k], float(v[k - 1]), float(v[k])
    if ga > 0 > gb:
        return float(a + (b - a) * ga / (ga - gb))
    return float(b if ga > 0 else a)


# --- the check -----------------------------------------------------------------------------------------
def check_motion(m: Manipulator, motion: Motion, t0: float, t1: float, limits: Limits,
                 margins: Margins = Margins(), dt: float = 1e-3) -> CheckResult:
    """Check ``motion`` over ``[t0, t1]`` [s] (module docstring)."""
    n = max(int(np.ceil((t1 - t0) / dt)), 1)
    if n > MAX_SAMPLES:
        raise TrajectoryError(f"checking {t1 - t0:.6g} s every {dt:g} s takes {n} samples (at most {MAX_SAMPLES}): "
                              f"sample every {(t1 - t0) / MAX_SAMPLES:.3g} s or more")
    t = t0 + (t1 - t0) * np.arange(n + 1) / n
    q0 = motion(np.array([t0]))[0]
    det0 = numpy_map("det")(q0, m.geometry_vector())[0]
    det_sign = 1.0 if float(np.ravel(det0)[0]) >= 0 else -1.0
    per_name = {}
    violations = []
    for names, g in _margin_functions(m, limits, margins, motion, det_sign):
        G = g(t)
        for k, name in enumerate(names):
            per_name[name] = G[k]
            bad = np.nonzero(G[k] < 0)[0]
            if not bad.size:
                continue
            j = int(bad[0])
            tc = float(t[0]) if j == 0 else locate(lambda s, k=k, g=g: g(s)[k], float(t[j - 1]), float(t[j]))
            q = motion(np.array([tc]))[0][:, 0]
            limit = _limit_text(name, m, limits, margins) if name != "det J = 0" else _crossing_text(G[k], j)
            violations.append(Violation(tc, (float(q[0]), float(q[1]), float(q[2])), limit,
                                        "at the start" if j == 0 else "located by root finding"))
    violations.sort(key=lambda v: v.t)
    return CheckResult(t, per_name, violations, det_sign)


def _crossing_text(row: np.ndarray, j: int) -> str:
    """det J = 0: a crossing that stays on the other side needs another assembly mode."""
    if row[-1] < 0:
        return "det J = 0: the path crosses a singularity into another assembly mode than its start's"
    return "det J = 0: the path crosses a singularity (and returns: the assembly mode is not kept)"
