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
from dataclasses import dataclass

import numpy as np

from ...errors import UserError
from ..algorithm import Algorithm, register
from ..system import CoupledSystem
from ..algorithm import AlgorithmOption, option_values



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
        self.z = self._cut_values()  # the cut inputs' values at t

    def _cut_values(self) -> np.ndarray:
        return self.system.v[self.cut_src] * self.cut_factor + self.cut_offset

    # --- the endings' wording (both engines) ----------------------------------------------------------
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
    def event_iteration(self, event) -> None:
        """The event iteration (:meth:`Algorithm.event_iteration`); after it the cut inputs and
        every slave's inputs at the point are the right limit's, and the next first guess does not
        extrapolate across the jump."""
        super().event_iteration(event)
        if self.status == "running":
            self.z, self.z_prev = self._cut_values(), None
            self.start_in = [b.copy() for b in self.system.in_buf]

    # --- the Algorithm interface -----------------------------------------------------------------
    def stopped_by(self, i: int, t: float) -> None:
        """:meth:`Algorithm.stopped_by` at the point the stopped step reached: the next grid point,
        or the event a cut step was retaken to (:attr:`stop_at`; the step is not completed)."""
        super().stopped_by(i, t, self.stop_at)

    def statistics(self) -> dict:
        """Passes per step, rollbacks, Jacobians: added to the run statistics."""
        p = np.array(self.passes or [0])
        return {"iterations_mean": float(p.mean()), "iterations_max": int(p.max()),
                "iterations_total": int(p.sum()), "start_iterations": self.init_passes, "rollbacks": self.rollbacks,
                "jacobians": self.jacobians, "directional_derivatives": self.directional,
                "finite_difference_steps": self.fd_steps, "broyden_updates": self.broyden,
                "cut_connections": list(self.cut_names), "options": dict(self.opt)}


__all__ = ["Iterative", "OPTIONS", "ChoiceOption"]
