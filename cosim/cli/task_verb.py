"""``rpr-cosim task``: plan a task (waypoints, limits) and check it before it runs.

    rpr-cosim task check TASK.yaml [--plot] [--out DIR] [--dt S]
    rpr-cosim task plan  TASK.yaml [--out DIR] [--dt S]

``check`` plans the motion, prints its peaks against the limits, and checks it (workspace,
stroke, det J and DSI margins, one assembly mode, leg speed, acceleration, force, power and drive
voltage, :mod:`models.motion_check`): it exits 0 when it passes and 1 with a one-line refusal
naming the time, the pose and the limit when it does not; ``--plot`` draws the path over the
workspace and det J maps.  ``plan`` writes the motion's samples (pose, rates, accelerations, leg
lengths, speeds, forces, voltages) to ``DIR/<task>.csv``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import UserError
from models.trajectory import TrajectoryError
from ..analysis.design_views import format_table
from ..analysis.task_file import load_task
from ..analysis.task_report import save_check_plot, summary_table, write_samples


def _dt(text: str) -> float:
    try:
        dt = float(text)
    except ValueError:
        dt = float("nan")
    if not (dt > 0 and dt < 10):
        raise UserError(f"--dt {text!r}: expected a sampling period in s, e.g. 1e-3")
    return dt


def _out(args) -> Path:
    out = args.out or Path("out/task")
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {str(out)!r}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    return out


def _check(args: argparse.Namespace) -> int:


    dt = _dt(args.dt)
    task = load_task(args.task)
    try:
        traj = task.plan()
        result = task.check(traj, dt)
    except TrajectoryError as exc:
        raise UserError(f"{args.task}: {exc}") from None
    print(format_table(summary_table(task, traj)))
    for v in result.violations:
        print(f"  limit broken: {v.line()}")
    if args.plot:
        path = save_check_plot(task, traj, result, _out(args) / f"{args.task.stem}_check.png")
        print(f"wrote {path}", file=sys.stderr)
    if result.refusal:
        print(f"rpr-cosim task check: {args.task}: {result.refusal.line()}", file=sys.stderr)
        return 1
    print(f"{args.task}: the motion passes every check ({len(result.t)} samples, {traj.duration:.6g} s)")
    return 0


def _plan(args: argparse.Namespace) -> int:


    dt = _dt(args.dt)
    task = load_task(args.task)
    try:
        traj = task.plan()
    except TrajectoryError as exc:
        raise UserError(f"{args.task}: {exc}") from None
    path = write_samples(task, traj, _out(args) / f"{args.task.stem}.csv", dt)
    print(f"wrote {path} ({traj.duration:.6g} s, {len(traj.P)} segments)")
    return 0
