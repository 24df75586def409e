"""From a file or plain data to a validated :class:`Scene`: read, merge, override, validate."""
from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from .merge import _components_as_map, load_raw
from .model import Scene
from .overrides import _to_y, apply_overrides, override_texts
from .problems import Loc, Problem, SceneError
from .validate import validate
from .yamlfile import YMap


#: How ``fidelity: auto`` becomes levels: ``(tree, scene path) -> (tree, one-line note)``; the
#: fidelity study's :func:`cosim.study.fidelity.resolve_auto` is one, given by the caller (the
#: loader never calls up into the studies).
AutoFidelity = Callable[[YMap, Path], tuple[YMap, str]]


def load(path: Path | str, overrides: Mapping[str, Any] | Sequence[str] | None = None, *, catalog=None,
         auto_fidelity: AutoFidelity | None = None) -> Scene:
    """Read, merge (includes), override and validate the scene at ``path``; ``fidelity: auto``
    is resolved by ``auto_fidelity`` (without one it is a problem at its line).

    Raises :class:`SceneError` listing every problem, each as ``file:line: error: message``."""
    path = Path(path)
    problems: list[Problem] = []
    tree = load_raw(path, problems)
    if tree is None:
        raise SceneError(problems)
    tree = apply_overrides(tree, overrides)
    auto = _auto_fidelity_loc(tree)
    if auto is not None:  # 'fidelity: auto': the cheapest levels within fidelity_tolerance
        if auto_fidelity is None:
            raise SceneError([Problem(auto[0], auto[1], NO_AUTO_FIDELITY)])
        tree, note = auto_fidelity(tree, path)
        problems.append(Problem(auto[0], auto[1], note, "note"))
    scene = validate(tree, path, catalog=catalog, problems=problems)
    scene.overrides = override_texts(overrides)
    return scene


NO_AUTO_FIDELITY = ("fidelity: auto is chosen by the fidelity study, which this caller did not provide: run the "
                    "scene with rpr-cosim, or pass auto_fidelity=cosim.study.fidelity.resolve_auto")


def _auto_fidelity_loc(tree: YMap) -> Loc | None:
    """Where the first ``fidelity: auto`` of a catalog component is, or None."""
    comps = tree.get("components")
    if isinstance(comps, YMap):
        for spec in comps.values():
            if isinstance(spec, YMap) and spec.get("fidelity") == "auto" and "model" in spec:
                return spec.loc("fidelity")
    return None


def from_dict(data: Mapping[str, Any], *, base_dir: Path | None = None, catalog=None) -> Scene:
    """Validate a scene given as plain data (e.g. built in Python or sent to a worker); relative
    FMU paths are taken from ``base_dir`` (default: the working directory)."""
    where = (str((base_dir or Path.cwd()) / "<dict>"), 0)
    tree = _to_y(copy.deepcopy(dict(data)), where)
    if "components" in tree:
        probs: list[Problem] = []
        tree["components"] = _components_as_map(tree["components"], probs)
        if probs:
            raise SceneError(probs)
    return validate(tree, (base_dir or Path.cwd()) / "<dict>", catalog=catalog)
