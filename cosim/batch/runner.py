"""Running a batch: resolve every run's scene (all checked before any run), skip the runs whose
rows exist, build the FMUs once, hand the rest to an executor and append each finished run's row.

Output directory (default ``runs/<batch name>``)::

    results.csv           one row per finished run (:mod:`cosim.batch.results`)
    batch.json            what the batch is: file, base scene, axes, metrics, columns
    runs/<run id>/        each run's trace <scene>.npy (``--format csv``: <scene>.csv) and sidecar
                          <scene>.json (and <scene>_reference.npy with a monolithic reference)
    plots/                the summary's charts (:mod:`cosim.batch.overview`)

A run directory without a row is an unfinished attempt (the batch was interrupted while it ran);
it is cleared and the run is done again when the batch is resumed.  Nothing else writes into the
directory at the same time: a batch takes the lock of runs and studies (:class:`cosim.outputs.
OutputLock`).
"""
from __future__ import annotations

import hashlib
import itertools
import json

import shutil
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import UserError
from ..outputs import OutputLock, check_out_dir, confined, write_bytes, write_text
from ..scenario import Problem, Scene, SceneError, apply_overrides, plain, validate
from ..scenario.overrides import override_texts
from .axes import Point, count, points
from .results import ResultsTable, base_columns
from .spec import Batch, BatchError, axis_units
from .worker import Outcome, Shared, Task, transportable
from ..scenario import suggest
from ..trace.traces import read_trace, trace_suffix
from .executors import LocalExecutor
from fmus.index import IndexedBlock
from ..scenario.recipes import component_fmu
from ..readers import read_json
from .results import write_parquet


@dataclass
class Planned:
    """A run of the batch with its resolved scene and id."""

    point: Point
    scene: Scene | None  # None: the point's scene does not validate (a failed row)
    run_id: str


@dataclass
class BatchOutcome:
    """What :func:`run_batch` did: the table's rows (all of them, earlier sessions included), the
    runs done now, skipped (rows existed) and failed, and the wall time."""

    out: Path
    columns: list[str]
    rows: list[dict[str, Any]]
    ran: int = 0
    skipped: int = 0
    failed: int = 0
    wall_s: float = 0.0
    run_wall_s: float = 0.0  # sum of the runs' own wall times (on their workers)
    prepare_s: float = 0.0  # resolving scenes and building FMUs
    duplicates: list[tuple[int, int]] = field(default_factory=list)


def resolve(batch: Batch, point: Point, *, catalog=None) -> Planned | Problem:
    """``point``'s validated scene and run id (the first 16 hex digits of the scene's hash), or
    the one-line problem (at the batch file's ``scene:`` line) that stops it from running."""
    tree = apply_overrides(batch.base_tree, point.overrides)
    try:
        scene = validate(tree, batch.scene_path, catalog=catalog)
    except SceneError as exc:
        err = next((q for q in exc.problems if q.severity == "error"), None)
        values = ", ".join(f"{k}={v!r}" for k, v in point.values.items())
        where = batch.where.get("scene", (str(batch.path), 0))
        return Problem(where[0], where[1], f"run {point.index} ({values}): {err.message if err else exc}")
    scene.overrides = override_texts(point.overrides)
    return Planned(point, scene, scene.hash[:16])


def invalid_id(batch: Batch, point: Point) -> str:
    """The id of a point whose scene does not validate (from its scene tree; no scene hash)."""
    tree = plain(apply_overrides(batch.base_tree, point.overrides))
    return "x" + hashlib.sha256(json.dumps(tree, sort_keys=True, default=str).encode()).hexdigest()[:15]


def plan(batch: Batch, *, catalog=None) -> tuple[list[Planned], list[tuple[int, int]]]:
    """Every run's validated scene and id, all at once (``batch --check``): a run whose scene does
    not validate is a :class:`BatchError` (the first five are listed); runs that resolve to the
    same scene run once (their index pairs are returned)."""
    planned: list[Planned] = []
    problems: list[Problem] = []
    seen: dict[str, int] = {}
    dups: list[tuple[int, int]] = []
    for p in points(batch):
        r = resolve(batch, p, catalog=catalog)
        if isinstance(r, Problem):
            problems.append(r)
            if len(problems) >= 5:
                break
            continue
        if r.run_id in seen:
            dups.append((seen[r.run_id], p.index))
            continue
        seen[r.run_id] = p.index
        planned.append(r)
    if problems:
        raise BatchError(problems)
    return planned, dups


class _Planner:
    """The runs still to do, resolved one at a time as the executor asks for them, so that
    checking run k+1's scene overlaps run k instead of delaying the first run.  The first point
    is resolved at once: when its scene does not validate, the batch stops before any run
    (:class:`BatchError`; the others most likely share its problem).  A later point whose scene
    does not validate becomes a failed row with the reason (``on_invalid``); points whose rows
    exist are skipped and those resolving to an earlier point's scene run once."""

    def __init__(self, batch: Batch, done: set[str], *, catalog=None):
        self.batch, self.done, self.catalog = batch, done, catalog
        self.points = points(batch)  # lazily: planning memory stays bounded
        self.n_points = count(batch)
        self.skipped = 0
        self.duplicates: list[tuple[int, int]] = []
        self.seen: dict[str, int] = {}  # run id -> first point resolving to it
        self.ids: set[str] = set()  # every run id met (valid scenes and invalid points)
        self.head: Planned | None = None
        self.first = next(self.points, None)
        if self.first is not None:
            first = resolve(batch, self.first, catalog=catalog)
            if isinstance(first, Problem):
                raise BatchError([first])
            self.head = first

    def runs(self, on_invalid: Callable[[Planned, str], None],
             on_skip: Callable[[str], None] = lambda run_id: None) -> Iterator[Planned]:
        """The runs to do, in the batch's order (see the class docstring); ``on_skip(run_id)`` for
        a run whose row exists, and for a point that duplicates an earlier one (``run_id`` "")."""
        head = [self.first] if self.first is not None else []
        for i, p in enumerate(itertools.chain(head, self.points)):
            r = self.head if i == 0 else resolve(self.batch, p, catalog=self.catalog)
            if isinstance(r, Problem):
                rid = invalid_id(self.batch, p)
                self.ids.add(rid)
                if rid in self.done:
                    self.skipped += 1
                    on_skip(rid)
                else:
                    on_invalid(Planned(p, None, rid), r.message)
                continue
            if r.run_id in self.seen:
                self.duplicates.append((self.seen[r.run_id], p.index))
                on_skip("")
                continue
            self.seen[r.run_id] = p.index
            self.ids.add(r.run_id)
            if r.run_id in self.done:
                self.skipped += 1
                on_skip(r.run_id)
                continue
            yield r


def _sha(path: Path) -> tuple[str, bytes]:
    data = Path(path).read_bytes()
    return hashlib.sha256(data).hexdigest(), data


class FmuShelf:
    """Each distinct FMU of a batch's runs, built (or fetched from the cache) once, by content
    hash: :meth:`add` gives a run's ``component -> content hash``; :attr:`blobs` holds the bytes."""

    def __init__(self, *, cache_dir: Path | None = None, log: Callable[[str], None] | None = None):
        self.cache_dir, self.log = cache_dir, log
        self.by_key: dict[tuple, str] = {}
        self.blobs: dict[str, bytes] = {}

    def add(self, run: Planned) -> dict[str, str]:


        m: dict[str, str] = {}
        for name, comp in run.scene.components.items():
            key = (("fmu", str(comp.fmu)) if comp.kind == "fmu" else
                   ("indexed", str(comp.block.fmu), comp.fmi) if isinstance(comp.block, IndexedBlock) else
                   ("block", id(comp.block), comp.fmi))
            if key not in self.by_key:
                if comp.kind == "fmu":
                    path = comp.fmu
                else:  # from the recipe index when it has the FMU, else built (and indexed)
                    log = self.log
                    path = component_fmu(comp, cache_dir=self.cache_dir,
                                         progress=(lambda msg, n=name: log(f"{n}: {msg}")) if log else None)
                digest, data = _sha(path)
                self.blobs[digest] = data
                self.by_key[key] = digest
            m[name] = self.by_key[key]
        return m


def build_fmus(runs: Sequence[Planned], *, cache_dir: Path | None = None,
               log: Callable[[str], None] | None = None) -> tuple[dict[str, dict[str, str]], dict[str, bytes]]:
    """Build (or fetch from the cache) each distinct FMU of ``runs`` once; returns each run's
    ``component -> content hash`` and the FMUs' bytes by hash."""
    shelf = FmuShelf(cache_dir=cache_dir, log=log)
    maps = {r.run_id: shelf.add(r) for r in runs}
    return maps, shelf.blobs


def _describe(batch: Batch, columns: list[str]) -> dict:
    units = axis_units(batch)
    return {"batch": batch.name, "file": str(batch.path), "scene": str(batch.scene_path),
            "description": batch.description, "set": batch.fixed,
            "axes": [{"name": a.name, "paths": list(a.paths), "kind": k, "unit": units.get(a.name, ""),
                      **({"values": list(a.values)} if a.dist is None else
                         {"dist": a.dist.kind, "params": [a.dist.a, a.dist.b]})}
                     for k, group in (("grid", batch.grid), ("zip", batch.zip), ("random", batch.random))
                     for a in group],
            "seed": batch.seed, "samples": batch.samples,
            "reference": str(batch.reference) if batch.reference else None,
            "metrics": [{"column": m.column, "signal": m.signal, "measure": m.measure, "arg": m.arg,
                         "target": m.target, "band": m.band} for m in batch.metrics],
            "columns": columns}


def _metrics_key(batch: Batch) -> str:
    d = [(m.column, m.target, m.band) for m in batch.metrics] + [str(batch.reference)]
    return hashlib.sha256(json.dumps(d, default=str).encode()).hexdigest()[:16]


def _check_reference(batch: Batch):
    """The reference trace of the batch (``{trace: file}``), checked against the metrics."""
    if not isinstance(batch.reference, Path):
        return None

    ref = read_trace(batch.reference)
    for m in batch.metrics:
        if m.target == "reference" and m.signal not in ref.columns:
            raise BatchError([Problem(m.where[0], m.where[1], f"metrics: the reference trace {batch.reference.name} "
                                                              f"has no column {m.signal!r}{suggest(m.signal, ref.names)}")])
    return ref


def row_of(run: Planned, outcome: Outcome, attempts: int) -> dict[str, Any]:
    """The results row of a run."""
    return {"run_id": run.run_id, "index": run.point.index, **run.point.values, "outcome": outcome.status,
            "reason": outcome.reason, **outcome.metrics, **outcome.stats, "wall_s": outcome.wall_s,
            "attempts": attempts, "worker": outcome.worker}


def _write_files(run_dir: Path, files: dict[str, bytes]) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        write_bytes(confined(run_dir, name), data)


def run_batch(batch: Batch, *, out: Path | None = None, executor=None, cache_dir: Path | None = None,
              reuse: bool = True, progress=None, log: Callable[[str], None] | None = None,
              on_start: Callable[[Task, int], None] | None = None, catalog=None,
              trace_format: str = "npy") -> BatchOutcome:
    """Run ``batch`` into ``out`` (default ``runs/<batch name>``) on ``executor`` (default: local
    processes, one per core), resuming: runs whose rows exist are skipped.

    Runs are resolved as they are handed out (:class:`_Planner`): the first before anything runs,
    each next one while the workers run the previous ones.  ``progress`` is a
    :class:`cosim.batch.overview.Progress` (or None); ``log`` gets one-line notes (FMU builds);
    ``on_start(task, pid)`` is called when a local worker starts a run.  A KeyboardInterrupt
    stops the workers and propagates; every finished run is in the table.  ``trace_format``:
    each run's trace file (:data:`cosim.trace.traces.TRACE_FORMATS`; default ``"npy"``, float64
    bytes that cost no formatting; ``"csv"`` for text); with ``"parquet"`` the table is also
    written as ``results.parquet`` at the end.
    """

    trace_suffix(trace_format)

    t0 = time.perf_counter()
    out = Path(out or Path("runs") / batch.name)
    ref = _check_reference(batch)
    columns = base_columns([a.name for a in batch.axes], batch.metric_columns)
    planner = _Planner(batch, set(), catalog=catalog)  # the first run's scene checked before anything is written
    check_out_dir(out)
    with OutputLock(out, log=log):  # the lock of runs and studies too: one writer per directory
        meta_path = out / "batch.json"
        key = _metrics_key(batch)
        if meta_path.is_file():

            old = read_json(meta_path, "batch description")
            old = old.get("metrics_key") if isinstance(old, dict) else None
            if old is not None and old != key:
                raise UserError(f"{out} holds results of a batch with other metrics or reference; choose another "
                                f"--out (or remove {out / 'results.csv'})")
        with ResultsTable(out / "results.csv", columns) as table:
            planner.done = table.done
            write_text(meta_path, json.dumps({**_describe(batch, columns), "metrics_key": key}, indent=2,
                                             default=str))
            res = BatchOutcome(out, columns, table.rows)
            outcome_of = {r["run_id"]: r["outcome"] for r in table.rows}
            if progress is not None:
                progress.begin(planner.n_points, 0, 0)

            def skipped(run_id: str) -> None:
                if progress is not None:
                    progress.skipped_run(outcome_of.get(run_id, "ok") == "ok", duplicate=not run_id)
            shelf = FmuShelf(cache_dir=cache_dir, log=log)
            by_id: dict[str, Planned] = {}
            ex = executor or LocalExecutor()

            def record(run: Planned, outcome: Outcome, attempts: int) -> None:
                table.append(row_of(run, outcome, attempts))
                res.ran += 1
                res.failed += outcome.status != "ok"
                res.run_wall_s += outcome.wall_s
                if progress is not None:
                    progress.finished(run.run_id, outcome.status == "ok", getattr(ex, "capacity", 1))

            def invalid(run: Planned, reason: str) -> None:
                record(run, Outcome(run.run_id, "failed", f"invalid scene: {reason}"), 0)

            def tasks() -> Iterator[Task]:
                shipped: set[str] | None = None  # what every worker has from the start: the first run's FMUs
                for r in planner.runs(invalid, skipped):
                    by_id[r.run_id] = r
                    fmus = shelf.add(r)
                    shutil.rmtree(out / "runs" / r.run_id, ignore_errors=True)  # an unfinished attempt
                    if shipped is None:
                        shipped = set(shelf.blobs)
                    extra = {d: shelf.blobs[d] for d in set(fmus.values()) - shipped}
                    yield Task(r.run_id, r.point.index, transportable(r.scene), fmus,
                               str((out / "runs" / r.run_id).resolve()), batch.metrics,
                               "monolithic" if batch.reference == "monolithic" else ("trace" if ref else None),
                               blobs=extra or None, trace_format=trace_format)

            todo = tasks()
            first = next(todo, None)  # resolves the first run and builds its FMUs: the workers' start
            res.prepare_s = time.perf_counter() - t0

            def started(task: Task, pid: int) -> None:
                if progress is not None:
                    progress.started(task.run_id)
                if on_start is not None:
                    on_start(task, pid)

            def finished(task: Task, outcome: Outcome) -> None:
                if outcome.files is not None:
                    _write_files(out / "runs" / task.run_id, outcome.files)
                record(by_id[task.run_id], outcome, task.attempt)

            if first is None:
                if progress is not None:
                    progress.end()
            else:
                if progress is not None:
                    progress.capacity = getattr(ex, "capacity", 1)
                    progress.show()
                try:
                    ex.run(itertools.chain([first], todo), Shared(dict(shelf.blobs), ref, reuse), finished, started)
                finally:
                    if progress is not None:
                        progress.end()
            res.skipped, res.duplicates = planner.skipped, planner.duplicates
            res.rows = [r for r in table.rows if r["run_id"] in planner.ids]
            if trace_format == "parquet":

                write_parquet(out / "results.parquet", columns, table.rows,
                              {**_describe(batch, columns), "metrics_key": key})
    res.wall_s = time.perf_counter() - t0
    return res


def default_log(msg: str) -> None:
    print(msg, file=sys.stderr)


__all__ = ["BatchOutcome", "FmuShelf", "Planned", "build_fmus", "invalid_id", "plan", "resolve", "row_of", "run_batch"]
