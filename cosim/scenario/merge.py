"""Includes and merging: the included scene under the including one, key by key; connections
extend and replace the ones they feed again."""
from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .problems import Problem, suggest
from .yamlfile import YList, YMap, _display, read_yaml
from .osp import is_osp, scene_tree as osp_tree
from .ssp_archive import scene_tree


def _components_as_map(node: Any, problems: list[Problem]) -> Any:
    """Accept ``components`` as a list of specs with ``name:`` and turn it into a mapping."""
    if not isinstance(node, YList):
        return node
    out = YMap()
    out.where = node.where
    for i, item in enumerate(node):
        if not isinstance(item, YMap) or "name" not in item:
            problems.append(Problem(*node.loc(i), "a component in a list needs a 'name:' key"))
            continue
        spec = YMap({k: v for k, v in item.items() if k != "name"})
        spec.where, spec.locs = item.where, {k: v for k, v in item.locs.items() if k != "name"}
        out[str(item["name"])] = spec
        out.locs[str(item["name"])] = node.loc(i)
    return out


def _kind(spec: Any) -> tuple[str, Any]:
    if isinstance(spec, Mapping):
        if "fmu" in spec:
            return "fmu", spec.get("fmu")
        if "modelica" in spec:
            return "modelica", (spec.get("modelica"), spec.get("model"))
        if "model" in spec:
            return "model", spec.get("model")
        if "hardware" in spec:
            return "hardware", "board"
        if "replay" in spec:
            return "replay", None  # another recording of the same signals: interpolation and units stay
    return "", None


def merge(base: Any, over: Any, *, path: str = "") -> Any:
    """Deep merge of ``over`` onto ``base`` (see :mod:`cosim.scenario`); returns a new tree."""
    if isinstance(base, YMap) and isinstance(over, YMap):
        out = YMap(base)
        out.where, out.locs = base.where, dict(base.locs)
        for k, v in over.items():
            sub = f"{path}.{k}" if path else str(k)
            if v is None:
                out.pop(k, None)
                out.locs.pop(k, None)
                continue
            if path == "components" and k in out and _kind(out[k])[0] and _kind(v)[0] and _kind(out[k]) != _kind(v):
                out[k] = v  # a different model or FMU: the old spec means nothing any more
            elif sub == "connections" and isinstance(out.get(k), YList) and isinstance(v, YList):
                out[k] = _merge_connections(out[k], v)
            elif k in out:
                out[k] = merge(out[k], v, path=sub)
            else:
                out[k] = v
            out.locs[k] = over.loc(k)
        return out
    return over


_ARROW = re.compile(r"^\s*(\S+)\s*(<->|->)\s*(\S+)\s*$")
#: An optional linear transformation after a signal connection: ``a.y -> b.u * 0.001 + 0.5``.
_TRANSFORM = re.compile(r"^(\s*\S+\s*->\s*\S+)(?:\s+\*\s*(\S+))?(?:\s+([-+])\s*(\S+))?\s*$")


def split_transform(text: str) -> tuple[str, float, float] | None:
    """``"a.y -> b.u * k + c"`` -> ``("a.y -> b.u", k, c)``; the text itself with (1, 0) when it
    has no transformation; None when the transformation is not two finite numbers."""
    m = _TRANSFORM.match(text)
    if not m or (m.group(2) is None and m.group(4) is None):
        return text, 1.0, 0.0
    try:
        factor = float(m.group(2)) if m.group(2) is not None else 1.0
        offset = float(m.group(4)) * (-1.0 if m.group(3) == "-" else 1.0) if m.group(4) is not None else 0.0
    except ValueError:
        return None
    if not (math.isfinite(factor) and math.isfinite(offset)):
        return None
    return m.group(1), factor, offset
#: an explicit type conversion on a signal: ``a.y -> b.u as Float64`` (see :mod:`cosim.slaves.types`)
_AS = re.compile(r"^(.*\S)\s+as\s+([A-Za-z][A-Za-z0-9]*)\s*$")


def _conn_keys(text: Any) -> set[str]:
    """What a connection occupies: the input it feeds, or both flanges of a bond."""
    conv = _AS.match(str(text))
    base = conv.group(1) if conv else str(text)
    m = _ARROW.match((split_transform(base) or (base,))[0])
    if not m:
        return set()
    a, arrow, b = m.groups()
    return {b} if arrow == "->" else {a, b}


def _merge_connections(base: YList, over: YList) -> YList:
    taken = set().union(*(_conn_keys(c) for c in over)) if over else set()
    out = YList()
    out.where = base.where
    for i, c in enumerate(base):
        if not (_conn_keys(c) & taken):
            out.append(c)
            out.locs.append(base.loc(i))
    for i, c in enumerate(over):
        out.append(c)
        out.locs.append(over.loc(i))
    return out


def load_raw(path: Path, problems: list[Problem], _chain: tuple[Path, ...] = ()) -> YMap | None:
    """The scene tree of ``path`` with its includes merged in (problems appended, not raised)."""
    path = Path(path)
    rp = path.resolve()
    if rp in _chain:
        cycle = " -> ".join(_display(p) for p in _chain + (rp,))
        problems.append(Problem(_display(path), 0, f"include cycle: {cycle}"))
        return None
    if path.suffix.lower() == ".ssp":  # an SSP archive read as a scene tree (cosim.scenario.ssp_archive)

        return scene_tree(path, problems)

    if is_osp(path):  # libcosim's OspSystemStructure.xml read as a scene tree (cosim.scenario.osp)

        return osp_tree(path, problems)
    data, found = read_yaml(path)
    problems.extend(found)
    if data is None:
        if not found:
            problems.append(Problem(_display(path), 1, "the scene is empty; expected a mapping with "
                                                        "'components:' and 'connections:'"))
        return None
    if not isinstance(data, YMap):
        problems.append(Problem(_display(path), 1, f"a scene is a mapping of keys (name, components, "
                                                    f"connections, ...), not a {type(data).__name__}"))
        return None
    if "components" in data:
        data["components"] = _components_as_map(data["components"], problems)
    inc = data.pop("include", None)
    if inc is None:
        return data
    loc = data.loc("include")
    data.locs.pop("include", None)
    incs = inc if isinstance(inc, list) else [inc]
    merged: YMap | None = None
    for item in incs:
        if not isinstance(item, str):
            problems.append(Problem(*loc, f"include must be a file name (or a list of them), got {item!r}"))
            continue
        target = (path.parent / item)
        if not target.is_file():
            near = suggest(item, [p.name for p in path.parent.glob("*.yaml")] + [p.name for p in path.parent.glob("*.ssp")]
                           + [p.name for p in path.parent.glob("*.xml")])
            problems.append(Problem(*loc, f"included scene {item!r} not found next to {path.name}{near}"))
            continue
        sub = load_raw(target, problems, _chain + (rp,))
        if sub is not None:
            merged = sub if merged is None else merge(merged, sub)
    return data if merged is None else merge(merged, data)
