"""A task for the robot: waypoints, how to time them, the limits and the margins of its check.

The same mapping describes a task in a task file (``rpr-cosim task``, ``rpr-cosim design``) and
a ``task_trajectory`` component's options in a scene::

    config: cross_leg                 # the design (models.geometry presets)
    method: ruckig                    # ruckig | toppra | spline (spline needs times)
    waypoints: [[-0.15, -0.15, 0.0], [-0.20, -0.12, 0.1], ...]   # (x [m], y [m], phi [rad])
    times: [0, 1, 2.5, ...]           # optional: one per waypoint, then method spline
    limits: {leg_speed: 0.3, leg_accel: 3, drive: table67, u_max: 10, m_act: 0.058,
             pose_speed: [0.1, 0.1, 0.5], pose_accel: [1, 1, 5], pose_jerk: [10, 10, 50]}
    margins: {det: 1.0, dsi: 0.1, dsi_phi: 1.0}
    start: 0.0                        # delay [s] before the motion (spline: added to its times)

Reading a CSV of waypoints is the caller's (a file belongs to cosim/); here ``waypoints`` is
already a list.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .geometry import GeometryError, Manipulator, preset
from .motion_check import CheckResult, Margins, check_motion
from .trajectory import METHODS, Limits, PiecewiseCubic, TrajectoryError, check_waypoints, limits_from, plan

KEYS = ("config", "method", "waypoints", "times", "limits", "margins", "start")


@dataclass(frozen=True)
class Task:
    """A parsed task (module docstring)."""

    manipulator: Manipulator
    waypoints: np.ndarray
    method: str = "ruckig"
    times: tuple[float, ...] | None = None
    limits: Limits = field(default_factory=Limits)
    margins: Margins = field(default_factory=Margins)
    start: float = 0.0

    def plan(self) -> PiecewiseCubic:
        """The planned motion, starting at ``start``."""
        traj = plan(self.manipulator, self.waypoints, self.method, self.limits, self.times)
        return traj.shifted(float(traj.breaks[0]) + self.start)

    def check(self, traj: PiecewiseCubic | None = None, dt: float = 1e-3) -> CheckResult:
        """:func:`models.motion_check.check_motion` over the planned motion."""
        traj = traj or self.plan()
        return check_motion(self.manipulator, traj.evaluate, float(traj.breaks[0]), float(traj.breaks[-1]),
                            self.limits, self.margins, dt)


def _margins(spec: Any) -> Margins:
    if spec is None:
        return Margins()
    if not isinstance(spec, dict):
        raise TrajectoryError(f"margins: expected a mapping of det, dsi, dsi_phi, got {spec!r}")
    bad = sorted(set(spec) - set(Margins.__dataclass_fields__))
    if bad:
        raise TrajectoryError(f"margins: unknown key {bad[0]!r} (expected det, dsi, dsi_phi)")
    out = {}
    for k, v in spec.items():
        try:
            x = float(v)
        except (TypeError, ValueError):
            x = math.nan
        if not (math.isfinite(x) and x >= 0):
            raise TrajectoryError(f"margins.{k}: expected a number >= 0, got {v!r}")
        out[k] = x
    return Margins(**out)


def task_from(spec: dict, config: str | None = None) -> Task:
    """A :class:`Task` from its mapping; every mistake raises :class:`TrajectoryError` naming the key."""
    if not isinstance(spec, dict):
        raise TrajectoryError(f"a task is a mapping of {', '.join(KEYS)}, got {type(spec).__name__}")
    bad = sorted(set(spec) - set(KEYS))
    if bad:
        raise TrajectoryError(f"unknown key {bad[0]!r} (expected one of {', '.join(KEYS)})")
    name = spec.get("config", config or "cross_leg")
    try:
        m = preset(str(name))
    except GeometryError as exc:
        raise TrajectoryError(f"config: {exc}") from None
    if "waypoints" not in spec:
        raise TrajectoryError("waypoints: missing (a list of [x, y, phi] poses)")
    w = check_waypoints(spec["waypoints"])
    times = spec.get("times")
    method = spec.get("method", "spline" if times is not None else "ruckig")
    if method not in METHODS:
        raise TrajectoryError(f"method {method!r}: expected one of {', '.join(METHODS)}")
    if times is not None and method != "spline":
        raise TrajectoryError(f"times: given with method {method}, which times the waypoints itself; "
                              "use method spline or drop the times")
    if method == "spline" and times is None:
        raise TrajectoryError("method spline: give one time per waypoint (times: [...])")
    start = spec.get("start", 0.0)
    if not isinstance(start, (int, float)) or not math.isfinite(start):
        raise TrajectoryError(f"start: expected a time in s, got {start!r}")
    return Task(m, w, method, tuple(float(t) for t in times) if times is not None else None,
                limits_from(spec.get("limits")), _margins(spec.get("margins")), float(start))
