"""The one driver loop of every run (:func:`drive`) and the contracts it drives: the stepper
(:class:`Stepper`), the outcome it owns (:class:`Outcome`), what a step returns
(:class:`StepResult`); the observers' contract is :class:`cosim.trace.observer.Observer`.

After libcosim's shape: an algorithm's step returns the step it actually took, or a failure
status; the loop runs what comes before a step, the step, then the observers.  A *stepper* is an
algorithm bound to its engine: a fixed-step algorithm on the grid ``t_k = start + k h``
(:class:`FixedStepper`: Jacobi, Gauss-Seidel, iterative; the compiled loop runs a block of steps
natively and returns its rows, a block counts as steps taken), or a variable-step one
(:class:`cosim.master.algorithms.adaptive.VariableStepper`: adaptive, ecco).  Both take their
engine as one seam: a fixed-step stepper a runner (:data:`Runner`: the compiled loop, or an
algorithm's own Python steps, :func:`python_runner`), a variable-step one a loop object.

Per block of steps :func:`drive` does, once for every algorithm:

1. before: a stop request (``stop()``) and real-time pacing of the block's first step on the
   wall clock (:mod:`cosim.master.realtime`; paced and observed runs go one step per block);
2. the block: ``stepper.block(rec, n)`` takes up to ``n`` steps and writes the recorded rows
   (time, the recorded values, then the guards' watched values) into ``rec``;
3. at an event (:attr:`Stepper.event`: the block ended early at an event time, its last row the
   left limit): the event iteration (:meth:`Stepper.event_iteration`), then the right limit, a
   second row at the same time (``docs/explanation/events.md``);
4. after, the observers: the guard first (it may cut the rows after the first offending one and
   end the run with its status), step observers (:class:`StepInfo`), the traces' ``record``,
   text events (String/Binary changes), events, progress.
"""
from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..trace.observer import Observer
from .system import CoupledSystem
from .lifecycle import slave_table


@dataclass
class StepInfo:
    """What a step observer sees after each step: the step from ``t`` [s] of ``h`` [s] actually
    taken, the live value vector ``v`` (outputs at ``t + h``; the input buffers
    ``system.in_buf[i]``, views of ``v``, hold the inputs the slaves were given at ``t``), the
    input slopes [unit/s] per slave over the step (linear inputs; None when every input was
    held), the system (its layout) and the number of steps taken ``k``.  Copy what you keep."""

    t: float
    h: float
    v: np.ndarray
    slopes: list[np.ndarray] | None
    system: CoupledSystem
    k: int


@dataclass(frozen=True)
class StepResult:
    """What a step returns when it did not simply reach its planned end: the time it actually
    reached ``t_ns`` [ns], that an event ended it there (``event``), and the component whose
    event it was (``component``, a slave index; None for a time event of the master's own)."""

    t_ns: int
    event: bool = False
    component: int | None = None
    kind: str = ""  # the indicator's name, or "time event"


class Outcome:
    """How a run stands, kept by one object per run (the algorithm, or the variable-step stepping
    it runs) and written by its engines, Python or compiled, as scipy's ``OdeSolver`` keeps its
    own: :attr:`status` (``"running"``, then ``"failed"``, ``"stopped"``, ``"unstable"`` or a
    guard's status) and :attr:`message` (why it ended)."""

    status: str = "running"
    message: str = ""

    def end(self, status: str, message: str) -> None:
        """End the run with ``status`` and ``message``."""
        self.status, self.message = status, message

    @property
    def running(self) -> bool:
        return self.status == "running"


class Stepper(ABC):
    """What :func:`drive` steps (the module docstring): an algorithm bound to its engine
    (its name: ``"compiled"``, ``"python"`` for an algorithm's own Python loop, or a registered engine's,
    :class:`cosim.master.engine.Engine`).  Its :attr:`status` and :attr:`message` are its
    :class:`Outcome`'s.  The event contract points (:attr:`event`, :meth:`event_iteration`,
    :meth:`next_output_ns`) default to a run without events, every step on its own grid."""

    def __init__(self, system: CoupledSystem, engine: str, outcome: Outcome):
        self.system, self.engine, self.outcome = system, engine, outcome
        #: (t, column, value) of recorded String/Binary changes since the observers last saw them
        self.text_events: list[tuple[float, str, str]] = []
        self.stepping_s = 0.0  # wall time inside blocks (the Python engine's master time is this minus the slaves')
        self.t_loop: float | None = None  # when the driver loop started (perf_counter)
        #: the last block ended early at an event (its last row the left limit), or None
        self.event: StepResult | None = None

    @property
    def status(self) -> str:
        return self.outcome.status

    @property
    def message(self) -> str:
        return self.outcome.message

    def end(self, status: str, message: str) -> None:
        self.outcome.end(status, message)

    @property
    @abstractmethod
    def t_ns(self) -> int:
        """The current communication point [ns]."""

    @property
    def t(self) -> float:
        """The current communication point [s]."""
        return self.t_ns / 1e9

    @abstractmethod
    def done(self) -> bool: ...

    @abstractmethod
    def rows_needed(self, max_steps: int) -> int:
        """Rows :meth:`block` may write for ``max_steps`` steps (one more is kept for an event)."""

    @abstractmethod
    def block(self, rec: np.ndarray, max_steps: int) -> int:
        """Up to ``max_steps`` steps; the recorded rows written into ``rec``; returns their count."""

    @abstractmethod
    def cut(self, t: float, rows_dropped: int) -> None:
        """A guard dropped the last ``rows_dropped`` rows: the run ends at ``t`` [s]."""

    @abstractmethod
    def progress(self) -> tuple[int, int]: ...

    @abstractmethod
    def step_info(self, t0_ns: int) -> StepInfo: ...

    @abstractmethod
    def fill(self, stats) -> None:
        """The run statistics of the steps taken (:class:`cosim.master.lifecycle.RunStats`)."""

    def close(self) -> None:
        """Free what the engine holds before the slaves are freed (nothing by default)."""

    # -- the event contract (docs/explanation/events.md); no component reports events yet ----------
    def event_iteration(self, event: StepResult) -> None:
        """At the event instant ``event.t_ns``, after its left-limit row: enter event mode in every
        component that has one, exchange, update discrete states until none asks for more (at most
        100 rounds), leave event mode.  Nothing by default."""

    def next_output_ns(self, t_ns: int) -> int | None:
        """The output grid: the next point after ``t_ns`` a variable step lands on (or interpolates
        to) for ``output_interval``; None by default (every accepted step is a row)."""
        return None

    def row(self, out: np.ndarray) -> None:
        """The current point as a row: time [s], the recorded values."""
        out[0] = self.t
        np.take(self.system.v, self.system.record_idx, out=out[1:])


#: A fixed-step engine: ``runner(n, record_every, rec) -> rows`` takes up to ``n`` macro steps, writes
#: a row (time, the recorded values) at every ``record_every``-th point, at an event (the left limit,
#: the event left pending on the algorithm) and at a stop, and returns the rows' count.
Runner = Callable[[int, int, np.ndarray], int]


def python_runner(alg: Any) -> Runner:
    """The runner of an algorithm's own Python steps (:meth:`cosim.master.algorithm.Algorithm.step`:
    an algorithm without a kernel; the test oracles')."""
    v, idx = alg.system.v, alg.system.record_idx

    def run(n: int, record_every: int, rec: np.ndarray) -> int:
        rows = 0
        for _ in range(n):
            ok = alg.step()
            event = alg.pending_event is not None
            if (ok and (alg.k % record_every == 0 and alg.t_event is None or event)) or alg.status == "stopped":
                rec[rows, 0] = alg.t
                np.take(v, idx, out=rec[rows, 1:])
                rows += 1
            if not ok or event:
                break
        return rows
    return run


class FixedStepper(Stepper):
    """A fixed-step :class:`~cosim.master.algorithm.Algorithm` on its engine ``engine`` (its name),
    whose :data:`Runner` takes its steps (:class:`cosim.master.engine._Compiled`,
    :class:`cosim.master.iterative_engine.CompiledIterative`, :func:`python_runner`); ``n_steps``
    macro steps, every ``record_every``-th point recorded."""

    def __init__(self, alg: Any,  # a cosim.master.algorithm.Algorithm (which imports this module)
                 runner: Runner, n_steps: int, record_every: int, engine: str = "compiled"):
        super().__init__(alg.system, engine, alg)
        self.alg, self.runner = alg, runner
        self.n_steps, self.record_every = n_steps, record_every

    @property
    def t_ns(self) -> int:
        return self.alg.t_ns

    @property
    def t(self) -> float:
        return self.alg.t

    def done(self) -> bool:
        return self.alg.k >= self.n_steps or self.alg.status != "running"

    def rows_needed(self, max_steps: int) -> int:
        return max_steps // self.record_every + 1

    def block(self, rec: np.ndarray, max_steps: int) -> int:
        n = min(max_steps, self.n_steps - self.alg.k)
        rows = self.runner(n, self.record_every, rec) if not self.system.typed.texts else self._text_block(rec, n)
        self._take_event()
        return rows

    def _take_event(self) -> None:
        """A step that ended at an event (its row the left limit): the event for the driver loop."""
        if self.alg.pending_event is not None:
            self.event, self.alg.pending_event = self.alg.pending_event, None

    def _text_block(self, rec: np.ndarray, n: int) -> int:
        """The runner's ``n`` steps up to one recorded point at a time, the recorded text variables'
        changes noted at each row that ends a call."""
        alg, rows, end = self.alg, 0, self.alg.k + n
        while alg.k < end and alg.status == "running":
            k = alg.k
            got = self.runner(min(end, (k // self.record_every + 1) * self.record_every) - k, self.record_every,
                              rec[rows:])
            if got:
                self.text_events += [(float(rec[rows + got - 1, 0]), c, x)
                                     for c, x in self.system.typed.text_changes()]
            rows += got
            if alg.k == k or alg.pending_event is not None:
                break
        return rows

    def event_iteration(self, event: StepResult) -> None:
        self.alg.event_iteration(event)

    def cut(self, t: float, rows_dropped: int) -> None:
        self.alg.k = round((t * 1e9 - self.alg.start_ns) / self.alg.step_ns)

    def progress(self) -> tuple[int, int]:
        return self.alg.k, self.n_steps

    def step_info(self, t0_ns: int) -> StepInfo:
        alg = self.alg
        slopes = alg.slopes if any(alg.interpolating) else None
        return StepInfo(t0_ns / 1e9, (self.t_ns - t0_ns) / 1e9, self.system.v, slopes, self.system, alg.k)

    def fill(self, stats) -> None:

        alg = self.alg
        if self.engine != "compiled":  # the compiled loops measure their own share themselves
            alg.master_ns = max(0, int(self.stepping_s * 1e9) - sum(alg.slave_ns))
        stats.steps_done = alg.k
        stats.master_s = alg.master_ns / 1e9
        stats.slaves = slave_table(self.system, alg.calls, alg.slave_ns, alg.rates)
        stats.extra = {**alg.statistics(), **alg.event_statistics()}


def guarded(guard, stepper: Stepper, rows: np.ndarray) -> np.ndarray:
    """``rows`` up to the first one ``guard`` trips on (all when it does not trip); a trip ends
    the run with the guard's status and reason at that row's time."""
    if guard is None or guard.tripped:
        return rows
    keep = guard.check(rows)
    if keep is None:
        return rows
    later = f" (afterwards: {stepper.message})" if stepper.status != "running" and stepper.message else ""
    stepper.end(guard.status, guard.reason + later)
    stepper.cut(float(rows[keep - 1, 0]), len(rows) - keep)
    return rows[:keep]


def record_start(stepper: Stepper, system: CoupledSystem, observers: Sequence[Observer], guard,
                 n_columns: int) -> None:
    """The row at the start time (guarded, recorded) and the text values there; every observer's
    ``initial(info)`` sees the initialised values (``h`` = 0, ``k`` = 0)."""
    for obs in observers:
        obs.initial(stepper.step_info(stepper.t_ns))
    row0 = np.concatenate([[stepper.t_ns / 1e9], system.v[system.record_idx]])[None, :]
    row0 = guarded(guard, stepper, row0)
    for obs in observers:
        obs.record(row0[:, :n_columns])
    for c, x in system.typed.text_changes() if system.typed.texts else ():
        for obs in observers:
            obs.record_text(stepper.t_ns / 1e9, c, x)


def drive(stepper: Stepper, system: CoupledSystem, observers: Sequence[Observer], *, n_columns: int, guard=None,
          pacer=None, progress: Callable[[int, int], None] | None = None,
          stop: Callable[[], str | None] | None = None, start_ns: int = 0) -> float:
    """Run ``stepper`` to its end (module docstring); returns the loop's wall time [s].
    ``n_columns``: the recorded columns (time first) observers get; the rows carry the guard's
    watched values after them.  ``pacer`` (:class:`cosim.master.realtime.Pacer`) paces each step's
    start at ``t - start_ns`` on the wall clock; ``stop()`` returning a reason ends the run as
    "stopped" before the next block."""
    watchers = [obs for obs in observers if obs.watches_steps()]
    single = pacer is not None or bool(watchers)
    chunk = 1 if single else 64
    width = 1 + len(system.record_idx)
    rec = np.empty((stepper.rows_needed(chunk) + 1, width))  # one more: an event's right limit
    t_loop = stepper.t_loop = time.perf_counter()
    while not stepper.done():
        if stop is not None:
            why = stop()
            if why:
                stepper.end("stopped", why)
                break
        t0_ns = stepper.t_ns
        if pacer is not None and not pacer.wait_ns(t0_ns - start_ns):
            stepper.end("failed", pacer.reason)
            break
        need = stepper.rows_needed(chunk) + 1
        if rec.shape[0] < need:
            rec = np.empty((need, width))
        tc = time.perf_counter()
        rows = stepper.block(rec, chunk)
        event = stepper.event
        if event is not None:  # the last row is the left limit; the right one after the event iteration
            stepper.event_iteration(event)
            stepper.row(rec[rows])
            rows += 1
        dt = time.perf_counter() - tc
        stepper.stepping_s += dt
        block = guarded(guard, stepper, rec[:rows])
        events = stepper.text_events
        if len(block) < rows and events:  # a guard cut the block: no text after its last row
            events[:] = [ev for ev in events if ev[0] <= block[-1, 0]]
        for obs in watchers:
            why = obs.step(stepper.step_info(t0_ns))
            if why and stepper.status == "running":
                stepper.end("failed", why)
        for obs in observers:
            obs.record(block[:, :n_columns])
        if events:
            for obs in observers:
                for ev in events:
                    obs.record_text(*ev)
            events.clear()
        if event is not None:
            stepper.event = None
            name = system.slaves[event.component].name if event.component is not None else ""
            for obs in observers:
                obs.record_event(event.t_ns / 1e9, name, event.kind or "time event")
        if progress:
            progress(*stepper.progress())
        if dt < 0.05 and chunk < 1 << 20 and not single:  # aim at ~0.1 s per block: responsive to Ctrl-C
            chunk *= 2
    return time.perf_counter() - t_loop


__all__ = ["FixedStepper", "Outcome", "Runner", "StepInfo", "StepResult", "Stepper", "drive", "guarded",
           "python_runner", "record_start"]
