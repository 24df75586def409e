"""The Python twin of the iterative kernel (``rpr_iter_run`` and ``rpr_iter_start`` in
``cosim/master/iterative_engine.c``), a test oracle: the product's :class:`Iterative` (its
layout, options, event iteration, the endings' wording: written once, in ``cosim/``) with the
Python iteration the kernel's is compared with, bit for bit: the start-time iteration, each
step's passes with fixed-point or Newton updates (the Jacobian by the chain rule along the order,
from directional derivatives or finite differences, Broyden updates between), the rollback of
every slave before a retake, and the cut at an FMI 3.0 event.  It runs through the product's one
seam, a runner (:func:`cosim.master.stepper.python_runner`), registered as the engine ``oracle``
(:mod:`oracles`)."""
from __future__ import annotations

import math

import numpy as np

from cosim.master import dense
from cosim.master.algorithm import MAX_EVENTS_PER_STEP, _ns
from cosim.master.algorithms import iterative
from cosim.master.algorithms.iterative import FD_REL, GROWTH_LIMIT
from cosim.master.stepper import StepResult
from cosim.slaves.slave import FAILING, Status


class Iterative(iterative.Iterative):
    """The iterative algorithm's steps in Python; the start-time iteration runs when it is made,
    as the kernel's runs when its engine is."""

    def __init__(self, system, step_ns, **kw):
        super().__init__(system, step_ns, **kw)
        self.last_in: list[np.ndarray | None] = [None] * len(system.slaves)  # each slave's inputs in this pass
        self.start()

    def start(self) -> None:
        """The Python loop's start-time iteration (without stepping: the loop's values made
        consistent before the first row); the compiled engine's is ``rpr_iter_start``
        (:class:`cosim.master.iterative_engine.CompiledIterative`).  A failing call ends the run."""
        bad = self._solve(self.t, 0.0, step=False)
        if bad is not None:
            self._fail(bad[0], bad[1], self.t)
        elif self.status == "running":
            self._accept()

    def _accept(self) -> None:
        """The inputs the slaves ended the step (or the start) with are their inputs at the new point."""
        for i, ends in enumerate(self.last_in):
            if ends is not None and len(ends):
                self.start_in[i] = ends.copy()

    def _ends(self, i: int, z: np.ndarray) -> np.ndarray:
        ends = self.system.source_values(i)
        if len(self.cut_index[i]):
            ends[self.cut_mask[i]] = z[self.cut_index[i]]
        return ends

    def _run_slave(self, i: int, t: float, h: float, ends: np.ndarray | None, step: bool) -> int:
        """Slave ``i`` from its saved state at ``t`` (restored if it stepped already) with inputs
        ending at ``ends``; outputs read into the value vector.  ``step`` False: only set the
        inputs and read the outputs (the start time)."""
        s, buf = self.system.slaves[i], self.system.in_buf[i]
        t0 = _ns()
        st = Status.OK
        if step and self.last_in[i] is not None:
            s.restore_state()
            self.rollbacks += 1
        if ends is not None:
            if step and self.interpolating[i]:
                buf[:] = self.start_in[i]
                np.subtract(ends, self.start_in[i], out=self.slopes[i])
                self.slopes[i] /= h
                st = s.push()
                if st not in FAILING:
                    st = s.push_slopes()
            else:
                buf[:] = ends
                st = s.push()
        if st not in FAILING and step:
            st = s.do_step(t, h)
            self.calls[i] += 1
            if st not in FAILING and st != Status.STOP_REQUESTED and ends is not None and self.interpolating[i]:
                buf[:] = ends  # the outputs at t+h see the inputs at t+h, whatever the FMU made of the slope
                st = s.push()
        if st not in FAILING and st != Status.STOP_REQUESTED:
            st = s.pull()
        self.slave_ns[i] += _ns() - t0
        self.last_in[i] = ends if ends is not None else np.zeros(0)
        return st

    def _pass(self, t: float, h: float, z: np.ndarray, step: bool, start: int = 0) -> tuple[int, int] | None:
        """One pass over the order from position ``start``; ``(slave, status)`` of a failing call."""
        for i in self.order[start:]:
            if not len(self.system.in_buf[i]):
                if step and self.last_in[i] is None:
                    st = self._run_slave(i, t, h, None, step)
                    if st in FAILING or st == Status.STOP_REQUESTED:
                        return i, st
                continue
            ends = self._ends(i, z)
            if self.last_in[i] is not None and np.array_equal(ends, self.last_in[i]):
                continue
            st = self._run_slave(i, t, h, ends, step)
            if st in FAILING or st == Status.STOP_REQUESTED:
                return i, st
        return None

    def _local_jacobian(self, i: int, cols: np.ndarray, t: float, h: float, step: bool) -> np.ndarray:
        """d(feeding outputs of slave i)/d(its inputs ``cols``) at the current point: directional
        derivatives (instantaneous) when provided and allowed, else finite differences of its step."""
        s, sysm = self.system.slaves[i], self.system
        names = [var for var, _ in self.feeding[i]]
        if self.opt["jacobian"] == "auto":
            t0 = _ns()
            jac = s.output_jacobian(names, [sysm.inputs[i][c] for c in cols])
            self.slave_ns[i] += _ns() - t0
            if jac is not None:
                self.directional += 1
                return np.asarray(jac, dtype=float).reshape(len(names), len(cols))
        rows = np.array([k for _, k in self.feeding[i]], dtype=np.int64)
        base_in, base_out = self.last_in[i].copy(), sysm.v[rows].copy()
        saved = sysm.out_buf[i].copy()
        jac = np.zeros((len(names), len(cols)))
        for q, c in enumerate(cols):
            ends = base_in.copy()
            d = FD_REL * max(1.0, abs(ends[c]))
            ends[c] += d
            st = self._run_slave(i, t, h, ends, step)
            self.fd_steps += int(step)
            if st in FAILING or st == Status.STOP_REQUESTED:
                raise _PassFailed(i, st)
            jac[:, q] = (sysm.v[rows] - base_out) / d
        sysm.out_buf[i][:] = saved  # the outputs of the unperturbed point (the slave re-steps next pass)
        return jac

    def _jacobian(self, t: float, h: float, step: bool) -> np.ndarray:
        """``dG/dz`` by the chain rule along the order (module docstring)."""
        sysm, m = self.system, len(self.cuts)
        self.jacobians += 1
        dv: dict[int, np.ndarray] = {}
        for i in self.order:
            nin = len(sysm.in_buf[i])
            if not nin or not self.feeding[i]:
                continue
            du = np.zeros((nin, m))
            aff = sysm.in_affine[i]
            for j in range(nin):
                if self.cut_mask[i][j]:
                    du[j, self.cut_index[i][np.count_nonzero(self.cut_mask[i][:j])]] = 1.0
                else:
                    row = dv.get(int(sysm.in_src[i][j]))
                    if row is not None:
                        du[j] = row * (aff[0][j] if aff is not None else 1.0)
            cols = np.flatnonzero(np.any(du != 0.0, axis=1))
            if not len(cols):
                continue
            dy = dense.matmul(self._local_jacobian(i, cols, t, h, step), du[cols])
            for q, (_, k) in enumerate(self.feeding[i]):
                dv[k] = dy[q]
        zero = np.zeros(m)
        return np.array([dv.get(int(k), zero) * f for k, f in zip(self.cut_src, self.cut_factor)]).reshape(m, m)

    def _scaled(self, r: np.ndarray, z: np.ndarray, g: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", over="ignore"):
            return np.abs(r) / (self.opt["atol"] + self.opt["rtol"] * np.maximum(np.abs(z), np.abs(g)))

    def _solve(self, t: float, h: float, step: bool) -> tuple[int, int] | None:
        """Iterate the step from ``t`` (or, without ``step``, the start point) to convergence.
        Returns ``(slave, status)`` of a failing call; non-convergence sets :attr:`status`."""
        opt, m = self.opt, len(self.cuts)
        self.last_in = [None] * len(self.last_in)
        if step:
            for i, s in enumerate(self.system.slaves):
                if len(self.system.in_buf[i]):
                    s.save_state()
        z = self.z.copy()
        if step and self.inputs == "linear" and self.z_prev is not None:
            z = 2.0 * self.z - self.z_prev
        self._z_now, self._h_now = z, h
        newton = opt["method"] == "newton"
        r_old = z_old = None
        r_first = err_old = None
        fresh_j = False
        max_iter = int(opt["max_iter"])
        try:
            for it in range(1, max_iter + 1):
                bad = self._pass(t, h, z, step)
                if bad is not None:
                    self._record_passes(it, step)
                    return bad
                g = self._cut_values()
                r = g - z
                e = self._scaled(r, z, g)
                err = float(np.max(e)) if m else 0.0
                size = float(np.max(np.abs(r))) if m else 0.0
                if not math.isfinite(err) or (r_first is not None and size > GROWTH_LIMIT * r_first):
                    return self._unstable(it, step, t, e, err, diverged=True)
                if err <= 1.0:
                    self._record_passes(it, step)
                    if step:
                        self.z_prev = self.z
                    self.z = z.copy()
                    return None
                if it == max_iter:
                    return self._unstable(it, step, t, e, err, diverged=False)
                r_first = size if r_first is None else r_first
                if newton:
                    if self.J is None or (err_old is not None and err > 0.5 * err_old and not fresh_j):
                        self.J, fresh_j = self._jacobian(t, h, step), True
                    elif r_old is not None:
                        dz, dr = z - z_old, r - r_old
                        den = dense.dot(dz, dz)
                        if den > 0:
                            jf = self.J - np.eye(m)
                            self.J = self.J + np.outer(dr - dense.matvec(jf, dz), dz) / den
                            self.broyden += 1
                    dz = dense.solve(np.eye(m) - self.J, r)
                    if dz is None:
                        dz = r  # a singular I - J: one plain fixed-point pass, then Broyden again
                else:
                    dz = opt["omega"] * r
                z_old, r_old, err_old = z, r, err
                z = z + dz
                self._z_now = z
        except _PassFailed as exc:
            return exc.slave, exc.status
        return None

    def _event_step(self) -> bool:
        """:meth:`Algorithm.step` with event-mode slaves: the iterated step from the current point
        (a grid point or an event) to the next grid point; where an event-mode slave returned early
        at ``t_e``, every slave is rolled back and the coupling iterated again over ``[t, t_e]``
        (the event ends the step for the whole coupling), then the event iteration.  A stop
        request in a step an event cuts (an event-mode slave stepped in it returned early) goes
        with the step: the retake to the event decides."""
        slaves, sysm = self.system.slaves, self.system
        t, t_end = self.t, self.time_at(self.k + 1)
        self.stop_at = None
        kept = (sysm.v.copy(), self.z.copy(), None if self.z_prev is None else self.z_prev.copy(),
                None if self.J is None else self.J.copy(), [x.copy() for x in self.start_in])
        for s in slaves:
            s.save_state()
        bad = self._step_impl(t, t_end - t)
        ends = {i: slaves[i].step_end() for i in self.event_slaves if self.last_in[i] is not None} \
            if bad is None or self.stop_requested(*bad) else {}  # (the ones stepped in it)
        tol = 1e-12 * (1.0 + abs(t_end))
        early = sorted((r, i) for i, (r, _) in ends.items() if r < t_end - tol)
        if self.status == "running" and early:
            t_e, who = early[0]
            self._events_in_step += 1
            if self._events_in_step > MAX_EVENTS_PER_STEP or t_e <= t:  # (an event at the step's start: no progress)
                self.chattering(who, t_e)
                return False
            for s in slaves:
                s.restore_state()
            v, self.z, self.z_prev, self.J, self.start_in = kept
            np.copyto(sysm.v, v)
            self.stop_at = t_e
            bad = self._step_impl(t, t_e - t)
            if bad is None and self.status == "running":
                self.t_event = t_e
                self.pending_event = StepResult(self.t_ns, True, who, "event")
                return True
        if self.status != "running":
            return False
        if bad is not None:
            if self.stop_requested(*bad):
                self.complete_after_stop(bad[0], t)
            else:
                self._fail(bad[0], bad[1], t)
            return False
        self.k, self.t_event, self._events_in_step = self.k + 1, None, 0
        asking = [i for i, (_, ev) in ends.items() if ev]
        if asking:
            self.pending_event = StepResult(self.t_ns, True, asking[0], "event")
        return True

    def _step_impl(self, t: float, h: float) -> tuple[int, int] | None:
        bad = self._solve(t, h, step=True)
        if bad is None and self.status == "running":
            self._accept()
        return bad

    def _finish_step(self, i: int, t: float, h: float) -> tuple[int, int] | None:
        """A slave asked to stop during a pass: the rest of that pass completes the step (over the
        step being iterated: the macro step ``h``, the rest of it after an event, or the part up to
        the event a cut step is retaken to)."""
        st = self._io(i, self.system.slaves[i].pull)
        if st in FAILING:
            return i, st
        return self._pass(t, self._h_now, self._z_now, True, start=self.order.index(i) + 1)


class _PassFailed(Exception):
    """A slave failed during a finite-difference step (carried out of the Jacobian)."""

    def __init__(self, slave: int, status: int):
        super().__init__(slave, status)
        self.slave, self.status = slave, status
