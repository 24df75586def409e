"""A run is a pure function of (scene, overrides): load and validate the scene, build (or fetch
from the cache) the FMUs of its catalog components, couple the slaves, step them with the
scene's master algorithm and return a :class:`RunResult`.  Everything it takes is plain data
(a path and a mapping), so a worker process can execute it."""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from ..errors import UserError
from .companion import companion
from .row_guards import scene_guard
from .instances import Instances
from ..master import ALGORITHMS, CoupledSystem, Link, simulate
from ..master.estimate import EstimatingObserver
from ..scenario import Scene, load
from ..scenario.overrides import override_texts
from ..slaves.fmu_slave import FmuSlave
from ..slaves.slave import Slave
from ..trace.traces import MemoryTrace, Trace, trace_suffix, trace_writer
from fmus.index import store_pending_replays
from ..outputs import OutputLock, check_ours, check_out_dir, check_set, confined, safe_name, settle_run
from ..scenario.units import units_of
from ..interrupts import signals_as_interrupts
from . import supervise
from ..master import RunStats, interruption_reason
from ..trace.traces import TraceWriteError, read_trace
from ..scenario.recipes import component_fmu, slave_description
from .choose import applied
from ..slaves.fmu_slave import unpack_fmu


def _quiet(message: str) -> None:
    """A log that says nothing."""


@dataclass(frozen=True)
class RunRequest:
    """What a run of a scene is asked for besides the scene, passed down whole: the ``--set``
    overrides as given (recorded in the trace's metadata), the output directory and trace format,
    the engine (overriding ``master.engine``), the FMU cache, the catalog and ``fidelity: auto``'s
    resolution for loading, the trace size limit, the supervision's call timeout, and where
    progress and log lines go (see :func:`run` for each)."""

    overrides: Mapping[str, Any] | Sequence[str] | None = None
    out_dir: Path | None = None
    trace_format: str = "csv"
    engine: str | None = None
    cache_dir: Path | None = None
    catalog: Any = None
    auto_fidelity: Any = None
    max_trace_bytes: int | str | None = None
    call_timeout: float | None = None
    progress: Callable[[int, int], None] | None = None
    log: Callable[[str], None] = _quiet

    @classmethod
    def of(cls, overrides: Mapping[str, Any] | Sequence[str] | None, base: "RunRequest | None",
           options: Mapping[str, Any]) -> "RunRequest":
        """The request of ``run(scene, overrides, request=base, **options)``: ``base`` (default: all
        defaults) with ``overrides`` (when given) and the keyword ``options`` (field names) set;
        a keyword that is no field is a :class:`TypeError` naming it, as a misspelt argument is."""
        unknown = sorted(set(options) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"run() got unexpected keyword argument(s) {', '.join(unknown)}; "
                            f"expected some of {', '.join(f.name for f in fields(cls))}")
        changes = {**options, **({"overrides": overrides} if overrides is not None else {})}
        if changes.get("log", _quiet) is None:
            changes["log"] = _quiet
        return replace(base or cls(), **changes)

    @property
    def override_list(self) -> list:
        """The overrides as a list (of items or ``"path=value"`` strings)."""
        ov = self.overrides
        return list(ov.items()) if isinstance(ov, Mapping) else list(ov or [])

    def pilot(self) -> "RunRequest":
        """The request of a run that only informs this one (a pilot, :mod:`cosim.run.choose`): in
        memory, quiet, the same engine."""
        return RunRequest(engine=self.engine)


@dataclass
class RunResult:
    """Outcome of :func:`run`: ``status`` is ``"ok"``, ``"failed"``, ``"stopped"`` (a component
    asked to end), ``"out_of_limits"`` or ``"unstable"`` (a guard, :mod:`cosim.run.row_guards`) or
    ``"interrupted"``; ``reason`` says why a run
    ended early; ``trace`` holds what was recorded
    (also the partial trace of a failed run); ``stats`` the run statistics
    (:class:`cosim.master.RunStats` as a dict)."""

    scene: Scene
    status: str
    reason: str
    trace: Trace
    stats: dict
    fmus: dict[str, Path] = field(default_factory=dict)
    trace_path: Path | None = None
    build_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def build_components(scene: Scene, *, cache_dir: Path | None = None,
                     progress: Callable[[str], None] | None = None) -> dict[str, Path]:
    """The FMU of every component: the external file, or the catalog block built by
    :func:`fmus.build_fmu` (cached by content, so a second run compiles nothing)."""
    paths: dict[str, Path] = {}
    for name, comp in scene.components.items():
        if comp.kind == "fmu":
            paths[name] = comp.fmu
            continue

        paths[name] = component_fmu(comp, cache_dir=cache_dir,
                                    progress=(lambda msg, n=name: progress(f"{n}: {msg}")) if progress else None)

    store_pending_replays()  # what the scene check computed, for the next process
    return paths


def couple(scene: Scene, slaves: Sequence[Slave], watch: Sequence[tuple[str, str]] = ()) -> CoupledSystem:
    """The coupled system of ``scene`` over ``slaves`` (one per component, in scene order);
    ``watch``: (component, variable) pairs sampled with the recorded ones but not traced."""
    index = {s.name: i for i, s in enumerate(slaves)}
    links = [Link(index[c.src], c.src_var, index[c.dst], c.dst_var, c.factor, c.offset, c.bond)
             for c in scene.connections]
    record = []
    for name in scene.outputs:
        comp, _, var = name.partition(".")
        record.append((index[comp], var))
    return CoupledSystem(slaves, links, record, [(index[c], v) for c, v in watch])


def scene_observers(scene: Scene, out_dir: Path | None, suffix: str = "",
                    trace_format: str = "csv") -> tuple[MemoryTrace, list, Path | None]:
    """The observers of a run of ``scene``: a :class:`MemoryTrace` and, with ``out_dir``, a
    trace writer streaming to ``out_dir/<name><suffix>.csv`` (``.parquet`` for
    ``trace_format="parquet"``; see :data:`cosim.trace.traces.TRACE_FORMATS`), returned as the
    trace path."""

    memory = MemoryTrace()
    if out_dir is None:
        return memory, [memory], None
    path = confined(out_dir, f"{safe_name(scene.name)}{suffix}{trace_suffix(trace_format)}")
    check_set(out_dir, f"{safe_name(scene.name)}{suffix}")
    check_ours(path)
    return memory, [memory, trace_writer(path, trace_format, extra={"scene_data": scene.data})], path


def scene_meta(scene: Scene) -> dict:
    """Trace metadata identifying the scene a run comes from."""

    units = units_of(scene)
    return {"scene": scene.name, "scene_file": str(scene.path) if scene.path else None, "scene_hash": scene.hash,
            "start_time": scene.start_time, "stop_time": scene.stop_time,
            "output_interval": scene.master.record_every * scene.master.step,
            "units": {name: units.get(name, "") for name in scene.outputs},
            **({"notes": [f"{p.severity}: {p.message}" for p in scene.warnings]} if scene.warnings else {})}


@dataclass(frozen=True)
class TraceEstimate:
    """Expected size of a run's trace: macro ``steps``, ``rows`` (incl. t = 0), ``columns``
    (incl. time) and ``bytes`` of CSV text (:data:`BYTES_PER_VALUE` per value)."""

    steps: int
    rows: int
    columns: int
    bytes: int
    #: a component may report events (FMI 3.0 event mode): two more rows at each (one where it falls on an
    #: output point, whose row is then the left limit)
    events: bool = False
    #: ``master.record: steps`` under a variable-step algorithm: a row per accepted step, ``rows`` a guess
    per_step: bool = False

    def __str__(self) -> str:
        rows = (f"one row per accepted step (about {self.rows:,} at the output interval)" if self.per_step
                else f"{self.rows:,} rows")
        more = " + 2 per event (1 at an output point)" if self.events else ""
        return (f"{self.steps:,} steps, {rows}{more} x {self.columns} columns, "
                f"trace about {human_bytes(self.bytes)}")


#: Average CSV bytes per recorded value (shortest round-trip decimal and a comma; measured
#: 19-21 on the shipped scenes).
BYTES_PER_VALUE = 21
#: Default largest trace a run may write [bytes]; ``$RPR_COSIM_MAX_TRACE`` or ``max_trace_bytes``.
MAX_TRACE_BYTES = 4 * 10 ** 9
MAX_TRACE_ENV = "RPR_COSIM_MAX_TRACE"


def human_bytes(n: float) -> str:
    """``n`` bytes as ``"3.4 MB"`` (powers of 1000)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} B"  # pragma: no cover


def parse_bytes(text: str | int | float) -> int:
    """``"20GB"``, ``"500 MB"``, ``"1e9"`` -> bytes; :class:`UserError` otherwise."""
    import re

    m = re.fullmatch(r"\s*([0-9.eE+]+)\s*([kKMGTP]?)B?\s*", str(text))
    try:
        value = float(m.group(1)) if m else float("nan")
    except ValueError:
        value = float("nan")
    if not m or not value >= 0:
        raise UserError(f"trace size limit {text!r}: expected a size such as 20GB, 500MB or 1e9")
    return int(value * 1000 ** " KMGTP".index(m.group(2).upper() or " "))


def estimate(scene: Scene) -> TraceEstimate:
    """The trace a run of ``scene`` would write (before anything is built)."""
    m = scene.master
    rows = scene.n_steps // m.record_every + 1
    cols = len(scene.outputs) + 1
    cls = ALGORITHMS[m.algorithm]
    events = (m.auto or cls.ends_steps_at_events) and any(c.description.has_event_mode
                                                          for c in scene.components.values())
    per_step = m.record == "steps" and (m.auto or cls.variable_step)
    return TraceEstimate(scene.n_steps, rows, cols, rows * cols * BYTES_PER_VALUE, events, per_step)


def check_trace_size(scene: Scene, max_trace_bytes: int | str | None = None) -> TraceEstimate:
    """The estimate of :func:`estimate`; :class:`UserError` with the numbers and the ways out
    when it exceeds ``max_trace_bytes`` (default ``$RPR_COSIM_MAX_TRACE`` or 4 GB)."""
    import os

    est = estimate(scene)
    limit = max_trace_bytes if max_trace_bytes is not None else os.environ.get(MAX_TRACE_ENV) or MAX_TRACE_BYTES
    limit = parse_bytes(limit)
    if est.bytes > limit:
        raise UserError(f"scene {scene.name}: the trace would be about {human_bytes(est.bytes)} ({est.rows:,} rows x "
                        f"{est.columns} columns), beyond the limit of {human_bytes(limit)}; raise the limit with "
                        f"--max-trace {human_bytes(est.bytes * 1.1).replace(' ', '')} (or ${MAX_TRACE_ENV}), or record "
                        f"less (master.output_interval, outputs) or a shorter stop_time")
    return est


def run(scene: Scene | str | Path, overrides: Mapping[str, Any] | Sequence[str] | None = None, *,
        slaves: Sequence[Slave] | None = None, request: RunRequest | None = None, **options: Any) -> RunResult:
    """Run a scene.

    Parameters
    ----------
    scene : a validated :class:`Scene` or the path of a scene file.
    overrides : ``--set`` style overrides (mapping path -> value, or ``"path=value"`` strings);
        with a :class:`Scene` they are applied by reloading its file.
    slaves : ready slaves in scene order instead of FMUs built from the scene (non-FMU slaves).
    request : a whole :class:`RunRequest` (its ``overrides`` are used when ``overrides`` is None);
        else the keyword ``options`` below are its fields.
    out_dir : write ``<name>.csv`` (streamed) and ``<name>.json`` (sidecar) there.
    trace_format : ``"csv"`` (plain, the default), ``"commented-csv"`` or ``"parquet"``
        (``<name>.parquet``), see :mod:`cosim.trace.traces`.
    catalog : the model catalog (default :mod:`models.blocks`).
    cache_dir : FMU cache directory (default ``$RPR_COSIM_CACHE`` or ``~/.cache/rpr-cosim/fmus``).
    progress : called as ``progress(steps_done, steps_total)`` during the run.
    log : one-line messages about building FMUs.
    engine : overrides ``master.engine`` (auto | compiled).
    max_trace_bytes : refuse a run whose trace would be larger (default ``$RPR_COSIM_MAX_TRACE``
        or 4 GB; a number of bytes or a text such as ``"20GB"``).
    auto_fidelity : how ``fidelity: auto`` is resolved when loading (see :func:`cosim.scenario.load`;
        :func:`cosim.study.fidelity.resolve_auto`).
    call_timeout : the longest one FMI call may take [s] before the run ends "hung" (default
        ``$RPR_COSIM_CALL_TIMEOUT`` or 60 s).

    FMU runs (``slaves`` not given) are supervised (:mod:`cosim.run.supervise`): the stepping
    happens in a child process, so an FMU that crashes, exits or hangs ends the run with the
    status "crashed" or "hung" (the component and FMI call in the reason) instead of taking the
    caller with it.

    Returns a :class:`RunResult`; a numerical failure or a failed trace write (disk full) is a
    status, not an exception.  A KeyboardInterrupt (also SIGTERM and SIGHUP, see
    :mod:`cosim.interrupts`) propagates after the trace files were finalised with the reason.
    Files go only under ``out_dir`` (:mod:`cosim.outputs`): one run per directory at a time,
    the trace written under a temporary name and moved into place at the end.
    """

    request = RunRequest.of(overrides, request, options)
    out_dir = request.out_dir
    trace_suffix(request.trace_format)  # an unknown format is one line before anything runs
    if out_dir is None:
        with signals_as_interrupts():
            return _as_chosen(_run(scene, request, slaves))
    check_out_dir(out_dir)
    with signals_as_interrupts(), OutputLock(out_dir, log=request.log):
        return _as_chosen(_run(scene, request, slaves))


def _as_chosen(res: RunResult) -> RunResult:
    """``res`` with its scene as the master ran it (the choice of :mod:`cosim.run.choose`, which
    the run's statistics carry: the stepping may have happened in a supervised child)."""
    choice = res.stats.get("choice") if isinstance(res.stats, dict) else None
    if choice and res.scene.master.auto:

        res.scene = applied(res.scene, choice)
    return res


def _run(scene: Scene | str | Path, request: RunRequest, slaves: Sequence[Slave] | None) -> RunResult:

    overrides, log = request.overrides, request.log
    if not isinstance(scene, Scene):
        scene = load(scene, overrides, catalog=request.catalog, auto_fidelity=request.auto_fidelity)
    elif overrides:
        if scene.path is None or not Path(scene.path).is_file():
            raise UserError("overrides need the scene's file; pass the path instead of a Scene")
        scene = load(scene.path, overrides, catalog=request.catalog, auto_fidelity=request.auto_fidelity)
    log(f"{scene.name}: {check_trace_size(scene, request.max_trace_bytes)}")
    t0 = time.perf_counter()
    if slaves is None:
        paths = build_components(scene, cache_dir=request.cache_dir, progress=log)
        build_s = time.perf_counter() - t0
        if supervise.enabled():

            for p in paths.values():  # here, so that this process removes the folders at exit whatever the child does
                unpack_fmu(p)
            return _supervised(scene, request, paths, None, build_s)
        status, reason, trace, stats, trace_path, build_step = _step(scene, request, paths, None)
        return RunResult(scene, status, reason, trace, stats, paths, trace_path, build_s + build_step)
    if [s.name for s in slaves] != list(scene.components):
        raise UserError(f"slaves must match the scene's components in order: {list(scene.components)}")
    if supervise.enabled() and all(type(s) is FmuSlave and s.fmu is None and not s.reuse for s in slaves):
        # fresh FMU slaves (a study's): supervised too, nothing of theirs is kept after the run
        return _supervised(scene, request, {}, slaves, 0.0)
    status, reason, trace, stats, trace_path, build_s = _step(scene, request, {}, slaves)
    return RunResult(scene, status, reason, trace, stats, {}, trace_path, build_s)


def _supervised(scene: Scene, request: RunRequest, paths: dict, slaves: Sequence[Slave] | None,
                build_s: float) -> RunResult:
    """:func:`_step` in a supervised child (:mod:`cosim.run.supervise`); a crash, a hung call or
    a child that had to be killed after a signal becomes the run's status (the signal is raised
    again once the files are settled)."""

    timeout = supervise.call_timeout(request.call_timeout)
    try:
        status, reason, trace, stats, trace_path, _ = supervise.supervised(
            lambda say: _step(scene, replace(request, log=say), paths, slaves), timeout_s=timeout, log=request.log)
    except supervise.Failed as failed:
        res = _settle_failed(scene, request.out_dir, paths, build_s, failed, request.trace_format)
        if failed.signal_exc is not None:
            raise failed.signal_exc from None
        return res
    return RunResult(scene, status, reason, trace, stats, paths, trace_path, build_s)


def _settle_failed(scene: Scene, out_dir: Path | None, paths: dict, build_s: float, failed,
                   trace_format: str = "csv") -> RunResult:
    """The result of a supervised run whose process crashed, hung or had to be killed: its files
    settled with the supervisor's status and reason (:func:`cosim.outputs.settle_run`), or written
    afresh when it had written nothing yet."""
    import numpy as np


    stats = RunStats(scene.master.algorithm, "", scene.master.step, scene.n_steps, status=failed.status,
                     reason=failed.reason)
    columns = ["time", *scene.outputs]
    if out_dir is None:
        return RunResult(scene, failed.status, failed.reason,
                         Trace(columns, np.zeros((0, len(columns))), scene_meta(scene), failed.status, failed.reason,
                               stats.as_dict()), stats.as_dict(), paths, None, build_s)
    path = confined(out_dir, f"{safe_name(scene.name)}{trace_suffix(trace_format)}")
    if settle_run(path, failed.status, failed.reason) is None:  # it died before writing anything
        ob = trace_writer(path, trace_format, extra={"scene_data": scene.data})
        ob.start(columns, scene_meta(scene))
        ob.finish(failed.status, failed.reason, stats.as_dict())
    trace = read_trace(path)
    stats.steps_done = max(0, len(trace.data) - 1) * scene.master.record_every
    trace.status, trace.reason, trace.stats = failed.status, failed.reason, stats.as_dict()
    return RunResult(scene, failed.status, failed.reason, trace, stats.as_dict(), paths, path, build_s)


def _step(scene: Scene, request: RunRequest, paths: dict, slaves: Sequence[Slave] | None) -> tuple:
    """Couple the slaves (FMUs from ``paths`` when ``slaves`` is None), step them (after the
    master's choice, :mod:`cosim.run.choose`, for a scene that names no algorithm, and a companion
    run for the error estimate, :mod:`cosim.master.estimate`) and return (status, reason, trace,
    stats, trace path, seconds spent making the slaves)."""

    t0 = time.perf_counter()
    given = list(slaves) if slaves is not None else None

    comps = list(scene.components.values())

    def prepared(s: Slave, c) -> Slave:
        if c.kind == "fmu" and s.description is not c.description and isinstance(s, FmuSlave):
            # what the scene check found (feedthrough, behavioural workarounds) also for slaves made elsewhere
            d = c.description
            s.description = replace(s.description, feedthrough=d.feedthrough, workarounds=d.workarounds,
                                    rollback_reason=d.rollback_reason,
                                    can_get_set_state=s.description.can_get_set_state and d.can_get_set_state)
            s.always_no_prior = "always_no_prior" in d.workarounds
        if not c.rollback and s.description.can_get_set_state:  # the scene forbids rollback of this component
            s.description = replace(s.description, can_get_set_state=False)
        if c.memoryless and not s.description.memoryless:  # evaluated within Jacobi's exchange
            s.description = replace(s.description, memoryless=True)
        return s

    def make_slave(i: int) -> Slave:
        """A fresh slave of component ``i`` (from the FMU of the slave handed over, when it was)."""
        c = comps[i]
        if given is not None:
            return prepared(FmuSlave(given[i].name, given[i].path, given[i].description), c)
        return prepared(FmuSlave(c.name, paths[c.name], c.description if c.kind == "fmu" else
                                 slave_description(c, paths[c.name])), c)

    main = [prepared(s, c) for s, c in zip(given, comps)] if given is not None else [make_slave(i) for i in
                                                                                       range(len(comps))]
    build_s = time.perf_counter() - t0
    repeat = repeatable(scene)
    if repeat is None and given is not None and not all(isinstance(s, FmuSlave) for s in given):
        repeat = "the slaves were handed over ready, not as FMUs: a run is not repeated"
    # one load per catalog FMU for the pilots, companions and the run; an external FMU's reset is not trusted
    instances = Instances(main, make_slave, [c.kind != "fmu" for c in comps])
    try:
        extra: dict = {}
        pilots: list[RunResult] = []
        if scene.master.auto:
            from .choose import choose

            companions: list = []

            def pilot(sc: Scene, companion_rtol: float | None = None) -> RunResult:
                pilots.append(_once(sc, Stepping(instances, repeat, companions), request.pilot(), None, {},
                                    companion_rtol))
                return pilots[-1]

            scene, choice = choose(scene, pilot if repeat is None else None, request.log, why_not=repeat)
            extra["choice"] = choice.as_dict()
            request.log(f"{scene.name}: {choice}")
        same = next((p for p in reversed(pilots) if p.scene.master == scene.master and p.scene.n_steps == scene.n_steps
                     and p.scene.stop_time == scene.stop_time and not p.trace.text), None)
        if same is not None:  # the last pilot ran the chosen setting over the whole run: it is the run
            res = _replay(same, scene, request, extra)
        else:
            res = _once(scene, Stepping(instances, repeat), request, main, extra)
    finally:
        instances.close()
    return res.status, res.reason, res.trace, res.stats, res.trace_path, build_s


def _run_meta(scene: Scene, overrides: Mapping[str, Any] | Sequence[str] | None) -> dict:
    """The trace metadata of a run of ``scene``; ``overrides``: every one it was loaded with (the
    scene's own record of them, :attr:`Scene.overrides`: ``--set``, a batch axis, the Python API),
    else those of the request, as ``path=value`` texts."""
    return {**scene_meta(scene), "inputs": scene.master.inputs,
            "components": {n: c.label for n, c in scene.components.items()},
            "connections": [str(c) for c in scene.connections],
            "overrides": scene.overrides or override_texts(overrides)}


#: Rows per block when a pilot run's rows are written as the run (:func:`_replay`).
REPLAY_ROWS = 32


def _replay(pilot: RunResult, scene: Scene, request: RunRequest, extra: dict) -> RunResult:
    """The run of ``scene`` that the pilot run ``pilot`` (the same scene at the same setting over
    the same span, with its companion, estimate and verdict) already is: its rows, status and
    statistics written to the run's observers (trace file, sidecar) with ``extra`` (the choice),
    instead of running it once more."""


    memory, inner, trace_path = scene_observers(scene, request.out_dir, trace_format=request.trace_format)
    progress = request.progress
    tr = pilot.trace
    status, reason, stats = pilot.status, pilot.reason, dict(pilot.stats, **extra)
    rows, n = tr.data, len(tr.data)
    chunk = max(1, min(n, REPLAY_ROWS))
    done = 0
    try:
        for ob in inner:
            ob.start(tr.columns, {**tr.meta, **_run_meta(scene, request.overrides), **extra})
        try:
            # in blocks, as a run records them: a full disk keeps whole rows, a signal or Ctrl-C
            # (from the progress callback too) ends the run "interrupted" with the rows written
            while done < n:
                for ob in inner:
                    ob.record(rows[done:done + chunk])
                done += min(chunk, n - done)
                if progress:
                    progress(round(scene.n_steps * done / n), scene.n_steps)
        except TraceWriteError as exc:  # disk full: the run failed with the reason, its rows so far kept
            status, reason = "failed", str(exc)
            stats = dict(stats, status=status, reason=reason)
        except KeyboardInterrupt as exc:
            status = "interrupted"
            reason = interruption_reason(exc, float(rows[done - 1, 0]) if done else None)
            stats = dict(stats, status=status, reason=reason)
            for ob in inner:
                ob.finish(status, reason, stats)
            raise
        for ob in inner:
            ob.finish(status, reason, stats)
    finally:
        for ob in inner:
            if ob.note:
                request.log(ob.note)
    t = memory.trace
    for ob in inner:  # a trace writer that failed at the end turns "ok" into "failed"
        if getattr(ob, "status", status) != status:
            status, reason = ob.status, ob.reason
            stats = dict(stats, status=status, reason=reason)
            t.status, t.reason = status, reason
    return RunResult(scene, status, reason, t, stats, {}, trace_path, 0.0)


def repeatable(scene: Scene) -> str | None:
    """None when a run of ``scene`` may be repeated without side effects (companion and pilot runs
    of :mod:`cosim.master.estimate` and :mod:`cosim.run.choose`); otherwise why not."""
    if scene.master.realtime is not None:
        return "a run paced in real time is not repeated (it may drive hardware)"
    comps = scene.data.get("components") or {}
    hw = [n for n, spec in comps.items() if isinstance(spec, Mapping) and "hardware" in spec]
    if hw:
        return f"{', '.join(hw)} is hardware: a run is not repeated"
    return None


@dataclass
class Stepping:
    """What the runs of one scene in a request share (pilots, companions, the run): the slave
    ``instances``, why a run may not be repeated (``repeat``, None: it may), and for the pilots
    the companions run so far (``companions``: (scene, (time, values)); None for the run itself)."""

    instances: Instances
    repeat: str | None
    companions: list | None = None


@dataclass(frozen=True)
class Watched:
    """What a run of a scene adds to its stepping that its companion run does not: progress, the
    trace metadata and the guard; it is also paced (``master.realtime``), timed, and recorded at
    ``master.output_interval`` (a companion records every step)."""

    progress: Callable[[int, int], None] | None
    meta: dict
    guard: Any


def simulate_scene(scene: Scene, system: CoupledSystem, observers: Sequence, engine: str | None,
                   watched: Watched | None) -> Any:
    """:func:`cosim.master.simulate` of ``scene`` over its coupled ``system``: the scene's master
    settings mapped to the run's, written once (``engine`` overrides ``master.engine``); ``watched``
    None for a companion run."""
    m, w = scene.master, watched
    return simulate(system, m.algorithm, step_ns=m.step_ns, n_steps=scene.n_steps, observers=observers,
                    start_values=[c.start_values() for c in scene.components.values()], engine=engine or m.engine,
                    order=_order(scene), inputs=m.inputs, start_ns=scene.start_ns, tolerances=_tolerances(scene),
                    options=m.options or None, rates=[c.rate for c in scene.components.values()],
                    # a variable-step companion lands on the run's own output grid (the same steps)
                    record_every=m.record_every if w or ALGORITHMS[m.algorithm].variable_step else 1,
                    record=m.record, timing=w is not None, progress=w and w.progress,
                    meta=w and w.meta, realtime=m.realtime if w else None, guard=w and w.guard)


def _companion_trace(scene: Scene, stepping: Stepping, engine: str | None, rtol: float | None = None
                     ) -> tuple[tuple | None, float, str]:
    """Run the companion of ``scene`` (:mod:`cosim.run.companion`; at ``rtol`` when given) on
    ``stepping.instances`` into memory: ``((time, values) or None, divisor, method)``; one that is
    the same scene as a companion in ``stepping.companions`` is not run again."""
    instances, ran = stepping.instances, stepping.companions
    comp = companion(scene, any(s.description.can_interpolate_inputs for s in instances.main), rtol)
    if comp.scene is None:
        return None, 1.0, comp.method
    cs = comp.scene
    same = next((tr for sc, tr in ran or () if sc.master == cs.master and sc.n_steps == cs.n_steps
                 and sc.stop_time == cs.stop_time), None)
    if same is not None:
        return same, comp.div, comp.method + " (the earlier pilot's)"
    slaves = instances.take()
    memory = MemoryTrace()
    system = couple(cs, slaves)
    try:
        simulate_scene(cs, system, [memory], engine, None)
    except UserError as exc:
        instances.ended("failed")
        return None, 1.0, f"{comp.method} could not run: {exc}"
    except Exception as exc:  # the companion failed: no estimate
        instances.ended("failed")
        return None, 1.0, f"{comp.method} failed: {type(exc).__name__}: {exc}"
    tr = memory.trace
    instances.ended(tr.status)
    if tr.status not in ("ok", "stopped"):  # a companion that failed says nothing of the run
        return None, 1.0, f"{comp.method} ended {tr.status}: {tr.reason}"
    if ran is not None and rtol is not None:  # a companion named by its rtol may be asked for again
        ran.append((cs, (tr.time, tr.data[:, 1:])))
    return (tr.time, tr.data[:, 1:]), comp.div, comp.method


def event_modes(scene: Scene) -> list[str]:
    """The modes (discrete variables) of the scene's components with state events, as recorded
    column names (a catalog block's ``mode.X`` and its output ``X``): their changes are events
    whose time depends on the run.  A sampled component's
    discrete variables change at its sample instants, the same in every run: not among them."""
    out = []
    for name, c in scene.components.items():
        d = c.description
        discrete = [v.name for v in d.variables.values()
                    if v.variability == "discrete" and v.causality in ("local", "output")]
        if not discrete or d.sample_period or (c.block is not None and getattr(c.block, "sample_times", None)):
            continue
        for v in discrete:  # a catalog block's mode "mode.stuck" is also its output "stuck"
            out.append(f"{name}.{v}")
            if v.startswith("mode.") and v[5:] in d.variables:
                out.append(f"{name}.{v[5:]}")
    return out


def held_values(scene: Scene) -> list[str]:
    """The held values of the scene's sampled components (their discrete variables, and the outputs
    of a sampler without states that no input feeds through), as recorded column names: an ADC's
    code and read-back length, a PWM duty; the estimate compares the quantised ones to one quantum
    (:func:`cosim.master.estimate.one_count_apart`)."""
    out = []
    for name, c in scene.components.items():
        d, b = c.description, c.block
        if not (d.sample_period or (b is not None and getattr(b, "sample_times", None))):
            continue
        out += [f"{name}.{v.name}" for v in d.variables.values()
                if v.variability == "discrete" and v.causality in ("local", "output")]
        if b is not None and not b.states:  # a sampler's outputs that no input feeds through: its held values
            through = b.feedthrough()
            out += [f"{name}.{v.name}" for v in b.outputs if not through.get(v.name)]
    return out


def _order(scene: Scene) -> list[int] | None:
    index = {n: i for i, n in enumerate(scene.components)}
    return [index[n] for n in scene.master.order] if scene.master.order else None


def _tolerances(scene: Scene) -> list:
    return [c.description.default_experiment.get("tolerance") for c in scene.components.values()]


def _once(scene: Scene, stepping: Stepping, request: RunRequest, slaves: Sequence[Slave] | None, extra: dict,
          companion_rtol: float | None = None) -> RunResult:
    """One run of ``scene`` on ``slaves`` (None: ``stepping.instances.take()``) with its error
    estimate (a companion run on ``instances.take()`` first, when ``stepping.repeat`` is None: at
    ``companion_rtol`` when given, one of ``stepping.companions`` when it is the same, see
    :func:`_companion_trace`), judged by it (:func:`cosim.master.estimate.judge`)."""

    instances, repeat, engine = stepping.instances, stepping.repeat, request.engine
    if repeat is None and not scene.master.estimate:
        ctrace, div, method = None, 1.0, "master.estimate: false"
    elif repeat is None:
        ctrace, div, method = _companion_trace(scene, stepping, engine, companion_rtol)
    else:
        ctrace, div, method = None, 1.0, repeat
    guard = scene_guard(scene)
    system = couple(scene, slaves if slaves is not None else instances.take(), guard.watch if guard else ())
    if guard:
        guard.bind(system.record_names + system.watch_names)
    memory, inner, trace_path = scene_observers(scene, request.out_dir, trace_format=request.trace_format)
    estimator = EstimatingObserver(inner, ctrace, div, method, scene.master.tolerance, extra, event_modes(scene),
                                   held_values(scene))
    meta = _run_meta(scene, request.overrides)
    try:
        stats = simulate_scene(scene, system, [estimator], engine, Watched(request.progress, meta, guard)).as_dict()
        stats = getattr(estimator, "stats", stats)
    except TraceWriteError:  # disk full: the observers finished with the reason; report it as a status
        if memory.trace is None or not memory.trace.stats:
            raise
        stats = memory.trace.stats
    finally:
        for ob in inner:
            if ob.note:
                request.log(ob.note)
    instances.ended(stats["status"])
    t = memory.trace
    for ob in inner:  # a trace writer that failed at the end turns "ok" into "failed"
        if getattr(ob, "status", stats["status"]) != stats["status"]:
            stats = dict(stats, status=ob.status, reason=ob.reason)
            t.status, t.reason = ob.status, ob.reason
    return RunResult(scene, stats["status"], stats["reason"], t, stats, {}, trace_path, 0.0)
