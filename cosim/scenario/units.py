"""The unit of every variable of a scene (``component.variable`` -> unit), from its FMUs or the
descriptions the scene validated."""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from ..slaves.description import describe_fmu


def units_of(scene, fmus: Mapping[str, Path] | None = None) -> dict[str, str]:
    """``component.variable`` -> unit, from each component's FMU (``fmus``: component -> FMU path,
    e.g. :attr:`RunResult.fmus`) or, without one, from the description the scene validated."""

    out: dict[str, str] = {}
    for name, comp in scene.components.items():
        path = (fmus or {}).get(name)
        desc = describe_fmu(path) if path is not None else comp.description
        for var in desc.variables.values():
            out[f"{name}.{var.name}"] = var.unit
    return out
