"""The run loop: initialise the slaves, step with an algorithm through an engine, hand rows to the
observers, and return the run's statistics (:class:`RunStats`)."""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import UserError
from .algorithm import algorithm
from .engine import _Compiled, _python_run, choose_engine
from .lifecycle import RunStats, _guarded, initialize, settled, slave_table
from .system import CoupledSystem


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
    ``realtime`` (a :class:`cosim.master.realtime.RealtimeSettings`) paces every step on the wall clock.

    ``guard`` (:class:`cosim.run.guards.Guard`) sees every row first, with the system's watched
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
            from .realtime import Pacer

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
