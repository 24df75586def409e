"""The calibrated scene: an overlay of the fitted scene (``include:`` it, then the ``--set``
overrides the fit ran with and the fitted values as ``components: {NAME: {params: ...}}``), so the
original stays as it is and ``rpr-cosim run`` runs the calibrated one."""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from ..scenario.overrides import _split_path, parse_set
from .solve import FitResult


def _nested(tree: dict, parts: list[str], value: Any) -> None:
    for p in parts[:-1]:
        tree = tree.setdefault(p, {})
    tree[parts[-1]] = value


def overlay_text(result: FitResult, scene_file: Path, where: Path, sets: Sequence[str] = ()) -> str:
    """YAML of the overlay written at ``where`` (the include path relative to it)."""
    scene = result.problem.scene
    tree: dict = {}
    for item in sets:
        path, value = parse_set(item)
        _nested(tree, _split_path(path), value)
    for e in result.estimates:
        _nested(tree, ["components", e.unknown.component, "params", e.unknown.name], float(f"{e.value:.10g}"))
    include = os.path.relpath(os.path.abspath(scene_file), os.path.abspath(Path(where).parent))
    lines = [f"# {scene.name} calibrated by rpr-cosim fit against {result.problem.data_path.name}:",
             f"# weighted RMS residual {result.rms_start:.4g} -> {result.rms_end:.4g} (relative to each signal's range)"]
    for e in result.estimates:
        ci = "not identifiable from these data" if e.half_width == float("inf") else f"+-{e.half_width:.3g}"
        unit = "" if e.unknown.unit in ("", "1") else f" {e.unknown.unit}"
        lines.append(f"#   {e.unknown.path} = {e.value:.6g}{unit} (95 %: {ci}; was {e.unknown.start:.6g})")
    body = yaml.safe_dump({"include": include, "name": f"{scene.name}_fitted",
                           "description": f"{scene.name} with parameters fitted to {result.problem.data_path.name}",
                           **tree}, sort_keys=False, default_flow_style=False)
    return "\n".join(lines) + "\n" + body


def write_overlay(result: FitResult, scene_file: Path, path: Path, sets: Sequence[str] = ()) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(overlay_text(result, scene_file, path, sets))
    return path


__all__ = ["overlay_text", "write_overlay"]
