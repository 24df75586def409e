"""Strong coupling: ``master.algorithm: iterative`` iterates every macro step to a consistent coupling.

A fixed-step master takes each input over ``[t, t+h]`` from a guess (its source's output at ``t``,
or an extrapolation) and never checks it; this one saves every slave's state (FMI get FMU state),
steps, compares the outputs that feed inputs with the values those inputs were given, and
restores and re-steps until they agree.  The converged step is the implicit coupling: every input
over the step ends at its source's output at ``t+h``, so an algebraic loop (a cycle of direct
feedthrough, which the other algorithms refuse) is solved at every communication point, and a
stiff coupling that makes Jacobi unstable at a step stays stable at it.

Unknowns.  Slaves step in a Gauss-Seidel order (the fewest connections against the order, or
``master.order``).  An input whose source comes earlier in the order takes the source's new output
at once (it is never guessed); the others, the *cut* connections, carry the unknowns ``z``: the
values of those inputs at ``t+h``.  One *pass* steps every slave from ``t`` with its inputs ending
at those values and gives their sources' outputs ``G(z)``; the residual is ``r = G(z) - z``.  A slave
whose inputs did not change since its last pass keeps its step (a slave without inputs steps once).

Inputs over the step (``master.inputs``): ``linear``: a slave that can interpolate inputs (FMI 2.0
``canInterpolateInputs``) follows the straight line from its inputs at ``t`` to their values at
``t+h`` (trapezoidal, second order); ``hold``, and slaves that cannot interpolate, hold the value at
``t+h`` over the step (implicit, first order).  Either way the outputs at ``t+h`` are evaluated
with the inputs at ``t+h``, as an algebraic loop needs.  The first guess of ``z`` is its value at
``t`` (``hold``) or the straight line through its values at ``t-h`` and ``t`` (``linear``).

Iteration (option ``method``):

``fixed_point``
    ``z <- z + omega r`` (``omega`` < 1 under-relaxes: needed when the loop gain exceeds 1).
``newton``
    ``z <- z + (I - J)^-1 r`` with ``J = dG/dz``, built by the chain rule along the order from each
    slave's Jacobian of its outputs with respect to its inputs: the FMU's directional derivatives
    (fmi2GetDirectionalDerivative; our CasADi FMUs provide them: ``providesDirectionalDerivative``)
    where the slave provides them and option ``jacobian`` is ``auto``, else finite differences of the
    slave's step (one more step per input).  A directional derivative is the instantaneous partial
    (the direct feedthrough at ``t+h``), exact for slaves without states; the part a step adds
    through the slave's states (``O(h)``) is learnt by Broyden's rank-one update after every pass.
    ``J`` is kept from one step to the next and rebuilt when a pass does not halve the residual.

A step has converged when ``|r_c| <= atol + rtol * max(|z_c|, |G_c|)`` for every cut connection;
the recorded values are the outputs of that last pass.  No convergence within ``max_iter`` passes,
or a non-finite or exploding residual, ends the run as ``"unstable"`` with the step, the residual
and the worst connection.  At the start time the same iteration (without stepping) makes the
loop's values consistent before the first row is recorded.

Statistics: passes (iterations) per step (mean and max), rollbacks (state restores), Jacobians
built (from directional derivatives or finite differences) and Broyden updates.

Engines: this class is the reference (Python loop); :mod:`cosim.master.iterative_engine` takes
the same steps in C (Python slaves and typed ports through callbacks, their
:meth:`output_jacobian` behind the directional derivative; FMI 3.0 event-mode components; the
start-time iteration), bit for bit (``tests/test_native.py``, ``tests/test_general_kernel.py``,
``tests/test_iterative_event_kernel.py``).  Newton's small linear algebra is
:mod:`cosim.master.dense` in both: a fixed order of operations that C repeats exactly.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ...errors import UserError
from ...slaves.slave import FAILING, Status
from ..algorithm import MAX_EVENTS_PER_STEP, Algorithm, register
from ..system import CoupledSystem
from ..algorithm import AlgorithmOption, option_values
from .. import dense
from ..stepper import StepResult

_ns = time.perf_counter_ns


@dataclass(frozen=True)
class ChoiceOption(AlgorithmOption):
    """An option whose value is one of a few names (declared like the numeric ones)."""

    choices: tuple[str, ...] = ()

    def check(self, value) -> str:
        if value not in self.choices:
            raise ValueError(f"{self.name} = {value!r} is not one of {', '.join(self.choices)}")
        return str(value)


METHODS = ("newton", "fixed_point")
JACOBIANS = ("auto", "finite_difference")
OPTIONS = (
    ChoiceOption("method", "newton", math.nan, math.nan, "", "iteration: Newton with Broyden updates, or "
                 "relaxed fixed point", choices=METHODS),
    AlgorithmOption("omega", 1.0, 1e-3, 2.0, "1", "relaxation of the fixed-point iteration: z += omega (G(z) - z)"),
    AlgorithmOption("rtol", 1e-8, 1e-14, 1.0, "1", "convergence: |G(z) - z| <= atol + rtol max(|z|, |G(z)|) per "
                                                "connection"),
    AlgorithmOption("atol", 1e-10, 0.0, math.inf, "signal unit", "absolute convergence tolerance"),
    AlgorithmOption("max_iter", 50, 1, 10000, "1", "passes per macro step before the run ends as unstable",
                    integer=True),
    ChoiceOption("jacobian", "auto", math.nan, math.nan, "", "Newton's slave Jacobians: 'auto' (directional "
                 "derivatives where the slave provides them, else finite differences of its step) or "
                 "'finite_difference'", choices=JACOBIANS),
)

#: A residual (largest |G(z) - z|) this many times the first one of a step is divergence: the run ends at once.
GROWTH_LIMIT = 1e8
#: Relative finite-difference perturbation of an input (about the square root of the float64 epsilon).
FD_REL = 1.5e-8


@register
class Iterative(Algorithm):
    """Strong coupling by fixed-point or Newton iteration within each macro step (module docstring)."""

    name = "iterative"
    #: compiled: :mod:`cosim.master.iterative_engine` (engine.ITERATIVE)
    native_code = 2
    ends_steps_at_events = True
    event_policy = ("a step ends at the earliest event of an FMI 3.0 event-mode component for the whole coupling: "
                    "every component is rolled back and the coupling iterated again to the event time, then the "
                    "event iteration; the rest of the step rejoins the grid")
    sequential = True
    needs_rollback = True
    solves_algebraic_loops = True
    options = OPTIONS

    def __init__(self, system: CoupledSystem, step_ns: int, *, options: dict | None = None, **kw):
        self.opt = option_values(options, OPTIONS)
        super().__init__(system, step_ns, **kw)
        fixed = [s.name for s in system.slaves if not s.can_rollback]
        if fixed:
            raise UserError(f"master algorithm iterative needs rollback (get/set state) but {', '.join(fixed)} "
                            f"cannot roll back; use gauss_seidel or jacobi")
        self._layout()
        self.passes: list[int] = []
        self.rollbacks = self.jacobians = self.directional = self.broyden = self.fd_steps = self.init_passes = 0
        self.J: np.ndarray | None = None
        self.z_prev: np.ndarray | None = None
        #: the event [s] a cut step is being retaken to (a stop request there ends the run at it), or None
        self.stop_at: float | None = None

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

    # --- set-up ------------------------------------------------------------------------------------
    def _setup_inputs(self, inputs: str) -> None:
        """Which slaves follow input slopes (``linear`` and able to); the base class's push stays plain."""
        if inputs not in ("hold", "linear"):
            raise UserError(f"inputs must be 'hold' or 'linear', got {inputs!r}")
        sysm = self.system
        self.inputs = inputs
        self.slopes = [np.zeros(len(b)) for b in sysm.in_buf]
        self.hist = [sysm.source_values(i) for i in range(len(sysm.slaves))]
        self.fresh = [np.zeros(len(b), dtype=bool) for b in sysm.in_buf]
        self.interpolating = [inputs == "linear" and bool(len(sysm.in_buf[i])) and s.bind_slopes(self.slopes[i])
                              for i, s in enumerate(sysm.slaves)]

    def _layout(self) -> None:
        """Cut connections (the unknowns ``z``) and, per slave, which inputs are cut."""
        sysm = self.system
        pos = {s: k for k, s in enumerate(self.order)}
        n = len(sysm.slaves)
        self.cut_mask = [np.zeros(len(sysm.in_buf[i]), dtype=bool) for i in range(n)]
        self.cut_index = [np.zeros(0, dtype=np.int64) for _ in range(n)]
        self.cut_names: list[str] = []
        cuts: list[tuple[int, int]] = []  # (slave, input position)
        for i in range(n):
            idx = []
            for j, var in enumerate(sysm.inputs[i]):
                ln = next(ln for ln in sysm.links if ln.dst == i and ln.dst_var == var)
                if pos[ln.src] >= pos[i]:
                    self.cut_mask[i][j] = True
                    idx.append(len(cuts))
                    cuts.append((i, j))
                    self.cut_names.append(f"{sysm.slaves[ln.src].name}.{ln.src_var} -> {sysm.slaves[i].name}.{var}")
            self.cut_index[i] = np.array(idx, dtype=np.int64)
        self.cuts = cuts
        src = np.array([sysm.in_src[i][j] for i, j in cuts], dtype=np.int64)
        aff = [sysm.in_affine[i] for i, _ in cuts]
        self.cut_src = src
        self.cut_factor = np.array([a[0][j] if a is not None else 1.0 for a, (_, j) in zip(aff, cuts)])
        self.cut_offset = np.array([a[1][j] if a is not None else 0.0 for a, (_, j) in zip(aff, cuts)])
        # outputs of each slave that feed some input: (name, index in v)
        feeds = {int(k) for arr in sysm.in_src for k in arr}
        self.feeding = [[(var, sysm.out_off[i] + q) for q, var in enumerate(sysm.reads[i])
                         if sysm.out_off[i] + q in feeds] for i in range(n)]
        self.start_in = [sysm.in_buf[i].copy() for i in range(n)]  # each slave's inputs at t
        self.last_in: list[np.ndarray | None] = [None] * n
        self.z = self._cut_values()  # the cut inputs' values at t

    def _cut_values(self) -> np.ndarray:
        return self.system.v[self.cut_src] * self.cut_factor + self.cut_offset

    # --- one pass: every slave from t with its inputs ending at the fresh outputs and z ----------
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

    # --- Newton's Jacobian dG/dz -----------------------------------------------------------------
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

    # --- the iteration -------------------------------------------------------------------------------
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

    def _record_passes(self, it: int, step: bool) -> None:
        if step:
            self.passes.append(it)
        else:
            self.init_passes += it

    def _unstable(self, it: int, step: bool, t: float, e: np.ndarray, err: float, diverged: bool) -> None:
        """End the run as unstable: the iteration from ``t`` (a step, or without ``step`` the start
        point) diverged or did not converge in ``it`` passes, scaled residuals ``e``, the largest
        ``err`` (both engines)."""
        self._record_passes(it, step)
        what = ("the coupling iteration diverged" if diverged else
                f"the coupling iteration did not converge within max_iter = {int(self.opt['max_iter'])} passes")
        worst = self.cut_names[int(np.nanargmax(np.where(np.isfinite(e), e, np.inf)))] if len(e) else "?"
        where = f"in the step from t = {t:.9g} s (step {self.k})" if step else f"at the start time t = {t:.9g} s"
        self.status = "unstable"
        self.message = (f"{what} {where}: scaled residual {err:.3g} > 1 after {it} passes, worst on {worst} "
                        f"(method {self.opt['method']}; try method: newton, a smaller omega or a smaller step)")
        return None

    # --- FMI 3.0 event mode (docs/explanation/events.md) ---------------------------------------------
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

    def event_iteration(self, event) -> None:
        """The event iteration (:meth:`Algorithm.event_iteration`); after it the cut inputs and
        every slave's inputs at the point are the right limit's, and the next first guess does not
        extrapolate across the jump."""
        super().event_iteration(event)
        if self.status == "running":
            self.z, self.z_prev = self._cut_values(), None
            self.start_in = [b.copy() for b in self.system.in_buf]

    # --- the Algorithm interface -----------------------------------------------------------------
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

    def stopped_by(self, i: int, t: float) -> None:
        """:meth:`Algorithm.stopped_by` at the point the stopped step reached: the next grid point,
        or the event a cut step was retaken to (:attr:`stop_at`; the step is not completed)."""
        at, self.t_event = self.stop_at, self.stop_at
        super().stopped_by(i, t)
        if at is not None:
            self.k -= 1

    def statistics(self) -> dict:
        """Passes per step, rollbacks, Jacobians: added to the run statistics."""
        p = np.array(self.passes or [0])
        return {"iterations_mean": float(p.mean()), "iterations_max": int(p.max()),
                "iterations_total": int(p.sum()), "start_iterations": self.init_passes, "rollbacks": self.rollbacks,
                "jacobians": self.jacobians, "directional_derivatives": self.directional,
                "finite_difference_steps": self.fd_steps, "broyden_updates": self.broyden,
                "cut_connections": list(self.cut_names), "options": dict(self.opt)}


class _PassFailed(Exception):
    """A slave failed during a finite-difference step (carried out of the Jacobian)."""

    def __init__(self, slave: int, status: int):
        super().__init__(slave, status)
        self.slave, self.status = slave, status


__all__ = ["Iterative", "OPTIONS", "ChoiceOption"]
