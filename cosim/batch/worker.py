"""What a worker process does for one run: make the FMUs it was sent available (once per
process, by content hash), take instances from its pool (reset, not reloaded, when a previous
run left them), call :func:`cosim.run.run` into the run's own directory, and measure the trace.

Everything a run needs travels as plain data: a :class:`Task` per run (the validated scene with
its CasADi blocks stripped, the content hash of each component's FMU, the metrics) and one
:class:`Shared` per worker (the FMUs' bytes by hash, the reference trace).  A worker needs no
shared filesystem: with ``Task.out_dir = None`` the run writes into a temporary directory and
its files come back in :attr:`Outcome.files`.

A local worker process is itself watched by the batch process; a Dask worker, which is not,
runs each task in a supervised stepping child it forks once per thread
(:func:`execute_supervised`, :class:`cosim.run.supervise.Server`).
"""
from __future__ import annotations

import atexit
import dataclasses
import os
import shutil
import socket
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import RUN_ERRORS, UserError
from ..scenario import Scene
from ..scenario.guard_settings import guard_needs
from ..slaves.fmu_slave import FmuSlave
from ..trace.traces import Trace, trace_suffix
from .metrics import MetricSpec, compute
from ..outputs import pid_alive, safe_name, settle_if_stale, settle_run
from ..scenario import from_dict
from ..trace import traces
from ..run import supervise
from . import preload
from ..slaves.description import describe_fmu
from ..slaves.fmu_slave import forget_unpacked, unpack_fmu


@dataclass
class Task:
    """One run for a worker."""

    run_id: str
    index: int
    scene: Scene  # validated, blocks stripped (see :func:`transportable`)
    fmus: dict[str, str]  # component -> content hash of its FMU
    out_dir: str | None  # the run's directory, or None: a temporary one, files returned
    metrics: list[MetricSpec]
    reference: str | None = None  # None, "monolithic" or "trace" (Shared.reference)
    attempt: int = 1
    blobs: dict[str, bytes] | None = None  # FMUs first needed by this run (not in Shared.blobs)
    started_at: float | None = None  # time.perf_counter() on its local worker when it started
    trace_format: str = "npy"  # cosim.trace.traces.TRACE_FORMATS; the batch default: binary, nothing to format


@dataclass
class Shared:
    """What every run of a batch shares, sent once per worker."""

    blobs: dict[str, bytes]  # content hash -> FMU file bytes
    reference: Trace | None = None
    reuse: bool = True  # keep instances between runs (FMI reset) instead of loading them again
    token: str = field(default_factory=lambda: uuid.uuid4().hex)  # names this batch's Shared


@dataclass
class Outcome:
    """What a run sends back: the row's cells but the axes, and the files when asked."""

    run_id: str
    status: str
    reason: str
    metrics: dict[str, float] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    worker: str = ""
    files: dict[str, bytes] | None = None


def transportable(scene: Scene) -> Scene:
    """``scene`` without its CasADi blocks (a worker runs FMUs, not blocks), small to send; what
    the run-time guards need of each block goes along as plain data (``Component.guard``,
    :func:`cosim.scenario.guard_settings.guard_needs`)."""
    comps = {n: dataclasses.replace(c, block=None, guard=guard_needs(c)) for n, c in scene.components.items()}
    return dataclasses.replace(scene, components=comps)


def _sweep_dead_workers() -> None:
    """Remove the FMU folders of worker processes that were killed before they could."""

    with os.scandir(tempfile.gettempdir()) as entries:  # a busy /tmp: scandir, not glob's fnmatch per entry
        found = [e.path for e in entries if e.name.startswith("rpr-batch-")]
    for d in found:
        pid = Path(d).name.split("-")[2] if Path(d).name.count("-") >= 3 else ""
        if pid.isdigit() and int(pid) != os.getpid() and not pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


class _State:
    """Per-process: where the FMUs were written, and the pool of kept instances."""

    def __init__(self) -> None:
        self.dir: Path | None = None
        self.paths: dict[str, Path] = {}
        self.descriptions: dict[str, Any] = {}  # content hash -> SlaveDescription (prepared)
        self.pool: dict[tuple[str, str], list[FmuSlave]] = {}
        self.lock = threading.Lock()
        self.loads = 0  # instances created (not reused) in this process

    def fmu_path(self, digest: str, blobs: dict[str, bytes]) -> Path:
        with self.lock:
            if digest not in self.paths:
                if self.dir is None:
                    _sweep_dead_workers()
                    self.dir = Path(tempfile.mkdtemp(prefix=f"rpr-batch-{os.getpid()}-"))
                    atexit.register(shutil.rmtree, self.dir, True)
                if digest not in blobs:
                    raise UserError(f"FMU {digest[:12]} was not sent to this worker")
                path = self.dir / f"{digest}.fmu"
                path.write_bytes(blobs[digest])
                self.paths[digest] = path
            return self.paths[digest]

    def prepare(self, blobs: dict[str, bytes]) -> None:
        """In the batch process before it forks its workers: write, unpack and describe every
        FMU once, for the workers to inherit (:meth:`remove_files` when the batch ends)."""

        for digest in blobs:
            path = self.fmu_path(digest, blobs)
            if digest not in self.descriptions:
                self.descriptions[digest] = describe_fmu(path)
            unpack_fmu(path)

    def detach(self) -> None:
        """In a forked worker: keep the parent's prepared FMU files (read only), drop its
        instances, and write any other FMU into a folder of this process."""
        self.pool, self.dir, self.loads = {}, None, 0
        self.lock = threading.Lock()

    def remove_files(self) -> None:
        """Remove the FMU files this process wrote and unpacked (at the end of a worker process,
        or of a batch that prepared them)."""

        if self.dir is None:
            return
        for digest, path in list(self.paths.items()):
            if path.parent == self.dir:
                forget_unpacked(path)
                del self.paths[digest]
                self.descriptions.pop(digest, None)
        shutil.rmtree(self.dir, ignore_errors=True)
        self.dir = None

    def take(self, name: str, digest: str, path: Path, reuse: bool) -> FmuSlave:
        if reuse:
            with self.lock:
                kept = self.pool.get((name, digest))
                if kept:
                    return kept.pop()
        self.loads += 1
        slave = FmuSlave(name, path, self.descriptions.get(digest))
        slave.reuse = reuse
        return slave

    def give(self, slave: FmuSlave, digest: str, healthy: bool) -> None:
        if slave.reuse and healthy and slave.fmu is not None:
            with self.lock:
                self.pool.setdefault((slave.name, digest), []).append(slave)
        else:
            slave.release()


STATE = _State()


def worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _stats(stats: dict) -> dict[str, Any]:
    return {"steps": stats.get("steps_done", 0), "simulated_s": stats.get("simulated_s", 0.0),
            "init_s": stats.get("init_s"), "loop_s": stats.get("wall_s"),
            "real_time_factor": stats.get("real_time_factor"), "run_s": stats.get("run_s")}


def _monolithic(scene: Scene, out_dir: Path, trace_format: str = "csv") -> tuple[Trace | None, str]:
    from ..run.reference import reference

    full = from_dict({**scene.data, "name": scene.name},
                     base_dir=scene.path.parent if scene.path else None)
    ref = reference(full, out_dir=out_dir, trace_format=trace_format)
    return ref.trace, ("" if ref.ok else f"monolithic reference {ref.status}: {ref.reason}")


def execute(task: Task, shared: Shared) -> Outcome:
    """Run one task (see the module docstring); a failure is an outcome, never an exception."""
    from ..run.execute import run

    t0 = time.perf_counter()
    tmp = None
    out_dir = Path(task.out_dir) if task.out_dir else Path(tmp := tempfile.mkdtemp(prefix="rpr-run-"))
    slaves: list[FmuSlave] = []
    status, reason, stats, trace = "failed", "", {}, None
    blobs = {**shared.blobs, **task.blobs} if task.blobs else shared.blobs
    try:
        for name, comp in task.scene.components.items():
            digest = task.fmus[name]
            # only the project's own FMUs are kept between runs: an external FMU's reset may not
            # reset (libcosim's Wheel keeps its position), so it is loaded anew for each run
            keep = shared.reuse and comp.kind == "model"
            slaves.append(STATE.take(name, digest, STATE.fmu_path(digest, blobs), keep))
        t_run = time.perf_counter()
        res = run(task.scene, out_dir=out_dir, slaves=slaves, trace_format=task.trace_format)
        status, reason, stats, trace = res.status, res.reason, dict(res.stats), res.trace
        stats["run_s"] = time.perf_counter() - t_run
    except RUN_ERRORS as exc:  # a user mistake or an FMU that cannot be built
        reason = str(exc)
    except Exception as exc:  # a run never takes the batch down: its failure is its row
        reason = f"{type(exc).__name__}: {exc}"
    finally:
        for s in slaves:
            STATE.give(s, task.fmus[s.name], status == "ok")
    metrics: dict[str, float] = {}
    if status == "ok" and task.metrics:
        ref, note = shared.reference, ""
        if task.reference == "monolithic":
            try:
                ref, note = _monolithic(task.scene, out_dir, task.trace_format)
            except UserError as exc:
                ref, note = None, f"no monolithic reference: {exc}"
        uses_ref = any(m.target == "reference" for m in task.metrics)
        if uses_ref and (ref is None or not len(ref.data)):
            plain = [m for m in task.metrics if m.target != "reference"]
            metrics = {**{m.column: float("nan") for m in task.metrics}, **compute(plain, trace)}
        else:
            metrics = compute(task.metrics, trace, ref)
        reason = note or reason
    files = None
    if tmp is not None:
        files = {p.name: p.read_bytes() for p in sorted(out_dir.iterdir()) if p.is_file()}
        shutil.rmtree(tmp, ignore_errors=True)
    return Outcome(task.run_id, status, reason, metrics, _stats(stats), time.perf_counter() - t0, worker_id(), files)


def settle_files(task: Task, status: str, reason: str) -> None:
    """The run's trace and sidecar in its directory, given ``status`` and ``reason`` (the process
    that stepped it died while they said "running")."""
    if not task.out_dir:
        return

    try:
        settle_run(os.path.join(task.out_dir, f"{safe_name(task.scene.name)}{trace_suffix(task.trace_format)}"),
                   status, reason)
        settle_if_stale(task.out_dir)  # the dead process's lock file goes too
    except (OSError, UserError):  # the row says it all the same
        pass


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file() and not p.is_symlink()}


class _Local(threading.local):
    server = None  # this thread's stepping child (cosim.run.supervise.Server)
    token = None  # the Shared it holds


_LOCAL = _Local()
_SERVERS: list = []  # every stepping child this process started, ended at exit
_SERVERS_LOCK = threading.Lock()


def end_steppers() -> None:
    """End this process's stepping children (each thread starts a new one at its next run: one
    forked after a change of the environment an FMU reads sees the change)."""
    with _SERVERS_LOCK:
        servers = list(_SERVERS)
        _SERVERS.clear()
    for server in servers:
        server.close()


atexit.register(end_steppers)


def _serve_runs() -> Callable[[tuple], Outcome]:
    """What a stepping child does with each request ``(task, token, shared or None)``: run the
    task with the Shared of that token (sent with the first run of each batch)."""
    kept: dict[str, Shared] = {}

    def handle(request: tuple) -> Outcome:
        task, token, shared = request
        if shared is not None:
            kept.clear()
            kept[token] = shared
        return execute(task, kept[token])

    return handle


def _start_stepping() -> None:
    """In a new stepping child: its own instances and FMU folder, and each run's trace written
    in the stepping thread (a run is one core, as on a local worker)."""

    STATE.detach()
    traces.WRITER_THREAD = False


def _server():
    """This thread's stepping child, started (again) when it has none alive."""

    if _LOCAL.server is None or not _LOCAL.server.alive:
        _LOCAL.server = supervise.Server(_serve_runs(), on_start=_start_stepping, on_exit=STATE.remove_files)
        _LOCAL.token = None
        with _SERVERS_LOCK:  # another thread's child is that thread's to check (checking reaps it)
            _SERVERS[:] = [s for s in _SERVERS if s.is_open] + [_LOCAL.server]
    return _LOCAL.server


def execute_supervised(task: Task, shared: Shared, call_timeout: float | None = None) -> Outcome:
    """:func:`execute` in this thread's stepping child (:class:`cosim.run.supervise.Server`),
    watched as ``rpr-cosim run`` watches its child: an FMU that crashes, exits or hangs in one
    call longer than ``call_timeout`` [s] makes the outcome "crashed" or "hung" (the component
    and FMI call in the reason, the run's files settled), the child is replaced at the next run,
    and this process goes on; a child killed by someone else (SIGKILL or SIGTERM: out of memory?)
    or dead outside any FMI call gets a second attempt in a new child, as a local worker's run
    does.  For processes that are not supervised themselves (Dask workers);
    a run without ``out_dir`` steps into a temporary directory of this process and its files
    come back in :attr:`Outcome.files`.

    The child is forked once per thread, after this process did what it would otherwise repeat
    (the imports, the compiled loops, the FMUs written, described and unpacked), and keeps its
    FMU instances between runs (reset, as a local worker does)."""

    t0 = time.perf_counter()
    preload.warm([task.scene])
    blobs = {**shared.blobs, **task.blobs} if task.blobs else shared.blobs
    STATE.prepare({d: blobs[d] for d in set(task.fmus.values()) if d in blobs})
    tmp = None
    if not task.out_dir:
        tmp = tempfile.mkdtemp(prefix="rpr-run-")
        task = dataclasses.replace(task, out_dir=tmp)
    try:
        for attempt in (1, 2):
            server = _server()
            try:
                out = server.call((task, shared.token, shared if _LOCAL.token != shared.token else None),
                                  call_timeout)
                _LOCAL.token = shared.token
                break
            except supervise.Failed as failed:
                if failed.from_outside and attempt == 1:  # killed by someone else (out of memory?): once more
                    shutil.rmtree(task.out_dir, ignore_errors=True)
                    os.makedirs(task.out_dir)
                    continue
                reason = failed.reason + (" (and so did its second attempt, in a new process)" if attempt > 1 else "")
                settle_files(task, failed.status, reason)
                out = Outcome(task.run_id, failed.status, reason)
        out.wall_s, out.worker = time.perf_counter() - t0, worker_id()
        if tmp is not None:
            out.files = _files(Path(tmp))
        return out
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def run_remote(task: Task, shared: Shared, call_timeout: float | None = None) -> Outcome:
    """The function a Dask worker calls (importable by name on the workers): the run supervised
    (:func:`execute_supervised`) unless ``$RPR_COSIM_SUPERVISE=0`` on the worker."""

    if not supervise.enabled():
        return execute(task, shared)
    return execute_supervised(task, shared, call_timeout)


__all__ = ["Outcome", "Shared", "STATE", "Task", "end_steppers", "execute", "execute_supervised", "run_remote", "settle_files",
           "transportable"]
