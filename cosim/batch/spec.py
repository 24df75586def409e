"""Batch files: YAML that names a base scene and what to vary over it, checked like a scene
(file, line, closest valid name) before anything runs.

Format (``scene`` and at least one of ``grid``/``zip``/``random`` are needed)::

    name: pid_gains                     # default: the file's stem
    description: free text
    scene: pid_step.yaml                # the base scene, relative to this file
    set: {stop_time: 3.0}               # overrides for every run (the paths of --set)
    grid:                               # every combination of these axes
      Kp: {path: "components.pid*.params.Kp", values: [10, 20, 30]}   # '*' over component names:
                                                                      # one value set on all matches
      components.pid1.params.Ki: [40, 80]           # a path as the axis name, a list of values
      master.step: {from: 1e-3, to: 1.25e-4, num: 4, scale: log}      # or linear (default)
    zip:                                # taken together, item by item (equal lengths)
      master.step: [1e-3, 5e-4]
      master.output_interval: [1e-3, 5e-4]
    random:                             # Monte Carlo samples, reproducible from the seed
      seed: 2024
      samples: 64
      axes:
        m_p: {path: components.mech.params.m_p, dist: normal, mean: 1.7, std: 0.17}
        b1:  {path: components.motor1.params.b, dist: log_uniform, low: 4e-5, high: 2e-4}
        R:   {path: components.motor1.params.R, dist: uniform, low: 0.5, high: 0.65}
    reference: monolithic               # or {trace: ref.csv}: what '*_error' metrics compare against
    metrics:                            # per recorded signal: a list of measures, or a mapping
      mech.platform.phi: {target: 0.2, band: 0.02, measure: [overshoot, settling_time, end_error, {at: [1.0]}]}
      mech.leg[1].f: [max_abs, rms]
    report:
      sort: mech.platform.phi:overshoot # a results column (default: the first metric)
      plots:
        - {kind: lines, metric: "mech.platform.phi:overshoot", x: Kp, lines: Kd}
        - {kind: heatmap, metric: "mech.platform.phi:settling_time", x: Kp, y: Kd}
        - {kind: hist, metric: "mech.platform.phi:end_error"}
        - {kind: traces, signal: mech.platform.phi, runs: 8}       # the 8 first by the sort column

The runs are the product grid x zip x samples (an absent block counts once).  Measures and
targets are described in :mod:`cosim.batch.metrics`.
"""
from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import RUN_ERRORS, UserError
from ..scenario import TOP_KEYS as SCENE_KEYS
from ..scenario import Problem, SceneError, YList, YMap, apply_overrides, load_raw, read_yaml, suggest, validate
from ..outputs import TRACE_SUFFIXES, name_problem, stem_name
from ..scenario.loading import NO_AUTO_FIDELITY
from ..scenario.overrides import expand_path
from .metrics import MEASURES, NEEDS_TARGET, MetricSpec
from .results import base_columns

Loc = tuple[str, int]

#: Default largest number of runs of a batch; ``$RPR_COSIM_MAX_RUNS`` or ``max_runs`` raise it.
MAX_RUNS = 100_000
MAX_RUNS_ENV = "RPR_COSIM_MAX_RUNS"

#: Top-level keys of a batch file -> what each holds (the checks below accept exactly these; the
#: documentation's batch-format reference is generated from these declarations).
TOP = {
    "name": "the batch's name (default: the file's stem); the output directory is runs/<name>",
    "description": "free text",
    "scene": "the base scene, relative to the batch file",
    "set": "overrides for every run: a mapping of the paths `--set` takes to values",
    "grid": "axes whose every combination runs: axis name -> values, or `{path, values}` / `{path, from, to, num, "
            "scale}`",
    "zip": "axes taken together, item by item (lists of equal lengths)",
    "random": "Monte Carlo samples: `{seed, samples, axes: {name: {path, dist, ...}}}`",
    "reference": "what `*_error` measures compare against: `monolithic` or `{trace: FILE}`",
    "metrics": "per recorded signal: a list of measures, or `{target, band, measure}`",
    "report": "`{sort: COLUMN, plots: [...]}`: the printed table's order and the charts",
}
#: Keys of one grid or zip axis given as a mapping -> what each holds.
AXIS = {
    "path": "the scene path it sets (as `--set`; `*` over component names sets every match)",
    "values": "the list of values",
    "from": "first value of a range",
    "to": "last value of a range",
    "num": "number of values of a range",
    "scale": "`linear` (default) or `log` spacing of a range",
}
#: Keys of ``random:`` -> what each holds.
RANDOM = {
    "seed": "a whole number: the samples are reproducible from it",
    "samples": "number of samples",
    "axes": "axis name -> `{path, dist, ...}` with the distribution's parameters",
}
TOP_KEYS = tuple(TOP)
AXIS_KEYS = tuple(AXIS)
RANDOM_KEYS = tuple(RANDOM)
DIST_KEYS = {"uniform": ("low", "high"), "normal": ("mean", "std"), "log_uniform": ("low", "high")}
METRIC_KEYS = ("target", "band", "measure")
PLOT_KINDS = {"lines": ("metric", "x", "lines"), "heatmap": ("metric", "x", "y"), "hist": ("metric",),
              "traces": ("signal", "runs")}


class BatchError(SceneError):
    """A batch file that cannot run; :attr:`problems` lists every problem found (one line each)."""


# --- the validated batch ------------------------------------------------------------------------
@dataclass(frozen=True)
class Distribution:
    """A sampling distribution: ``uniform(low, high)``, ``normal(mean, std)`` or
    ``log_uniform(low, high)`` (uniform in log, ``0 < low < high``)."""

    kind: str
    a: float
    b: float

    def sample(self, rng: np.random.Generator) -> float:
        if self.kind == "uniform":
            return float(rng.uniform(self.a, self.b))
        if self.kind == "normal":
            return float(rng.normal(self.a, self.b))
        return float(math.exp(rng.uniform(math.log(self.a), math.log(self.b))))

    def typical(self) -> float:
        """A value inside the support (for checking the path before sampling)."""
        return math.sqrt(self.a * self.b) if self.kind == "log_uniform" else (
            self.a if self.kind == "normal" else 0.5 * (self.a + self.b))


@dataclass(frozen=True)
class Axis:
    """One swept quantity: its column ``name``, the scene ``paths`` it sets (several when the
    path had a '*' over component names), and its ``values`` (grid, zip) or ``dist`` (random)."""

    name: str
    paths: tuple[str, ...]
    values: tuple = ()
    dist: Distribution | None = None
    where: Loc = ("", 0)
    value_locs: tuple[Loc, ...] = ()

    def key(self) -> int:
        """A stable integer for this axis in the random streams (from its name)."""
        return int.from_bytes(hashlib.sha256(self.name.encode()).digest()[:4], "little")


@dataclass(frozen=True)
class PlotSpec:
    kind: str  # lines | heatmap | hist | traces
    metric: str | None = None
    x: str | None = None
    y: str | None = None  # heatmap rows, or the 'lines' axis
    signal: str | None = None
    runs: Any = 8  # traces: how many runs (first by the sort column), or a list of run ids
    where: Loc = ("", 0)


@dataclass
class Batch:
    """A validated batch file (see the module docstring)."""

    name: str
    path: Path
    description: str
    scene_path: Path
    fixed: dict[str, Any]
    grid: list[Axis]
    zip: list[Axis]
    random: list[Axis]
    seed: int | None
    samples: int
    reference: str | Path | None  # None, "monolithic" or the path of a trace file
    metrics: list[MetricSpec]
    sort: str | None
    plots: list[PlotSpec]
    base_tree: YMap = field(repr=False, default=None)
    where: dict[str, Loc] = field(default_factory=dict)
    notes: list[Problem] = field(default_factory=list)  # warnings and notes (e.g. the 'auto' fidelity chosen)

    @property
    def axes(self) -> list[Axis]:
        return [*self.grid, *self.zip, *self.random]

    @property
    def metric_columns(self) -> list[str]:
        return [m.column for m in self.metrics]

    @property
    def n_runs(self) -> int:
        n = math.prod(len(a.values) for a in self.grid)
        if self.zip:
            n *= len(self.zip[0].values)
        return n * (self.samples if self.random else 1)


#: Scene paths that are times [s].
_TIME_PATHS = ("stop_time", "start_time", "master.step", "master.output_interval")


def axis_units(batch: Batch) -> dict[str, str]:
    """Axis name -> the unit of the scene value it sets: a component parameter's unit (from its
    description), seconds for the times and steps; absent where none is known."""
    out: dict[str, str] = {}
    try:
        scene = validate(apply_overrides(batch.base_tree, batch.fixed), batch.scene_path)
    except (SceneError, UserError):  # a chart's label only: without the scene, no unit
        return out
    for axis in batch.axes:
        path = axis.paths[0] if axis.paths else ""
        parts = path.split(".")
        if path in _TIME_PATHS:
            out[axis.name] = "s"
        elif len(parts) == 4 and parts[0] == "components" and parts[2] == "params":
            comp = scene.components.get(parts[1])
            var = comp.description.variables.get(parts[3]) if comp is not None and comp.description else None
            if var is not None and var.unit:
                out[axis.name] = var.unit
    return out


# --- checking -----------------------------------------------------------------------------------
def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class _Checker:
    limit = MAX_RUNS  # the run limit of the batch being read (load_batch sets it)

    def __init__(self, file: str):
        self.file = file
        self.problems: list[Problem] = []

    def err(self, where: Loc, msg: str) -> None:
        self.problems.append(Problem(where[0] or self.file, where[1], msg))

    @property
    def failed(self) -> bool:
        return any(p.severity == "error" for p in self.problems)

    def keys(self, node: YMap, allowed: Sequence[str], what: str) -> bool:
        ok = True
        for k in node:
            if k not in allowed:
                self.err(node.loc(k), f"unknown key {k!r} in {what}{suggest(str(k), allowed)} "
                                      f"(expected: {', '.join(allowed)})")
                ok = False
        return ok

    def mapping(self, tree: YMap, key: str, what: str) -> YMap | None:
        node = tree.get(key)
        if node is None:
            return None
        if not isinstance(node, YMap):
            self.err(tree.loc(key), f"{what} must be a mapping, got {node!r}")
            return None
        return node


def _grid_values(ck: _Checker, name: str, node: Any, where: Loc) -> tuple[tuple, tuple[Loc, ...]]:
    """Values of a grid/zip axis given as a list or as {from, to, num, scale}."""
    if isinstance(node, YList):
        if not node:
            ck.err(where, f"axis {name!r} is empty; give at least one value")
            return (), ()
        bad = [(i, v) for i, v in enumerate(node) if isinstance(v, (YMap, YList))]
        for i, v in bad:
            ck.err(node.loc(i), f"axis {name!r}: value {v!r} must be a number or a word, not a "
                                f"{'mapping' if isinstance(v, YMap) else 'list'}")
        return tuple(node), tuple(node.loc(i) for i in range(len(node)))
    if isinstance(node, YMap) and ("from" in node or "to" in node or "num" in node):
        ok = all(_is_number(node.get(k)) for k in ("from", "to")) and isinstance(node.get("num"), int) \
            and not isinstance(node.get("num"), bool)
        if not ok:
            ck.err(node.where, f"axis {name!r}: a range needs numbers from:, to: and a whole num:, "
                               f"e.g. {{from: 10, to: 50, num: 5}}")
            return (), ()
        num, scale = node["num"], node.get("scale", "linear")
        if num < 1:
            ck.err(node.loc("num"), f"axis {name!r} is empty: num = {num}; give at least 1")
            return (), ()
        if num > ck.limit:  # refused before the values are made
            ck.err(node.loc("num"), f"axis {name!r}: num = {num:,} values, more than the limit of {ck.limit:,} "
                                    f"runs; sweep fewer values or raise the limit (${MAX_RUNS_ENV})")
            return (), ()
        if scale not in ("linear", "log"):
            ck.err(node.loc("scale"), f"axis {name!r}: scale = {scale!r}{suggest(str(scale), ['linear', 'log'])}; "
                                      f"expected linear or log")
            return (), ()
        a, b = float(node["from"]), float(node["to"])
        if scale == "log" and not (a > 0 and b > 0):
            ck.err(node.where, f"axis {name!r}: a log range needs positive from: and to:, got {a:g} and {b:g}")
            return (), ()
        vals = np.geomspace(a, b, num) if scale == "log" else np.linspace(a, b, num)
        return tuple(float(v) for v in vals), (node.where,) * num
    ck.err(where, f"axis {name!r}: expected a list of values or {{from:, to:, num:}}, got {node!r}")
    return (), ()


def _axis(ck: _Checker, name: Any, node: Any, where: Loc, components: Sequence[str], kind: str) -> Axis | None:
    name = str(name)
    path = name
    if isinstance(node, YMap) and "path" in node:
        path = node["path"]
        if not isinstance(path, str):
            ck.err(node.loc("path"), f"axis {name!r}: path must be a scene path like components.pid1.params.Kp")
            return None
    elif "." not in name and name not in SCENE_KEYS:
        ck.err(where, f"axis {name!r} is not a scene path; give one with path: (e.g. {{path: "
                      f"components.pid1.params.Kp, values: [...]}}) or use the path as the name")
        return None
    paths, msg = expand_path(path, components)
    if msg:
        ck.err(node.loc("path") if isinstance(node, YMap) and "path" in node else where, msg)
        return None
    if kind == "random":
        return _random_axis(ck, name, node, where, tuple(paths))
    if isinstance(node, YMap):
        allowed = AXIS_KEYS
        if not ck.keys(node, allowed, f"axis {name!r}"):
            return None
        if "values" in node:
            vals, locs = _grid_values(ck, name, node["values"], node.loc("values"))
        elif any(k in node for k in ("from", "to", "num")):
            vals, locs = _grid_values(ck, name, node, where)
        else:
            ck.err(where, f"axis {name!r} needs values: [...] or from:, to:, num:")
            return None
    else:
        vals, locs = _grid_values(ck, name, node, where)
    if not vals:
        return None
    return Axis(name, tuple(paths), vals, None, where, locs)


def _random_axis(ck: _Checker, name: str, node: Any, where: Loc, paths: tuple[str, ...]) -> Axis | None:
    if not isinstance(node, YMap) or "dist" not in node:
        ck.err(where, f"random axis {name!r} needs a distribution, e.g. {{path: ..., dist: uniform, low: 1, high: 2}} "
                      f"(dist: {', '.join(DIST_KEYS)})")
        return None
    kind = node["dist"]
    if kind not in DIST_KEYS:
        ck.err(node.loc("dist"), f"random axis {name!r}: unknown distribution {kind!r}{suggest(str(kind), DIST_KEYS)} "
                                 f"(known: {', '.join(DIST_KEYS)})")
        return None
    a_key, b_key = DIST_KEYS[kind]
    if not ck.keys(node, ("path", "dist", a_key, b_key), f"random axis {name!r} ({kind})"):
        return None
    for k in (a_key, b_key):
        if k not in node:
            ck.err(node.where, f"random axis {name!r}: {kind} needs {a_key}: and {b_key}:")
            return None
        if not _is_number(node[k]):
            ck.err(node.loc(k), f"random axis {name!r}: {k} = {node[k]!r} is not a finite number")
            return None
    a, b = float(node[a_key]), float(node[b_key])
    if kind == "normal" and not b > 0:
        ck.err(node.loc("std"), f"random axis {name!r}: std = {b:g} must be positive")
        return None
    if kind != "normal" and not a < b:
        ck.err(node.loc("high"), f"random axis {name!r}: {kind} needs low < high, got low = {a:g}, high = {b:g}")
        return None
    if kind == "log_uniform" and not a > 0:
        ck.err(node.loc("low"), f"random axis {name!r}: log_uniform needs low > 0, got {a:g}")
        return None
    return Axis(name, paths, (), Distribution(kind, a, b), where, ())


def _axes(ck: _Checker, tree: YMap, key: str, components: Sequence[str], kind: str | None = None) -> list[Axis]:
    node = ck.mapping(tree, key, f"{key} (axis name -> values)")
    if node is None:
        return []
    if not node:
        ck.err(tree.loc(key), f"{key} has no axes")
    out = []
    for name, spec in node.items():
        ax = _axis(ck, name, spec, node.loc(name), components, kind or key)
        if ax is not None:
            out.append(ax)
    return out


def _random(ck: _Checker, tree: YMap, components: Sequence[str]) -> tuple[list[Axis], int | None, int]:
    node = ck.mapping(tree, "random", "random (seed, samples, axes)")
    if node is None:
        return [], None, 0
    ck.keys(node, RANDOM_KEYS, "random")
    seed = node.get("seed")
    if "seed" not in node:
        ck.err(node.where, "random needs seed: (a whole number), so that the samples can be drawn again")
        seed = None
    elif not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        ck.err(node.loc("seed"), f"random.seed = {seed!r} must be a whole number (0 or more)")
        seed = None
    samples = node.get("samples")
    if not isinstance(samples, int) or isinstance(samples, bool) or samples < 1:
        ck.err(node.loc("samples") if "samples" in node else node.where,
               f"random.samples = {samples!r} must be a whole number of runs (1 or more)")
        samples = 0
    axes = _axes(ck, node, "axes", components, "random") if "axes" in node else []
    if "axes" not in node:
        ck.err(node.where, "random needs axes: (name -> {path:, dist:, ...})")
    return axes, seed, samples


def _reference(ck: _Checker, tree: YMap, base: Path) -> str | Path | None:
    if "reference" not in tree:
        return None
    node = tree["reference"]
    if node == "monolithic":
        return "monolithic"
    if isinstance(node, YMap) and set(node) == {"trace"} and isinstance(node["trace"], str):
        p = base / node["trace"]
        if not p.is_file():
            near = suggest(Path(node["trace"]).name, [q.name for q in p.parent.glob("*") if q.suffix in TRACE_SUFFIXES]) \
                if p.parent.is_dir() else ""
            ck.err(node.loc("trace"), f"reference trace {node['trace']!r} not found (looked in {p.parent}){near}")
            return None
        return p
    ck.err(tree.loc("reference"), f"reference = {node!r}; expected monolithic (each run's scene integrated as one "
                                  f"ODE) or {{trace: file.csv}}")
    return None


def _metrics(ck: _Checker, tree: YMap, has_reference: bool) -> list[MetricSpec]:
    node = ck.mapping(tree, "metrics", "metrics (signal -> measures)")
    if node is None:
        return []
    out: list[MetricSpec] = []
    for signal, spec in node.items():
        where = node.loc(signal)
        target, band, measures = None, 0.02, spec
        if isinstance(spec, YMap):
            if not ck.keys(spec, METRIC_KEYS, f"metrics of {signal}"):
                continue
            target = spec.get("target")
            band = spec.get("band", 0.02)
            measures = spec.get("measure")
            if measures is None:
                ck.err(spec.where, f"metrics of {signal}: measure: is missing (e.g. [max, rms, end_error])")
                continue
            if not _is_number(band) or not 0 < band < 1:
                ck.err(spec.loc("band"), f"metrics of {signal}: band = {band!r} must be a fraction of the step "
                                         f"between 0 and 1 (e.g. 0.02)")
                continue
            if target is not None and not (_is_number(target) or isinstance(target, str)):
                ck.err(spec.loc("target"), f"metrics of {signal}: target = {target!r}; expected a number, a "
                                           f"recorded signal or 'reference'")
                continue
            if target == "reference" and not has_reference:
                ck.err(spec.loc("target"), f"metrics of {signal}: target: reference needs the batch's "
                                           f"reference: (monolithic or {{trace: file.csv}})")
                continue
        if isinstance(measures, str):
            measures = YList([measures])
            measures.where, measures.locs = where, [where]
        if not isinstance(measures, YList) or not measures:
            ck.err(where, f"metrics of {signal}: expected a list of measures ({', '.join(MEASURES)})")
            continue
        if target is None and has_reference:
            target = "reference"
        for i, m in enumerate(measures):
            mloc = measures.loc(i)
            if isinstance(m, YMap) and set(m) == {"at"}:
                ts = m["at"] if isinstance(m["at"], list) else [m["at"]]
                if not ts or not all(_is_number(t) and t >= 0 for t in ts):
                    ck.err(mloc, f"metrics of {signal}: at: expects instants in seconds (>= 0), got {m['at']!r}")
                    continue
                out += [MetricSpec(str(signal), "at", float(t), target, band, mloc) for t in ts]
                continue
            if not isinstance(m, str) or m not in MEASURES:
                ck.err(mloc, f"metrics of {signal}: unknown measure {m!r}{suggest(str(m), MEASURES)} "
                             f"(measures: {', '.join(MEASURES)}, {{at: [t, ...]}})")
                continue
            if m in NEEDS_TARGET and target is None:
                ck.err(mloc, f"metrics of {signal}: {m} needs a target: (a number or a recorded signal) or the "
                             f"batch's reference:")
                continue
            out.append(MetricSpec(str(signal), m, None, target, float(band), mloc))
    cols = [m.column for m in out]
    for m in out:
        if cols.count(m.column) > 1:
            ck.err(m.where, f"metric {m.column} is listed twice")
            cols = [c for c in cols if c != m.column]
    return out


def _report(ck: _Checker, tree: YMap, columns: Sequence[str], axes: Sequence[str],
            metrics: Sequence[str]) -> tuple[str | None, list[PlotSpec]]:
    node = ck.mapping(tree, "report", "report (sort, plots)")
    if node is None:
        return None, []
    ck.keys(node, ("sort", "plots"), "report")
    sort = node.get("sort")
    if sort is not None and sort not in columns:
        ck.err(node.loc("sort"), f"report.sort = {sort!r} is not a column{suggest(str(sort), columns)} "
                                 f"(metrics: {', '.join(metrics) or 'none'})")
        sort = None
    plots: list[PlotSpec] = []
    items = node.get("plots", [])
    if not isinstance(items, list):
        ck.err(node.loc("plots"), "report.plots must be a list of {kind: lines|heatmap|hist|traces, ...}")
        return sort, []
    for i, p in enumerate(items):
        where = items.loc(i) if isinstance(items, YList) else node.loc("plots")
        if not isinstance(p, YMap) or p.get("kind") not in PLOT_KINDS:
            kind = p.get("kind") if isinstance(p, YMap) else p
            ck.err(where, f"plot {kind!r}{suggest(str(kind), PLOT_KINDS)}: expected a mapping with kind: "
                          f"{' | '.join(PLOT_KINDS)}")
            continue
        kind = p["kind"]
        if not ck.keys(p, ("kind", *PLOT_KINDS[kind]), f"a {kind} plot"):
            continue
        ok = True
        for k in PLOT_KINDS[kind]:
            v = p.get(k)
            if k == "metric":
                if v not in metrics:
                    ck.err(p.loc(k) if k in p else where, f"{kind} plot: metric = {v!r}{suggest(str(v), metrics)} "
                                                          f"(metrics: {', '.join(metrics) or 'none'})")
                    ok = False
            elif k in ("x", "y", "lines"):
                if v is None and k == "lines":
                    continue
                if v not in axes:
                    ck.err(p.loc(k) if k in p else where, f"{kind} plot: {k} = {v!r} is not an axis"
                                                          f"{suggest(str(v), axes)} (axes: {', '.join(axes)})")
                    ok = False
            elif k == "signal":
                if not isinstance(v, str):
                    ck.err(p.loc(k) if k in p else where, f"traces plot: signal: names a recorded signal")
                    ok = False
            elif k == "runs" and v is not None:
                if not ((isinstance(v, int) and not isinstance(v, bool) and v > 0) or v == "all"
                        or (isinstance(v, list) and all(isinstance(x, str) for x in v))):
                    ck.err(p.loc(k), f"traces plot: runs = {v!r}; expected a number of runs, 'all' or a list of run ids")
                    ok = False
        if ok:
            plots.append(PlotSpec(kind, p.get("metric"), p.get("x"), p.get("y", p.get("lines")), p.get("signal"),
                                  p.get("runs", 8), where))
    return sort, plots


def _check_paths(ck: _Checker, base: YMap, scene_path: Path, fixed: dict, grid: Sequence[Axis],
                 zipped: Sequence[Axis], rnd: Sequence[Axis], set_loc: Loc, catalog=None) -> None:
    """Apply each axis value (alone, over the fixed overrides) to the base scene and validate it,
    so that a wrong path or value is reported at the batch file's line."""
    def trial(over: dict) -> str:
        try:
            validate(apply_overrides(base, over), scene_path, catalog=catalog)
        except SceneError as exc:
            errs = [p for p in exc.problems if p.severity == "error"]
            return errs[0].message if errs else str(exc)
        return ""

    msg = trial(fixed)
    if msg:
        ck.err(set_loc, f"set: {msg}")
        return
    for ax in [*grid, *rnd]:
        values = ax.values if ax.dist is None else (ax.dist.typical(),)
        locs = ax.value_locs or (ax.where,) * len(values)
        for v, loc in zip(values, locs):
            msg = trial({**fixed, **{p: v for p in ax.paths}})
            if msg:
                ck.err(loc, f"axis {ax.name!r} = {v!r}: {msg}")
                break
    for i in range(len(zipped[0].values) if zipped else 0):  # zipped values go together
        msg = trial({**fixed, **{p: ax.values[i] for ax in zipped for p in ax.paths}})
        if msg:
            row = ", ".join(f"{ax.name}={ax.values[i]!r}" for ax in zipped)
            ck.err(zipped[0].value_locs[i], f"zip item {i + 1} ({row}): {msg}")
            break


def _resolve_auto(ck: _Checker, base: YMap, scene_path: Path, fixed: dict, where: Loc, auto_fidelity) -> YMap:
    """``fidelity: auto`` in the base scene is resolved once (as :func:`cosim.scenario.load`
    does), with the batch's fixed overrides; every run then uses the levels chosen."""
    comps = base.get("components")
    if not (isinstance(comps, YMap) and any(isinstance(c, YMap) and c.get("fidelity") == "auto" and "model" in c
                                            for c in comps.values())):
        return base
    if auto_fidelity is None:
        ck.err(where, NO_AUTO_FIDELITY)
        return base
    try:
        tree, note = auto_fidelity(apply_overrides(base, fixed), scene_path)
    except RUN_ERRORS as exc:
        ck.err(where, f"fidelity: auto: {exc}")
        return base
    ck.problems.append(Problem(where[0], where[1], note, "note"))
    return tree


def max_runs(value: object = None) -> int:
    """The run limit: ``value``, else ``$RPR_COSIM_MAX_RUNS``, else :data:`MAX_RUNS`."""
    import os

    raw = value if value is not None else os.environ.get(MAX_RUNS_ENV) or MAX_RUNS
    try:
        n = int(float(raw))
    except (TypeError, ValueError, OverflowError):
        n = -1
    if n < 1 or isinstance(raw, bool):
        raise UserError(f"{'max_runs' if value is not None else '$' + MAX_RUNS_ENV}: expected a whole number of runs "
                        f"(1 or more), got {raw!r}")
    return n


def _count_runs(ck: _Checker, data: YMap, grid: Sequence[Axis], zipped: Sequence[Axis], samples: int | None,
                has_random: bool, limit: int) -> None:
    """Refuse, with the numbers, a batch of more than ``limit`` runs (counted, not expanded)."""
    sizes = [f"{len(a.values):,} ({a.name})" for a in grid]
    n = math.prod(len(a.values) for a in grid)
    if zipped:
        n *= len(zipped[0].values)
        sizes.append(f"{len(zipped[0].values):,} (zip)")
    if has_random and isinstance(samples, int):
        n *= samples
        sizes.append(f"{samples:,} (random.samples)")
    if n > limit:
        ck.err(data.where, f"the batch makes {n:,} runs ({' x '.join(sizes)}), more than the limit of {limit:,}; "
                           f"split it, sweep fewer values, or raise the limit (${MAX_RUNS_ENV})")


def load_batch(path: Path | str, *, catalog=None, auto_fidelity=None, max_runs_: int | None = None) -> Batch:
    """Read and check a batch file; raises :class:`BatchError` listing every problem (each one
    line, ``file:line: error: message``).  ``fidelity: auto`` in its scene is resolved by
    ``auto_fidelity`` (see :func:`cosim.scenario.load`).  A batch of more runs than
    ``max_runs_`` (default :func:`max_runs`) is refused before anything is expanded."""
    path = Path(path)
    limit = max_runs(max_runs_)
    data, problems = read_yaml(path)
    file = problems[0].file if problems else str(path)
    ck = _Checker(file)
    ck.problems.extend(problems)
    if data is None:
        if not problems:
            ck.err((file, 1), "the batch file is empty; expected scene:, and grid:, zip: or random:")
        raise BatchError(ck.problems)
    if not isinstance(data, YMap):
        ck.err((file, 1), f"a batch file is a mapping (scene, grid, zip, random, metrics, ...), not a "
                          f"{type(data).__name__}")
        raise BatchError(ck.problems)
    file = data.where[0]
    ck.file = file
    ck.keys(data, TOP_KEYS, "the batch")
    name = data.get("name") if data.get("name") is not None else stem_name(path.stem)
    problem = name_problem(name)
    if problem:  # the batch's name names its output directory: the rules of a scene's name
        ck.err(data.loc("name"), f"batch {problem.replace('(it names the trace files under --out)', '(it names the output directory runs/<name>)')}")
    scene_rel = data.get("scene")
    if not isinstance(scene_rel, str):
        ck.err(data.loc("scene") if "scene" in data else data.where,
               "the batch needs scene: the base scene file (relative to this file), e.g. scene: pid_step.yaml")
        raise BatchError(ck.problems)
    scene_path = path.parent / scene_rel
    if not scene_path.is_file():
        near = suggest(Path(scene_rel).name, [p.name for p in scene_path.parent.glob("*.yaml")]) \
            if scene_path.parent.is_dir() else ""
        ck.err(data.loc("scene"), f"base scene {scene_rel!r} not found (looked in {scene_path.parent}){near}")
        raise BatchError(ck.problems)
    scene_problems: list[Problem] = []
    base = load_raw(scene_path, scene_problems)
    if base is None or any(p.severity == "error" for p in scene_problems):
        raise BatchError(ck.problems + scene_problems)
    comps = list(base.get("components", {}) or {})
    fixed: dict[str, Any] = {}
    fixed_locs: dict[str, Loc] = {}
    node = ck.mapping(data, "set", "set (path -> value)")
    for k, v in (node or {}).items():
        paths, msg = expand_path(str(k), comps)
        if msg:
            ck.err(node.loc(k), f"set: {msg}")
        for p in paths:
            fixed[p], fixed_locs[p] = v, node.loc(k)
    base = _resolve_auto(ck, base, scene_path, fixed, data.loc("scene"), auto_fidelity)
    ck.limit = limit
    grid = _axes(ck, data, "grid", comps)
    zipped = _axes(ck, data, "zip", comps)
    rnd, seed, samples = _random(ck, data, comps)
    _count_runs(ck, data, grid, zipped, samples, "random" in data, limit)
    if ck.failed:  # nothing more is worth checking (and a huge batch is not walked)
        raise BatchError(ck.problems)
    if not ("grid" in data or "zip" in data or "random" in data) and not ck.failed:
        ck.err(data.where, "the batch varies nothing; add grid:, zip: or random: axes")
    if zipped and len({len(a.values) for a in zipped}) > 1:
        lens = ", ".join(f"{a.name!r} has {len(a.values)} (line {a.where[1]})" for a in zipped)
        ck.err(data.loc("zip"), f"zip axes must have equal lengths: {lens}")
    seen: dict[str, Axis] = {}
    for ax in [*grid, *zipped, *rnd]:
        for p in ax.paths:
            if p in seen:
                ck.err(ax.where, f"axis {ax.name!r} sets {p}, which axis {seen[p].name!r} (line "
                                 f"{seen[p].where[1]}) sets already")
            elif p in fixed:
                ck.err(ax.where, f"axis {ax.name!r} sets {p}, which set: fixes (line {fixed_locs[p][1]})")
            seen[p] = ax
    names = [a.name for a in [*grid, *zipped, *rnd]]
    reference = _reference(ck, data, path.parent)
    metrics = _metrics(ck, data, "reference" in data)  # a bad reference is one problem, not one per metric

    columns = base_columns(names, [m.column for m in metrics])
    sort, plots = _report(ck, data, columns, names, [m.column for m in metrics])
    if not ck.failed:
        _check_paths(ck, base, scene_path, fixed, grid, zipped, rnd, data.loc("set"), catalog)
    if not ck.failed:
        _check_signals(ck, base, scene_path, fixed, metrics, plots, catalog)
    if any(p.severity == "error" for p in ck.problems):
        raise BatchError(ck.problems)
    return Batch(str(name), path, str(data.get("description", "")), scene_path, fixed,
                 grid, zipped, rnd, seed, samples, reference, metrics, sort, plots, base,
                 {k: data.loc(k) for k in data}, [p for p in ck.problems if p.severity != "error"])


def _check_signals(ck: _Checker, base: YMap, scene_path: Path, fixed: dict, metrics: Sequence[MetricSpec],
                   plots: Sequence[PlotSpec], catalog=None) -> None:
    """Metric and plot signals must be recorded outputs of the scene."""
    try:
        scene = validate(apply_overrides(base, fixed), scene_path, catalog=catalog)
    except SceneError:
        return
    outputs = scene.outputs
    for m in metrics:
        for sig, what in ((m.signal, "signal"), (m.target if isinstance(m.target, str) and m.target != "reference"
                                                  else None, "target")):
            if sig is not None and sig not in outputs:
                ck.err(m.where, f"metrics: {what} {sig!r} is not recorded by the scene{suggest(sig, outputs)} "
                                f"(add it to the scene's outputs:)")
    for p in plots:
        if p.kind == "traces" and p.signal not in outputs:
            ck.err(p.where, f"traces plot: signal {p.signal!r} is not recorded by the scene{suggest(p.signal, outputs)}")


__all__ = ["Axis", "Batch", "BatchError", "Distribution", "PlotSpec", "load_batch"]
