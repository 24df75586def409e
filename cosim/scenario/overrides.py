"""``--set PATH=VALUE`` overrides applied to a scene tree, and the tree back as plain data."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import yaml

from ..errors import UserError
from .merge import merge
from .problems import Loc
from .yamlfile import YList, YMap, _Loader


def parse_set(item: str) -> tuple[str, Any]:
    """``"path=value"`` -> (path, value parsed as YAML, so numbers, lists and words work)."""
    path, sep, text = str(item).partition("=")
    path = path.strip()
    if not sep or not path:
        raise UserError(f"--set {item!r}: expected PATH=VALUE, e.g. --set master.step=5e-4 or "
                        f"--set components.pid1.params.Kp=40")
    loader = _Loader(text.strip() or "''", f"--set {item}")
    try:
        value = loader.get_single_data()
    except yaml.YAMLError:
        value = text.strip()
    finally:
        loader.dispose()
    return path, value


def _split_path(path: str) -> list[str]:
    parts = path.split(".")
    for i, p in enumerate(parts):
        if p in ("params", "start", "options") and i >= 2 and parts[0] == "components" and i + 1 < len(parts):
            return parts[:i + 1] + [".".join(parts[i + 1:])]
    return parts


def apply_overrides(tree: YMap, overrides: Mapping[str, Any] | Sequence[str] | None) -> YMap:
    """Apply ``--set`` style overrides (a mapping path -> value, or ``"path=value"`` strings)."""
    if not overrides:
        return tree
    items = list(overrides.items()) if isinstance(overrides, Mapping) else [parse_set(s) for s in overrides]
    for path, value in items:
        keys = _split_path(path)
        label = (f"--set {path}={value}", 0)
        over: Any = _to_y(value, label)
        for k in reversed(keys):
            m = YMap({k: over})
            m.where, m.locs = label, {k: label}
            over = m
        tree = merge(tree, over)
    return tree


def _to_y(value: Any, where: Loc) -> Any:
    if isinstance(value, Mapping):
        m = YMap({k: _to_y(v, where) for k, v in value.items()})
        m.where, m.locs = where, {k: where for k in value}
        return m
    if isinstance(value, (list, tuple)):
        s = YList([_to_y(v, where) for v in value])
        s.where, s.locs = where, [where] * len(value)
        return s
    return value


def plain(node: Any) -> Any:
    """The tree as plain dicts and lists (for hashing, JSON and worker processes)."""
    if isinstance(node, Mapping):
        return {str(k): plain(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return [plain(v) for v in node]
    return node
