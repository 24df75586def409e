"""How a run of the master begins and ends: the slaves initialised in dependency order, the run's
statistics (:class:`RunStats`), and the one place that settles a run's status and reason
(:func:`settled`), whatever algorithm or loop stepped it."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

from ..errors import UserError
from ..slaves.slave import FAILING, Slave, Status
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
    realtime: dict | None = None  # lateness statistics of a paced run (cosim.master.realtime)
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


@dataclass
class VariableStats(RunStats):
    """Run statistics of a variable-step run: the simulated time is where the last accepted step
    ended; ``adaptive`` holds accepted/rejected steps, rollbacks and the smallest/largest step."""

    t_end: float = 0.0
    adaptive: dict = field(default_factory=dict)

    @property
    def simulated_s(self) -> float:
        return self.t_end

    def as_dict(self) -> dict:
        return {**super().as_dict(), **self.adaptive}


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
