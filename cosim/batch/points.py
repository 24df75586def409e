"""A batch built in code from a base scene and an explicit list of runs, for studies whose runs
set different scene paths (e.g. ``master.step`` for one algorithm, ``master.options.rtol`` for
another), which no product of axes describes.

Each run is a pair ``(values, overrides)``: ``values`` are its cells in the results table (one
column per name, empty where a run has no value), ``overrides`` the scene paths it sets on top
of the batch's ``fixed`` ones.  Everything else is the ordinary batch: :func:`run_batch` plans,
builds the FMUs once, runs on any executor, writes ``runs/<run id>/`` and resumes.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..scenario import load_raw
from .spec import Axis, Batch, BatchError, _Checker, _resolve_auto


@dataclass
class PointsBatch(Batch):
    """A :class:`Batch` whose runs are listed (:attr:`points`) rather than expanded from axes
    (:func:`cosim.batch.axes.expand` takes them as they are)."""

    points: list[tuple[dict[str, Any], dict[str, Any]]] = field(default_factory=list)


def points_batch(scene_path: Path | str, points: Sequence[tuple[Mapping[str, Any], Mapping[str, Any]]], *,
                 name: str, fixed: Mapping[str, Any] | None = None, description: str = "",
                 auto_fidelity=None) -> PointsBatch:
    """A batch of the scene at ``scene_path`` running each of ``points`` (module docstring), with
    ``fixed`` overrides (scene path -> value) under every run.  No metrics and no reference: the
    caller measures the runs' traces.  A base scene that does not load is a :class:`BatchError`."""
    scene_path = Path(scene_path)
    problems: list = []
    base = load_raw(scene_path, problems)
    if base is None or any(p.severity == "error" for p in problems):
        raise BatchError(problems)
    fixed = dict(fixed or {})
    ck = _Checker(str(scene_path))
    base = _resolve_auto(ck, base, scene_path, fixed, (str(scene_path), 0), auto_fidelity)
    if ck.failed:
        raise BatchError(ck.problems)
    listed = [(dict(v), dict(o)) for v, o in points]
    names = list(dict.fromkeys(k for v, _ in listed for k in v))
    columns = [Axis(n, (), tuple(v.get(n) for v, _ in listed)) for n in names]
    return PointsBatch(name, scene_path, description, scene_path, fixed, [], columns, [], None, 1, None, [], None,
                       [], base, {}, [p for p in ck.problems if p.severity != "error"], points=listed)


__all__ = ["PointsBatch", "points_batch"]
