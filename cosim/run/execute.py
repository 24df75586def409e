"""A run is a pure function of (scene, overrides): load and validate the scene, build (or fetch
from the cache) the FMUs of its catalog components, couple the slaves, step them with the
scene's master algorithm and return a :class:`RunResult`.  Everything it takes is plain data
(a path and a mapping), so a worker process can execute it."""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..errors import UserError
from .companion import companion
from .guards import scene_guard
from .instances import Instances
from ..master import CoupledSystem, Link, simulate
from ..master.estimate import EstimatingObserver
from ..scenario import Scene, load
from ..slaves.fmu import FmuSlave
from ..slaves.slave import Slave
from ..trace.traces import MemoryTrace, Trace, trace_suffix, trace_writer


@dataclass
class RunResult:
    """Outcome of :func:`run`: ``status`` is ``"ok"``, ``"failed"``, ``"stopped"`` (a component
    asked to end), ``"out_of_limits"`` or ``"unstable"`` (a guard, :mod:`cosim.run.guards`) or
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
        from ..scenario.recipes import component_fmu

        paths[name] = component_fmu(comp, cache_dir=cache_dir,
                                    progress=(lambda msg, n=name: progress(f"{n}: {msg}")) if progress else None)
    from fmus.index import store_pending_replays

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
    from ..outputs import check_ours, confined, safe_name

    memory = MemoryTrace()
    if out_dir is None:
        return memory, [memory], None
    path = confined(out_dir, f"{safe_name(scene.name)}{suffix}{trace_suffix(trace_format)}")
    check_ours(path)
    return memory, [memory, trace_writer(path, trace_format, extra={"scene_data": scene.data})], path


def scene_meta(scene: Scene) -> dict:
    """Trace metadata identifying the scene a run comes from."""
    from ..scenario.units import units_of

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

    def __str__(self) -> str:
        return (f"{self.steps:,} steps, {self.rows:,} rows x {self.columns} columns, "
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
    rows = scene.n_steps // scene.master.record_every + 1
    cols = len(scene.outputs) + 1
    return TraceEstimate(scene.n_steps, rows, cols, rows * cols * BYTES_PER_VALUE)


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
        out_dir: Path | None = None, catalog=None, cache_dir: Path | None = None,
        progress: Callable[[int, int], None] | None = None, log: Callable[[str], None] | None = None,
        engine: str | None = None, slaves: Sequence[Slave] | None = None,
        max_trace_bytes: int | str | None = None, auto_fidelity=None, trace_format: str = "csv",
        call_timeout: float | None = None) -> RunResult:
    """Run a scene.

    Parameters
    ----------
    scene : a validated :class:`Scene` or the path of a scene file.
    overrides : ``--set`` style overrides (mapping path -> value, or ``"path=value"`` strings);
        with a :class:`Scene` they are applied by reloading its file.
    out_dir : write ``<name>.csv`` (streamed) and ``<name>.json`` (sidecar) there.
    trace_format : ``"csv"`` (plain, the default), ``"commented-csv"`` or ``"parquet"``
        (``<name>.parquet``), see :mod:`cosim.trace.traces`.
    catalog : the model catalog (default :mod:`models.blocks`).
    cache_dir : FMU cache directory (default ``$RPR_COSIM_CACHE`` or ``~/.cache/rpr-cosim/fmus``).
    progress : called as ``progress(steps_done, steps_total)`` during the run.
    log : one-line messages about building FMUs.
    engine : overrides ``master.engine`` (auto | compiled | python).
    slaves : ready slaves in scene order instead of FMUs built from the scene (non-FMU slaves).
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
    from ..interrupts import signals_as_interrupts
    from ..outputs import OutputLock, check_out_dir

    say = log or (lambda m: None)
    trace_suffix(trace_format)  # an unknown format is one line before anything runs
    if out_dir is None:
        with signals_as_interrupts():
            return _as_chosen(_run(scene, overrides, None, catalog, cache_dir, progress, say, engine, slaves,
                                   max_trace_bytes, auto_fidelity, call_timeout, trace_format))
    check_out_dir(out_dir)
    with signals_as_interrupts(), OutputLock(out_dir, log=say):
        return _as_chosen(_run(scene, overrides, out_dir, catalog, cache_dir, progress, say, engine, slaves,
                               max_trace_bytes, auto_fidelity, call_timeout, trace_format))


def _as_chosen(res: RunResult) -> RunResult:
    """``res`` with its scene as the master ran it (the choice of :mod:`cosim.run.choose`, which
    the run's statistics carry: the stepping may have happened in a supervised child)."""
    choice = res.stats.get("choice") if isinstance(res.stats, dict) else None
    if choice and res.scene.master.auto:
        from .choose import applied

        res.scene = applied(res.scene, choice)
    return res


def _run(scene, overrides, out_dir, catalog, cache_dir, progress, log, engine, slaves, max_trace_bytes,
         auto_fidelity, call_timeout=None, trace_format="csv") -> RunResult:
    from . import supervise

    if not isinstance(scene, Scene):
        scene = load(scene, overrides, catalog=catalog, auto_fidelity=auto_fidelity)
    elif overrides:
        if scene.path is None or not Path(scene.path).is_file():
            raise UserError("overrides need the scene's file; pass the path instead of a Scene")
        scene = load(scene.path, overrides, catalog=catalog, auto_fidelity=auto_fidelity)
    log(f"{scene.name}: {check_trace_size(scene, max_trace_bytes)}")
    t0 = time.perf_counter()
    if slaves is None:
        paths = build_components(scene, cache_dir=cache_dir, progress=log)
        build_s = time.perf_counter() - t0
        if supervise.enabled():
            from ..slaves.fmu import unpack_fmu

            for p in paths.values():  # here, so that this process removes the folders at exit whatever the child does
                unpack_fmu(p)
            return _supervised(scene, out_dir, paths, None, progress, log, engine, overrides, call_timeout, build_s,
                               trace_format)
        status, reason, trace, stats, trace_path, build_step = _step(scene, out_dir, paths, None, progress, log,
                                                                     engine, overrides, trace_format)
        return RunResult(scene, status, reason, trace, stats, paths, trace_path, build_s + build_step)
    if [s.name for s in slaves] != list(scene.components):
        raise UserError(f"slaves must match the scene's components in order: {list(scene.components)}")
    if supervise.enabled() and all(type(s) is FmuSlave and s.fmu is None and not s.reuse for s in slaves):
        # fresh FMU slaves (a study's): supervised too, nothing of theirs is kept after the run
        return _supervised(scene, out_dir, {}, slaves, progress, log, engine, overrides, call_timeout, 0.0,
                           trace_format)
    status, reason, trace, stats, trace_path, build_s = _step(scene, out_dir, {}, slaves, progress, log, engine,
                                                              overrides, trace_format)
    return RunResult(scene, status, reason, trace, stats, {}, trace_path, build_s)


def _supervised(scene, out_dir, paths, slaves, progress, log, engine, overrides, call_timeout, build_s,
                trace_format="csv") -> RunResult:
    """:func:`_step` in a supervised child (:mod:`cosim.run.supervise`); a crash, a hung call or
    a child that had to be killed after a signal becomes the run's status (the signal is raised
    again once the files are settled)."""
    from . import supervise

    timeout = supervise.call_timeout(call_timeout)
    try:
        status, reason, trace, stats, trace_path, _ = supervise.supervised(
            lambda say: _step(scene, out_dir, paths, slaves, progress, say, engine, overrides, trace_format),
            timeout_s=timeout, log=log)
    except supervise.Failed as failed:
        res = _settle_failed(scene, out_dir, paths, build_s, failed, trace_format)
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

    from ..master import RunStats
    from ..outputs import confined, safe_name, settle_run
    from ..trace.traces import read_trace

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


def _step(scene: Scene, out_dir, paths, slaves, progress, log, engine, overrides, trace_format="csv"):
    """Couple the slaves (FMUs from ``paths`` when ``slaves`` is None), step them (after the
    master's choice, :mod:`cosim.run.choose`, for a scene that names no algorithm, and a companion
    run for the error estimate, :mod:`cosim.master.estimate`) and return (status, reason, trace,
    stats, trace path, seconds spent making the slaves)."""
    from ..scenario.recipes import slave_description

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
                pilots.append(_once(sc, instances, None, None, None, engine, repeat, {},
                                    companion_rtol=companion_rtol, companions=companions))
                return pilots[-1]

            scene, choice = choose(scene, pilot if repeat is None else None, log, why_not=repeat)
            extra["choice"] = choice.as_dict()
            log(f"{scene.name}: {choice}")
        over = list(overrides.items()) if isinstance(overrides, Mapping) else list(overrides or [])
        same = next((p for p in reversed(pilots) if p.scene.master == scene.master and p.scene.n_steps == scene.n_steps
                     and p.scene.stop_time == scene.stop_time and not p.trace.text), None)
        if same is not None:  # the last pilot ran the chosen setting over the whole run: it is the run
            res = _replay(same, scene, out_dir, progress, extra, log, over, trace_format)
        else:
            res = _once(scene, instances, main, out_dir, progress, engine, repeat, extra, log, over, trace_format)
    finally:
        instances.close()
    return res.status, res.reason, res.trace, res.stats, res.trace_path, build_s


def _run_meta(scene: Scene, overrides: Sequence) -> dict:
    """The trace metadata of a run of ``scene``."""
    return {**scene_meta(scene), "inputs": scene.master.inputs,
            "components": {n: c.label for n, c in scene.components.items()},
            "connections": [str(c) for c in scene.connections], "overrides": list(overrides)}


#: Rows per block when a pilot run's rows are written as the run (:func:`_replay`).
REPLAY_ROWS = 32


def _replay(pilot: RunResult, scene: Scene, out_dir, progress, extra: dict, log, overrides: Sequence,
            trace_format: str = "csv") -> RunResult:
    """The run of ``scene`` that the pilot run ``pilot`` (the same scene at the same setting over
    the same span, with its companion, estimate and verdict) already is: its rows, status and
    statistics written to the run's observers (trace file, sidecar) with ``extra`` (the choice),
    instead of running it once more."""
    from ..trace.traces import TraceWriteError

    from ..master import interruption_reason

    memory, inner, trace_path = scene_observers(scene, out_dir, trace_format=trace_format)
    tr = pilot.trace
    status, reason, stats = pilot.status, pilot.reason, dict(pilot.stats, **extra)
    rows, n = tr.data, len(tr.data)
    chunk = max(1, min(n, REPLAY_ROWS))
    done = 0
    try:
        for ob in inner:
            ob.start(tr.columns, {**tr.meta, **_run_meta(scene, overrides), **extra})
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
            if getattr(ob, "note", ""):
                log(ob.note)
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


def _companion_trace(scene: Scene, instances: Instances, engine, rtol: float | None = None,
                     ran: list | None = None) -> tuple[tuple | None, float, str]:
    """Run the companion of ``scene`` (:mod:`cosim.run.companion`; at ``rtol`` when given) on
    ``instances`` into memory: ``((time, values) or None, divisor, method)``.  ``ran`` keeps the
    companions run so far as (scene, trace): one that is the same scene again is not run again."""
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
        simulate(system, cs.master.algorithm, step_ns=cs.master.step_ns, n_steps=cs.n_steps, record_every=1,
                 observers=[memory], start_values=[c.start_values() for c in cs.components.values()],
                 engine=engine or cs.master.engine, order=_order(cs), inputs=cs.master.inputs, start_ns=cs.start_ns,
                 tolerances=_tolerances(cs), options=cs.master.options or None,
                 rates=[c.rate for c in cs.components.values()], timing=False)
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


def _order(scene: Scene) -> list[int] | None:
    index = {n: i for i, n in enumerate(scene.components)}
    return [index[n] for n in scene.master.order] if scene.master.order else None


def _tolerances(scene: Scene) -> list:
    return [c.description.default_experiment.get("tolerance") for c in scene.components.values()]


def _once(scene: Scene, instances: Instances, slaves, out_dir, progress, engine, repeat: str | None, extra: dict,
          log: Callable[[str], None] = lambda m: None, overrides: Sequence = (), trace_format: str = "csv",
          companion_rtol: float | None = None, companions: list | None = None) -> RunResult:
    """One run of ``scene`` on ``slaves`` (None: ``instances.take()``) with its error estimate (a
    companion run on ``instances.take()`` first, when ``repeat`` is None: at ``companion_rtol``
    when given, one of ``companions`` when it is the same, see :func:`_companion_trace`), judged
    by it (:func:`cosim.master.estimate.judge`)."""
    from ..trace.traces import TraceWriteError

    if repeat is None and not scene.master.estimate:
        ctrace, div, method = None, 1.0, "master.estimate: false"
    elif repeat is None:
        ctrace, div, method = _companion_trace(scene, instances, engine, companion_rtol, companions)
    else:
        ctrace, div, method = None, 1.0, repeat
    guard = scene_guard(scene)
    system = couple(scene, slaves if slaves is not None else instances.take(), guard.watch if guard else ())
    if guard:
        guard.bind(system.record_names + system.watch_names)
    memory, inner, trace_path = scene_observers(scene, out_dir, trace_format=trace_format)
    estimator = EstimatingObserver(inner, ctrace, div, method, scene.master.tolerance, extra)
    observers = [estimator]
    meta = _run_meta(scene, overrides)
    try:
        stats = simulate(system, scene.master.algorithm, step_ns=scene.master.step_ns, n_steps=scene.n_steps,
                         record_every=scene.master.record_every, observers=observers,
                         start_values=[c.start_values() for c in scene.components.values()],
                         engine=engine or scene.master.engine, order=_order(scene), progress=progress, meta=meta,
                         inputs=scene.master.inputs, start_ns=scene.start_ns, tolerances=_tolerances(scene),
                         realtime=scene.master.realtime, options=scene.master.options or None,
                         guard=guard, rates=[c.rate for c in scene.components.values()]).as_dict()
        stats = getattr(estimator, "stats", stats)
    except TraceWriteError:  # disk full: the observers finished with the reason; report it as a status
        if memory.trace is None or not memory.trace.stats:
            raise
        stats = memory.trace.stats
    finally:
        for ob in inner:
            if getattr(ob, "note", ""):
                log(ob.note)
    instances.ended(stats["status"])
    t = memory.trace
    for ob in inner:  # a trace writer that failed at the end turns "ok" into "failed"
        if getattr(ob, "status", stats["status"]) != stats["status"]:
            stats = dict(stats, status=ob.status, reason=ob.reason)
            t.status, t.reason = ob.status, ob.reason
    return RunResult(scene, stats["status"], stats["reason"], t, stats, {}, trace_path, 0.0)
