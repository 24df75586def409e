"""The compiled engines of the variable-step masters ``adaptive`` and ``ecco``: their step loops in C.

The same steps as :class:`cosim.master.algorithms.adaptive.AdaptiveStepper` (the Python loop stays the reference
implementation; ``tests/test_adaptive_engine.py`` checks that both take the same steps and produce the
same values, bit for bit): save every slave's FMU state (``fmi2GetFMUstate`` into one state per
slave, allocated by the first call and reused), a Gauss-Seidel step with linear inputs, the
coupling error estimate, the PI controller, and on a rejected step ``fmi2SetFMUstate`` and a retry.
Every operation is done in the same order and precision as the Python loop (no fused
multiply-add: ``-std=c99`` keeps ``-ffp-contract=off``; ``nearbyint`` rounds half to even like
Python's ``round``), which is what makes the two agree exactly.

One call runs until it has taken ``max_steps`` accepted steps (recording those that land on an
output point, the same rows as the Python loop), spent its wall-time budget (so that Python
handles signals between calls), reached the stop time, or met something it leaves to Python: a
stop request, the step floor, a failing get/set of an FMU state, or an event.  With FMI 3.0
event-mode components a step is cut at the earliest early return (every slave rolled back and the
step retaken to the event, counted as a cut), and a call returns after an accepted step at whose
end a component asks for event handling: the event iteration runs in Python
(:class:`cosim.master.algorithm.EventIteration`), which moves the inputs' history by the jump
(:meth:`AdaptiveStepper.after_events` on the same arrays the loop reads).

``ecco`` (:class:`CompiledEcco`, the loop of :class:`cosim.master.algorithms.ecco.EccoStepper`)
takes the same Gauss-Seidel step with linear inputs, never rolled back, and sizes the next step
from the bonds' energy residual, with the same per-bond statistics and endings.

Timing (per-slave wall time in the run statistics) reads the clock once per slave, as the
fixed-step loop does: a slave's time includes preparing its inputs; the master's own time is the
rest (saving and restoring states, the estimate, the controller, recording).
"""
from __future__ import annotations

import ctypes
import math
from functools import lru_cache

import numpy as np

from .entries import ADAPT_RUN, ADAPTIVE_CONTROL, ECCO_CONTROL, ECCO_RUN, AdaptiveEnd, EccoEnd, struct
from .kernels import SlaveArray, compile_loop

CControl = struct(ADAPTIVE_CONTROL)
CEccoControl = struct(ECCO_CONTROL)


#: Longest wall time of one call [ns]: it returns to Python (signals, progress) at least this often.
CALL_BUDGET_NS = 100_000_000


@lru_cache(maxsize=1)
def library() -> ctypes.CDLL:
    """Compile (once, cached on disk: :func:`cosim.master.kernels.compile_loop`) and load the engine."""
    return compile_loop("adaptive_engine.c", "rpr_adapt", [ADAPT_RUN, ECCO_RUN])


class _CompiledVariable:
    """What the compiled adaptive and ecco loops share: the slaves' structs with the stepper's
    input history (fresh inputs, slopes, the sources' last two values), the recorded columns and
    the per-slave counters."""

    def __init__(self, stepper, states: bool):
        self.py = stepper  # the Python stepper: its setup, statistics and messages
        sysm = stepper.system
        self.lib = library()
        self.arr = arr = SlaveArray(sysm, states=states or bool(stepper.event_slaves), callbacks=True)
        for i in stepper.event_slaves:  # FMI 3.0 event mode: the slaves' own step reports (Slave.event_slots)
            arr[i].event_mode = 1
            arr[i].step_flags, arr[i].last_time, arr[i].planned_end = sysm.slaves[i].event_slots()
        for i in range(len(arr)):
            c = arr[i]
            n_in = c.n_in
            interp = bool(stepper.interp[i]) and n_in > 0
            c.interp, c.set_der = int(interp), arr.entries[i].set_input_derivatives if interp else 0
            if n_in:
                c.orders = arr.buffer(np.ones(n_in, dtype=np.int32), np.int32)
                c.fresh = arr.buffer(stepper.fresh[i].astype(np.int8), np.int8)
                # the stepper's own input history: its after_events moves it by an event's jump
                c.cur, c.prev = arr.buffer(stepper.cur_src[i]), arr.buffer(stepper.prev_src[i])
                c.guess, c.slope = arr.buffer(np.zeros(n_in)), arr.buffer(stepper.slopes[i])
        self.order = np.array(stepper.order, dtype=np.int32)
        self.rec_idx = np.ascontiguousarray(sysm.record_idx, dtype=np.int64)  # recorded, then watched (guards)
        self.h_rec = np.empty(0, dtype=np.int64)

    @property
    def t_ns(self) -> int:
        return int(self.ctl.t_ns)

    @property
    def t(self) -> float:
        return self.ctl.t_ns / 1e9

    @property
    def master_ns(self) -> int:
        """The master's own time in the compiled loop [ns] (outside the slaves' calls)."""
        return int(self.ctl.master_ns)

    @property
    def calls(self) -> list[int]:
        return [int(c.calls) for c in self.arr.arr]

    @property
    def slave_ns(self) -> list[int]:
        return [int(c.ns) for c in self.arr.arr]

    def _rows(self, rec: np.ndarray) -> None:
        if len(self.h_rec) < len(rec):
            self.h_rec = np.empty(len(rec), dtype=np.int64)

    def _events_in(self) -> None:
        """Before a call: the count of events in a row, kept by the Python stepper."""
        self.ctl.n_event = len(self.py.event_slaves)
        self.ctl.events_here = self.py._events_here

    def _returned(self, rec: np.ndarray, rows: int, code: int, event: int, no_progress: int) -> int:
        """After a call that returned with end code ``code``: the Python stepper at the same point
        (time, events in a row); at ``event`` its :meth:`_note_event` counts the event and makes
        it pending (its row, the left limit, added when the step did not land on an output point),
        at ``no_progress`` its :meth:`_no_progress` ends the run; returns the rows."""
        py, ctl = self.py, self.ctl
        py.t_ns, py._events_here = self.t_ns, int(ctl.events_here)
        if code == event:
            py._note_event()
            if py.pending_event is not None and not py._on_output(py.t_ns):
                rec[rows, 0] = py.t
                np.take(py.system.v, py.system.record_idx, out=rec[rows, 1:])
                rows += 1
        elif code == no_progress:
            py._no_progress(int(ctl.t_e_ns))
        return rows

    def _ended(self, code: int, bad: int, st: int, value: float = math.nan, count: int = 0) -> None:
        """The loop returned with end code ``code``: the Python stepper, at the same point, ends
        the run and words it (its ``_end``, the one wording of each ending)."""
        self.py.t_ns = self.t_ns
        self.py._end(code, bad, st, value, count)

    def close(self) -> None:
        """Free the FMU states (before the instances are freed)."""
        self.arr.free_states()


class CompiledAdaptive(_CompiledVariable):
    """Drop-in for :class:`cosim.master.algorithms.adaptive.AdaptiveStepper` whose accepted-step loop runs in C.
    It shares the stepper's setup (order, fresh inputs, options) and its outcome (status and
    message), and exposes the same ``t_ns``, ``stats``, ``calls`` and ``slave_ns``; :meth:`run` replaces the
    Python loop of :class:`cosim.master.algorithms.adaptive.VariableStepper` one block at a time."""

    def __init__(self, stepper, timing: bool = True):
        super().__init__(stepper, states=True)
        opt = stepper.opt
        self.v_saved = np.empty_like(stepper.system.v)
        self.lo, self.hi = stepper.lo, stepper.hi
        self.ctl = ctl = CControl()
        ctl.t_ns, ctl.stop_ns, ctl.h, ctl.h_prev, ctl.err_prev = (stepper.t_ns, stepper.stop_ns, stepper.h,
                                                                   stepper.h_prev, stepper.err_prev)
        ctl.start_ns, ctl.grid_ns = stepper.start_ns, stepper.grid_ns
        for name in ("rtol", "atol", "h_ref", "h_min", "h_max", "safety", "fac_min", "fac_max"):
            setattr(ctl, name, opt[name])
        ctl.k_i, ctl.k_p = stepper.k_i, stepper.k_p
        ctl.p_lin, ctl.p_hold = stepper.order_p_linear, stepper.order_p_hold
        ctl.any_interp, ctl.timing = int(any(stepper.interp)), int(timing)
        ctl.h_min_taken, ctl.h_max_taken = math.inf, 0.0

    @property
    def stats(self):
        st, c = self.py.stats, self.ctl
        st.accepted, st.rejected, st.rollbacks, st.discards = c.accepted, c.rejected, c.rollbacks, c.discards
        st.h_min_taken, st.h_max_taken, st.event_cuts = c.h_min_taken, c.h_max_taken, c.event_cuts
        return st

    def run(self, rec: np.ndarray) -> int:
        """Up to ``len(rec)`` accepted steps, until the stop time, the call's time budget or the end
        of the run; the rows (time and the recorded values) of those that land on an output point
        written into ``rec``; returns their count."""
        sysm, ctl = self.py.system, self.ctl
        self._rows(rec)
        before = ctl.accepted
        self._events_in()
        rows = int(self.lib.rpr_adapt_run(
            self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, len(sysm.v),
            self.v_saved.ctypes.data, self.lo.ctypes.data, self.hi.ctypes.data, ctypes.byref(ctl),
            self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx), rec.ctypes.data,
            self.h_rec.ctypes.data, len(rec), CALL_BUDGET_NS))
        self.arr.reraise()  # a callback slave's exception, raised here
        self.py.stats.steps.extend((self.h_rec[:ctl.accepted - before] / 1e9).tolist())
        rows = self._returned(rec, rows, ctl.status, AdaptiveEnd.EVENT, AdaptiveEnd.NO_PROGRESS)
        if ctl.status not in (AdaptiveEnd.RUNNING, AdaptiveEnd.EVENT, AdaptiveEnd.NO_PROGRESS):
            self._ended(ctl.status, ctl.bad_slave, ctl.bad_status, ctl.last_err)
        return rows


class CompiledEcco(_CompiledVariable):
    """Drop-in for :class:`cosim.master.algorithms.ecco.EccoStepper` whose stepping runs in C: the
    same steps (never retried), the same bond statistics and endings, bit for bit
    (``tests/test_native.py``); the same interface as :class:`CompiledAdaptive`."""

    def __init__(self, stepper, timing: bool = True):
        super().__init__(stepper, states=False)
        opt, bonds = stepper.opt, stepper.bonds
        nb = len(bonds)
        self.v_saved = np.empty_like(stepper.system.v)
        self.ctl = ctl = CEccoControl()
        ctl.t_ns, ctl.stop_ns, ctl.h, ctl.h_prev, ctl.err_prev = (stepper.t_ns, stepper.stop_ns, stepper.h,
                                                                   stepper.h_prev, stepper.err_prev)
        ctl.start_ns, ctl.grid_ns = stepper.start_ns, stepper.grid_ns
        for name in ("rtol", "atol", "h_min", "h_max", "safety", "fac_min", "fac_max", "k_i", "k_p"):
            setattr(ctl, name, opt[name])
        ctl.timing, ctl.n_bonds, ctl.floor_patience = int(timing), nb, stepper.patience
        ctl.h_min_taken, ctl.h_max_taken = math.inf, 0.0
        buf = self.arr.buffer
        ctl.out_idx = buf(np.array([b.out_idx for b in bonds]).ravel(), np.int64)
        ctl.in_idx = buf(np.array([b.in_idx for b in bonds]).ravel(), np.int64)
        ctl.side = buf(np.array([b.side for b in bonds]).ravel(), np.int32)
        ctl.slot = buf(np.array([b.slot for b in bonds]).ravel(), np.int32)
        ctl.y0, ctl.scaled = buf(np.zeros(2 * nb)), buf(np.zeros(nb))
        self.bond_stats = {k: np.zeros(nb) for k in ("max_scaled", "max_residual", "residual_sum",
                                                     "abs_residual_sum", "energy")}
        self.bond_stats["over"] = np.zeros(nb, dtype=np.int64)
        for k, a in self.bond_stats.items():
            setattr(ctl, k, buf(a, a.dtype))

    @property
    def stats(self):
        st, c = self.py.stats, self.ctl
        st.accepted, st.h_min_taken, st.h_max_taken = c.accepted, c.h_min_taken, c.h_max_taken
        st.event_cuts = c.event_cuts
        for k, b in enumerate(self.py.bonds):
            rec = st.bonds[b.name]
            for name, a in self.bond_stats.items():
                setattr(rec, name, int(a[k]) if name == "over" else float(a[k]))
        return st

    def run(self, rec: np.ndarray) -> int:
        """Steps into ``rec`` as :meth:`CompiledAdaptive.run`."""
        sysm, ctl = self.py.system, self.ctl
        self._rows(rec)
        before = ctl.accepted
        self._events_in()
        rows = int(self.lib.rpr_ecco_run(
            self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, len(sysm.v),
            self.v_saved.ctypes.data, ctypes.byref(ctl),
            self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx), rec.ctypes.data,
            self.h_rec.ctypes.data, len(rec), CALL_BUDGET_NS))
        self.arr.reraise()  # a callback slave's exception, raised here
        self.py.stats.steps.extend((self.h_rec[:ctl.accepted - before] / 1e9).tolist())
        rows = self._returned(rec, rows, ctl.status, EccoEnd.EVENT, EccoEnd.NO_PROGRESS)
        if ctl.status not in (EccoEnd.RUNNING, EccoEnd.EVENT, EccoEnd.NO_PROGRESS):
            self._ended(ctl.status, ctl.bad_slave, ctl.bad_status, ctl.end_scaled, ctl.at_floor)
        return rows


#: The compiled loop of each stepper class, by the ``native_loop`` its class itself declares (a
#: subclass that changes the stepping declares none and runs in Python).
LOOPS = {"adaptive": CompiledAdaptive, "ecco": CompiledEcco}
#: The loops that end their steps at FMI 3.0 events (a step cut at the earliest early return, every
#: slave rolled back and the step retaken to it; the event iteration in Python between calls)
EVENT_LOOPS = frozenset({"adaptive", "ecco"})


def has_compiled(stepper_cls: type) -> bool:
    """Whether ``stepper_cls`` has a compiled loop here."""
    return stepper_cls.__dict__.get("native_loop") in LOOPS


def ends_steps_at_events(stepper_cls: type) -> bool:
    """Whether the compiled loop of ``stepper_cls`` ends its steps at FMI 3.0 events."""
    return has_compiled(stepper_cls) and stepper_cls.__dict__["native_loop"] in EVENT_LOOPS


def compiled_stepper(stepper, timing: bool = True) -> _CompiledVariable:
    """The compiled drop-in of ``stepper`` (:class:`CompiledAdaptive` or :class:`CompiledEcco`)."""
    loop = LOOPS.get(type(stepper).__dict__.get("native_loop"))
    if loop is None:
        raise ValueError(f"no compiled loop runs {type(stepper).__name__}")
    return loop(stepper, timing)
