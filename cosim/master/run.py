"""The run loop: initialise the slaves, step with an algorithm through an engine, hand rows to the
observers, and return the run's statistics (:class:`RunStats`)."""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from ..errors import UserError
from ..slaves import FAILING, Slave, Status
from .algorithm import Algorithm, algorithm
from .engine import _Compiled, _python_run, choose_engine
from .system import CoupledSystem


@dataclass
class RunStats:
    """Statistics of one run: per-slave doStep calls and wall time [s] (inside its FMI calls),
    the master's own time [s] (everything else in the stepping loop), totals."""

    algorithm: str
    engine: str
    step: float
    steps_planned: int
    steps_done: int = 0
    status: str = "running"
    reason: str = ""
    init_s: float = 0.0
    wall_s: float = 0.0
    master_s: float = 0.0
    slaves: dict[str, dict[str, float]] = field(default_factory=dict)
    guards: dict = field(default_factory=dict)
    realtime: dict | None = None  # lateness statistics of a paced run (cosim.realtime)
    extra: dict = field(default_factory=dict)  # the algorithm's own statistics (its statistics())

    @property
    def simulated_s(self) -> float:
        return self.steps_done * self.step

    @property
    def real_time_factor(self) -> float:
        """Simulated time over wall time of the stepping loop (> 1: faster than real time)."""
        return self.simulated_s / self.wall_s if self.wall_s > 0 else float("inf")

    def as_dict(self) -> dict:
        return {"algorithm": self.algorithm, "engine": self.engine, "step": self.step,
                "steps_planned": self.steps_planned, "steps_done": self.steps_done, "status": self.status,
                "reason": self.reason, "init_s": self.init_s, "wall_s": self.wall_s, "master_s": self.master_s,
                "simulated_s": self.simulated_s, "real_time_factor": self.real_time_factor, "slaves": self.slaves,
                **({"guards": self.guards} if self.guards else {}), **self.extra,
                **({"realtime": self.realtime} if self.realtime is not None else {})}


def interruption_reason(exc: KeyboardInterrupt, t: float | None) -> str:
    """The reason of a run ended by Ctrl-C or a signal (``exc`` names the signal, see
    :mod:`cosim.interrupts`), at simulated time ``t`` when known."""
    return f"interrupted by {str(exc) or 'the user (KeyboardInterrupt)'}" + (f" at t = {t:.9g} s" if t is not None else "")


class Ending:
    """How a run ended: ``status`` and ``reason`` (set by the run's block when it completes)."""

    def __init__(self) -> None:
        self.status, self.reason = "failed", ""

    def from_loop(self, loop) -> None:
        """ok, or the status and message the loop (an algorithm or stepper) stopped with."""
        self.status, self.reason = ("ok", "") if loop.status == "running" else (loop.status, loop.message)


@contextmanager
def settled(stats: RunStats, system: CoupledSystem, observers: Sequence, now: Callable[[], float | None],
            fill: Callable[[], None]) -> Iterator[Ending]:
    """The block that runs a scene: however it ends, ``stats`` gets its status and reason (an
    exception is a failure, Ctrl-C or a signal an interruption at simulated time ``now()``), then
    ``fill()`` completes the statistics, the observers finish and the slaves are terminated and
    freed; an exception propagates after that."""
    end = Ending()
    try:
        yield end
    except KeyboardInterrupt as exc:
        end.status, end.reason = "interrupted", interruption_reason(exc, now())
        raise
    except BaseException as exc:
        end.status, end.reason = "failed", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        stats.status, stats.reason = end.status, end.reason
        fill()
        for obs in observers:
            obs.finish(end.status, end.reason, stats.as_dict())
        for s in system.slaves:
            s.terminate()
            s.free()


def slave_table(system: CoupledSystem, calls: Sequence[int], slave_ns: Sequence[int],
                rates: Sequence[int] | None = None) -> dict[str, dict[str, float]]:
    """Per-slave run statistics: doStep calls and wall time [s] inside the slave's calls (and the
    slave's ``rate``, doSteps per macro step, when it is not 1)."""
    return {s.name: {"do_step_calls": int(calls[i]), "wall_s": slave_ns[i] / 1e9,
                     **({"rate": int(rates[i])} if rates and rates[i] != 1 else {})}
            for i, s in enumerate(system.slaves)}


def initialize(system: CoupledSystem, start_values: Sequence[dict[str, float]], *, start_time: float = 0.0,
               stop_time: float, tolerances: Sequence[float | None] | None = None, allow_loops: bool = False) -> None:
    """Instantiate, set start values, run the initial exchange (feedthrough order) and leave
    initialisation mode; afterwards ``system.v`` holds every bound variable at ``t_0`` (with
    ``allow_loops``, values on an algebraic loop are not consistent yet: the algorithm solves it)."""
    seq = system.init_sequence(allow_loops)
    for s, start in zip(system.slaves, start_values):
        s.instantiate()
        s.set_start(start)
    system.bind()
    for i, s in enumerate(system.slaves):
        tol = tolerances[i] if tolerances else None
        if tol is None:
            s.enter_initialization(start_time, stop_time)
        else:
            s.enter_initialization(start_time, stop_time, tol)
    for i, s in enumerate(system.slaves):
        _check(s, s.pull(), "reading outputs in initialisation mode")
    for i in seq:
        system.gather(i)
        _check(system.slaves[i], system.slaves[i].push(), "setting inputs in initialisation mode")
        _check(system.slaves[i], system.slaves[i].pull(), "reading outputs in initialisation mode")
    for i, s in enumerate(system.slaves):
        system.gather(i)
        _check(s, s.push(), "setting inputs in initialisation mode")
        s.exit_initialization()
    for s in system.slaves:
        _check(s, s.pull(), "reading outputs at the start time")


def _check(slave: Slave, status: int, what: str) -> None:
    if status in FAILING:
        raise UserError(f"{slave.name}: {what} returned {Status(status).name}"
                        + (f": {slave.last_message}" if slave.last_message else ""))


def _guarded(guard, alg: Algorithm, rows: np.ndarray, step_ns: int) -> np.ndarray:
    """``rows`` up to the first one ``guard`` trips on (all when it does not trip); a trip ends
    the run with the guard's status and reason at that row's time."""
    if guard is None or guard.tripped:
        return rows
    keep = guard.check(rows)
    if keep is None:
        return rows
    later = f" (afterwards: {alg.message})" if alg.status != "running" and alg.message else ""
    alg.status, alg.message = guard.status, guard.reason + later
    alg.k = round((rows[keep - 1, 0] * 1e9 - alg.start_ns) / step_ns)
    return rows[:keep]


def simulate(system: CoupledSystem, algorithm_name: str, *, step_ns: int, n_steps: int, record_every: int = 1,
             observers: Sequence = (), start_values: Sequence[dict[str, float]] | None = None,
             engine: str = "auto", order: Sequence[int] | None = None, timing: bool = True,
             progress: Callable[[int, int], None] | None = None, meta: dict | None = None,
             inputs: str = "hold", start_ns: int = 0, tolerances: Sequence[float | None] | None = None,
             realtime=None, options: dict | None = None, guard=None,
             rates: Sequence[int] | None = None) -> RunStats:
    """Initialise ``system`` and run ``n_steps`` macro steps of ``step_ns`` nanoseconds, inputs
    held or linear over each step (``inputs``, see :mod:`cosim.master`).

    Observers receive ``start(columns, meta)``, ``record(rows)`` (rows of time and the recorded
    values, at ``t_0`` and every ``record_every`` steps) and ``finish(status, reason, stats)``,
    also when the run fails or is interrupted (then the exception propagates after ``finish``).
    ``realtime`` (a :class:`cosim.realtime.RealtimeSettings`) paces every step on the wall clock.

    ``guard`` (:class:`cosim.guards.Guard`) sees every row first, with the system's watched
    variables after the recorded ones; when it trips, the rows after the offending one are
    dropped and the run ends with the guard's status and reason.
    """
    cls = algorithm(algorithm_name)
    multirate = {s.name: int(r) for s, r in zip(system.slaves, rates or ()) if r != 1}
    if multirate and not getattr(cls, "multirate", False):
        raise UserError(f"master algorithm {cls.name} does not step slaves at several rates "
                        f"({', '.join(f'{n}.rate = {r}' for n, r in multirate.items())}); use jacobi or gauss_seidel")
    if getattr(cls, "needs_rollback", False):
        fixed = [s.name for s in system.slaves if not s.can_rollback]
        if fixed:
            raise UserError(f"master algorithm {cls.name} needs rollback (get/set state) but {', '.join(fixed)} "
                            f"cannot roll back (canGetAndSetFMUstate=false, e.g. hardware); use ecco (step "
                            f"control from power bonds, no rollback) or a fixed-step algorithm such as gauss_seidel "
                            f"or jacobi")
    if getattr(cls, "variable_step", False):
        if realtime is not None:  # the pacer works on a fixed step grid: refuse rather than run unpaced
            raise UserError(f"master algorithm {cls.name} chooses its own steps and cannot be paced in real time "
                            f"yet; drop master.realtime or use gauss_seidel or jacobi")
        from .algorithms.adaptive import simulate_variable

        return simulate_variable(system, cls, step_ns=step_ns, n_steps=n_steps, observers=observers,
                                 start_values=start_values, order=order, progress=progress, meta=meta,
                                 options=options, start_ns=start_ns, tolerances=tolerances, engine=engine)
    if record_every < 1:
        raise UserError(f"record_every must be >= 1, got {record_every}")
    stats = RunStats(cls.name, "", step_ns / 1e9, n_steps)
    columns = ["time"] + system.record_names
    for obs in observers:
        obs.start(columns, dict(meta or {}, algorithm=cls.name, step=step_ns / 1e9,
                                **({"rates": multirate} if multirate else {})))
    alg, t_loop, pacer = None, None, None

    def fill() -> None:
        if guard is not None:
            stats.guards = guard.summary()
        if alg is not None:
            stats.steps_done = alg.k
            stats.master_s = alg.master_ns / 1e9
            stats.slaves = slave_table(system, alg.calls, alg.slave_ns, alg.rates)
            stats.extra = alg.statistics() if hasattr(alg, "statistics") else {}
        if stats.wall_s == 0.0 and t_loop is not None:
            stats.wall_s = time.perf_counter() - t_loop
        if pacer is not None:
            stats.realtime = pacer.finish()

    with settled(stats, system, observers, lambda: alg.t if alg else None, fill) as end:
        if realtime is not None:  # before initialisation: the pacer quiets the heap first
            from ..realtime import Pacer

            pacer = Pacer(step_ns, n_steps, realtime)
        t0 = time.perf_counter()
        initialize(system, start_values or [{} for _ in system.slaves], start_time=start_ns / 1e9,
                   stop_time=(start_ns + n_steps * step_ns) / 1e9, tolerances=tolerances,
                   allow_loops=getattr(cls, "solves_algebraic_loops", False))
        alg = cls(system, step_ns, order=order, timing=timing, inputs=inputs, start_ns=start_ns, rates=rates,
                  **({"options": options} if getattr(cls, "options", ()) else {}))
        stats.engine = choose_engine(system, cls, engine, start_ns)
        runner = _Compiled(alg).run if stats.engine == "compiled" else (lambda n, e, r: _python_run(alg, n, e, r))
        stats.init_s = time.perf_counter() - t0
        row0 = np.concatenate([[alg.t], system.v[system.record_idx]])[None, :]
        row0 = _guarded(guard, alg, row0, step_ns)
        for obs in observers:
            obs.record(row0[:, :len(columns)])
        for c, x in system.typed.text_changes() if system.typed.texts else ():
            for obs in observers:
                if hasattr(obs, "record_text"):
                    obs.record_text(alg.t, c, x)
        chunk, t_loop, stepping = min(64, n_steps) or 1, time.perf_counter(), 0.0
        if pacer is not None:
            chunk = 1
        width = 1 + len(system.record_idx)
        rec = np.empty((max(1, chunk // record_every + 1), width))
        while alg.k < n_steps and alg.status == "running":
            if pacer is not None and not pacer.wait(alg.k):
                alg.status, alg.message = "failed", pacer.reason
                break
            n = min(chunk, n_steps - alg.k)
            if rec.shape[0] < n // record_every + 1:
                rec = np.empty((n // record_every + 1, width))
            tc = time.perf_counter()
            rows = runner(n, record_every, rec)
            dt = time.perf_counter() - tc
            stepping += dt
            block = _guarded(guard, alg, rec[:rows], step_ns)
            if len(block) < rows:  # a guard cut the block: no text after its last row
                alg.text_events[:] = [ev for ev in alg.text_events if ev[0] <= block[-1, 0]]
            for obs in observers:
                obs.record(block[:, :len(columns)])
                for ev in alg.text_events if hasattr(obs, "record_text") else ():
                    obs.record_text(*ev)
            alg.text_events.clear()
            if progress:
                progress(alg.k, n_steps)
            if dt < 0.05 and chunk < 1 << 20 and pacer is None:  # aim at ~0.1 s per chunk: responsive to Ctrl-C
                chunk *= 2
        stats.wall_s = time.perf_counter() - t_loop
        if stats.engine == "python":  # the compiled loop measures its own share itself
            alg.master_ns = max(0, int(stepping * 1e9) - sum(alg.slave_ns))
        end.from_loop(alg)
    return stats
