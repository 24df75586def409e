"""YAML with line numbers: mappings and lists that remember the file and line of every entry, and
the guarded reader (size, anchors) that produces them."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from .problems import Loc, Problem
from ..errors import UserError
from ..readers import read_regular


class YMap(dict):
    """A mapping that remembers where it and each of its keys were written."""

    where: Loc = ("", 0)

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.locs: dict[Any, Loc] = {}

    def loc(self, key: Any) -> Loc:
        return self.locs.get(key, self.where)


class YList(list):
    """A list that remembers where it and each item were written."""

    where: Loc = ("", 0)

    def __init__(self, *a):
        super().__init__(*a)
        self.locs: list[Loc] = []

    def loc(self, i: int) -> Loc:
        return self.locs[i] if i < len(self.locs) else self.where


class _Loader(yaml.SafeLoader):
    """SafeLoader that builds :class:`YMap`/:class:`YList` with source lines, reports duplicate
    keys, and reads ``1e-3`` as a number (YAML 1.2 floats)."""

    def __init__(self, stream, filename: str):
        super().__init__(stream)
        self.filename = filename
        self.duplicates: list[Problem] = []


_FLOAT = re.compile(r"^[-+]?(?:\d[\d_]*(?:\.[\d_]*)?|\.\d[\d_]*)(?:[eE][-+]?\d+)?$|^[-+]?\.(?:inf|Inf|INF)$|^\.(?:nan|NaN|NAN)$")
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))


def _construct_map(loader: _Loader, node: yaml.MappingNode) -> YMap:
    m = YMap()
    m.where = (loader.filename, node.start_mark.line + 1)
    loader.flatten_mapping(node)
    for knode, vnode in node.value:
        key = loader.construct_object(knode, deep=True)
        line = knode.start_mark.line + 1
        if isinstance(key, (list, dict)):  # a complex key (``? [a, b]``): no name of ours is one
            loader.duplicates.append(Problem(loader.filename, line, f"a key must be a name or a number, not a "
                                                                     f"{'list' if isinstance(key, list) else 'mapping'} "
                                                                     f"({'? [...]' if isinstance(key, list) else '? {...}'}); "
                                                                     f"write it as a plain key"))
            continue
        if key in m:
            loader.duplicates.append(Problem(loader.filename, line, f"duplicate key {key!r} (first at line "
                                                                     f"{m.locs[key][1]}); the last one would win"))
        m[key] = loader.construct_object(vnode, deep=True)
        m.locs[key] = (loader.filename, line)
    return m


def _construct_seq(loader: _Loader, node: yaml.SequenceNode) -> YList:
    seq = YList()
    seq.where = (loader.filename, node.start_mark.line + 1)
    for item in node.value:
        seq.append(loader.construct_object(item, deep=True))
        seq.locs.append((loader.filename, item.start_mark.line + 1))
    return seq


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_map)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_seq)


def _display(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


#: Largest number of YAML values a scene may expand to (aliases count at every use).
MAX_YAML_NODES = 200_000
#: Deepest nesting of lists and mappings a file may have (no scene or batch needs more than ~10).
MAX_YAML_DEPTH = 100


def _expanded_size(root: Any) -> tuple[int, bool, int]:
    """Number of values the YAML node graph ``root`` stands for with every alias expanded,
    counted without expanding (memoised on the shared nodes; a recursive alias or anything past
    :data:`MAX_YAML_NODES` counts as too many), whether any node is used twice (an alias), and
    the deepest nesting."""
    too_many = MAX_YAML_NODES + 1
    memo: dict[int, int] = {}
    open_: set[int] = set()
    stack = [(root, False, 1)] if root is not None else []
    shared, deepest = False, 0
    while stack:
        node, done, depth = stack.pop()
        deepest = max(deepest, depth)
        if deepest > MAX_YAML_DEPTH:
            return 0, shared, deepest
        kids = ([k for pair in node.value for k in pair] if isinstance(node, yaml.MappingNode)
                else node.value if isinstance(node, yaml.SequenceNode) else [])
        if done:
            open_.discard(id(node))
            memo[id(node)] = min(1 + sum(memo.get(id(k), too_many) for k in kids), too_many)
            continue
        if id(node) in memo:
            shared = True
            continue
        if id(node) in open_:
            return too_many, True, deepest  # an alias inside its own anchor
        open_.add(id(node))
        stack.append((node, True, depth))
        for k in kids:
            if id(k) in open_:
                return too_many, True, deepest
            if id(k) not in memo:
                stack.append((k, False, depth + 1))
            else:
                shared = True
    return memo.get(id(root), 0), shared, deepest


class _TooDeep(Exception):
    """The file nests deeper than :data:`MAX_YAML_DEPTH`."""


def _nests_too_deep(text: str) -> bool:
    """True when ``text`` nests mappings or lists deeper than :data:`MAX_YAML_DEPTH`, found from the
    parser's events (iterative), so that the composer, which recurses once per level, never runs
    into the interpreter's recursion limit (where a finaliser that runs at that depth would fail
    too).  A syntax error is left to the loader, which reports it with its line."""
    depth = 0
    try:
        for ev in yaml.parse(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
            if isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_YAML_DEPTH:
                    return True
            elif isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
    except (yaml.YAMLError, RecursionError):
        return False
    return False


def read_yaml(path: Path, what: str = "scene") -> tuple[Any, list[Problem]]:
    """Parse one YAML file (``what`` names it in messages) into YMap/YList; syntax errors and
    duplicate keys become problems."""
    name = _display(path)

    try:
        raw = read_regular(Path(path), what)
    except UserError as exc:
        return None, [Problem(name, 0, str(exc).split(": ", 1)[-1])]
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        col = exc.start - raw.rfind(b"\n", 0, exc.start)
        return None, [Problem(name, line, f"the scene is not UTF-8 text (byte 0x{raw[exc.start]:02x} at column "
                                          f"{col}); save it as UTF-8")]
    try:
        loader = _Loader(text, name)
    except yaml.YAMLError as exc:  # the reader refuses control characters (NUL, ...) up front
        line = text[:getattr(exc, "position", 0) or 0].count("\n") + 1
        return None, [Problem(name, line, f"YAML: {str(exc).splitlines()[0]}")]
    try:
        if _nests_too_deep(text):
            raise _TooDeep
        try:
            node = loader.get_single_node()
        except RecursionError:  # the composer recurses once per level
            node = None
            raise _TooDeep from None
        size, shared, depth = _expanded_size(node)
        if depth > MAX_YAML_DEPTH:
            raise _TooDeep
        if size > MAX_YAML_NODES:
            why = ("(anchors and aliases repeat content); write it out plainly" if shared else
                   "; a file of rpr-cosim needs far fewer (a batch axis of many values: {from:, to:, num:})")
            return None, [Problem(name, 1, f"the file expands to more than {MAX_YAML_NODES:,} YAML values {why}"
                                  if shared else f"the file holds more than {MAX_YAML_NODES:,} YAML values{why}")]
        data = loader.construct_document(node) if node is not None else None
    except _TooDeep:
        return None, [Problem(name, 1, f"lists or mappings nested more than {MAX_YAML_DEPTH} levels deep; no scene "
                                       f"or batch needs that (an unclosed '[' or '{{'?)")]
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else 0
        what = exc.problem or str(exc)
        hint = ""
        if "found character '*'" in str(exc) or "alias" in str(exc):
            hint = " (quote strings that start with '*', e.g. \"*.x\")"
        elif "'['" in str(exc) or "flow" in str(exc):
            hint = " (quote names with brackets inside [ ] lists, e.g. [\"mech.leg[*].f\"])"
        return None, [Problem(name, line, f"YAML syntax: {what}{hint}")]
    except yaml.YAMLError as exc:  # e.g. a NUL or other control character
        line = text[:getattr(exc, "position", 0) or 0].count("\n") + 1
        return None, [Problem(name, line, f"YAML: {str(exc).splitlines()[0]}")]
    finally:
        loader.dispose()
    return data, loader.duplicates
