"""The compiled engine of ``master.algorithm: iterative``: its macro steps in C.

The same steps as :class:`cosim.master.algorithms.iterative.Iterative` (the Python loop stays the
reference; ``tests/test_native.py`` checks that both give the same values bit for bit, the same
passes per step, rollbacks, Jacobians and Broyden updates, and the same endings): save every
slave's FMU state, passes over the Gauss-Seidel order with each slave restored and re-stepped
only when its inputs changed, the residual of the cut connections, and the fixed-point or
Newton update (Jacobian by the chain rule from directional derivatives or finite differences,
Broyden's update, the solve of :mod:`cosim.master.dense` in the same order of
operations).  The start-time iteration stays in Python (it runs once, before the loop).

One call runs up to ``nsteps`` macro steps (returning early after its wall-time budget) and
hands back a failure, a stop request (after completing the step, as the Python loop does) or a
step that did not converge, with what the Python side needs to word it alike.
"""
from __future__ import annotations

import ctypes
from ctypes import c_int64
from functools import lru_cache

import numpy as np

from ..errors import UserError
from ..slaves.slave import Status
from .entries import ITER_RUN, ITERATIVE_CONTROL, IterativeEnd, struct
from .kernels import SlaveArray, compile_loop
from .algorithms.iterative import FD_REL, GROWTH_LIMIT

CControl = struct(ITERATIVE_CONTROL)

#: Longest wall time of one call [ns]: it returns to Python (signals, progress) at least this often.
CALL_BUDGET_NS = 250_000_000


@lru_cache(maxsize=1)
def library() -> ctypes.CDLL:
    """Compile (once, cached on disk: :func:`cosim.master.kernels.compile_loop`) and load the engine."""
    return compile_loop("iterative_engine.c", "rpr_iter", [ITER_RUN])


class CompiledIterative:
    """Runs :class:`cosim.master.algorithms.iterative.Iterative`'s macro steps in C, with the shape
    of :class:`cosim.master.engine._Compiled` (``run(nsteps, rec_every, rec) -> rows``), updating
    the algorithm's step count, status, counters and statistics as its own loop would."""

    def __init__(self, alg):
        self.lib = library()
        self.alg = alg
        sysm = alg.system
        m, nv = len(alg.cuts), len(sysm.v)
        self.arr = arr = SlaveArray(sysm, callbacks=True)
        max_in = max([len(b) for b in sysm.in_buf] + [1])
        max_out = max([len(b) for b in sysm.out_buf] + [1])
        max_feed = max([len(f) for f in alg.feeding] + [1])
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
                c.start_in = arr.buffer(alg.start_in[i].astype(np.float64).copy())
                c.last_in = arr.buffer(np.zeros(n_in))
            if alg.interpolating[i]:
                c.interp, c.set_der = 1, arr.entries[i].set_input_derivatives
                c.orders = arr.buffer(np.ones(n_in, dtype=np.int32), np.int32)
                c.slope = arr.buffer(alg.slopes[i])
            out_pos = {int(k) - sysm.out_off[i] for _, k in alg.feeding[i]}
            feed = np.array(sorted(out_pos), dtype=np.int32)
            c.n_feed = len(feed)
            c.feed = arr.buffer(feed, np.int32)
        self.ctl = ctl = CControl()
        opt = alg.opt
        ctl.m, ctl.max_iter, ctl.newton = m, int(opt["max_iter"]), int(opt["method"] == "newton")
        ctl.jac_auto, ctl.linear = int(opt["jacobian"] == "auto"), int(alg.inputs == "linear")
        ctl.timing = int(alg.timing)
        ctl.omega, ctl.rtol, ctl.atol = opt["omega"], opt["rtol"], opt["atol"]

        ctl.growth, ctl.fd_rel = GROWTH_LIMIT, FD_REL
        # the start's counts, counted on
        ctl.rollbacks, ctl.jacobians, ctl.directional = alg.rollbacks, alg.jacobians, alg.directional
        ctl.broyden, ctl.fd_steps = alg.broyden, alg.fd_steps
        buf = arr.buffer
        self.z = np.array(alg.z, dtype=np.float64)
        self.z_prev = np.zeros(m) if alg.z_prev is None else np.array(alg.z_prev, dtype=np.float64)
        ctl.has_z_prev = int(alg.z_prev is not None)
        if alg.J is not None:
            self.J = np.ascontiguousarray(alg.J, dtype=np.float64)
            ctl.has_J = 1
        else:
            self.J = np.zeros((m, m))
        self.e = np.zeros(m)
        self.zi = np.zeros(m)
        ctl.z, ctl.z_prev, ctl.J, ctl.e, ctl.zi = buf(self.z), buf(self.z_prev), buf(self.J), buf(self.e), buf(self.zi)
        for name in ("g", "r", "z_old", "r_old", "dz", "w"):
            setattr(ctl, name, buf(np.zeros(max(m, 1))))
        ctl.A = buf(np.zeros(max(m * m, m, 1)))
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
        self.order = np.array(alg.order, dtype=np.int32)
        self.rec_idx = sysm.record_idx
        self.n_rows = c_int64()
        self.budget_ns = CALL_BUDGET_NS

    def run(self, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
        alg, sysm, ctl = self.alg, self.alg.system, self.ctl
        if len(self.passes) < nsteps:
            self.passes = np.zeros(nsteps, dtype=np.int32)
            ctl.passes = self.passes.ctypes.data
        ctl.master_ns = 0
        t_fail = alg.t
        done = int(self.lib.rpr_iter_run(
            self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, len(sysm.v),
            ctypes.byref(ctl), alg.k, nsteps, alg.start_ns, alg.step_ns,
            self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx), rec_every, rec.ctypes.data,
            ctypes.byref(self.n_rows), self.budget_ns))
        code = int(ctl.status)
        counted = done if code in (IterativeEnd.OK, IterativeEnd.STOPPED) else done + 1  # the step that ended the run counts its passes too
        alg.passes += [int(p) for p in self.passes[:counted] if p >= 0]
        for i, c in enumerate(self.arr.arr):
            alg.calls[i], alg.slave_ns[i] = c.calls, c.ns
        alg.rollbacks, alg.jacobians, alg.directional = int(ctl.rollbacks), int(ctl.jacobians), int(ctl.directional)
        alg.broyden, alg.fd_steps = int(ctl.broyden), int(ctl.fd_steps)
        alg.master_ns += ctl.master_ns
        self.arr.reraise()  # a callback slave's exception (a model's error, Ctrl-C), raised here
        rows = int(self.n_rows.value)
        if code == IterativeEnd.STOPPED:
            alg.k += done - 1
            alg.stopped_by(ctl.bad_slave, alg.t)
            rec[rows, 0] = alg.t
            np.take(sysm.v, sysm.record_idx, out=rec[rows, 1:])
            return rows + 1
        alg.k += done
        t_fail = alg.t
        bad, st = int(ctl.bad_slave), int(ctl.bad_status)
        if code == IterativeEnd.FAILED:
            alg._fail(bad, st, t_fail)
        elif code in (IterativeEnd.DIVERGED, IterativeEnd.NOT_CONVERGED):
            what = ("the coupling iteration diverged" if code == IterativeEnd.DIVERGED else
                    f"the coupling iteration did not converge within max_iter = {int(ctl.max_iter)} passes")
            alg.passes.pop()  # _unstable records the step's passes itself
            alg._unstable(int(ctl.fail_it), True, t_fail, self.e.copy(), what, float(ctl.fail_err))
        elif code:
            s = sysm.slaves[bad]
            what = {IterativeEnd.SAVE: "getting the FMU state", IterativeEnd.RESTORE: "setting the FMU state",
                    IterativeEnd.DIRECTIONAL: "get directional derivative"}[code]
            name = Status(st).name if st in Status._value2member_map_ else str(st)
            raise UserError(f"{s.name}: {what} failed ({name})" + (f": {s.last_message}" if s.last_message else ""))
        return rows


__all__ = ["CompiledIterative", "library"]
