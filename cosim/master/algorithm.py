"""The :class:`Algorithm` base class of master algorithms and their registry: an algorithm is a
module under :mod:`cosim.master.algorithms` with a class decorated by :func:`register`."""
from __future__ import annotations

import difflib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import UserError
from ..slaves.slave import FAILING, Status
from .graph import gauss_seidel_order
from .stepper import Outcome
from .system import CoupledSystem
from .multirate import check_rates, substepper

_ns = time.perf_counter_ns


@dataclass(frozen=True)
class AlgorithmOption:
    """An option an algorithm declares: scene validation, ``--set``, help and metadata use it."""

    name: str
    default: float
    lower: float
    upper: float
    unit: str
    description: str
    integer: bool = False  # a count (e.g. iterations): whole numbers only

    def check(self, value) -> float:
        """The value as a float; ValueError with the bounds when it is not acceptable."""
        kind = "a whole number" if self.integer else "a number"
        if isinstance(value, bool):
            raise ValueError(f"{self.name} must be {kind} [{self.unit or '1'}]")
        try:
            v = float(value)
        except (TypeError, ValueError):  # a list, a mapping, a word
            raise ValueError(f"{self.name} = {value!r} must be {kind} [{self.unit or '1'}]") from None
        if self.integer and not v.is_integer():
            raise ValueError(f"{self.name} = {value!r} must be a whole number (a count, {self.lower:g} to "
                             f"{self.upper:g})")
        if not (math.isfinite(v) and self.lower <= v <= self.upper):
            raise ValueError(f"{self.name} = {value!r} is outside [{self.lower:g}, {self.upper:g}] [{self.unit or '1'}]")
        return v


def option_values(given: dict | None, declared: Sequence[AlgorithmOption]) -> dict[str, float]:
    """Defaults overridden by ``given`` (unknown names and bad values raise ValueError)."""
    known = {o.name: o for o in declared}
    out = {o.name: o.default for o in declared}
    for k, v in (given or {}).items():
        if k not in known:
            close = difflib.get_close_matches(str(k), known, n=1)
            raise ValueError(f"unknown option {k!r}" + (f"; did you mean {close[0]!r}?" if close else "")
                             + f" (options: {', '.join(known)})")
        out[k] = known[k].check(v)
    if "h_min" in out and "h_max" in out and out["h_min"] > out["h_max"]:
        raise ValueError(f"h_min = {out['h_min']:g} s is larger than h_max = {out['h_max']:g} s")
    return out


def _gatherer(system: CoupledSystem, i: int) -> Callable[[], None]:
    """A function copying slave i's connected inputs from their sources into its input buffer
    (plain memoryview copies: a numpy call costs about a microsecond, more than a few items)."""
    src = [int(x) for x in system.in_src[i]]
    if not src:
        return lambda: None
    if system.in_affine[i] is not None:
        return lambda: system.gather(i)
    if len(src) > 8:
        v, idx, buf = system.v, system.in_src[i], system.in_buf[i]
        return lambda: np.take(v, idx, out=buf)
    mv, mb = memoryview(system.v), memoryview(system.in_buf[i])
    pairs = list(enumerate(src))
    if len(src) == 1:
        s0 = src[0]

        def one() -> None:
            mb[0] = mv[s0]
        return one

    def copy() -> None:
        for j, s in pairs:
            mb[j] = mv[s]
    return copy


def late_note(late: dict) -> str:
    """The sidecar's and the summary's note on an event a component received late (an entry of
    :attr:`Algorithm.late_events`)."""
    return (f"{late['component']} had stepped past {late['event_of']}'s event at t = {late['t']:.9g} s and cannot "
            f"roll back: the event reached it at the next communication point, t = {late['reached']:.9g} s")


#: Events in one macro step beyond which a run with event-mode components ends (chattering).
MAX_EVENTS_PER_STEP = 1000


class EventIteration:
    """The event iteration across the coupling at an event time (docs/explanation/events.md), one
    for every algorithm that ends its steps at events: it needs ``system``, ``order``,
    ``event_slaves`` (the slaves in FMI 3.0 event mode), ``_gather``/``_push``/``_pull`` per slave,
    the outcome (``status``, ``message``, ``failed_slave``), the counters ``events`` and
    ``late_events``, ``event_policy`` and ``t`` (the event time [s]); :meth:`bind_events` sets
    those an algorithm does not keep itself."""

    #: what the algorithm does with events, as run --check and the sidecar say it
    event_policy: str = ""

    def bind_events(self, system: CoupledSystem) -> None:
        """The event slaves, counters and per-slave input/output calls of ``system``."""
        self.event_slaves = [i for i, x in enumerate(system.slaves) if x.event_mode]
        self.events, self.late_events, self.failed_slave = 0, [], None
        self._gather = [_gatherer(system, i) for i in range(len(system.slaves))]
        self._push = [x.push for x in system.slaves]
        self._pull = [x.pull for x in system.slaves]

    def event_iteration(self, event) -> None:
        """At the event time: every event-mode slave enters event mode; then rounds of exchange
        (every slave's inputs from the current outputs) and discrete-state updates until none asks
        for more and the outputs no longer change (at most 100 rounds); then step mode again
        (docs/explanation/events.md)."""
        slaves, ev = self.system.slaves, self.event_slaves
        self.events += 1
        for i in ev:
            if self._check_event_call(i, slaves[i].enter_event_mode(), "entering event mode"):
                return
        asking: list[int] = []
        before = self.system.v.copy()
        for _ in range(100):
            for i in self.order:
                self._gather[i]()
                if self._check_event_call(i, self._push[i](), "setting inputs in event mode"):
                    return
            asking = []
            for i in ev:
                st, more, terminate = slaves[i].update_discrete_states()
                if self._check_event_call(i, st, "updating discrete states"):
                    return
                if terminate:  # the values it updated are the run's last (the right limit)
                    for j in range(len(slaves)):
                        self._pull[j]()
                    self.status, self.failed_slave = "stopped", i
                    self.message = f"stopped by {slaves[i].name} at t = {self.t:.9g} s: it asked to terminate the " \
                                   f"simulation in its event iteration"
                    return
                if more:
                    asking.append(i)
            for i in range(len(slaves)):
                if self._check_event_call(i, self._pull[i](), "reading outputs in event mode"):
                    return
            changed = not np.array_equal(self.system.v, before, equal_nan=True)
            if not asking and not changed:  # settled: no update asked for and the exchange at a fixed point
                break
            np.copyto(before, self.system.v)
        else:
            self.status = "event_iteration_failed"
            self.message = (f"the event iteration at t = {self.t:.9g} s did not settle in 100 rounds: "
                            f"{', '.join(slaves[i].name for i in asking)} kept asking for new discrete states")
            return
        for i in ev:
            if self._check_event_call(i, slaves[i].enter_step_mode(), "entering step mode"):
                return

    def _check_event_call(self, i: int, status: int, what: str) -> bool:
        """True (and the run failed, naming slave ``i``, the time and ``what``) for a failing status."""
        if status not in FAILING:
            return False
        sl = self.system.slaves[i]
        self.status, self.failed_slave = "failed", i
        self.message = (f"{sl.name}: {what} at the event at t = {self.t:.9g} s returned {Status(status).name}"
                        + (f": {sl.last_message}" if sl.last_message else ""))
        return True

    def event_statistics(self) -> dict:
        """What the run did with events (for the run statistics): the events handled and the late
        ones; a model-exchange component's solver figures and its own events (``model_exchange``)."""
        me = {x.name: {**x.solver_stats(), "events": [[t, kind] for t, kind in x.events()[:1000]]}
              for x in self.system.slaves if hasattr(x, "solver_stats")}
        out = {"model_exchange": me} if me else {}
        if not self.event_slaves:
            return out
        names = [self.system.slaves[i].name for i in self.event_slaves]
        notes = [late_note(e) for e in self.late_events[:100]]
        return {**out, "events": {"mode": self.event_policy, "event_mode": names, "handled": self.events,
                                  "late": self.late_events[:10_000], **({"notes": notes} if notes else {})}}



class MasterAlgorithm:
    """What the registry and the run (:func:`cosim.master.simulate`) know of every master
    algorithm, fixed or variable step: its name, declared options and abilities.  A fixed-step
    algorithm subclasses :class:`Algorithm` (the run binds it to its engine,
    :func:`cosim.master.engine.fixed_stepper`); a variable-step one (``adaptive``, ``ecco``)
    subclasses this directly and names the function that makes its stepper (``stepper_for``,
    see :mod:`cosim.master.stepper`)."""

    name: ClassVar[str]
    #: the options it declares (:class:`AlgorithmOption`), checked at scene load and by the run
    options: ClassVar[tuple] = ()
    #: it chooses its own steps (every accepted step is recorded)
    variable_step: ClassVar[bool] = False
    #: every slave must save and restore its state (a step may be retried)
    needs_rollback: ClassVar[bool] = False
    #: its steps can be paced on the wall clock (``master.realtime``)
    paceable: ClassVar[bool] = True
    #: a slave may take several doSteps per macro step (:mod:`cosim.master.multirate`)
    multirate: ClassVar[bool] = False
    #: it solves algebraic loops (initialisation allows them)
    solves_algebraic_loops: ClassVar[bool] = False
    #: it runs algebraic loops with a one-step delay (Jacobi: initialisation allows them)
    delays_algebraic_loops: ClassVar[bool] = False
    #: algorithm code of the compiled fixed-step loop implementing the same steps, or None
    native_code: ClassVar[int | None] = None
    #: ends a step at an FMI 3.0 event-mode component's event (early return) for the whole coupling
    #: and runs the event iteration there (docs/explanation/events.md); others leave events inside doStep
    ends_steps_at_events: ClassVar[bool] = False
    #: what the algorithm does with events, as run --check and the sidecar say it
    event_policy: ClassVar[str] = ("events are handled inside each component's steps and reach the others at the next "
                                   "communication point (FMI 3.0 event mode not used)")
    #: a variable-step algorithm's stepper factory (:func:`cosim.master.algorithms.adaptive.variable_stepper`);
    #: None: a fixed-step algorithm, bound by :func:`cosim.master.engine.fixed_stepper`
    stepper_for: ClassVar[Callable | None] = None
    #: a variable-step algorithm's stepping class (None: :class:`cosim.master.algorithms.adaptive.AdaptiveStepper`)
    stepper: ClassVar[type | None] = None


class Algorithm(MasterAlgorithm, EventIteration, Outcome):
    """Base class of fixed-step master algorithms: its state (step count, :attr:`status`,
    counters, events), what every engine shares (the event iteration, the completion of a step
    after a stop request, the endings' wording) and the compiled kernel that takes its steps
    (:attr:`native_code`, see :mod:`cosim.master.fastloop`).  An algorithm without a kernel
    implements :meth:`_step_impl` (and :meth:`_event_step`), its own Python loop, which the public
    :meth:`step` runs.  Numerical failure comes back as a status and :attr:`message`, never
    as an exception; bad arguments raise at once."""

    #: slaves step one after another in :attr:`order` (later ones see earlier ones' new outputs)
    sequential: ClassVar[bool] = False

    def __init__(self, system: CoupledSystem, step_ns: int, *, order: Sequence[int] | None = None,
                 timing: bool = True, inputs: str = "hold", start_ns: int = 0,
                 rates: Sequence[int] | None = None):
        if not (isinstance(step_ns, (int, np.integer)) and step_ns > 0):
            raise UserError(f"the communication step must be a positive whole number of nanoseconds, got {step_ns!r}")
        self.system = system
        self.step_ns = int(step_ns)
        self.h = self.step_ns / 1e9
        self.start_ns = int(start_ns)  # the start time [ns]; the compiled loop runs only from 0
        self.k = 0
        self.failed_slave: int | None = None
        n = len(system.slaves)
        # a sequential algorithm steps FMI 3.0 event-mode slaves as early as the coupling allows: their
        # early return then cuts the later slaves' step, and fewer have stepped past the event
        events_first = [i for i, x in enumerate(system.slaves) if x.event_mode] if self.sequential else ()
        self.order = list(order) if order is not None else gauss_seidel_order(n, system.slave_edges(), events_first)
        if sorted(self.order) != list(range(n)):
            raise UserError(f"master order must list every slave once, got {self.order}")
        self.calls = [0] * n  # doStep calls per slave
        self.slave_ns = [0] * n  # wall time [ns] inside each slave's calls
        self.master_ns = 0  # the master's own time [ns] in the stepping loop
        self.timing = timing
        s = system.slaves
        self._push = [x.push for x in s]
        self._pull = [x.pull for x in s]
        self._do = [x.do_step for x in s]
        self._gather = [_gatherer(system, i) for i in range(n)]
        #: memoryless slaves (``SlaveDescription.memoryless``, e.g. a ``sum`` block) in stepping order, each
        #: after the slaves that feed it: an algorithm that exchanges at t_k evaluates them within the
        #: exchange (:meth:`_exchange`), with no delay of their own, as libcosim evaluates its functions
        self.exchange = [i for i in self.order if s[i].description.memoryless]
        self._setup_inputs(inputs)
        self._setup_rates(rates)
        #: slaves in FMI 3.0 event mode (set by the run for an algorithm that :attr:`ends_steps_at_events`)
        self.event_slaves = [i for i, x in enumerate(s) if x.event_mode]
        self.t_event: float | None = None  # the time [s] of an event that cut the current grid step
        self.pending_event = None  # a cosim.master.stepper.StepResult for the run loop
        self.events = 0  # events handled by the event iteration
        self.late_events: list[dict] = []  # an event a slave that cannot roll back had already stepped past
        self._ahead: set[int] = set()  # slaves at the grid point already while the others finish a cut step
        self._events_in_step = 0  # events in the current macro step (chattering beyond MAX_EVENTS_PER_STEP)

    def _setup_rates(self, rates: Sequence[int] | None) -> None:
        """:attr:`rates`: doSteps per macro step of each slave (:mod:`cosim.master.multirate`)."""

        self.rates = check_rates(rates, self.step_ns, self.system.names)
        if any(r > 1 for r in self.rates) and not self.multirate:
            raise UserError(f"master algorithm {self.name} does not step slaves at several rates; "
                            f"use jacobi or gauss_seidel, or remove the components' rate")
        for i, r in enumerate(self.rates):
            if r > 1:
                self._do[i] = substepper(self, i)

    def _setup_inputs(self, inputs: str) -> None:
        """Per slave: whether it gets input slopes (:attr:`interpolating`), the slope buffer, the
        inputs' previous source values (:attr:`hist`, from ``system.v`` at the current point) and
        which inputs are interpolated rather than extrapolated (:attr:`fresh`)."""
        if inputs not in ("hold", "linear"):
            raise UserError(f"inputs must be 'hold' or 'linear', got {inputs!r}")
        sysm, n = self.system, len(self.system.slaves)
        self.inputs = inputs
        self.slopes = [np.zeros(len(b)) for b in sysm.in_buf]
        self.hist = [sysm.source_values(i) for i in range(len(sysm.in_src))]
        self.fresh = [np.zeros(len(b), dtype=bool) for b in sysm.in_buf]
        self.interpolating = [False] * n
        if inputs == "hold":
            return
        pos = {s: k for k, s in enumerate(self.order)}
        for i, slave in enumerate(sysm.slaves):
            if not slave.bind_slopes(self.slopes[i]):
                continue
            self.interpolating[i] = True
            if self.sequential:
                self.fresh[i][:] = [pos[ln.src] < pos[i] for ln in sysm.links if ln.dst == i]
            self._push[i] = self._linear_push(i)

    def _linear_push(self, i: int) -> Callable[[], int]:
        """Slave i's push with slopes (after its gather; see :mod:`cosim.master`)."""
        buf, hist, slope, fresh = self.system.in_buf[i], self.hist[i], self.slopes[i], self.fresh[i]
        tmp, inv_h = np.empty_like(buf), 1.0 / self.h
        slave = self.system.slaves[i]
        push, push_slopes = slave.push, slave.push_slopes

        def push_linear() -> int:
            np.subtract(buf, hist, out=slope)
            np.multiply(slope, inv_h, out=slope)
            np.copyto(tmp, buf)
            np.copyto(buf, hist, where=fresh)
            np.copyto(hist, tmp)
            st = push()
            return st if st in FAILING else push_slopes()
        return push_linear

    @property
    def t(self) -> float:
        """Current communication point [s]: ``(start_ns + k * step_ns) / 1e9``, or the time of the
        event that cut the step to it."""
        return self.time_at(self.k) if self.t_event is None else self.t_event

    @property
    def t_ns(self) -> int:
        """Current communication point [ns] (an event's time rounded to the nanosecond)."""
        return self.start_ns + self.k * self.step_ns if self.t_event is None else round(self.t_event * 1e9)

    def time_at(self, k: int) -> float:
        """Communication point ``k`` [s]."""
        return (self.start_ns + k * self.step_ns) / 1e9

    def step(self) -> bool:
        """One macro step ``t_k -> t_k+1`` of an algorithm's own Python loop (:meth:`_step_impl`,
        :meth:`_event_step`; :func:`cosim.master.stepper.python_runner` runs it); False (with
        :attr:`status`, :attr:`message`) when the run ends: a failure, a stop request (then the
        step is completed first, see :meth:`complete_after_stop`), or a status the step itself set
        (e.g. ``"unstable"``: an iteration that did not converge)."""
        if self.status != "running":
            raise RuntimeError(f"{self.name}: cannot step a run that is {self.status}")
        if self.event_slaves:
            return self._event_step()
        t = self.time_at(self.k)
        bad = self._step_impl(t, self.h)
        if self.status != "running":
            return False
        if bad is None:
            self.k += 1
            return True
        if self.stop_requested(*bad):
            self.complete_after_stop(bad[0], t)
            return False
        self._fail(bad[0], bad[1], t)
        return False

    def chattering(self, who: int, t_e: float) -> None:
        """End the run: slave ``who`` had more than :data:`MAX_EVENTS_PER_STEP` events in the
        current macro step, the last at ``t_e`` [s] (both engines)."""
        self.status, self.failed_slave = "failed", who
        self.message = (f"{self.system.slaves[who].name}: more than {MAX_EVENTS_PER_STEP} events in the step from "
                        f"t = {self.time_at(self.k):.9g} s (chattering); the last at t = {t_e:.9g} s")

    def late(self, j: int, who: int, t_e: float, reached: float) -> None:
        """Note that slave ``j``, which cannot roll back, had stepped to ``reached`` [s] past slave
        ``who``'s event at ``t_e`` [s] (:attr:`late_events`; both engines)."""
        slaves = self.system.slaves
        self.late_events.append({"component": slaves[j].name, "t": t_e, "event_of": slaves[who].name,
                                 "reached": reached})

    def stop_requested(self, i: int, status: int) -> bool:
        """Is ``status`` from slave ``i`` a request to end the simulation (FMI 3.0
        terminateSimulation, FMI 2.0 Discard with fmi2Terminated)?"""
        return status == Status.STOP_REQUESTED or (
            status == Status.DISCARD and self.system.slaves[i].asked_to_stop())

    def complete_after_stop(self, i: int, t: float) -> None:
        """Slave ``i`` asked to stop in the step from ``t`` (a step without event-mode slaves: an
        event step completes itself and calls :meth:`stopped_by`): the other slaves complete that
        step (so every output belongs to ``t_k+1``), then the run ends as ``stopped`` at ``t_k+1``,
        a point the run loop records."""
        bad = self._finish_step(i, t, self.h)
        if bad is not None and not self.stop_requested(*bad):
            self._fail(bad[0], bad[1], t)
            return
        self.stopped_by(i, t)

    def stopped_by(self, i: int, t: float, at: float | None = None) -> None:
        """Slave ``i`` asked to stop in the step from ``t`` [s] and the others completed that step:
        the run ends as ``stopped`` where the step ended, ``t_k+1`` or, ``at``, the event [s] that
        cut it (every engine; docs/explanation/events.md)."""
        if at is None:
            self.k += 1
        self.t_event = at
        sl = self.system.slaves[i]
        detail = sl.stop_detail()
        self.status, self.failed_slave = "stopped", i
        self.message = (f"stopped by {sl.name} at t = {self.t:.9g} s: it asked to terminate the simulation in the "
                        f"step from t = {t:.9g} s" + (f" ({detail})" if detail else "")
                        + (f"; its last message: {sl.last_message}" if sl.last_message else ""))

    def statistics(self) -> dict:
        """The algorithm's own figures for the run statistics (none by default)."""
        return {}

    def _finish_step(self, i: int, t: float, h: float) -> tuple[int, int] | None:
        """Complete the step from ``t`` after slave ``i`` stepped and asked to stop; returns
        ``(slave, status)`` of a failing call, or None."""
        raise NotImplementedError(f"{self.name} cannot complete a step after a stop request")

    def _step_impl(self, t: float, h: float) -> tuple[int, int] | None:
        """An algorithm with a Python loop of its own (one registered without a kernel; the test
        oracles): advance every slave from ``t`` by ``h``; return ``(slave index,
        status)`` of the first failing call, or None."""
        raise NotImplementedError(f"{self.name} steps in its compiled loop (cosim.master.engine)")

    def _event_step(self) -> bool:
        """:meth:`step` with FMI 3.0 event-mode slaves, in an algorithm's own Python loop (see
        :meth:`_step_impl`): to the next grid point or the earliest event."""
        raise NotImplementedError(f"{self.name} steps in its compiled loop (cosim.master.engine)")

    def _fail(self, i: int, status: int, t: float) -> None:
        sl = self.system.slaves[i]
        self.failed_slave = i
        if status == Status.STOP_REQUESTED:
            self.status = "stopped"
            self.message = f"{sl.name} asked to terminate the simulation at t = {t:.9g} s (step {self.k})"
        else:
            self.status = "failed"
            name = Status(status).name if status in Status._value2member_map_ else str(status)
            self.message = (f"{sl.name} returned {name} in the step from t = {t:.9g} s (step {self.k})"
                            + (f": {sl.last_message}" if sl.last_message else ""))

    # helpers for subclasses: one slave's part of a step, timed ----------------------------------------
    def _io(self, i: int, fn: Callable[[], int]) -> int:
        t0 = _ns()
        st = fn()
        self.slave_ns[i] += _ns() - t0
        return st

    def _exchange(self) -> tuple[int, int] | None:
        """Evaluate the memoryless slaves (:attr:`exchange`) on the outputs just read: each takes its
        inputs now (held: no slope) and gives its outputs at once.  Returns ``(slave, status)`` of a
        failing call, or None."""
        for i in self.exchange:
            self._gather[i]()
            sl = self.system.slaves[i]
            st = self._io(i, sl.push)
            if st not in FAILING:
                st = self._io(i, sl.pull)
            if st in FAILING:
                return i, st
        return None

    def _advance(self, i: int, t: float, h: float) -> int:
        t0 = _ns()
        st = self._do[i](t, h)
        self.slave_ns[i] += _ns() - t0
        self.calls[i] += 1
        return st


ALGORITHMS: dict[str, type[MasterAlgorithm]] = {}


def register(cls: type[MasterAlgorithm]) -> type[MasterAlgorithm]:
    """Class decorator: make an algorithm available by its ``name``.  A fixed-step algorithm
    without a kernel (:attr:`Algorithm.native_code` None) must step in Python: a class that does
    not define :meth:`Algorithm._step_impl` is a :class:`TypeError` here, not at its first step."""
    if issubclass(cls, Algorithm) and cls.native_code is None and cls._step_impl is Algorithm._step_impl:
        raise TypeError(f"master algorithm {cls.name!r} ({cls.__qualname__}) has no compiled loop "
                        f"(native_code None) and no _step_impl: define _step_impl(t, h), its Python step")
    ALGORITHMS[cls.name] = cls
    return cls


def algorithm(name: str) -> type[MasterAlgorithm]:
    """The algorithm class called ``name``; :class:`UserError` with the closest names otherwise."""
    try:
        return ALGORITHMS[name]
    except KeyError:
        close = difflib.get_close_matches(str(name), ALGORITHMS, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise UserError(f"unknown master algorithm {name!r}{hint} (known: {', '.join(sorted(ALGORITHMS))})") from None
