"""Error-controlled macro steps with rollback: ``master.algorithm: adaptive``.

Each macro step ``t -> t + h`` is a Gauss-Seidel step with linear inputs (interpolated from
sources that already stepped, extrapolated from the others; inputs of slaves that cannot
interpolate are held).  Before it, every slave's state is saved (FMI ``get FMU state``).

Error estimate (from the coupling itself, no extra steps): an extrapolated input was a guess of
its source's output at ``t + h``; once the source has stepped, the guess is compared with the
value it actually produced.  The scaled error of the step is
``err = max_c |y_c(t+h) - guess_c| * (h / h_ref) / (atol + rtol * range_c)`` over the extrapolated
connections ``c``, where ``range_c`` is the range (max - min) the signal has covered so far: the
tolerance is relative to how much a signal moves, the measure users compare traces by
(``rpr-cosim compare``).  The factor ``h / h_ref`` weighs the mismatch by the step it acts over:
what a receiving slave integrates is the impulse ``|y - guess| * h``, so a mismatch over a step of
``h_ref`` counts in full and one over a microsecond step a thousandth as much.  Without it the first
milliseconds, where the motors' currents move on a 0.44 ms time constant and the range covered so
far is still small, took half of all steps at microsecond size without making the run more
accurate.  The guess of a linear extrapolation is off by ``O(h^2)``, of a held input by ``O(h)``;
with the weight the controller's order ``p`` is 3 and 2.

A step with ``err <= 1`` is accepted; otherwise, or when a slave returns Discard (e.g. its own
integrator diverged), every slave is restored and the step retried smaller.  The next step follows
a PI controller (Gustafsson): ``h_new = h * clip(safety * err^(-kI/p) * err_prev^(kP/p), fac_min,
fac_max)``, within ``[h_min, h_max]``, landing exactly on the stop time.  Time is counted in whole
nanoseconds.  A step below ``h_min`` that still fails ends the run as "unstable" with the reason.

The first step (``h_init``, default 0.1 us) has no error estimate: there is no input history to
extrapolate from yet; the controller then grows the step by at most ``fac_max`` per step.

Output grid: the steps land on every output point ``start + k output_interval`` (a proposal that
reaches the next point is cut to it, one that does not is evened out over the way there, so that no
sliver of a step is left before a point; a step cut to a point does not shrink the next proposal, as
at the stop time), and the trace has a row there, the same instants as a fixed-step run's and as the
companion's that estimates the error: values the coupling computed, not interpolated.
``master.record: steps`` records every accepted step instead (no landing: an irregular time column).

Events (FMI 3.0 event mode and early return, docs/explanation/events.md): an event is a step
boundary.  When an event-mode slave returns early at ``t_e`` inside a step, every slave is rolled
back and the step retaken to ``t_e`` (counted as a cut, not a rejection; the controller keeps its
proposal); the trace records the left limit, the event iteration runs across the coupling, then the
right limit, and the inputs' extrapolation history is moved by the jump.

Statistics: accepted and rejected steps, rollbacks, smallest and largest step, steps cut at events.

Engine: the steps are taken in C (``rpr_adapt_run`` in ``cosim/master/adaptive_engine.c``, bound
by :mod:`cosim.master.adaptive_engine`: FMUs directly, Python slaves and typed ports through
callbacks, transformed connections, FMI 3.0 events with the event iteration and
:meth:`AdaptiveStepper.after_events` in Python between its calls); :class:`AdaptiveStepper` here
holds the run's state, the endings' wording and the event handling both share.  Its Python twin,
the test oracle the bit-for-bit tests compare the kernel with, is ``tests/oracles/variable.py``
(``tests/test_adaptive_engine.py``, ``tests/test_general_kernel.py``,
``tests/test_variable_event_kernel.py``; likewise for ecco, ``tests/test_native.py``).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ...errors import UserError
from ...slaves.slave import Status
from ..algorithm import MAX_EVENTS_PER_STEP, AlgorithmOption, EventIteration, MasterAlgorithm, option_values, register
from ..graph import gauss_seidel_order
from ..adaptive_engine import compiled_stepper
from ..engine import REGISTERED, choose_engine, variable_loop
from ..entries import AdaptiveEnd
from ..lifecycle import slave_table
from ..stepper import Outcome, StepInfo, StepResult, Stepper


OPTIONS = (
    AlgorithmOption("rtol", 3e-5, 1e-12, 1.0, "1", "coupling error per step, relative to the range the signal has "
                                               "covered so far"),
    AlgorithmOption("atol", 1e-6, 0.0, math.inf, "signal unit", "absolute tolerance of the coupling error per step"),
    AlgorithmOption("h_ref", 1e-3, 1e-9, math.inf, "s", "step over which a coupling mismatch counts in full; over a "
                                                          "step h it counts h / h_ref (its impulse)"),
    AlgorithmOption("h_init", 1e-7, 1e-9, 1.0, "s", "first macro step (taken without an error estimate: no input "
                                                     "history yet to extrapolate from)"),
    AlgorithmOption("h_min", 1e-9, 1e-9, 1.0, "s", "smallest macro step; below it the run ends as unstable"),
    AlgorithmOption("h_max", 0.05, 1e-9, math.inf, "s", "largest macro step"),
    AlgorithmOption("safety", 0.8, 0.1, 1.0, "1", "safety factor of the step controller"),
    AlgorithmOption("fac_min", 0.2, 0.01, 1.0, "1", "smallest step ratio from one step to the next"),
    AlgorithmOption("fac_max", 4.0, 1.0, 100.0, "1", "largest step ratio from one step to the next"),
)


@dataclass
class AdaptiveStats:
    accepted: int = 0
    rejected: int = 0
    rollbacks: int = 0
    h_min_taken: float = math.inf
    h_max_taken: float = 0.0
    discards: int = 0
    steps: list[float] = field(default_factory=list)  # accepted step sizes [s], in order
    event_cuts: int = 0  # steps retaken to end at an event (not rejections)

    def as_dict(self) -> dict:
        return {"accepted_steps": self.accepted, "rejected_steps": self.rejected, "rollbacks": self.rollbacks,
                "smallest_step": self.h_min_taken if self.accepted else None,
                "largest_step": self.h_max_taken if self.accepted else None, "discards": self.discards,
                **({"steps_cut_at_events": self.event_cuts} if self.event_cuts else {})}


class AdaptiveStepper(EventIteration, Outcome):
    """The stepping of :mod:`cosim.master.algorithms.adaptive` over an initialised, bound ``system``:
    its state (time, input history, ranges, controller, statistics) and :class:`~cosim.master.stepper.Outcome`,
    which its loop (:class:`cosim.master.adaptive_engine.CompiledAdaptive`) writes and words by
    :meth:`_end`.  ``grid_ns``: the output interval [ns] its steps land on
    (from ``start_ns``; 0: none, only the stop time)."""

    order_p_linear, order_p_hold = 3.0, 2.0  # mismatch O(h^2) / O(h), weighted by h
    k_i, k_p = 0.7, 0.4
    #: every slave must save/restore its state (a rejected step is rolled back)
    needs_rollback = True
    #: the compiled loop of exactly this class (:mod:`cosim.master.adaptive_engine`)
    native_loop = "adaptive"

    def __init__(self, system, order: Sequence[int], options: dict[str, float], start_ns: int, stop_ns: int,
                 grid_ns: int = 0):
        self.system = system
        self.order = list(order)
        self.opt = options
        self.stop_ns = stop_ns
        self.t_ns = start_ns
        self.start_ns, self.grid_ns = start_ns, int(grid_ns)
        self.bind_events(system)
        #: the last accepted step ended at an event (a StepResult for the run loop), else None
        self.pending_event: StepResult | None = None
        self._events_here = 0  # events in a row within one output interval (one instant without a grid)
        self._event_window = -1  # that interval's index (the instant [ns] without a grid)
        sysm, n = system, len(system.slaves)
        for s in sysm.slaves if self.needs_rollback else ():
            if not s.can_rollback:
                raise UserError(f"master algorithm adaptive needs rollback (get/set state), but {s.name} cannot roll "
                                f"back; use gauss_seidel or jacobi with a fixed step")
        pos = {s: k for k, s in enumerate(self.order)}
        self.fresh = [np.array([pos[ln.src] < pos[i] for ln in sysm.links if ln.dst == i], dtype=bool)
                      for i in range(n)]
        self.slopes = [np.zeros(len(b)) for b in sysm.in_buf]
        self.interp = [s.bind_slopes(self.slopes[i]) for i, s in enumerate(sysm.slaves)]
        self.prev_src = [sysm.v[src].copy() for src in sysm.in_src]  # source values at the previous point
        self.cur_src = [sysm.v[src].copy() for src in sysm.in_src]  # and at the current one
        self.h_prev = 0.0
        self.lo, self.hi = sysm.v.copy(), sysm.v.copy()  # running range of every value
        self.h = min(max(options["h_init"], options["h_min"]), options["h_max"])
        self.err_prev = 1.0
        self.stats = AdaptiveStats()

    @property
    def t(self) -> float:
        return self.t_ns / 1e9

    def _on_output(self, t_ns: int) -> bool:
        """Is ``t_ns`` an output point (on the grid, or the stop time; every point without a grid)?"""
        return not self.grid_ns or t_ns >= self.stop_ns or (t_ns - self.start_ns) % self.grid_ns == 0

    # -- the output grid (docs/explanation/events.md, "Trace rows") ------------------------------------
    def target_ns(self) -> int:
        """The next output point after the current time [ns]: on the grid ``start + k grid_ns``,
        at most the stop time (the stop time itself without a grid)."""
        if not self.grid_ns:
            return self.stop_ns
        k = (self.t_ns - self.start_ns) // self.grid_ns + 1
        return min(self.start_ns + k * self.grid_ns, self.stop_ns)

    # -- events: a step boundary (docs/explanation/events.md) -------------------------------------------
    def _no_progress(self, at_ns: int) -> bool:
        """An event-mode slave returned early at the step's start: the run ends (False)."""
        who = min(self.event_slaves, key=lambda i: self.system.slaves[i].step_end()[0])
        self.failed_slave = who
        self.end("failed", f"{self.system.slaves[who].name} returned early at t = {at_ns / 1e9:.9g} s, the start of "
                           f"its step, without an event to handle there")
        return False

    def _note_event(self) -> None:
        """After an accepted step: an event-mode slave that asks for event handling at its end makes
        the step's end an event (:attr:`pending_event`, its row the left limit)."""
        asking = [i for i in self.event_slaves if self.system.slaves[i].step_end()[1]]
        if not asking:
            self._events_here = 0
            return
        window = (self.t_ns - self.start_ns) // self.grid_ns if self.grid_ns else self.t_ns
        if window != self._event_window:  # the first event of another output interval: a new count
            self._events_here, self._event_window = 0, window
        self._events_here += 1
        if self._events_here > MAX_EVENTS_PER_STEP:
            self.failed_slave = asking[0]
            span = "within one output interval" if self.grid_ns else "at one instant"
            self.end("failed", f"{self.system.slaves[asking[0]].name}: more than {MAX_EVENTS_PER_STEP} events in a row "
                               f"{span}, at t = {self.t:.9g} s (chattering)")
            return
        self.pending_event = StepResult(self.t_ns, True, asking[0], "event")

    def after_events(self) -> None:
        """After the event iteration: the inputs' history carries the jump (the sources' values at
        the event's left and previous points moved by it, so that the next step's extrapolation
        keeps its slope), and the ranges take in the right limit."""
        sysm = self.system
        for i, src in enumerate(sysm.in_src):
            if len(src):
                jump = sysm.v[src] - self.cur_src[i]
                self.cur_src[i] += jump
                self.prev_src[i] += jump
        np.maximum(self.hi, sysm.v, out=self.hi)
        np.minimum(self.lo, sysm.v, out=self.lo)

    def _end(self, code: int, bad: int = -1, st: int = 0, value: float = math.nan, count: int = 0) -> None:
        """End the run for end code ``code`` (:class:`cosim.master.entries.AdaptiveEnd`), as its
        loop returned it: ``bad`` the slave it concerns (-1: none), ``st`` its
        FMI status, ``value`` the scaled error at the step floor.  A failed FMU state get/set is a
        UserError."""
        s = self.system.slaves[bad] if bad >= 0 else None
        said = f": {s.last_message}" if s is not None and s.last_message else ""
        if code == AdaptiveEnd.STOP_REQUESTED:
            self.end("stopped", f"{s.name} asked to terminate the simulation at t = {self.t:.9g} s")
        elif code == AdaptiveEnd.STEP_FLOOR:
            who = s.name if s is not None else "the coupling error"
            detail = f"{s.name} returned {Status(st).name}{said}" if s is not None else \
                f"scaled coupling error {value:.3g} > 1"
            self.end("unstable", f"the step floor h_min = {self.opt['h_min']:g} s was reached at t = {self.t:.9g} s "
                                 f"({detail}; limited by {who})")
        else:
            what = "getting" if code == AdaptiveEnd.GET_STATE else "setting"
            raise UserError(f"{s.name}: {what} the FMU state failed ({Status(st).name}){said}")

class VariableStepper(Stepper):
    """A variable-step stepping (:class:`AdaptiveStepper` or a subclass) on its loop ``loop`` (the
    compiled one, :class:`cosim.master.adaptive_engine.CompiledAdaptive` / ``CompiledEcco``, or a
    registered engine's with their interface: ``run(rec) -> rows``, ``t_ns``, ``stats``, ``calls``,
    ``slave_ns``, ``master_ns`` (None: not measured), ``close()``) as the driver loop
    (:func:`cosim.master.stepper.drive`) steps it: one recorded row per accepted step, with the
    guards' watched values after the recorded ones.  Its outcome is the stepping's, which the loop
    writes.  Rows: at every output point the steps land on (every accepted step without a grid,
    ``master.record: steps``), and two at each event."""

    def __init__(self, stepping: AdaptiveStepper, loop, engine: str = "compiled"):
        super().__init__(stepping.system, engine, stepping)
        self.py, self.loop = stepping, loop
        self.start_ns, self.stop_ns = stepping.t_ns, stepping.stop_ns
        self.dropped = 0  # accepted steps after the row where a guard ended the run
        self._t_cut: float | None = None  # where a guard ended the run [s]

    @property
    def t_ns(self) -> int:
        return self.loop.t_ns

    def done(self) -> bool:
        return self.loop.t_ns >= self.stop_ns or self.status != "running"

    def rows_needed(self, max_steps: int) -> int:
        return max_steps

    def block(self, rec: np.ndarray, max_steps: int) -> int:
        if not self.system.typed.texts:
            rows = self.loop.run(rec[:max_steps])
            self._take_event()
            return rows
        rows = 0  # recorded text variables: one accepted step per call, their changes noted at each row
        for _ in range(max_steps):
            got = self.loop.run(rec[rows:rows + 1])
            rows += got
            if got:
                self.text_events += [(float(rec[rows - 1, 0]), c, x) for c, x in self.system.typed.text_changes()]
            self._take_event()
            if self.done() or self.event is not None:
                break
        return rows

    def _take_event(self) -> None:
        """A step that ended at an event (its row the left limit): the event for the driver loop."""
        if self.py.pending_event is not None:
            self.event, self.py.pending_event = self.py.pending_event, None

    def next_output_ns(self, t_ns: int) -> int | None:
        return self.py.target_ns() if self.py.grid_ns else None

    def event_iteration(self, event: StepResult) -> None:
        self.py.event_iteration(event)
        if self.py.running:
            self.py.after_events()

    def cut(self, t: float, rows_dropped: int) -> None:
        self._t_cut = t

    def progress(self) -> tuple[int, int]:
        return self.loop.t_ns - self.start_ns, self.stop_ns - self.start_ns

    def step_info(self, t0_ns: int):
        py = self.py
        slopes = py.slopes if any(py.interp) else None
        return StepInfo(t0_ns / 1e9, (self.t_ns - t0_ns) / 1e9, self.system.v, slopes, self.system,
                        self.loop.stats.accepted)

    def fill(self, stats) -> None:
        """The run statistics (:class:`cosim.master.lifecycle.VariableStats`)."""
        st = self.loop
        acc = st.stats
        if self._t_cut is not None:  # a guard dropped the rows after t_cut: the steps after it are not the run's
            ends = self.start_ns + np.cumsum(np.round(np.asarray(acc.steps) * 1e9))
            self.dropped = int(np.sum(ends > round(self._t_cut * 1e9)))
        stats.steps_done = acc.accepted - self.dropped
        stats.t_end = self.t if self._t_cut is None else self._t_cut
        if self.dropped:
            del acc.steps[len(acc.steps) - self.dropped:]
            acc.accepted -= self.dropped
        stats.adaptive = acc.as_dict()
        stats.steps_planned = stats.steps_done  # no plan: the controller chose every step
        stats.slaves = slave_table(self.system, st.calls, st.slave_ns)
        if self.py.event_slaves:
            stats.extra.update(self.py.event_statistics())
        own = st.master_ns  # the compiled loop measures its own share itself
        stats.master_s = own / 1e9 if own is not None else max(0.0, stats.wall_s - sum(st.slave_ns) / 1e9)

    def close(self) -> None:
        self.loop.close()


def variable_stepper(system, *, cls, step_ns: int, n_steps: int, order: Sequence[int] | None = None,
                     options: dict | None = None, start_ns: int = 0, engine: str = "auto", record_every: int = 1,
                     record: str = "grid", **_fixed_step_only) -> VariableStepper:
    """The stepper of the variable-step algorithm ``cls`` (its ``stepper`` class, default
    :class:`AdaptiveStepper`) over the initialised ``system``, to ``start_ns + n_steps * step_ns``
    (the scene's stop time; ``step_ns`` is only the fixed-step master's step), landing on the
    output grid of ``record_every * step_ns`` (``record="steps"``: no grid, every accepted step
    recorded).  ``engine``: see :func:`cosim.master.engine.choose_engine`."""
    stop_ns = start_ns + n_steps * step_ns
    opts = option_values(options, cls.options)
    seq = list(order) if order is not None else gauss_seidel_order(len(system.slaves), system.slave_edges())
    kind = cls.stepper or AdaptiveStepper
    name = choose_engine(system, engine, variable_loop(cls.name, kind))
    other = REGISTERED.get(name)
    stepping = (other.stepping(kind) if other is not None else kind)(
        system, seq, opts, start_ns, stop_ns, step_ns * record_every if record == "grid" else 0)
    stepping.event_policy = cls.event_policy
    return VariableStepper(stepping, other.loop(stepping) if other is not None else compiled_stepper(stepping), name)


@register
class Adaptive(MasterAlgorithm):
    """Registry entry of the error-controlled master (module docstring): its stepper
    (:func:`variable_stepper`) is driven by the one run loop, :func:`cosim.master.simulate`."""

    name = "adaptive"
    variable_step = True
    needs_rollback = True
    ends_steps_at_events = True
    event_policy = ("an event of an FMI 3.0 event-mode component is a step boundary for the whole coupling: the "
                    "step is retaken to the event time (no rejection counted), then the event iteration")
    options = OPTIONS
    stepper = AdaptiveStepper
    #: a rejected step is rolled back and retried: its steps cannot be paced on the wall clock
    paceable = False
    stepper_for = staticmethod(variable_stepper)
