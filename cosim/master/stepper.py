"""The one driver loop of every run (:func:`drive`) and the stepper protocol it drives.

After libcosim's shape: an algorithm's step returns the step it actually took, or a failure
status; the loop runs what comes before a step, the step, then the observers.  A *stepper*
(:class:`Stepper`) is an algorithm bound to its engine: a fixed-step algorithm on the grid
``t_k = start + k h`` (:class:`FixedStepper`: Jacobi, Gauss-Seidel, iterative; the compiled loop
runs a block of steps natively and returns its rows, a block counts as steps taken), or a
variable-step one (:class:`cosim.master.algorithms.adaptive.VariableStepper`: adaptive, ecco).

Per block of steps :func:`drive` does, once for every algorithm:

1. before: a stop request (``stop()``) and real-time pacing of the block's first step on the
   wall clock (:mod:`cosim.master.realtime`; paced and observed runs go one step per block);
2. the block: ``stepper.block(rec, n)`` takes up to ``n`` steps and writes the recorded rows
   (time, the recorded values, then the guards' watched values) into ``rec``;
3. after, the observers: the guard first (it may cut the rows after the first offending one and
   end the run with its status), step observers (:class:`StepInfo`), the traces' ``record``,
   text events (String/Binary changes), progress.

Step observers: an observer with a method ``step(info)`` sees every step (blocks of one step
then); a non-empty string it returns ends the run as "failed" with that reason.  A method
``initial(info)`` sees the values at the start time, once, after initialisation.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from .system import CoupledSystem

if TYPE_CHECKING:
    from .algorithm import Algorithm


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


class Stepper(Protocol):
    """What :func:`drive` steps (see the module docstring)."""

    status: str
    message: str
    text_events: list[tuple[float, str, str]]

    @property
    def t_ns(self) -> int: ...  # the current communication point [ns]

    def block(self, rec: np.ndarray, max_steps: int) -> int: ...

    def rows_needed(self, max_steps: int) -> int: ...

    def cut(self, t: float, rows_dropped: int) -> None: ...

    def end(self, status: str, message: str) -> None: ...

    def progress(self) -> tuple[int, int]: ...

    def step_info(self, t0_ns: int) -> StepInfo: ...

    def done(self) -> bool: ...


class FixedStepper:
    """A fixed-step :class:`~cosim.master.algorithm.Algorithm` on its engine: ``runner(n,
    record_every, rec) -> rows`` (:class:`cosim.master.engine._Compiled` or
    :func:`cosim.master.engine._python_run`), ``n_steps`` macro steps, every ``record_every``-th
    point recorded."""

    def __init__(self, alg: "Algorithm", runner: Callable[[int, int, np.ndarray], int], engine: str, n_steps: int,
                 record_every: int):
        self.alg, self.runner, self.engine = alg, runner, engine
        self.n_steps, self.record_every = n_steps, record_every
        self.system = alg.system
        self.stepping_s = 0.0  # wall time inside blocks (the Python engine's master time is this minus the slaves')

    @property
    def status(self) -> str:
        return self.alg.status

    @property
    def message(self) -> str:
        return self.alg.message

    @property
    def text_events(self) -> list:
        return self.alg.text_events

    @property
    def t_ns(self) -> int:
        return self.alg.start_ns + self.alg.k * self.alg.step_ns

    @property
    def t(self) -> float:
        return self.alg.t

    def done(self) -> bool:
        return self.alg.k >= self.n_steps or self.alg.status != "running"

    def rows_needed(self, max_steps: int) -> int:
        return max_steps // self.record_every + 1

    def block(self, rec: np.ndarray, max_steps: int) -> int:
        return self.runner(min(max_steps, self.n_steps - self.alg.k), self.record_every, rec)

    def cut(self, t: float, rows_dropped: int) -> None:
        self.alg.k = round((t * 1e9 - self.alg.start_ns) / self.alg.step_ns)

    def end(self, status: str, message: str) -> None:
        self.alg.status, self.alg.message = status, message

    def progress(self) -> tuple[int, int]:
        return self.alg.k, self.n_steps

    def step_info(self, t0_ns: int) -> StepInfo:
        alg = self.alg
        slopes = alg.slopes if any(alg.interpolating) else None
        return StepInfo(t0_ns / 1e9, (self.t_ns - t0_ns) / 1e9, self.system.v, slopes, self.system, alg.k)

    def fill(self, stats) -> None:
        """The run statistics of the steps taken (:class:`cosim.master.lifecycle.RunStats`)."""
        from .lifecycle import slave_table

        alg = self.alg
        if self.engine == "python":  # the compiled loop measures its own share itself
            alg.master_ns = max(0, int(self.stepping_s * 1e9) - sum(alg.slave_ns))
        stats.steps_done = alg.k
        stats.master_s = alg.master_ns / 1e9
        stats.slaves = slave_table(self.system, alg.calls, alg.slave_ns, alg.rates)
        stats.extra = alg.statistics() if hasattr(alg, "statistics") else {}

    def close(self) -> None:
        """Nothing to free (the compiled fixed-step loop keeps no FMU state)."""


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


def record_start(stepper: Stepper, system: CoupledSystem, observers: Sequence, guard, n_columns: int) -> None:
    """The row at the start time (guarded, recorded) and the text values there; a step observer
    with a method ``initial(info)`` sees the initialised values (``h`` = 0, ``k`` = 0)."""
    for obs in observers:
        if hasattr(obs, "initial"):
            obs.initial(stepper.step_info(stepper.t_ns))
    row0 = np.concatenate([[stepper.t_ns / 1e9], system.v[system.record_idx]])[None, :]
    row0 = guarded(guard, stepper, row0)
    for obs in observers:
        obs.record(row0[:, :n_columns])
    for c, x in system.typed.text_changes() if system.typed.texts else ():
        for obs in observers:
            if hasattr(obs, "record_text"):
                obs.record_text(stepper.t_ns / 1e9, c, x)


def drive(stepper: Stepper, system: CoupledSystem, observers: Sequence, *, n_columns: int, guard=None,
          pacer=None, progress: Callable[[int, int], None] | None = None,
          stop: Callable[[], str | None] | None = None, start_ns: int = 0) -> float:
    """Run ``stepper`` to its end (module docstring); returns the loop's wall time [s].
    ``n_columns``: the recorded columns (time first) observers get; the rows carry the guard's
    watched values after them.  ``pacer`` (:class:`cosim.master.realtime.Pacer`) paces each step's
    start at ``t - start_ns`` on the wall clock; ``stop()`` returning a reason ends the run as
    "stopped" before the next block."""
    watchers = [obs for obs in observers if hasattr(obs, "step")]
    texters = [obs for obs in observers if hasattr(obs, "record_text")]
    single = pacer is not None or bool(watchers)
    chunk = 1 if single else 64
    width = 1 + len(system.record_idx)
    rec = np.empty((stepper.rows_needed(chunk), width))
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
        need = stepper.rows_needed(chunk)
        if rec.shape[0] < need:
            rec = np.empty((need, width))
        tc = time.perf_counter()
        rows = stepper.block(rec, chunk)
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
            for obs in texters:
                for ev in events:
                    obs.record_text(*ev)
            events.clear()
        if progress:
            progress(*stepper.progress())
        if dt < 0.05 and chunk < 1 << 20 and not single:  # aim at ~0.1 s per block: responsive to Ctrl-C
            chunk *= 2
    return time.perf_counter() - t_loop


__all__ = ["FixedStepper", "StepInfo", "Stepper", "drive", "guarded", "record_start"]
