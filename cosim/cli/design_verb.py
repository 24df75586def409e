"""``rpr-cosim design``: the thesis's Chapter 8 design checks (fixed-joint shaft, bearings, clamp,
actuator), from its own inputs and under the loads of tasks or recorded runs.

    rpr-cosim design [--task FILE]... [--trace FILE]... [--drive table67|fa200] [--out DIR] [--plot]

Prints one table (a column per case, the thesis's printed values beside its inputs' column) and
saves it as ``design.csv`` in ``--out``; ``--plot`` saves each task's or trace's load over time
against the shaft's and the actuator's limits.  Exit status 1 when a margin is negative.
"""
from __future__ import annotations

import argparse
import sys

from ..errors import UserError
from models.geometry import preset
from models.trajectory import DRIVES
from ..analysis import design_checks as R
from ..analysis.design_views import format_table, write_csv
from ..analysis.task_file import load_task
from ..trace.traces import read_trace


def run(args: argparse.Namespace) -> int:


    if args.drive is not None and args.drive not in DRIVES:
        raise UserError(f"--drive {args.drive!r}: expected one of {', '.join(DRIVES)}")
    cases, plots = [R.thesis_case()], []
    drive = DRIVES[args.drive] if args.drive else None
    for path in args.task:
        task = load_task(path)
        drive = drive or task.limits.drive
        loads = R.loads_from_task(task, f"task {path.stem}")
        cases.append(R.task_case(loads, task.manipulator))
        plots.append((loads, task.manipulator))
    for path in args.trace:
        loads = R.loads_from_trace(read_trace(path), f"trace {path.stem}")
        cases.append(R.task_case(loads, preset()))
        plots.append((loads, preset()))
    drive = drive or DRIVES["table67"]
    table = R.design_table(cases, drive)
    print(format_table(table))
    if args.out.exists() and not args.out.is_dir():
        raise UserError(f"--out {str(args.out)!r}: exists and is not a directory")
    args.out.mkdir(parents=True, exist_ok=True)
    write_csv(table, args.out / "design.csv")
    print(f"wrote {args.out / 'design.csv'}", file=sys.stderr)
    if args.plot:
        for loads, m in plots:
            stem = "".join(ch if ch.isalnum() else "_" for ch in loads.label)
            path = R.save_load_plot(loads, m, drive, args.out / f"{stem}_loads.png")
            print(f"wrote {path}", file=sys.stderr)
    bad = R.negative_margins(table)
    for line in bad:
        print(f"negative margin: {line}")
    return 1 if bad else 0
