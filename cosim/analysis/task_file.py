"""Task files (``rpr-cosim task``, ``rpr-cosim design --task``): a YAML mapping as described in
:mod:`models.task`, whose ``waypoints`` may also name a CSV file (relative to the task file) with
columns ``x, y, phi`` and optionally ``t`` (then the times of the waypoints)."""
from __future__ import annotations

import csv
import io
from pathlib import Path

from models.task import Task, task_from
from models.trajectory import TrajectoryError

from ..errors import UserError
from ..readers import open_regular
from ..scenario.yamlfile import read_yaml


def read_waypoints_csv(path: Path) -> tuple[list[list[float]], list[float] | None]:
    """Waypoints (and times, if a ``t`` column is present) from a CSV with a header row."""
    try:
        with open_regular(path, "waypoints file") as fh:
            rows = list(csv.DictReader(io.TextIOWrapper(fh, newline="")))
    except OSError as exc:
        raise UserError(f"{path}: cannot read the waypoints ({exc.strerror or exc})") from None
    if not rows:
        raise UserError(f"{path}: no waypoints (expected a header x,y,phi[,t] and one row per waypoint)")
    need = {"x", "y", "phi"}
    missing = need - set(rows[0])
    if missing:
        raise UserError(f"{path}: missing column(s) {', '.join(sorted(missing))} (expected x, y, phi and optionally t)")
    out, times = [], [] if "t" in rows[0] else None
    for n, r in enumerate(rows, start=2):
        try:
            out.append([float(r["x"]), float(r["y"]), float(r["phi"])])
            if times is not None:
                times.append(float(r["t"]))
        except (TypeError, ValueError):
            raise UserError(f"{path}, line {n}: expected numbers in x, y, phi" + (", t" if times is not None else "")) from None
    return out, times


def task_from_mapping(spec: dict, where: str, base: Path | None = None) -> Task:
    """A task from its mapping; a ``waypoints`` string is a CSV path relative to ``base``; every
    mistake is a :class:`UserError` naming ``where``."""
    spec = dict(spec)
    if isinstance(spec.get("waypoints"), str):
        path = (base or Path(".")) / spec["waypoints"]
        try:
            spec["waypoints"], times = read_waypoints_csv(path)
        except UserError as exc:
            raise UserError(f"{where}: waypoints: {exc}") from None
        if times is not None and "times" not in spec:
            spec["times"] = times
            spec.setdefault("method", "spline")
    try:
        return task_from(spec)
    except TrajectoryError as exc:
        raise UserError(f"{where}: {exc}") from None


def load_task(path: Path) -> Task:
    """Read and parse a task file (a regular file under the size limit, depth-bounded YAML, as a
    scene is read)."""
    path = Path(path)
    spec, problems = read_yaml(path, "task file")
    if problems:
        first = problems[0]
        line = f", line {first.line}" if first.line else ""
        raise UserError(f"{path}{line}: {first.message}")
    if not isinstance(spec, dict):
        raise UserError(f"{path}: a task file is a mapping (config, method, waypoints, limits, margins...)")
    spec = dict(spec)
    spec.pop("name", None)
    spec.pop("description", None)
    return task_from_mapping(spec, str(path), path.parent)
