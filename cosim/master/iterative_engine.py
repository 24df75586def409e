"""The compiled engine of ``master.algorithm: iterative``: its macro steps in C.

The steps of :class:`cosim.master.algorithms.iterative.Iterative`, their one implementation (the
Python twin is the test oracle ``tests/oracles/iterative.py``; ``tests/test_native.py`` checks
that both give the same values bit for bit, the same
passes per step, rollbacks, Jacobians and Broyden updates, and the same endings): save every
slave's FMU state, passes over the Gauss-Seidel order with each slave restored and re-stepped
only when its inputs changed, the residual of the cut connections, and the fixed-point or
Newton update (Jacobian by the chain rule from directional derivatives or finite differences,
Broyden's update, the solve of :mod:`cosim.master.dense` in the same order of
operations).  The start-time iteration is the kernel's too (``rpr_iter_start``: the same
iteration without stepping, as :meth:`Iterative.start` does it).

One call runs up to ``nsteps`` macro steps (returning early after its wall-time budget) and
hands back a failure, a stop request (after completing the step, as the Python loop does) or a
step that did not converge, with what the Python side needs to word it alike.  With FMI 3.0
event-mode components each step is the oracle's ``Iterative._event_step`` (``tests/oracles/iterative.py``) in C: the
step cut at the earliest early return, every slave restored and the coupling iterated again to
the event; the call returns there (``FixedEnd.EVENT``, the event state in ``fx_ctl`` as the
Jacobi/Gauss-Seidel kernel keeps it), the one event iteration runs in Python
(:meth:`Iterative.event_iteration`, which resets the iteration's point: :meth:`CompiledIterative.run`
hands it over both ways).
"""
from __future__ import annotations

import ctypes
from ctypes import c_int64
from functools import lru_cache

import numpy as np

from ..errors import UserError
from ..slaves.slave import Status
from .algorithm import MAX_EVENTS_PER_STEP
from .entries import FIXED_CONTROL, ITER_RUN, ITER_START, ITERATIVE_CONTROL, FixedEnd, IterativeEnd, struct
from .kernels import SlaveArray, compile_loop
from .stepper import StepResult
from .algorithms.iterative import FD_REL, GROWTH_LIMIT

CControl = struct(ITERATIVE_CONTROL)

#: Longest wall time of one call [ns]: it returns to Python (signals, progress) at least this often.
CALL_BUDGET_NS = 250_000_000


@lru_cache(maxsize=1)
def library() -> ctypes.CDLL:
    """Compile (once, cached on disk: :func:`cosim.master.kernels.compile_loop`) and load the engine."""
    return compile_loop("iterative_engine.c", "rpr_iter", [ITER_RUN, ITER_START])


class CompiledIterative:
    """Runs :class:`cosim.master.algorithms.iterative.Iterative`'s start-time iteration (at once)
    and macro steps in C, with the shape of :class:`cosim.master.engine._Compiled` (``run(nsteps,
    rec_every, rec) -> rows``), updating the algorithm's step count, status, counters, event state
    and statistics as its own loop would."""

    def __init__(self, alg):
        self.lib = library()
        self.alg = alg
        sysm = alg.system
        m, nv = len(alg.cuts), len(sysm.v)
        # (states: a slave that rolls back only in Python, a model-exchange FMU through its
        # continuous states, is called back around its own save_state/restore_state)
        self.arr = arr = SlaveArray(sysm, callbacks=True, states=True)
        max_in = max([len(b) for b in sysm.in_buf] + [1])
        max_out = max([len(b) for b in sysm.out_buf] + [1])
        max_feed = max([len(f) for f in alg.feeding] + [1])
        #: each slave's inputs at the current point (the C side's; handed over with the algorithm's)
        self.start_in = [np.array(x, dtype=np.float64) for x in alg.start_in]
        for i, s in enumerate(sysm.slaves):
            c, cb = arr[i], arr.callbacks[i]
            # an FMU's own state slot (freed with the instance); a callback slave keeps its state itself
            c.state = arr.state_slot(i) if cb is not None else s.state_slot()
            c.get_state, c.set_state = arr.entries[i].get_state, arr.entries[i].set_state
            if alg.opt["jacobian"] == "auto" and cb is None:
                c.dir_der = arr.entries[i].directional_derivative
            elif alg.opt["jacobian"] == "auto":  # the slave's output_jacobian, by its variables' names
                c.dir_der = cb.directional(dict(zip(sysm.out_vrs[i].tolist(), sysm.reads[i])),
                                           dict(zip(sysm.in_vrs[i].tolist(), sysm.inputs[i])))
            n_in = c.n_in
            if n_in:
                cut = np.full(n_in, -1, dtype=np.int64)
                cut[alg.cut_mask[i]] = alg.cut_index[i]
                c.cut = arr.buffer(cut, np.int64)
                c.start_in = arr.buffer(self.start_in[i])
                c.last_in = arr.buffer(np.zeros(n_in))
            if alg.interpolating[i]:
                c.interp, c.set_der = 1, arr.entries[i].set_input_derivatives
                c.orders = arr.buffer(np.ones(n_in, dtype=np.int32), np.int32)
                c.slope = arr.buffer(alg.slopes[i])
            out_pos = {int(k) - sysm.out_off[i] for _, k in alg.feeding[i]}
            feed = np.array(sorted(out_pos), dtype=np.int32)
            c.n_feed = len(feed)
            c.feed = arr.buffer(feed, np.int32)
        self.ev = self._events(alg)
        self.ctl = ctl = CControl()
        opt = alg.opt
        ctl.m, ctl.max_iter, ctl.newton = m, int(opt["max_iter"]), int(opt["method"] == "newton")
        ctl.jac_auto, ctl.linear = int(opt["jacobian"] == "auto"), int(alg.inputs == "linear")
        ctl.timing = int(alg.timing)
        ctl.omega, ctl.rtol, ctl.atol = opt["omega"], opt["rtol"], opt["atol"]

        ctl.growth, ctl.fd_rel = GROWTH_LIMIT, FD_REL
        ctl.rollbacks, ctl.jacobians, ctl.directional = alg.rollbacks, alg.jacobians, alg.directional
        ctl.broyden, ctl.fd_steps = alg.broyden, alg.fd_steps
        buf = arr.buffer
        self.z, self.z_prev, self.J = np.zeros(m), np.zeros(m), np.zeros((m, m))
        self.e = np.zeros(m)
        self.zi = np.zeros(m)
        ctl.z, ctl.z_prev, ctl.J, ctl.e, ctl.zi = buf(self.z), buf(self.z_prev), buf(self.J), buf(self.e), buf(self.zi)
        for name in ("g", "r", "z_old", "r_old", "dz", "w", "z_kept", "z_prev_kept"):
            setattr(ctl, name, buf(np.zeros(max(m, 1))))
        ctl.A, ctl.J_kept = buf(np.zeros(max(m * m, m, 1))), buf(np.zeros(max(m * m, 1)))
        ctl.v_kept, ctl.start_kept = buf(np.zeros(nv)), buf(np.zeros(max(sum(c.n_in for c in arr.arr), 1)))
        ctl.dv, ctl.dv_has = buf(np.zeros(nv * max(m, 1))), buf(np.zeros(nv, dtype=np.int8), np.int8)
        ctl.du, ctl.L = buf(np.zeros(max_in * max(m, 1))), buf(np.zeros(max_feed * max_in))
        ctl.cols = buf(np.zeros(max_in, dtype=np.int32), np.int32)
        for name, size in (("ends", max_in), ("base_in", max_in), ("base_out", max_feed), ("saved_out", max_out),
                           ("seed", max_in), ("sens", max_feed)):
            setattr(ctl, name, buf(np.zeros(size)))
        ctl.known, ctl.unknown = buf(np.zeros(max_in, dtype=np.uint32), np.uint32), buf(
            np.zeros(max_feed, dtype=np.uint32), np.uint32)
        ctl.cut_src, ctl.cut_factor = buf(alg.cut_src, np.int64), buf(alg.cut_factor.astype(np.float64))
        ctl.cut_offset = buf(alg.cut_offset.astype(np.float64))
        self.passes = np.zeros(0, dtype=np.int32)
        self._passes_for(1)
        self.order = np.array(alg.order, dtype=np.int32)
        self.rec_idx = sysm.record_idx
        self.n_rows = c_int64()
        self.budget_ns = CALL_BUDGET_NS
        self._start()

    def _events(self, alg):
        """The event state (``fx_ctl``, as :class:`cosim.master.engine._Compiled` keeps it; None
        without event-mode slaves) and the event-mode slaves' step reports
        (:meth:`cosim.slaves.slave.Slave.event_slots`)."""
        if not alg.event_slaves:
            return None
        for i in alg.event_slaves:
            c = self.arr[i]
            c.event_mode = 1
            c.step_flags, c.last_time, c.planned_end = alg.system.slaves[i].event_slots()
        ev = struct(FIXED_CONTROL)()
        ev.n_event, ev.max_events = len(alg.event_slaves), MAX_EVENTS_PER_STEP
        return ev

    def _passes_for(self, solves: int) -> None:
        if len(self.passes) < solves:
            self.passes = np.zeros(solves, dtype=np.int32)
            self.ctl.passes = self.passes.ctypes.data

    def _hand_in(self) -> None:
        """The iteration's point from the algorithm (its event iteration may have moved it)."""
        alg, ctl = self.alg, self.ctl
        self.z[:] = alg.z
        ctl.has_z_prev = int(alg.z_prev is not None)
        if alg.z_prev is not None:
            self.z_prev[:] = alg.z_prev
        for mine, its in zip(self.start_in, alg.start_in):
            mine[:] = its

    def _hand_back(self) -> list[int]:
        """The call's counters and the iteration's point to the algorithm; the passes of its solves."""
        alg, ctl = self.alg, self.ctl
        for i, c in enumerate(self.arr.arr):
            alg.calls[i], alg.slave_ns[i] = c.calls, c.ns
        alg.rollbacks, alg.jacobians, alg.directional = int(ctl.rollbacks), int(ctl.jacobians), int(ctl.directional)
        alg.broyden, alg.fd_steps = int(ctl.broyden), int(ctl.fd_steps)
        alg.z = self.z.copy()
        alg.z_prev = self.z_prev.copy() if ctl.has_z_prev else None
        alg.J = self.J.copy() if ctl.has_J else None
        alg.start_in = [x.copy() for x in self.start_in]
        return [int(p) for p in self.passes[:ctl.n_passes]]

    def _start(self) -> None:
        """:meth:`Iterative.start` in C: the coupling made consistent at the start time."""
        alg, sysm, ctl = self.alg, self.alg.system, self.ctl
        self._hand_in()
        code = int(self.lib.rpr_iter_start(self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data,
                                           len(sysm.v), ctypes.byref(ctl), alg.t))
        alg.init_passes += sum(self._hand_back())
        self.arr.reraise()
        self._ended(code, alg.t, step=False)

    def run(self, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
        alg, sysm, ctl, ev = self.alg, self.alg.system, self.ctl, self.ev
        self._passes_for(nsteps + 1)  # an event step that is cut iterates twice (then the call returns)
        ctl.master_ns = 0
        self._hand_in()
        if ev is not None:
            ev.has_t_event, ev.t_event = alg.t_event is not None, alg.t_event or 0.0
            ev.events_in_step = alg._events_in_step
        done = int(self.lib.rpr_iter_run(
            self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, len(sysm.v),
            ctypes.byref(ctl), alg.k, nsteps, alg.start_ns, alg.step_ns,
            self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx), rec_every, rec.ctypes.data,
            ctypes.byref(self.n_rows), self.budget_ns, None if ev is None else ctypes.byref(ev)))
        code = int(ctl.status)
        alg.passes += self._hand_back()
        alg.master_ns += ctl.master_ns
        self.arr.reraise()  # a callback slave's exception (a model's error, Ctrl-C), raised here
        end = FixedEnd.RUNNING
        if ev is not None:  # the event state as Iterative._event_step leaves it
            alg.t_event = ev.t_event if ev.has_t_event else None
            alg._events_in_step, end = ev.events_in_step, FixedEnd(ev.status)
        rows = int(self.n_rows.value)
        alg.k += done
        if code == IterativeEnd.STOPPED:  # the step completed, or (EVENT) the retake to the event
            alg.stop_at = ev.t_e if end == FixedEnd.EVENT else None
            alg.stopped_by(ctl.bad_slave, alg.t)
            return rows + self._row(rec, rows)
        if code == IterativeEnd.OK and end in (FixedEnd.EVENT, FixedEnd.GRID_EVENT):  # its row, the left limit
            alg.pending_event = StepResult(alg.t_ns, True, int(ev.who), "event")
            return rows + self._row(rec, rows)
        if code == IterativeEnd.OK and end == FixedEnd.CHATTERING:
            alg.chattering(int(ev.who), ev.t_e)
        self._ended(code, alg.t, step=True)
        return rows

    def _row(self, rec: np.ndarray, row: int) -> int:
        """The current point as row ``row`` of ``rec`` (time, the recorded values); 1."""
        rec[row, 0] = self.alg.t
        np.take(self.alg.system.v, self.alg.system.record_idx, out=rec[row, 1:])
        return 1

    def _ended(self, code: int, t: float, step: bool) -> None:
        """The run's ending for the kernel's end ``code`` of a step from ``t`` (or, without
        ``step``, of the start point), worded by the algorithm as its own loop words it."""
        alg, ctl = self.alg, self.ctl
        bad, st = int(ctl.bad_slave), int(ctl.bad_status)
        if code == IterativeEnd.FAILED:
            alg._fail(bad, st, t)
        elif code in (IterativeEnd.DIVERGED, IterativeEnd.NOT_CONVERGED):
            alg._unstable(int(ctl.fail_it), step, t, self.e.copy(), float(ctl.fail_err),
                          diverged=code == IterativeEnd.DIVERGED)
        elif code:
            s = alg.system.slaves[bad]
            what = {IterativeEnd.SAVE: "getting the FMU state", IterativeEnd.RESTORE: "setting the FMU state",
                    IterativeEnd.DIRECTIONAL: "get directional derivative"}[code]
            name = Status(st).name if st in Status._value2member_map_ else str(st)
            raise UserError(f"{s.name}: {what} failed ({name})" + (f": {s.last_message}" if s.last_message else ""))


__all__ = ["CompiledIterative", "library"]
