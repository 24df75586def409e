"""Scenes: YAML files that assemble components into a co-simulation, checked before anything runs.

Format (every key but ``components`` and ``connections`` optional; lines starting ``#`` are comments)::

    name: pid_step
    description: free text
    include: base.yaml          # another scene, merged under this one (paths relative to this file)
    start_time: 0.0             # [s] (default: the FMUs' DefaultExperiment, else 0)
    stop_time: 5.0              # [s] (default: the FMUs' DefaultExperiment)
    components:                 # a mapping name -> spec (or a list of specs with a 'name:' key)
      mech:   {model: mechanism, fidelity: rigid, options: {config: cross_leg}, params: {leg[1].m_act: 0.058}}
      pid1:   {model: pid, params: {Kp: 30, Ki: 80, Kd: 20, u_max: 12}}
      plant:  {fmu: plant.fmu, params: {k: 1e4}, start: {x: 0.1}}    # any external FMU
    connections:
      - target.leg[1].s -> pid1.setpoint        # signal: output -> input
      - stair.counter -> plant.u as Float64     # an explicit type conversion (cosim.fmitypes)
      - motor1.flange <-> mech.leg[1]           # power bond between two flanges
      - mech.leg[1].s -> pid1.measurement * 1000 + 0.5   # signal through a linear transformation
    master: {algorithm: gauss_seidel, step: 1e-3, order: [target, pid1, motor1, mech],
             engine: auto, output_interval: 1e-3}
    outputs: ["mech.platform.*", "mech.leg[*].f"]   # fnmatch over "component.variable"
    guards: {stroke: stop, singularity: warn}       # physical guards (cosim.guards); all "stop" by default

Component spec: ``model`` (a name of :func:`models.blocks.catalog`) with optional ``fidelity``
and ``options`` (construction options of :func:`models.blocks.make`), or ``fmu`` (a path);
``params`` sets parameters by name (structural ones go to ``make``, the others are set on the
instance at start-up, so one compiled FMU serves every value); ``start`` sets start values of
inputs and states (for an FMU: inputs and variables with initial = exact or approx; parameters
and FMI 3.0 structural parameters go under ``params``, any FMI type, arrays as lists); ``fmi`` picks the FMI version of a built FMU ("2.0" default, or "3.0").

A bond ``a.p <-> b.q`` joins two flanges: the side whose flange computes the effort
(``effort_out``) feeds its effort output to the other side's effort input, and the other side
feeds its flow output back; both sides must differ in causality.

Includes merge deeply: mappings key by key (the including file wins; ``null`` deletes), a
component whose ``model``/``fmu`` changes is replaced whole, ``connections`` extend the included
ones (a connection into an input, or a bond on a flange, that the included scene already feeds
replaces it), other lists are replaced.  ``--set path=value`` overrides work the same way:
``master.step=5e-4``, ``components.pid1.params.Kp=40``, ``components.mech.params.leg[1].m_act=0.06``
(everything after ``params.`` or ``start.`` is one variable name).

Validation collects every problem (file, line, message with the closest valid name) and raises
:class:`SceneError` listing them all; warnings (e.g. an unconnected input without a start value)
are kept on :attr:`Scene.warnings`.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import fnmatch
import hashlib
import json
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import yaml

from .errors import UserError
from .master import ALGORITHMS, find_algebraic_loop
from .fmitypes import TYPES, canonical, conversion, display, parse_start
from .slaves import SlaveDescription, Variable, describe_block, describe_fmu, resolve_shapes

Loc = tuple[str, int]  # (file, line); line 0 = no line (a --set override)

TOP_KEYS = ("name", "description", "include", "start_time", "stop_time", "components", "connections", "master",
            "outputs", "fidelity_tolerance", "fidelity_signals", "guards")
COMPONENT_KEYS = ("model", "fidelity", "options", "params", "start", "fmu", "fmi", "description", "hardware", "rate")
MASTER_KEYS = ("algorithm", "step", "order", "engine", "output_interval", "inputs", "realtime", "options")
#: How a slave's inputs vary over a communication step (see :mod:`cosim.master`).
INPUT_MODES = ("hold", "linear")
ENGINES = ("auto", "compiled", "python")
FMI_VERSIONS = ("2.0", "3.0")


# --- problems ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Problem:
    """One finding of validation: where, what, and how bad."""

    file: str
    line: int
    message: str
    severity: str = "error"

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line else self.file
        return f"{where}: {self.severity}: {self.message}"


class SceneError(UserError):
    """A scene that cannot run; :attr:`problems` lists every error (and warning) found."""

    def __init__(self, problems: Sequence[Problem]):
        self.problems = list(problems)
        errors = [p for p in self.problems if p.severity == "error"]
        super().__init__("\n".join(str(p) for p in errors) or "invalid scene")


def suggest(name: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest of ``choices`` (difflib), else ``""``."""
    close = difflib.get_close_matches(str(name), list(choices), n=1, cutoff=0.5)
    return f"; did you mean {close[0]!r}?" if close else ""


# --- YAML with line numbers -------------------------------------------------------------------
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


def _expanded_size(root: Any) -> int:
    """Number of values the YAML node graph ``root`` stands for with every alias expanded,
    counted without expanding (memoised on the shared nodes; a recursive alias or anything past
    :data:`MAX_YAML_NODES` counts as too many)."""
    too_many = MAX_YAML_NODES + 1
    memo: dict[int, int] = {}
    open_: set[int] = set()
    stack = [(root, False)] if root is not None else []
    while stack:
        node, done = stack.pop()
        kids = ([k for pair in node.value for k in pair] if isinstance(node, yaml.MappingNode)
                else node.value if isinstance(node, yaml.SequenceNode) else [])
        if done:
            open_.discard(id(node))
            memo[id(node)] = min(1 + sum(memo.get(id(k), too_many) for k in kids), too_many)
            continue
        if id(node) in memo:
            continue
        if id(node) in open_:
            return too_many  # an alias inside its own anchor
        open_.add(id(node))
        stack.append((node, True))
        for k in kids:
            if id(k) in open_:
                return too_many
            if id(k) not in memo:
                stack.append((k, False))
    return memo.get(id(root), 0)


def read_yaml(path: Path) -> tuple[Any, list[Problem]]:
    """Parse one YAML file into YMap/YList; syntax errors and duplicate keys become problems."""
    name = _display(path)
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        return None, [Problem(name, 0, f"cannot read the scene: {exc.strerror or exc}")]
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
        node = loader.get_single_node()
        size = _expanded_size(node)
        if size > MAX_YAML_NODES:
            return None, [Problem(name, 1, f"the scene expands to more than {MAX_YAML_NODES:,} YAML values "
                                           f"(anchors and aliases repeat content); write it out plainly")]
        data = loader.construct_document(node) if node is not None else None
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


# --- include and merge ------------------------------------------------------------------------
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
        if "model" in spec:
            return "model", spec.get("model")
        if "hardware" in spec:
            return "hardware", "board"
    return "", None


def merge(base: Any, over: Any, *, path: str = "") -> Any:
    """Deep merge of ``over`` onto ``base`` (see the module docstring); returns a new tree."""
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
#: an explicit type conversion on a signal: ``a.y -> b.u as Float64`` (see :mod:`cosim.fmitypes`)
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
    if path.suffix.lower() == ".ssp":  # an SSP archive read as a scene tree (cosim.ssp)
        from .ssp import scene_tree

        return scene_tree(path, problems)
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
            near = suggest(item, [p.name for p in path.parent.glob("*.yaml")] + [p.name for p in path.parent.glob("*.ssp")])
            problems.append(Problem(*loc, f"included scene {item!r} not found next to {path.name}{near}"))
            continue
        sub = load_raw(target, problems, _chain + (rp,))
        if sub is not None:
            merged = sub if merged is None else merge(merged, sub)
    return data if merged is None else merge(merged, data)


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


# --- the validated scene ----------------------------------------------------------------------
@dataclass
class Component:
    """A validated component: how to build it and what it looks like."""

    name: str
    kind: str  # "model" or "fmu"
    description: SlaveDescription
    model: str | None = None
    fidelity: str | None = None
    options: dict[str, Any] = field(default_factory=dict)
    params: dict[str, float] = field(default_factory=dict)  # set on the instance at start-up
    start: dict[str, float] = field(default_factory=dict)
    fmu: Path | None = None
    fmi: str = "2.0"
    block: Any = None  # the models.block.Block of a model component
    where: Loc = ("", 0)
    rate: int = 1  # doSteps per macro step (cosim.multirate)

    @property
    def label(self) -> str:
        return f"{self.model}/{self.fidelity}" if self.kind == "model" else (self.fmu.name if self.fmu else "?")

    def start_values(self) -> dict[str, float]:
        """Everything to set before initialisation: parameters, then start values."""
        return {**self.params, **self.start}


@dataclass(frozen=True)
class Connection:
    """A signal ``src.src_var -> dst.dst_var``; ``bond`` names the bond it comes from, if any."""

    src: str
    src_var: str
    dst: str
    dst_var: str
    bond: str | None = None
    where: Loc = ("", 0)
    as_type: str | None = None  # an explicit conversion to the destination's type
    factor: float = 1.0  # dst = factor * src + offset (a linear transformation, e.g. from an SSP)
    offset: float = 0.0

    def __str__(self) -> str:
        text = f"{self.src}.{self.src_var} -> {self.dst}.{self.dst_var}"
        if self.factor != 1.0:
            text += f" * {self.factor!r}"
        if self.offset != 0.0:
            text += f" {'-' if self.offset < 0 else '+'} {abs(self.offset)!r}"
        return text + (f" as {self.as_type}" if self.as_type else "")


@dataclass
class MasterSettings:
    algorithm: str
    step: float  # [s]
    step_ns: int
    order: list[str] | None
    engine: str
    record_every: int  # output interval in steps
    inputs: str = "hold"  # "hold" or "linear" (first-order hold, FMUs that can interpolate inputs)
    realtime: Any = None  # cosim.realtime.RealtimeSettings when the run is paced on the wall clock
    options: dict[str, float] = field(default_factory=dict)  # the algorithm's own options (its declaration)


@dataclass
class Scene:
    """A validated scene, ready to run (see :func:`load`)."""

    name: str
    path: Path | None
    description: str
    stop_time: float
    n_steps: int
    components: dict[str, Component]
    connections: list[Connection]
    bonds: list[tuple[str, str, str, str]]  # (comp, flange, comp, flange)
    master: MasterSettings
    outputs: list[str]
    data: dict  # the merged tree as plain data
    hash: str
    warnings: list[Problem] = field(default_factory=list)
    start_time: float = 0.0  # [s] the scene's start_time, else the FMUs' default experiment, else 0
    start_ns: int = 0
    guards: Any = None  # cosim.guards.GuardSettings (physical guards of a run)


# --- catalog access ---------------------------------------------------------------------------
def default_catalog():
    """The model catalog module :mod:`models.blocks`."""
    try:
        import models.blocks as blocks
    except ModuleNotFoundError as exc:
        if exc.name == "models.blocks":
            raise UserError("the model catalog (models.blocks) is not installed in this build; "
                            "only 'fmu:' components can be used") from None
        raise
    return blocks


@lru_cache(maxsize=64)
def _make(catalog, model: str, fidelity: str, frozen: tuple) -> Any:
    return catalog.make(model, fidelity, **dict(frozen))


def make_block(catalog, model: str, fidelity: str, options: Mapping[str, Any]):
    """``catalog.make`` with a cache keyed by the arguments (blocks are immutable in use)."""
    try:
        frozen = tuple(sorted((k, v if not isinstance(v, list) else tuple(v)) for k, v in options.items()))
        hash(frozen)
    except TypeError:
        return catalog.make(model, fidelity, **options)
    return _make(catalog, model, fidelity, frozen)


# --- validation -------------------------------------------------------------------------------
def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class _Checker:
    def __init__(self, tree: YMap, path: Path | None, catalog):
        self.tree, self.path, self.catalog = tree, path, catalog
        self.problems: list[Problem] = []

    def err(self, where: Loc, msg: str) -> None:
        self.problems.append(Problem(where[0], where[1], msg))

    def warn(self, where: Loc, msg: str) -> None:
        self.problems.append(Problem(where[0], where[1], msg, "warning"))

    def number(self, node: YMap, key: str, what: str, *, required: bool = False, default=None):
        if key not in node:
            if required:
                self.err(node.where, f"{what} is missing; expected a number in seconds")
            return default
        v = node[key]
        if not _is_number(v) or not math.isfinite(v):
            self.err(node.loc(key), f"{what} = {v!r} is not a finite number")
            return None
        return float(v)

    def unknown_keys(self, node: YMap, allowed: Sequence[str], what: str) -> None:
        for k in node:
            if k not in allowed:
                self.err(node.loc(k), f"unknown key {k!r} in {what}{suggest(str(k), allowed)} "
                                      f"(expected: {', '.join(allowed)})")

    # components ---------------------------------------------------------------------------------
    def component(self, name: str, spec: Any, where: Loc) -> Component | None:
        if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", str(name)):
            self.err(where, f"component name {name!r} must be an identifier (letters, digits, '_'; no dots)")
            return None
        if not isinstance(spec, YMap):
            self.err(where, f"component {name!r}: expected a mapping with 'model:' or 'fmu:', got {spec!r}")
            return None
        self.unknown_keys(spec, COMPONENT_KEYS, f"component {name!r}")
        for key in ("options", "params", "start"):
            if key in spec and not isinstance(spec[key], YMap):
                self.err(spec.loc(key), f"component {name!r}: {key} must be a mapping name: value, got {spec[key]!r}")
                return None
        fmi = spec.get("fmi", "2.0")
        fmi = {2: "2.0", 3: "3.0", 2.0: "2.0", 3.0: "3.0"}.get(fmi, str(fmi)) if not isinstance(fmi, bool) else str(fmi)
        if fmi not in FMI_VERSIONS:
            self.err(spec.loc("fmi"), f"component {name!r}: fmi = {spec.get('fmi')!r}; expected \"2.0\" or \"3.0\"")
            return None
        if "model" in spec and "fmu" in spec:
            self.err(spec.where, f"component {name!r} has both 'model:' and 'fmu:'; keep one")
            return None
        if "hardware" in spec:
            return self._hardware_component(name, spec)
        if "fmu" in spec:
            return self._fmu_component(name, spec, fmi)
        if "model" in spec:
            return self._model_component(name, spec, fmi)
        self.err(spec.where, f"component {name!r} needs 'model:' (a catalog model) or 'fmu:' (a file)")
        return None

    def _fmu_component(self, name: str, spec: YMap, fmi: str) -> Component | None:
        where = spec.loc("fmu")
        rel = spec["fmu"]
        if not isinstance(rel, str):
            self.err(where, f"component {name!r}: fmu must be a file path, got {rel!r}")
            return None
        base = Path(where[0]).parent if where[1] else (self.path.parent if self.path else Path.cwd())
        fpath = (base / rel) if not Path(rel).is_absolute() else Path(rel)
        if not fpath.is_file():
            near = suggest(Path(rel).name, [p.name for p in fpath.parent.glob("*.fmu")]) if fpath.parent.is_dir() else ""
            self.err(where, f"component {name!r}: FMU file {rel!r} not found (looked in {_display(fpath.parent)}){near}")
            return None
        for key in ("fidelity", "options"):
            if key in spec:
                self.err(spec.loc(key), f"component {name!r}: '{key}' applies to catalog models, not to an FMU")
        try:
            desc = describe_fmu(fpath)
        except UserError as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        comp = Component(name, "fmu", desc, fmu=fpath.resolve(), fmi=desc.fmi_version or fmi, where=spec.where)
        self._values(comp, spec)
        return comp

    def _hardware_component(self, name: str, spec: YMap) -> Component | None:
        """``{hardware: {address: HOST:PORT, key: FILE}}``: the hardware FMU (:mod:`hardware.fmu`),
        built and cached with these start values; then an FMU component like any other."""
        node, where = spec["hardware"], spec.loc("hardware")
        if not isinstance(node, Mapping) or any(k not in ("address", "key") for k in node):
            self.err(where, f"component {name!r}: hardware must be a mapping {{address: HOST:PORT, key: FILE}}, "
                            f"got {node!r}")
            return None
        from hardware.fmu import build_hil_fmu
        from hardware.protocol import parse_address

        address, key = str(node.get("address", "127.0.0.1:5005")), str(node.get("key", "board.key"))
        try:
            parse_address(address)
        except ValueError as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        base = Path(where[0]).parent if where[1] else (self.path.parent if self.path else Path.cwd())
        try:
            keyfile = base / Path(key).expanduser()
        except RuntimeError as exc:  # '~user' that does not exist, or no home directory
            self.err(where, f"component {name!r}: key file {key!r}: {exc}")
            return None
        if not keyfile.is_file():
            self.err(where, f"component {name!r}: key file {_display(keyfile)} not found; make one with "
                            f"'rpr-cosim board keygen {key}' and copy it to the board")
            return None
        for k in ("model", "fidelity", "options", "fmu"):
            if k in spec:
                self.err(spec.loc(k), f"component {name!r}: '{k}' does not apply to a hardware component")
                return None
        try:
            fpath = build_hil_fmu()  # one build; address and key are string start values
        except (ValueError, OSError) as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        comp = Component(name, "fmu", describe_fmu(fpath), fmu=fpath, where=spec.where)
        self._values(comp, spec)
        comp.params.update(address=address, key_file=str(keyfile.resolve()))
        return comp

    def _model_component(self, name: str, spec: YMap, fmi: str) -> Component | None:
        try:
            catalog = self.catalog if self.catalog is not None else default_catalog()
        except UserError as exc:
            self.err(spec.loc("model"), f"component {name!r}: {exc}")
            return None
        cat = catalog.catalog()
        model = spec["model"]
        if not isinstance(model, str) or model not in cat:
            self.err(spec.loc("model"), f"component {name!r}: unknown model {model!r}{suggest(str(model), cat)} "
                                        f"(catalog: {', '.join(sorted(cat))})")
            return None
        fidelity = spec.get("fidelity", cat[model][0])
        if not isinstance(fidelity, str) or fidelity not in cat[model]:
            self.err(spec.loc("fidelity"), f"component {name!r}: model {model} has no fidelity {fidelity!r}"
                                           f"{suggest(str(fidelity), cat[model])} (expected one of "
                                           f"{', '.join(cat[model])})")
            return None
        options = dict(spec.get("options", {}))
        known_opts = getattr(catalog, "options", None)
        if known_opts is not None:
            allowed = list(known_opts(model, fidelity))
            bad = [k for k in options if k not in allowed]
            for k in bad:
                self.err(spec["options"].loc(k), f"component {name!r}: {model}/{fidelity} has no option {k!r}"
                                                 f"{suggest(str(k), allowed)} (options: {', '.join(allowed) or 'none'})")
            if bad:
                return None
        from models.block import BlockError

        try:
            block = make_block(catalog, model, fidelity, options)
        except (BlockError, ValueError, TypeError) as exc:
            self.err(spec.loc("options") if "options" in spec else spec.loc("model"), f"component {name!r}: {exc}")
            return None
        params = spec.get("params", YMap())
        structural = {p.name for p in block.params if p.structural}
        fixed = {k: params[k] for k in params if k in structural}
        if fixed:
            try:
                block = make_block(catalog, model, fidelity, {**options, **fixed})
            except (BlockError, ValueError, TypeError) as exc:
                self.err(params.loc(next(iter(fixed))), f"component {name!r}: {exc}")
                return None
        desc = describe_block(block, f"{model}/{fidelity}")
        comp = Component(name, "model", desc, model=model, fidelity=fidelity, options=options, fmi=fmi,
                         block=block, where=spec.where)
        self._values(comp, spec, skip=set(fixed))
        return comp

    def _values(self, comp: Component, spec: YMap, skip: set[str] = frozenset()) -> None:
        """Check ``params`` and ``start`` against the component's variables."""
        if comp.kind == "fmu":
            self._fmu_values(comp, spec)
            return
        vs = comp.description.variables
        params = spec.get("params", YMap())
        pnames = [v.name for v in vs.values() if v.causality == "parameter"]
        bounds = {p.name: (p.lower, p.upper, p.unit) for p in comp.block.params} if comp.block is not None else {}
        for k, val in params.items():
            where = params.loc(k)
            if k in skip:
                continue
            if k not in vs or vs[k].causality != "parameter":
                if comp.kind == "model" and k in ("config", "form", "integrator", "substeps", "rotor", "profile",
                                                  "derivative", "anti_windup", "sample_period"):
                    self.err(where, f"component {comp.name!r}: {k!r} is a construction option, not a parameter; "
                                    f"put it under 'options:'")
                elif k in vs:
                    self.err(where, f"component {comp.name!r}: {k!r} is a{'n' if vs[k].causality[0] in 'aeiou' else ''} "
                                    f"{vs[k].causality}, not a parameter; use 'start:' for start values")
                else:
                    self.err(where, f"component {comp.name!r} ({comp.label}) has no parameter {k!r}"
                                    f"{suggest(str(k), pnames)}")
                continue
            if vs[k].type != "Real":
                self.err(where, f"component {comp.name!r}: parameter {k!r} is {vs[k].type}; only Real parameters "
                                f"can be set from a scene")
                continue
            if not _is_number(val) or not math.isfinite(val):
                self.err(where, f"component {comp.name!r}: parameter {k} = {val!r} is not a finite number")
                continue
            if k in bounds:
                lo, hi, unit = bounds[k]
                if not (lo <= val <= hi):
                    self.err(where, f"component {comp.name!r}: parameter {k} = {val} is outside [{lo}, {hi}]"
                                    f"{' ' + unit if unit else ''}")
                    continue
            if vs[k].variability in ("constant",):
                self.err(where, f"component {comp.name!r}: parameter {k!r} is a constant and cannot be set")
                continue
            comp.params[k] = float(val)
        start = spec.get("start", YMap())
        settable = [v.name for v in vs.values() if v.causality in ("input", "local", "output")]
        for k, val in start.items():
            where = start.loc(k)
            if k not in vs:
                self.err(where, f"component {comp.name!r} ({comp.label}) has no variable {k!r}{suggest(str(k), settable)}")
                continue
            var = vs[k]
            if var.causality == "parameter":
                self.err(where, f"component {comp.name!r}: {k!r} is a parameter; set it under 'params:'")
                continue
            if var.causality == "output":
                self.err(where, f"component {comp.name!r}: {k!r} is an output; outputs are computed and have no "
                                f"start value to set")
                continue
            if not _is_number(val) or not math.isfinite(val):
                self.err(where, f"component {comp.name!r}: start value {k} = {val!r} is not a finite number")
                continue
            if var.causality == "local" and comp.block is not None and not _exact_start(comp.block, k):
                self.err(where, f"component {comp.name!r}: state {k!r} starts from the parameters (its start is "
                                f"calculated); set those parameters instead")
                continue
            comp.start[k] = float(val)

    def _fmu_values(self, comp: Component, spec: YMap) -> None:
        """``params`` and ``start`` of an FMU component, any FMI type (see :mod:`cosim.fmitypes`):
        parameters (and FMI 3.0 structural parameters, which size the arrays) under ``params``;
        inputs and variables with initial = exact or approx under ``start``."""
        params, start = spec.get("params", YMap()), spec.get("start", YMap())
        vs = comp.description.variables
        pkinds = ("parameter", "structuralParameter")
        pnames = [v.name for v in vs.values() if v.causality in pkinds and v.variability != "constant"]
        snames = [v.name for v in vs.values() if _start_settable(v)]
        structural: dict[str, int] = {}
        for pass_ in ("structural", "other"):
            for k, val in params.items():
                var = vs.get(k)
                if (var is not None and var.causality == "structuralParameter") != (pass_ == "structural"):
                    continue
                where = params.loc(k)
                if var is None or var.causality not in pkinds:
                    if var is None:
                        self.err(where, f"component {comp.name!r} ({comp.label}) has no parameter {k!r}"
                                        f"{suggest(str(k), pnames)}")
                    elif _start_settable(var):
                        self.err(where, f"component {comp.name!r}: {k!r} is a{'n' if var.causality[0] in 'aeiou' else ''} "
                                        f"{var.causality} (initial = {var.initial}), not a parameter; set its start value "
                                        f"under 'start:'")
                    else:
                        self.err(where, f"component {comp.name!r}: {k!r} is a{'n' if var.causality[0] in 'aeiou' else ''} "
                                        f"{var.causality} computed by the FMU; it cannot be set")
                    continue
                if var.variability == "constant":
                    self.err(where, f"component {comp.name!r}: parameter {k!r} is a constant and cannot be set")
                    continue
                value = self._typed_value(comp, var, val, where, "parameter")
                if value is None:
                    continue
                if pass_ == "structural":
                    structural[k] = int(value[0])
                comp.params[k] = value
            if pass_ == "structural" and structural:
                comp.description = resolve_shapes(comp.description, structural)
                vs = comp.description.variables
        for k, val in start.items():
            where = start.loc(k)
            var = vs.get(k)
            if var is None:
                self.err(where, f"component {comp.name!r} ({comp.label}) has no variable {k!r}{suggest(str(k), snames)}")
                continue
            if var.causality == "structuralParameter":
                self.err(where, f"component {comp.name!r}: {k!r} is a structural parameter (it sizes arrays and is set "
                                f"in configuration mode); set it under 'params:'")
                continue
            if var.causality == "parameter":
                self.err(where, f"component {comp.name!r}: {k!r} is a parameter; set it under 'params:'")
                continue
            if not _start_settable(var):
                what = {"output": "an output", "local": "a local variable", "independent": "the independent variable",
                        "calculatedParameter": "a calculated parameter"}.get(var.causality, var.causality)
                self.err(where, f"component {comp.name!r}: {k!r} is {what} computed by the FMU (initial = "
                                f"{var.initial or 'calculated'}); FMI allows start values only for inputs and "
                                f"variables with initial = exact or approx (here: {', '.join(snames) or 'none'})")
                continue
            value = self._typed_value(comp, var, val, where, "start value")
            if value is not None:
                comp.start[k] = value

    def _typed_value(self, comp: Component, var: Variable, val: Any, where: Loc, what: str):
        """``val`` as the values of ``var`` (a float for a scalar Float64, else a list), or None
        after reporting why it does not fit."""
        ft = TYPES.get(var.type)
        tname = display(var.type, comp.description.fmi_version)
        if ft is None:
            self.err(where, f"component {comp.name!r}: {var.name!r} is a {var.fmi_type} variable; rpr-cosim sets "
                            f"and connects {', '.join(sorted({display(t, comp.description.fmi_version) for t in TYPES}))}")
            return None
        flat = _flatten(val)
        try:
            vals = parse_start(flat, ft, var.size, f"{what} {var.name} ({tname}"
                                                   f"{', shape ' + 'x'.join(map(str, var.shape)) if var.shape else ''})", tname)
        except ValueError as exc:
            self.err(where, f"component {comp.name!r}: {exc}")
            return None
        if var.fast:
            return float(vals[0])
        return [x.item() if hasattr(x, "item") else x for x in vals]

    # connections ----------------------------------------------------------------------------------
    def endpoint(self, text: str, comps: dict[str, Component], where: Loc, side: str) -> tuple[str, str] | None:
        name, dot, var = text.partition(".")
        if not dot or not var:
            self.err(where, f"{side} {text!r} must be component.variable (e.g. mech.leg[1].s)")
            return None
        if name not in comps:
            self.err(where, f"unknown component {name!r} in {text!r}{suggest(name, comps)}")
            return None
        return name, var

    def signal(self, src: str, sv: str, dst: str, dv: str, comps: dict[str, Component], where: Loc,
               bond: str | None = None, as_type: str | None = None) -> Connection | None:
        a, b = comps[src].description.variables, comps[dst].description.variables
        ok = True
        for comp, var, vs in ((src, sv, a), (dst, dv, b)):
            if var not in vs:
                flange = comps[comp].description.flange(var)
                if flange is not None:
                    self.err(where, f"{comp}.{var} is a flange; join flanges with '<->' (a bond), not '->'")
                else:
                    cands = [n for n in vs if vs[n].causality in ("input", "output")]
                    self.err(where, f"component {comp!r} ({comps[comp].label}) has no variable {var!r}"
                                    f"{suggest(var, cands)}")
                ok = False
        if not ok:
            return None
        ca_, cb = a[sv].causality, b[dv].causality
        lhs, rhs = f"{src}.{sv}", f"{dst}.{dv}"
        if ca_ == "output" and cb == "output":
            self.err(where, f"connects two outputs ({lhs} and {rhs}); a connection goes from an output to an input")
            return None
        if ca_ == "input" and cb == "input":
            self.err(where, f"connects two inputs ({lhs} and {rhs}); a connection goes from an output to an input")
            return None
        if ca_ == "input" and cb == "output":
            self.err(where, f"is reversed: {lhs} is an input and {rhs} an output; write '{rhs} -> {lhs}'")
            return None
        if ca_ != "output":
            self.err(where, f"{lhs} is a{'n' if ca_[0] in 'aeiou' else ''} {ca_}, not an output; "
                            f"only outputs can feed a connection")
            return None
        if cb != "input":
            hint = f"; set it under components.{dst}.params" if cb == "parameter" else ""
            self.err(where, f"{rhs} is a{'n' if cb[0] in 'aeiou' else ''} {cb}, not an input{hint}")
            return None
        if not self.types_agree(comps[src], a[sv], comps[dst], b[dv], where, as_type):
            return None
        return Connection(src, sv, dst, dv, bond, where, as_type)

    def types_agree(self, ca: Component, va: Variable, cb: Component, vb: Variable, where: Loc,
                    as_type: str | None) -> bool:
        """Equal types and sizes, or an allowed conversion asked for with ``as TYPE`` (see
        :mod:`cosim.fmitypes`); otherwise report the types and the remedy."""
        lhs, rhs = f"{ca.name}.{va.name}", f"{cb.name}.{vb.name}"
        ta, tb = display(va.type, ca.description.fmi_version), display(vb.type, cb.description.fmi_version)
        for comp, var, t in ((ca, va, ta), (cb, vb, tb)):
            if var.type not in TYPES:
                self.err(where, f"{comp.name}.{var.name} is a {t} variable; {t} variables cannot be connected")
                return False
        if va.shape != vb.shape:
            shape = lambda v: "a scalar" if not v.shape else "an array of shape " + "x".join(map(str, v.shape))
            self.err(where, f"size mismatch: {lhs} is {shape(va)} ({ta}) but {rhs} is {shape(vb)} ({tb})")
            return False
        if as_type is not None and canonical(as_type) != vb.type:
            self.err(where, f"'as {as_type}' must name the type of {rhs}, which is {tb}")
            return False
        if va.type == vb.type:
            return True
        why = conversion(va.type, vb.type)
        if why is not None:
            self.err(where, f"type mismatch: {lhs} is {ta} but {rhs} is {tb}, and {ta} -> {tb} is no allowed "
                            f"conversion: {why}")
            return False
        if as_type is None:
            self.err(where, f"type mismatch: {lhs} is {ta} but {rhs} is {tb}; to convert, write "
                            f"'{lhs} -> {rhs} as {tb}'")
            return False
        return True

    def connections(self, comps: dict[str, Component]) -> tuple[list[Connection], list[tuple]]:
        node = self.tree.get("connections", YList())
        if not isinstance(node, list):
            self.err(self.tree.loc("connections"), "connections must be a list of 'a.out -> b.in' or "
                                                   "'a.flange <-> b.flange' strings")
            return [], []
        conns: list[Connection] = []
        bonds: list[tuple] = []
        fed: dict[tuple[str, str], Connection] = {}
        bonded: dict[tuple[str, str], Loc] = {}
        for i, item in enumerate(node):
            where = node.loc(i) if isinstance(node, YList) else self.tree.loc("connections")
            as_type = None
            if isinstance(item, str) and (conv := _AS.match(item)):
                item, as_type = conv.group(1), conv.group(2)
            affine = split_transform(item) if isinstance(item, str) else (item, 1.0, 0.0)
            if affine is None:
                self.err(where, f"connection {item!r}: a transformation reads '* FACTOR + OFFSET' with numbers, "
                                f"e.g. 'a.y -> b.u * 0.001 + 0.5'")
                continue
            item, factor, offset = affine
            m = _ARROW.match(item) if isinstance(item, str) else None
            if m and as_type is not None and m.group(2) != "->":
                self.err(where, f"'as {as_type}' converts a signal ('a.out -> b.in as TYPE'), not a bond")
                continue
            if not m:
                self.err(where, f"connection {item!r} must read 'a.out -> b.in' (a signal) or "
                                f"'a.flange <-> b.flange' (a power bond)")
                continue
            lhs, arrow, rhs = m.groups()
            a = self.endpoint(lhs, comps, where, "left side")
            b = self.endpoint(rhs, comps, where, "right side")
            if a is None or b is None:
                continue
            new: list[Connection] = []
            if arrow == "->":
                c = self.signal(*a, *b, comps, where, as_type=as_type)
                if c is not None:
                    new.append(dataclasses.replace(c, factor=factor, offset=offset))
            elif factor != 1.0 or offset != 0.0:
                self.err(where, f"bond {lhs} <-> {rhs}: a power bond takes no transformation")
                continue
            else:
                fa, fb = comps[a[0]].description.flange(a[1]), comps[b[0]].description.flange(b[1])
                bad = False
                for (cn, fn), fl in ((a, fa), (b, fb)):
                    if fl is None:
                        names = [f.name for f in comps[cn].description.flanges]
                        kind = f" ({fn!r} is a variable, not a flange)" if fn in comps[cn].description.variables else ""
                        self.err(where, f"component {cn!r} ({comps[cn].label}) has no flange {fn!r}{kind}"
                                        f"{suggest(fn, names)} (flanges: {', '.join(names) or 'none'})")
                        bad = True
                    elif (cn, fn) in bonded:
                        self.err(where, f"flange {cn}.{fn} is already bonded (line {bonded[(cn, fn)][1]}); "
                                        f"a flange takes one bond")
                        bad = True
                if bad:
                    continue
                if fa.causality == fb.causality:
                    what = "effort" if fa.causality == "effort_out" else "flow"
                    self.err(where, f"bond {lhs} <-> {rhs}: both flanges compute the {what} ({fa.causality}); "
                                    f"one side must take it as input")
                    continue
                eff, flo = ((a, fa), (b, fb)) if fa.causality == "effort_out" else ((b, fb), (a, fa))
                label = f"{lhs} <-> {rhs}"
                for c in (self.signal(eff[0][0], eff[1].effort, flo[0][0], flo[1].effort, comps, where, label),
                          self.signal(flo[0][0], flo[1].flow, eff[0][0], eff[1].flow, comps, where, label)):
                    if c is not None:
                        new.append(c)
                if len(new) == 2:
                    bonds.append((a[0], a[1], b[0], b[1]))
                    bonded[a] = bonded[b] = where
            for c in new:
                key = (c.dst, c.dst_var)
                if key in fed:
                    self.err(where, f"input {c.dst}.{c.dst_var} is already connected (from "
                                    f"{fed[key].src}.{fed[key].src_var}, line {fed[key].where[1]}); an input takes "
                                    f"one source")
                    continue
                fed[key] = c
                conns.append(c)
        return conns, bonds

    def unconnected(self, comps: dict[str, Component], conns: list[Connection]) -> None:
        fed = {(c.dst, c.dst_var) for c in conns}
        for comp in comps.values():
            for u in comp.description.of("input"):
                if (comp.name, u) not in fed and u not in comp.start:
                    var = comp.description.variables[u]
                    start = var.start if var.start is not None else var.raw_start
                    self.warn(comp.where, f"input {comp.name}.{u} is not connected and has no start value in the "
                                          f"scene; it keeps its default start value {start if start is not None else 0.0}")

    def algebraic_loops(self, comps: dict[str, Component], conns: list[Connection]) -> None:
        edges = [((c.src, c.src_var), (c.dst, c.dst_var)) for c in conns]
        for comp in comps.values():
            for y, us in comp.description.feedthrough.items():
                edges += [((comp.name, u), (comp.name, y)) for u in us]
        cyc = find_algebraic_loop(edges)
        if cyc:
            text = " -> ".join(f"{c}.{v}" for c, v in cyc)
            first = next((c for c in conns if (c.src, c.src_var) in cyc and (c.dst, c.dst_var) in cyc), conns[0])
            self.err(first.where, f"algebraic loop (a cycle of direct feedthrough): {text}; break it with a "
                                  f"component that has a state on the path (e.g. a motor with inductance, "
                                  f"fidelity full, or a continuous PID)")

    # master, time, outputs ------------------------------------------------------------------------------
    def master(self, comps: dict[str, Component]) -> MasterSettings | None:
        node = self.tree.get("master", YMap())
        if not isinstance(node, YMap):
            self.err(self.tree.loc("master"), f"master must be a mapping (algorithm, step, ...), got {node!r}")
            return None
        self.unknown_keys(node, MASTER_KEYS, "master")
        alg = node.get("algorithm", "gauss_seidel")
        ok = True
        if not isinstance(alg, str) or alg not in ALGORITHMS:
            self.err(node.loc("algorithm"), f"unknown master algorithm {alg!r}{suggest(str(alg), ALGORITHMS)} "
                                            f"(known: {', '.join(sorted(ALGORITHMS))})")
            ok = False
        if not node.where[0]:
            node.where = self.tree.where
        default_step = self.fmu_default(comps, "step", "master.step") if "step" not in node else None
        step = default_step or self.number(node, "step", "master.step", required=True)
        step_ns = None
        if step is not None:
            if not 0 < step <= 1e6:
                self.err(node.loc("step"), f"master.step = {step} must be positive and at most 1e6 (seconds)")
                ok = False
            else:
                step_ns = round(step * 1e9)
                if step_ns < 1 or abs(step_ns - step * 1e9) > 1e-6 * max(1.0, step * 1e9):
                    self.err(node.loc("step"), f"master.step = {step} s is not a whole number of nanoseconds")
                    ok = False
        else:
            ok = False
        engine = node.get("engine", "auto")
        if engine not in ENGINES:
            self.err(node.loc("engine"), f"master.engine = {engine!r}{suggest(str(engine), ENGINES)}; "
                                         f"expected one of {', '.join(ENGINES)}")
            ok = False
        inputs = node.get("inputs", "hold")
        if inputs not in INPUT_MODES:
            self.err(node.loc("inputs"), f"master.inputs = {inputs!r}{suggest(str(inputs), INPUT_MODES)}; expected "
                                         f"hold (zero-order hold) or linear (inputs interpolated or extrapolated "
                                         f"over the step)")
            ok = False
        order = node.get("order")
        if order is not None:
            if not isinstance(order, list) or not all(isinstance(x, str) for x in order):
                self.err(node.loc("order"), "master.order must be a list of component names")
                ok = False
            else:
                for x in order:
                    if x not in comps:
                        self.err(node.loc("order"), f"master.order names unknown component {x!r}{suggest(x, comps)}")
                        ok = False
                dup = sorted({x for x in order if order.count(x) > 1})
                missing = [c for c in comps if c not in order]
                if dup:
                    self.err(node.loc("order"), f"master.order lists {', '.join(dup)} more than once")
                    ok = False
                if missing and ok:
                    self.err(node.loc("order"), f"master.order must list every component; missing: {', '.join(missing)}")
                    ok = False
        record_every = 1
        if "output_interval" in node and step_ns:
            oi = self.number(node, "output_interval", "master.output_interval")
            if oi is not None:
                k = round(oi * 1e9 / step_ns) if 0 < oi <= 1e9 else 0
                if oi <= 0 or k < 1 or abs(k * step_ns - oi * 1e9) > 1e-6 * oi * 1e9:
                    self.err(node.loc("output_interval"), f"master.output_interval = {oi} s must be a positive "
                                                          f"whole multiple of master.step = {step} s")
                    ok = False
                else:
                    record_every = k
        if step_ns and not self.rates(comps, step_ns, alg):
            ok = False
        if step_ns:
            for comp in comps.values():
                ts, sub = comp.description.sample_period, step / comp.rate
                if ts:
                    n = round(sub / ts)
                    if n < 1 or abs(n * ts - sub) > 1e-9 * max(ts, sub):
                        good = ts * max(1, n) * comp.rate
                        at = f" / rate {comp.rate}" if comp.rate > 1 else ""
                        self.err(node.loc("step"), f"master.step{at} = {sub} s is not a whole multiple of the sample "
                                                   f"period {ts} s of {comp.name} ({comp.label}); a sampled block "
                                                   f"advances whole samples: use e.g. step: {good:g}")
                        ok = False
        realtime = self.realtime(node)
        options = self._algorithm_options(node, alg) if isinstance(alg, str) and alg in ALGORITHMS else {}
        if options is None:
            ok = False
        if not ok or step_ns is None or realtime is False:
            return None
        return MasterSettings(alg, step_ns / 1e9, step_ns, list(order) if order else None, engine, record_every,
                              inputs, realtime, options)

    def rates(self, comps: dict[str, Component], step_ns: int, alg: Any) -> bool:
        """``components.X.rate`` (doSteps per macro step, :mod:`cosim.multirate`): a whole number
        >= 1 dividing ``master.step`` into whole nanoseconds, for an algorithm that steps slaves at
        several rates.  Sets each component's ``rate``; False when one is wrong (reported)."""
        from .multirate import rate_problem

        node, good = self.tree.get("components"), True
        for name, comp in comps.items():
            spec = node.get(name) if isinstance(node, YMap) else None
            if not isinstance(spec, YMap) or "rate" not in spec:
                continue
            problem = rate_problem(spec["rate"], step_ns)
            if problem:
                self.err(spec.loc("rate"), f"component {name!r}: {problem}")
                good = False
                continue
            comp.rate = int(spec["rate"])
            cls = ALGORITHMS.get(alg) if isinstance(alg, str) else None
            if comp.rate > 1 and cls is not None and not getattr(cls, "multirate", False):
                multi = sorted(n for n, c in ALGORITHMS.items() if getattr(c, "multirate", False))
                self.err(spec.loc("rate"), f"component {name!r}: rate = {comp.rate}, but master algorithm {alg} "
                                           f"steps every slave once per step; multirate needs {' or '.join(multi)}")
                good = False
        return good

    def realtime(self, node: YMap):
        """``master.realtime``: true/false or {max_misses: N, spin: S, priority: P}; the settings,
        None (not paced) or False (invalid, reported)."""
        from .realtime import RealtimeSettings

        rt = node.get("realtime", False)
        if rt is False or rt is None:
            return None
        if rt is True:
            return RealtimeSettings()
        if not isinstance(rt, Mapping):
            self.err(node.loc("realtime"), f"master.realtime = {rt!r}; expected true, false or "
                                           f"{{max_misses: N, spin: seconds, priority: P}}")
            return False
        bad = [k for k in rt if k not in ("max_misses", "spin", "priority")]
        mm, spin, prio = rt.get("max_misses", 50), rt.get("spin", 300e-6), rt.get("priority", 0)
        whole = [isinstance(v, int) and not isinstance(v, bool) for v in (mm, prio)]
        if bad or not all(whole) or mm < 1 or not 0 <= prio <= 99 or not _is_number(spin) or not 0 <= spin < 0.1:
            self.err(node.loc("realtime"), f"master.realtime = {dict(rt)!r}; expected max_misses: a whole number "
                                           f">= 1, spin: seconds in [0, 0.1), priority: 0 (normal) .. 99 (SCHED_FIFO)")
            return False
        return RealtimeSettings(int(mm), float(spin), int(prio))

    def _algorithm_options(self, node: YMap, alg: str) -> dict[str, float] | None:
        """``master.options`` checked against the options the algorithm declares (None on error)."""
        declared = getattr(ALGORITHMS[alg], "options", ())
        given = node.get("options", YMap())
        if not isinstance(given, YMap):
            self.err(node.loc("options"), f"master.options must be a mapping of option -> value, got {given!r}")
            return None
        if given and not declared:
            self.err(node.loc("options"), f"master algorithm {alg} has no options")
            return None
        from .adaptive import option_values

        try:
            return option_values(dict(given), declared)
        except ValueError as exc:
            bad = next((k for k in given if str(k) in str(exc)), None)
            self.err(given.loc(bad) if bad is not None else node.loc("options"), f"master.options: {exc}")
            return None

    def fmu_default(self, comps: dict[str, Component], key: str, what: str) -> float | None:
        """The FMUs' DefaultExperiment value ``key`` (start, stop, step) when they agree; an error
        naming them when they differ; None when none gives one."""
        given = {c.name: c.description.default_experiment[key] for c in comps.values()
                 if key in c.description.default_experiment}
        if len(set(given.values())) > 1:
            text = ", ".join(f"{n}: {v:g} s" for n, v in given.items())
            self.err(self.tree.where, f"the FMUs' default experiments disagree on the {what} ({text}); set {what} "
                                      f"in the scene")
            return None
        return next(iter(given.values()), None)

    def times(self, master: MasterSettings | None, comps: dict[str, Component]
              ) -> tuple[float | None, int | None, float, int]:
        """(stop_time, n_steps, start_time, start_ns): the scene's values, else the FMUs' default
        experiment; the run goes from start_time to stop_time in whole steps."""
        start, start_ns = 0.0, 0
        if "start_time" in self.tree:
            start = self.number(self.tree, "start_time", "start_time")
        else:
            start = self.fmu_default(comps, "start", "start_time") or 0.0
        if start is not None and not abs(start) < 1e12:
            self.err(self.tree.loc("start_time"), f"start_time = {start} must be a finite number of seconds below 1e12")
            start = None
        if start is not None:
            start_ns = round(start * 1e9)
            if abs(start_ns - start * 1e9) > 1e-6 * max(1.0, abs(start) * 1e9):
                self.err(self.tree.loc("start_time"), f"start_time = {start} s is not a whole number of nanoseconds")
                start = None
        if start is None:
            return None, None, 0.0, 0
        if "stop_time" in self.tree:
            stop = self.number(self.tree, "stop_time", "stop_time")
        else:
            stop = self.fmu_default(comps, "stop", "stop_time")
            if stop is None and not any(p.severity == "error" and "stop_time" in p.message for p in self.problems):
                self.err(self.tree.where, "stop_time is missing; expected a number in seconds (no FMU of the scene "
                                          "gives one in its default experiment)")
        if stop is None:
            return None, None, start, start_ns
        if not stop < 1e12:
            self.err(self.tree.loc("stop_time"), f"stop_time = {stop} must be a finite number of seconds below 1e12")
            return None, None, start, start_ns
        if stop <= start:
            self.err(self.tree.loc("stop_time"), f"stop_time = {stop} must be positive (seconds from the start)"
                     if start == 0 else f"stop_time = {stop} must be after the start time {start} s")
            return None, None, start, start_ns
        if master is None:
            return stop, None, start, start_ns
        span = stop * 1e9 - start_ns
        n = round(span / master.step_ns)
        if abs(n * master.step_ns - span) > 1e-6 * span:
            lo, hi = math.floor(span / master.step_ns), math.ceil(span / master.step_ns)
            self.err(self.tree.loc("stop_time"), f"stop_time = {stop} s is not a whole number of steps of "
                                                 f"{master.step} s{f' from the start {start:g} s' if start else ''}; use "
                                                 f"{start + lo * master.step:g} or {start + hi * master.step:g}")
            return None, None, start, start_ns
        return stop, n, start, start_ns

    def outputs(self, comps: dict[str, Component]) -> list[str]:
        node = self.tree.get("outputs")
        signals = [f"{c.name}.{v}" for c in comps.values() for v in c.description.of("output", "input")
                   if c.description.variables[v].type in TYPES]
        if node is None:
            return [f"{c.name}.{v}" for c in comps.values() for v in c.description.of("output")
                    if c.description.variables[v].type in TYPES]
        if isinstance(node, str):
            node = [node]
        if not isinstance(node, list):
            self.err(self.tree.loc("outputs"), "outputs must be a list of 'component.variable' patterns")
            return []
        every = {f"{c.name}.{v}": var for c in comps.values() for v, var in c.description.variables.items()
                 if var.type in TYPES and var.causality != "independent"}
        out: list[str] = []
        for i, pat in enumerate(node):
            where = node.loc(i) if isinstance(node, YList) else self.tree.loc("outputs")
            if not isinstance(pat, str):
                self.err(where, f"output pattern {pat!r} must be a string 'component.variable'")
                continue
            if pat in every:
                hits = [pat]
            else:
                rx = re.compile(fnmatch.translate(pat.replace("[", "\0").replace("]", "\1"))
                                .replace("\0", r"\[").replace("\1", r"\]"))
                hits = [s for s in signals if rx.match(s)]
            if not hits:
                self.err(where, f"output pattern {pat!r} matches no input or output{suggest(pat, signals)}")
            out.extend(h for h in hits if h not in out)
        return out


def _start_settable(var: Variable) -> bool:
    """FMI allows a start value before initialisation: inputs, and non-parameter variables with
    initial = exact or approx."""
    if var.variability == "constant" or var.causality in ("independent", "parameter", "structuralParameter",
                                                          "calculatedParameter"):
        return False
    return var.causality == "input" or var.initial in ("exact", "approx")


def _flatten(val: Any) -> Any:
    """Nested YAML lists (a matrix) as one row-major list; anything else unchanged."""
    if isinstance(val, (list, tuple)):
        out: list = []
        for x in val:
            out.extend(_flatten(x) if isinstance(x, (list, tuple)) else [x])
        return out
    return val


def _exact_start(block, state: str) -> bool:
    import casadi as ca

    i = block.index("states", state)
    return not (block.p.numel() and ca.depends_on(block.start[i], block.p))


def _hash(data: dict, comps: Mapping[str, Component]) -> str:
    h = hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode())
    for name in sorted(comps):
        c = comps[name]
        if c.fmu is not None:
            h.update(name.encode() + hashlib.sha256(c.fmu.read_bytes()).digest())
    return h.hexdigest()


def validate(tree: YMap, path: Path | None = None, *, catalog=None, problems: list[Problem] | None = None) -> Scene:
    """Check a merged scene tree; raises :class:`SceneError` with every problem found."""
    ck = _Checker(tree, path, catalog)
    ck.problems.extend(problems or [])
    ck.unknown_keys(tree, [k for k in TOP_KEYS if k != "include"], "the scene")
    node = tree.get("components")
    comps: dict[str, Component] = {}
    if not isinstance(node, YMap) or not node:
        ck.err(tree.loc("components") if "components" in tree else tree.where,
               "the scene needs 'components:', a mapping of name -> {model: ...} or {fmu: ...}")
    else:
        for name, spec in node.items():
            c = ck.component(str(name), spec, node.loc(name))
            if c is not None:
                comps[c.name] = c
    broken = isinstance(node, YMap) and len(comps) != len(node)
    conns, bonds = ck.connections(comps) if comps else ([], [])
    master = ck.master(comps)
    stop, n_steps, start, start_ns = ck.times(master, comps)
    outputs = ck.outputs(comps) if comps else []
    if comps and not broken:
        ck.unconnected(comps, conns)
    if conns:
        ck.algebraic_loops(comps, conns)
    from .guards import check_scene, parse_settings

    guards = parse_settings(tree.get("guards"), lambda _key: tree.loc("guards"), ck.err)
    if comps and not broken:
        check_scene(guards, comps, stop - start if stop is not None else None, ck.err, ck.warn)
    errors = [p for p in ck.problems if p.severity == "error"]
    if errors:
        raise SceneError(ck.problems)
    from .outputs import name_problem, stem_name

    name = tree.get("name") or stem_name(path.stem if path else "scene")
    if name_problem(name):
        ck.err(tree.loc("name"), name_problem(name))
        raise SceneError(ck.problems)
    data = plain(tree)
    return Scene(str(name), path, str(tree.get("description", "")), stop, n_steps, comps, conns, bonds, master,
                 outputs, data, _hash(data, comps), [p for p in ck.problems if p.severity != "error"], start, start_ns,
                 guards)


def load(path: Path | str, overrides: Mapping[str, Any] | Sequence[str] | None = None, *, catalog=None) -> Scene:
    """Read, merge (includes), override and validate the scene at ``path``.

    Raises :class:`SceneError` listing every problem, each as ``file:line: error: message``."""
    path = Path(path)
    problems: list[Problem] = []
    tree = load_raw(path, problems)
    if tree is None:
        raise SceneError(problems)
    tree = apply_overrides(tree, overrides)
    auto = _auto_fidelity_loc(tree)
    if auto is not None:  # 'fidelity: auto': the cheapest levels within fidelity_tolerance (cosim.study.fidelity)
        from .study.fidelity import resolve_auto

        tree, note = resolve_auto(tree, path)
        problems.append(Problem(auto[0], auto[1], note, "note"))
    return validate(tree, path, catalog=catalog, problems=problems)


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
