"""``--set PATH=VALUE`` overrides applied to a scene tree, and the tree back as plain data.

A path is the dotted keys of the scene (``master.step``, ``components.pid1.params.Kp``); a ``*``,
``?`` or ``[...]`` in the component name sets every matching component
(``components.pid*.params.Kp=40``), the same paths a batch axis takes (:func:`expand_path`)."""
from __future__ import annotations

import difflib
import fnmatch
from collections.abc import Mapping, Sequence
from typing import Any

import yaml

from ..errors import UserError
from .merge import merge
from .problems import Loc, suggest
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


def override_texts(overrides: Mapping[str, Any] | Sequence[str] | None) -> list[str]:
    """``overrides`` (a mapping path -> value or ``"path=value"`` texts) as ``"path=value"`` texts,
    each value written as ``--set`` would take it (JSON for numbers, lists and mappings)."""
    import json

    if not overrides:
        return []
    if not isinstance(overrides, Mapping):
        return [str(s).strip() for s in overrides]
    return [f"{k}={v if isinstance(v, str) else json.dumps(v, default=str)}" for k, v in overrides.items()]


def _split_path(path: str) -> list[str]:
    parts = path.split(".")
    for i, p in enumerate(parts):
        if p in ("params", "start", "options") and i >= 2 and parts[0] == "components" and i + 1 < len(parts):
            return parts[:i + 1] + [".".join(parts[i + 1:])]
    return parts


def _suggest_pattern(pattern: str, components: Sequence[str]) -> str:
    """``"; did you mean 'pid*'?"`` for a wildcard ``pattern`` that matches nothing: its literal
    start (before the first wildcard) replaced by the closest start of a component name (one
    letter more or less allowed), where the pattern so mended matches a component."""
    cut = min(pattern.index(c) for c in "*?[" if c in pattern)
    head, tail = pattern[:cut], pattern[cut:]
    for n in (len(head), len(head) + 1, len(head) - 1) if head else ():  # the same length first
        starts = sorted({c[:n] for c in components if 0 < n <= len(c)})
        for start in difflib.get_close_matches(head, starts, n=3, cutoff=0.5):
            mended = start + tail
            if any(fnmatch.fnmatchcase(c, mended) for c in components):
                return f"; did you mean {mended!r}?"
    return ""


def expand_path(path: str, components: Sequence[str]) -> tuple[list[str], str]:
    """The scene paths of ``path`` (a '*', '?' or '[' in the component name matches every
    component it fits) and an error message ('' when fine).  ``--set`` and batch axes use it."""
    parts = path.split(".")
    if not all(parts):
        return [], f"path {path!r} has an empty part; expected e.g. components.pid1.params.Kp or master.step"
    if parts[0] != "components" or len(parts) < 2:
        return [path], ""
    name = parts[1]
    if any(c in name for c in "*?["):
        hits = [c for c in components if fnmatch.fnmatchcase(c, name)]
        if not hits:
            return [], (f"{name!r} in {path!r} matches no component of the scene{_suggest_pattern(name, components)} "
                        f"(components: {', '.join(components)})")
        return [".".join(["components", h, *parts[2:]]) for h in hits], ""
    if name not in components:
        return [], f"unknown component {name!r} in {path!r}{suggest(name, components)}"
    if len(parts) < 3:
        return [], f"path {path!r} names a whole component; sweep one of its values, e.g. {path}.params.<name>"
    return [path], ""


def apply_overrides(tree: YMap, overrides: Mapping[str, Any] | Sequence[str] | None) -> YMap:
    """Apply ``--set`` style overrides (a mapping path -> value, or ``"path=value"`` strings); a
    wildcard in a component name sets every matching component (:func:`expand_path`)."""
    if not overrides:
        return tree
    items = list(overrides.items()) if isinstance(overrides, Mapping) else [parse_set(s) for s in overrides]
    comps = tree.get("components") if isinstance(tree, Mapping) else None
    names = [str(c) for c in comps] if isinstance(comps, Mapping) else []
    expanded = []
    for path, value in items:
        parts = str(path).split(".")
        if len(parts) >= 2 and parts[0] == "components" and any(c in parts[1] for c in "*?["):
            paths, msg = expand_path(str(path), names)
            if msg:
                raise UserError(f"--set {path}={value}: {msg}")
            expanded += [(p, value) for p in paths]
        else:
            expanded.append((path, value))
    for path, value in expanded:
        keys = _split_path(path)
        if len(keys) == 2 and keys[0] == "components":
            names.append(keys[1])  # a component set whole: later paths may reach into it
        elif len(keys) > 2 and keys[0] == "components" and names and keys[1] not in names:
            raise UserError(f"--set {path}={value}: the scene has no component {keys[1]!r}{suggest(keys[1], names)} "
                            f"(components: {', '.join(names)}); a new component is set whole, e.g. "
                            f"--set 'components.{keys[1]}={{model: pid}}'")
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
