"""Running a batch: resolve every run's scene (all checked before any run), skip the runs whose
rows exist, build the FMUs once, hand the rest to an executor and append each finished run's row.

Output directory (default ``runs/<batch name>``)::

    results.csv           one row per finished run (:mod:`cosim.batch.results`)
    batch.json            what the batch is: file, base scene, axes, metrics, columns
    runs/<run id>/        each run's trace <scene>.csv and sidecar <scene>.json (and
                          <scene>_reference.csv with a monolithic reference)
    plots/                the summary's charts (:mod:`cosim.batch.report`)

A run directory without a row is an unfinished attempt (the batch was interrupted while it ran);
it is cleared and the run is done again when the batch is resumed.  Two batches never write into
one directory at the same time (a lock file).
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import UserError
from ..outputs import pid_alive
from ..scenario import Problem, Scene, SceneError, apply_overrides, validate
from .axes import Point, expand
from .results import ResultsTable, base_columns
from .spec import Batch, BatchError
from .worker import Outcome, Shared, Task, transportable


@dataclass
class Planned:
    """A run of the batch with its resolved scene and id."""

    point: Point
    scene: Scene
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


def plan(batch: Batch, *, catalog=None) -> tuple[list[Planned], list[tuple[int, int]]]:
    """Every run's validated scene and id (the first 16 hex digits of the scene's hash).  A run
    whose scene does not validate is reported before anything runs (:class:`BatchError`); runs
    that resolve to the same scene run once (their index pairs are returned)."""
    planned: list[Planned] = []
    problems: list[Problem] = []
    seen: dict[str, int] = {}
    dups: list[tuple[int, int]] = []
    where = batch.where.get("scene", (str(batch.path), 0))
    for p in expand(batch):
        try:
            scene = validate(apply_overrides(batch.base_tree, p.overrides), batch.scene_path, catalog=catalog)
        except SceneError as exc:
            err = next((q for q in exc.problems if q.severity == "error"), None)
            values = ", ".join(f"{k}={v!r}" for k, v in p.values.items())
            problems.append(Problem(where[0], where[1], f"run {p.index} ({values}): "
                                                        f"{err.message if err else exc}"))
            if len(problems) >= 5:
                break
            continue
        rid = scene.hash[:16]
        if rid in seen:
            dups.append((seen[rid], p.index))
            continue
        seen[rid] = p.index
        planned.append(Planned(p, scene, rid))
    if problems:
        raise BatchError(problems)
    return planned, dups


def _sha(path: Path) -> tuple[str, bytes]:
    data = Path(path).read_bytes()
    return hashlib.sha256(data).hexdigest(), data


def build_fmus(runs: Sequence[Planned], *, cache_dir: Path | None = None,
               log: Callable[[str], None] | None = None) -> tuple[dict[str, dict[str, str]], dict[str, bytes]]:
    """Build (or fetch from the cache) each distinct FMU of ``runs`` once; returns each run's
    ``component -> content hash`` and the FMUs' bytes by hash."""
    from fmus.index import IndexedBlock

    from ..recipes import component_fmu

    by_key: dict[tuple, str] = {}
    blobs: dict[str, bytes] = {}
    maps: dict[str, dict[str, str]] = {}
    for r in runs:
        m: dict[str, str] = {}
        for name, comp in r.scene.components.items():
            key = (("fmu", str(comp.fmu)) if comp.kind == "fmu" else
                   ("indexed", str(comp.block.fmu), comp.fmi) if isinstance(comp.block, IndexedBlock) else
                   ("block", id(comp.block), comp.fmi))
            if key not in by_key:
                if comp.kind == "fmu":
                    path = comp.fmu
                else:  # from the recipe index when it has the FMU, else built (and indexed)
                    path = component_fmu(comp, cache_dir=cache_dir,
                                         progress=(lambda msg, n=name: log(f"{n}: {msg}")) if log else None)
                digest, data = _sha(path)
                blobs[digest] = data
                by_key[key] = digest
            m[name] = by_key[key]
        maps[r.run_id] = m
    return maps, blobs


class _Lock:
    """An exclusive lock on ``<out>/.lock`` (one batch per output directory).  Forked workers
    share it; when the batch that wrote its pid there is gone, its workers (which end within
    ~0.2 s of it) are waited for up to :attr:`GRACE_S`."""

    GRACE_S = 3.0

    def __init__(self, out: Path):
        self.path = out / ".lock"

    def __enter__(self):
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fh = open(self.path, "a+")
        deadline = time.monotonic() + self.GRACE_S
        while True:
            try:
                fcntl.flock(self.fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                self.fh.seek(0)
                who = self.fh.read().strip()
                pid = who.split()[-1] if who else ""
                if pid.isdigit() and not pid_alive(int(pid)) and time.monotonic() < deadline:
                    time.sleep(0.05)  # a killed batch's workers still hold it until they notice
                    continue
            self.fh.close()
            raise UserError(f"{self.path.parent}: another batch is running there ({who or 'pid unknown'}); wait for "
                            f"it or choose another --out") from None
        self.fh.seek(0)
        self.fh.truncate()
        self.fh.write(f"pid {os.getpid()}\n")
        self.fh.flush()
        return self

    def __exit__(self, *exc):
        fcntl.flock(self.fh, fcntl.LOCK_UN)
        self.fh.close()


def _describe(batch: Batch, columns: list[str]) -> dict:
    return {"batch": batch.name, "file": str(batch.path), "scene": str(batch.scene_path),
            "description": batch.description, "set": batch.fixed,
            "axes": [{"name": a.name, "paths": list(a.paths), "kind": k,
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
    from ..scenario import suggest
    from ..trace import read_trace

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
        tmp = run_dir / f".{name}.tmp"
        tmp.write_bytes(data)
        os.replace(tmp, run_dir / name)


def run_batch(batch: Batch, *, out: Path | None = None, executor=None, cache_dir: Path | None = None,
              reuse: bool = True, progress=None, log: Callable[[str], None] | None = None,
              on_start: Callable[[Task, int], None] | None = None, catalog=None) -> BatchOutcome:
    """Run ``batch`` into ``out`` (default ``runs/<batch name>``) on ``executor`` (default: local
    processes, one per core), resuming: runs whose rows exist are skipped.

    ``progress`` is a :class:`cosim.batch.report.Progress` (or None); ``log`` gets one-line notes
    (FMU builds); ``on_start(task, pid)`` is called when a local worker starts a run.  A
    KeyboardInterrupt stops the workers and propagates; every finished run is in the table.
    """
    from .executors import LocalExecutor

    t0 = time.perf_counter()
    out = Path(out or Path("runs") / batch.name)
    ref = _check_reference(batch)
    planned, dups = plan(batch, catalog=catalog)
    columns = base_columns([a.name for a in batch.axes], batch.metric_columns)
    with _Lock(out):
        meta_path = out / "batch.json"
        key = _metrics_key(batch)
        if meta_path.is_file():
            old = json.loads(meta_path.read_text()).get("metrics_key")
            if old is not None and old != key:
                raise UserError(f"{out} holds results of a batch with other metrics or reference; choose another "
                                f"--out (or remove {out / 'results.csv'})")
        with ResultsTable(out / "results.csv", columns) as table:
            meta_path.write_text(json.dumps({**_describe(batch, columns), "metrics_key": key}, indent=2,
                                            default=str))
            done = table.done
            todo = [r for r in planned if r.run_id not in done]
            res = BatchOutcome(out, columns, table.rows, skipped=len(planned) - len(todo), duplicates=dups)
            if progress is not None:
                progress.begin(len(planned), res.skipped, sum(r["outcome"] != "ok" for r in table.rows
                                                                if r["run_id"] in {p.run_id for p in planned}))
            if todo:
                maps, blobs = build_fmus(todo, cache_dir=cache_dir, log=log)
                for r in todo:  # an unfinished attempt of an interrupted batch
                    shutil.rmtree(out / "runs" / r.run_id, ignore_errors=True)
                tasks = [Task(r.run_id, r.point.index, transportable(r.scene), maps[r.run_id],
                              str((out / "runs" / r.run_id).resolve()), batch.metrics,
                              "monolithic" if batch.reference == "monolithic" else ("trace" if ref else None))
                         for r in todo]
                by_id = {r.run_id: r for r in todo}
                shared = Shared(blobs, ref, reuse)
                ex = executor or LocalExecutor()
                res.prepare_s = time.perf_counter() - t0

                def started(task: Task, pid: int) -> None:
                    if progress is not None:
                        progress.started(task.run_id)
                    if on_start is not None:
                        on_start(task, pid)

                def finished(task: Task, outcome: Outcome) -> None:
                    if outcome.files is not None:
                        _write_files(out / "runs" / task.run_id, outcome.files)
                    table.append(row_of(by_id[task.run_id], outcome, task.attempt))
                    res.ran += 1
                    res.failed += outcome.status != "ok"
                    res.run_wall_s += outcome.wall_s
                    if progress is not None:
                        progress.finished(task.run_id, outcome.status == "ok", getattr(ex, "capacity", 1))

                if progress is not None:
                    progress.capacity = getattr(ex, "capacity", 1)
                    progress.show()
                try:
                    ex.run(tasks, shared, finished, started)
                finally:
                    if progress is not None:
                        progress.end()
            res.rows = [r for r in table.rows if r["run_id"] in {p.run_id for p in planned}]
    res.wall_s = time.perf_counter() - t0
    return res


def default_log(msg: str) -> None:
    print(msg, file=sys.stderr)


__all__ = ["BatchOutcome", "Planned", "build_fmus", "plan", "row_of", "run_batch"]
