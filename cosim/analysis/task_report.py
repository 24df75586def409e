"""Reports of a planned task: its summary against the limits, its samples as CSV and the path
drawn over the workspace and det J maps with where the check fails (``rpr-cosim task``)."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from models import analysis as A
from models.motion_check import CheckResult
from models.task import Task
from models.trajectory import PiecewiseCubic, TrajectoryError, leg_profile, leg_ratios, peaks

from ..errors import UserError

from .design_views import Table
from ..outputs import staged
from .charts import save_figure
from .design_views import _figure
from .task_file import task_from_mapping


def summary_table(task: Task, traj: PiecewiseCubic) -> Table:
    """Duration and every peak against its limit (ratio 1 = saturated)."""
    lim = task.limits
    pk = peaks(task.manipulator, traj, lim)
    ratios = leg_ratios(pk, lim)
    rows = [["duration", "s", traj.duration, None, None],
            ["leg speed", "m/s", pk.leg_speed, lim.leg_speed, ratios["leg speed"]],
            ["leg acceleration", "m/s2", pk.leg_accel, lim.leg_accel, ratios["leg acceleration"]],
            [f"leg force ({lim.drive.name})", "N", pk.force, lim.drive.F_max, ratios["leg force"]],
            ["leg power", "W", pk.power, lim.drive.power, pk.power / lim.drive.power],
            ["drive voltage", "V", pk.voltage, lim.u_max, ratios["drive voltage"]]]
    for d, (name, unit) in enumerate((("x", "m"), ("y", "m"), ("phi", "rad"))):
        rows.append([f"pose rate {name}", f"{unit}/s", float(pk.pose_speed[d]), lim.pose_speed[d] if task.method == "ruckig" else None,
                     float(pk.pose_speed[d]) / lim.pose_speed[d] if task.method == "ruckig" else None])
    return Table(f"Planned task ({task.method}, {len(task.waypoints)} waypoints)",
                 ["quantity", "unit", "peak", "limit", "peak / limit"], rows)


def write_samples(task: Task, traj: PiecewiseCubic, path: Path, dt: float = 1e-3) -> Path:
    """The motion every ``dt`` [s]: time, pose, rates, accelerations, leg lengths, speeds, forces, voltages."""

    t = np.append(np.arange(traj.breaks[0], traj.breaks[-1], dt), traj.breaks[-1])
    q, qd, qdd = traj.evaluate(t)
    prof = leg_profile(task.manipulator, traj, t, task.limits)
    cols = ["time", "x", "y", "phi", "vx", "vy", "omega", "ax", "ay", "alpha"]
    cols += [f"leg[{i}].{k}" for k in ("s", "v", "a", "f", "u") for i in (1, 2, 3)]
    data = np.vstack([t, q, qd, qdd, prof["L"], prof["Ld"], prof["Ldd"], prof["F"], prof["u"]]).T
    with staged(path) as part, open(part, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        w.writerows([[repr(float(v)) for v in row] for row in data])
    return path


def save_check_plot(task: Task, traj: PiecewiseCubic, result: CheckResult, path: Path, grid: int = 300) -> Path:
    """The path over the det J map (and the workspace, blank outside) at the orientation where the
    check fails (else the start's), the singularity curves, the waypoints and the failure."""
    from matplotlib.collections import LineCollection


    m = task.manipulator
    refusal = result.refusal
    phi = refusal.pose[2] if refusal else float(task.waypoints[0][2])
    maps = A.dexterity_maps(m, A.thesis_grid(grid), phi)
    locus = A.singularity_locus(maps)
    fig = _figure(7.0, 5.8)
    ax = fig.add_subplot(1, 1, 1)
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad=(1.0, 1.0, 1.0, 0.0))
    data = np.ma.masked_invalid(maps.det)
    lim = float(np.max(np.abs(data))) if data.count() else 1.0
    ext = [100 * v for v in maps.grid.extent]
    im = ax.imshow(data, origin="lower", extent=ext, cmap=cmap, vmin=-lim, vmax=lim, interpolation="nearest")
    fig.colorbar(im, ax=ax, label=f"det J (cm) at phi = {phi:.4g} rad")
    if locus.segments.size:
        ax.add_collection(LineCollection(100 * locus.segments, colors="black", linewidths=1.0, label="det J = 0"))
    t = result.t
    q, _, _ = traj.evaluate(t)
    ax.plot(100 * q[0], 100 * q[1], color="green", lw=2, label="path")
    w = np.asarray(task.waypoints)
    ax.plot(100 * w[:, 0], 100 * w[:, 1], "ko", ms=4, label="waypoints")
    for v in result.violations[:5]:
        ax.plot(100 * v.pose[0], 100 * v.pose[1], "rx" if v is refusal else "m+", ms=10, mew=2)
    if refusal:
        ax.annotate(f"t = {refusal.t:.4f} s: {refusal.limit.split(':')[0]}", (100 * refusal.pose[0], 100 * refusal.pose[1]),
                    textcoords="offset points", xytext=(8, 8), fontsize=8, color="red")
    ax.set_title(("refused: " + refusal.limit if refusal else "the path passes every check")[:90], fontsize=9)
    ax.set_xlabel("X position (cm)")
    ax.set_ylabel("Y position (cm)")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=7)
    return save_figure(fig, path, dpi="figure")


def scene_motion_checks(scene) -> list[tuple[str, Task, PiecewiseCubic, CheckResult]]:
    """The motion check (:mod:`models.motion_check`) of every ``task_trajectory`` component of a
    scene, from its options (the task it plans): ``(component, task, motion, result)``."""

    out = []
    for name, comp in scene.components.items():
        if comp.model != "task_trajectory":
            continue
        task = task_from_mapping(comp.options, f"component {name!r}")
        try:
            traj = task.plan()
            out.append((name, task, traj, task.check(traj)))
        except TrajectoryError as exc:
            raise UserError(f"component {name!r}: {exc}") from None
    return out
