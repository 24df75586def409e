"""The run: initialise the slaves, bind the scene's algorithm to its engine as a stepper, drive it
with the one loop (:func:`cosim.master.stepper.drive`: pacing, stop requests, guards, the
observers), and return the run's statistics (:class:`RunStats`)."""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from ..errors import UserError
from .algorithm import algorithm, option_values
from .lifecycle import RunStats, VariableStats, initialize, settled
from .engine import ends_steps_at_events, fixed_stepper, needs_compiler
from .stepper import drive, record_start
from .system import CoupledSystem
from .realtime import Pacer, slave_figures


def simulate(system: CoupledSystem, algorithm_name: str, *, step_ns: int, n_steps: int, record_every: int = 1,
             observers: Sequence = (), start_values: Sequence[dict[str, float]] | None = None,
             engine: str = "auto", order: Sequence[int] | None = None, timing: bool = True,
             progress: Callable[[int, int], None] | None = None, meta: dict | None = None,
             inputs: str = "hold", start_ns: int = 0, tolerances: Sequence[float | None] | None = None,
             realtime=None, options: dict | None = None, guard=None,
             rates: Sequence[int] | None = None, stop: Callable[[], str | None] | None = None,
             record: str = "grid") -> RunStats:
    """Initialise ``system`` and run it from ``start_ns`` to ``start_ns + n_steps * step_ns``:
    ``n_steps`` macro steps of ``step_ns`` nanoseconds for a fixed-step algorithm, inputs held or
    linear over each step (``inputs``, see :mod:`cosim.master`); a variable-step algorithm
    (adaptive, ecco) chooses its own steps, ``step_ns`` its first one's hint.

    Observers (:class:`cosim.trace.observer.Observer`) receive ``start(columns, meta)``,
    ``initial(info)``, ``record(rows)`` (rows of time and the recorded values, at ``t_0`` and every
    ``record_every`` steps, where a variable-step run lands a step too; with ``record="steps"`` every
    accepted step of a variable-step run instead; two rows at each event), ``step(info)`` after
    every step where they override it (:class:`cosim.master.stepper.StepInfo`), ``record_text``,
    ``record_event``, ``statistics()`` and ``finish(status, reason, stats)``, also when the run
    fails or is interrupted (then the exception propagates after ``finish``).
    ``realtime`` (a :class:`cosim.master.realtime.RealtimeSettings`) paces every step on the wall clock.
    ``stop()``, asked before every block of steps, ends the run as "stopped" when it returns a reason.
    What an observer's ``statistics()`` returns (not None) goes into the run statistics (the
    sidecar), under its ``name`` (default: its class name).

    ``guard`` (:class:`cosim.run.row_guards.Guard`) sees every row first, with the system's watched
    variables after the recorded ones; when it trips, the rows after the offending one are
    dropped and the run ends with the guard's status and reason.
    """
    cls = algorithm(algorithm_name)
    needs_compiler(cls, engine)  # the engine named, and a C compiler for its loop, before anything runs
    variable = cls.variable_step
    multirate = {s.name: int(r) for s, r in zip(system.slaves, rates or ()) if r != 1}
    if multirate and not cls.multirate:
        raise UserError(f"master algorithm {cls.name} does not step slaves at several rates "
                        f"({', '.join(f'{n}.rate = {r}' for n, r in multirate.items())}); use jacobi or gauss_seidel")
    if cls.needs_rollback:
        fixed = [s.name for s in system.slaves if not s.can_rollback]
        if fixed:
            why = "; ".join(f"{s.name}: {s.description.rollback_reason}" for s in system.slaves
                            if s.name in fixed and s.description.rollback_reason)
            raise UserError(f"master algorithm {cls.name} needs rollback (get/set state) but {', '.join(fixed)} "
                            f"cannot roll back ({why or 'canGetAndSetFMUstate=false, e.g. hardware'}); use ecco (step "
                            f"control from power bonds, no rollback) or a fixed-step algorithm such as gauss_seidel "
                            f"or jacobi")
    for i, s_ in enumerate(system.slaves):  # FMI noSetFMUStatePriorToCurrentPoint: true unless the algorithm may restore states
        s_.forward_only = not cls.needs_rollback
        # FMI 3.0 event mode and early return where the FMU has them and the algorithm ends steps at events
        # (on the engine asked for: every compiled loop of such an algorithm ends its steps at events too)
        # (a variable-step master cuts its step at an event by rolling every slave back: all must roll back)
        # (a multirate component's sub-steps run on the macro step's own sub-instants and cannot end at an
        # event: in a scene with one, every component keeps its events inside doStep)
        s_.event_mode = bool(ends_steps_at_events(cls, engine) and (inputs == "hold" or variable)
                             and getattr(s_, "fmi3", False)
                             and s_.description.has_event_mode and not (rates and any(r != 1 for r in rates))
                             and not (variable and not all(x.can_rollback for x in system.slaves)))
    if any(s_.event_mode for s_ in system.slaves) and (len(system.slaves) > 1 or variable):
        for s_ in system.slaves:  # an early return rolls the others back to the event time
            if s_.can_rollback:
                s_.forward_only = False
    if realtime is not None and not cls.paceable:  # refuse rather than run unpaced
        raise UserError(f"master algorithm {cls.name} chooses its own steps and cannot be paced in real time "
                        f"(it rolls rejected steps back); drop master.realtime or use ecco, gauss_seidel or jacobi")
    if record_every < 1:
        raise UserError(f"record_every must be >= 1, got {record_every}")
    if record not in ("grid", "steps"):
        raise UserError(f"record must be grid or steps, got {record!r}")
    stats = (VariableStats if variable else RunStats)(cls.name, "", step_ns / 1e9, n_steps)
    columns = ["time"] + system.record_names
    extra = {"options": option_values(options, cls.options)} if variable else {}
    for obs in observers:
        obs.start(columns, dict(meta or {}, algorithm=cls.name, step=step_ns / 1e9,
                                **({"rates": multirate} if multirate else {}), **extra))
    stepper, pacer = None, None

    def fill() -> None:
        if guard is not None:
            stats.guards = guard.summary()
        if stepper is not None:
            if stats.wall_s == 0.0 and stepper.t_loop is not None:  # the loop was cut short
                stats.wall_s = time.perf_counter() - stepper.t_loop
            stepper.fill(stats)
            stats.extra = with_events(system, cls, stats.extra)
            stepper.close()  # before the slaves are freed (a compiled stepper's FMU states)
        for obs in observers:  # an observer's own figures (e.g. an error estimate) go into the statistics
            figures = obs.statistics()
            if figures is not None:
                stats.extra[obs.name] = figures
        if pacer is not None:

            stats.realtime = pacer.finish()
            if figures := slave_figures(system):  # e.g. the board daemon's own tick jitter and CPU
                stats.realtime["slaves"] = figures

    with settled(stats, system, observers, lambda: stepper.t if stepper else None, fill) as end:
        if realtime is not None:  # before initialisation: the pacer quiets the heap first

            pacer = Pacer(step_ns, n_steps, realtime)
        t0 = time.perf_counter()
        initialize(system, start_values or [{} for _ in system.slaves], start_time=start_ns / 1e9,
                   stop_time=(start_ns + n_steps * step_ns) / 1e9, tolerances=tolerances,
                   allow_loops=cls.solves_algebraic_loops or cls.delays_algebraic_loops)
        make = cls.stepper_for or fixed_stepper  # variable-step algorithms bring their own
        stepper = make(system, step_ns=step_ns, n_steps=n_steps, record_every=record_every, order=order,
                    cls=cls, timing=timing, inputs=inputs, start_ns=start_ns, rates=rates, options=options, engine=engine,
                    record=record)
        stats.engine = stepper.engine
        stats.init_s = time.perf_counter() - t0
        record_start(stepper, system, observers, guard, len(columns))
        stats.wall_s = drive(stepper, system, observers, n_columns=len(columns), guard=guard, pacer=pacer,
                             progress=progress, stop=stop, start_ns=start_ns)
        end.from_loop(stepper)
    return stats


def with_events(system: CoupledSystem, cls, extra: dict) -> dict:
    """The run statistics ``extra`` with what algorithm ``cls`` does with events (``events.mode``,
    said for every algorithm when a component may have events) and each model-exchange
    component's solver figures and events (``model_exchange``) where the stepper gave none."""
    out = dict(extra or {})
    if any(s.description.has_events for s in system.slaves):
        out["events"] = {"mode": cls.event_policy, **(out.get("events") or {})}
    me = {s.name: {**s.solver_stats(), "events": [[t, kind] for t, kind in s.events()[:1000]]}
          for s in system.slaves if hasattr(s, "solver_stats")}
    if me:
        out["model_exchange"] = {**me, **(out.get("model_exchange") or {})}
    return out
