"""Step-size control from the energy residual of power bonds: ``master.algorithm: ecco``.

The idea of ECCO (Sadjina, Kyllingstad, Skjong and Pedersen, "Energy conservation and power
bonds in co-simulations: non-iterative adaptive step size control and error estimation",
Engineering with Computers, 2017; the ``ecco_algorithm`` of libcosim): across a power bond
``a.p <-> b.q`` each side computes the power it exchanges from its own output and the input it was
given, ``P_a = y_a * u_a`` (e.g. the motor's force times the velocity it saw) and
``P_b = y_b * u_b`` (the leg's velocity times the force it saw).  With perfect coupling both are
the same power at every instant; a co-simulation hands each side held, extrapolated or
interpolated inputs, so energy is created or lost at the bond.  That energy residual is the error
estimate, and it needs no rollback: it is measured after the step, and the step size it asks for
applies to the next step.  This is the algorithm for slaves that cannot save and restore their
state (the hardware plant, or a component declared ``rollback: false`` in its scene).

Per bond and step ``t -> t + h`` (a Gauss-Seidel step with linear inputs, taken by
:class:`cosim.master.algorithms.adaptive.AdaptiveStepper`), with the outputs ``y(t)``, ``y(t+h)``
and the input each side actually saw, ``u(t)`` and ``u(t) + slope * h`` at the step's end (a held
input has slope 0):

* energy residual (trapezoidal rule over the step) [J]:
  ``dE = h/2 * [(P_a - P_b)(t) + (P_a - P_b)(t+h)]``;
* energy the bond carried over the step [J]:
  ``E = h/2 * max(|P_a(t)| + |P_a(t+h)|, |P_b(t)| + |P_b(t+h)|)``;
* scaled residual (the ECCO paper's relative error): ``eps = |dE| / (atol + rtol * E)``.

The step's error is the largest ``eps`` over the bonds (every bond within its tolerance, where
libcosim takes a root mean square).  The next step follows a PI controller on it,
``h_new = h * clip((safety / eps)^k_i * (eps_prev / eps)^k_p, fac_min, fac_max)`` (Soederlind's
form: a steady error settles at ``safety``, a growing one cuts the step at once) within
``[h_min, h_max]``, landing exactly on the stop time; time is counted in whole nanoseconds.  A step
is never retried, so the defaults aim low (``safety`` 0.1) and change the step smoothly (small
gains, ``fac_max`` 1.2): a step with ``eps > 1`` is kept, counted as over tolerance, and the next
one is smaller.  A Discard or error from any slave ends the run as "failed" with the slave's
reason; a residual that is not finite, or one over tolerance for ``floor_steps`` (100) steps in a row
at ``h_min``, as "unstable" (``floor_steps: 0``: the run goes on at ``h_min``, as libcosim's ECCO does,
those steps counted as over tolerance).

Statistics (the run's sidecar, ``statistics``): accepted steps, smallest and largest step, the
stepping order, and per bond the largest scaled residual of a step, the largest residual [J], the
residual summed over the run (signed: the energy the coupling created) and its absolute sum [J],
the energy carried [J], the net residual scaled like a step's (``|sum dE| / (atol + rtol * sum
E)``) and the steps over tolerance.

Engine: the steps are taken in C (``rpr_ecco_run`` in ``cosim/master/adaptive_engine.c``, bound
by :class:`cosim.master.adaptive_engine.CompiledEcco`), FMI 3.0 events included; :class:`EccoStepper`
holds the run's state and the endings' wording.  Its Python twin, the test oracle, is
``tests/oracles/variable.py`` (bit for bit: ``tests/test_native.py``, ``tests/test_general_kernel.py``,
``tests/test_variable_event_kernel.py``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Sequence

import numpy as np

from ...errors import UserError
from ...slaves.slave import Status
from ..algorithm import MasterAlgorithm, register
from ..system import CoupledSystem
from ..algorithm import AlgorithmOption
from ..entries import EccoEnd
from .adaptive import AdaptiveStats, AdaptiveStepper, variable_stepper

OPTIONS = (
    AlgorithmOption("rtol", 1e-3, 1e-12, 1.0, "1", "energy residual of a bond per step, relative to the energy "
                                               "the bond carried over the step"),
    AlgorithmOption("atol", 1e-7, 0.0, math.inf, "J", "absolute tolerance of the energy residual of a bond per step"),
    AlgorithmOption("h_init", 1e-6, 1e-9, 1.0, "s", "first macro step (no input history yet to extrapolate from)"),
    AlgorithmOption("h_min", 1e-7, 1e-9, 1.0, "s", "smallest macro step"),
    AlgorithmOption("h_max", 0.01, 1e-9, math.inf, "s", "largest macro step"),
    AlgorithmOption("safety", 0.1, 0.01, 1.0, "1", "the scaled residual the step controller aims at (a step "
                                                  "cannot be retried: the margin absorbs what it did not foresee)"),
    AlgorithmOption("fac_min", 0.2, 0.01, 1.0, "1", "smallest step ratio from one step to the next"),
    AlgorithmOption("fac_max", 1.2, 1.0, 100.0, "1", "largest step ratio from one step to the next"),
    AlgorithmOption("k_i", 0.1, 0.0, 2.0, "1", "integral gain of the PI step controller (exponent of the residual)"),
    AlgorithmOption("k_p", 0.2, 0.0, 2.0, "1", "proportional gain of the PI step controller (exponent of the "
                                               "residual's change)"),
    AlgorithmOption("floor_steps", 100, 0, 1e9, "1", "steps in a row over tolerance at h_min after which the run ends "
                                                     "as unstable (0: never; it goes on at h_min, as libcosim's ECCO "
                                                     "does, the steps over tolerance counted)", integer=True),
)


@dataclass
class Bond:
    """One power bond by indices into the system's value vector: each side's output and the
    input buffer it steps with (``slot``: position among that slave's inputs)."""

    name: str
    side: tuple[int, int]  # the two slaves
    out_idx: np.ndarray  # v indices of y_a, y_b
    in_idx: np.ndarray  # v indices of u_a, u_b (the input buffers)
    slot: tuple[int, int]  # positions of u_a, u_b in their slaves' inputs (slope buffers)


def find_bonds(system: CoupledSystem) -> list[Bond]:
    """The power bonds of ``system``: pairs of links carrying the same ``bond`` label, one each
    way between two slaves.  A bond whose halves are transformed or missing is a UserError."""
    halves: dict[str, list] = {}
    for ln in system.links:
        if ln.bond:
            halves.setdefault(ln.bond, []).append(ln)
    bonds = []
    for name, lns in halves.items():
        if len(lns) != 2 or lns[0].src != lns[1].dst or lns[0].dst != lns[1].src:
            raise UserError(f"power bond {name}: expected one link each way between two slaves, got "
                            f"{', '.join(f'{ln.src}.{ln.src_var} -> {ln.dst}.{ln.dst_var}' for ln in lns)}")
        if any(ln.transformed for ln in lns):
            raise UserError(f"power bond {name}: a bond carries effort and flow unchanged (no factor or offset)")
        to_b, to_a = lns
        a, b = to_b.src, to_a.src
        slot_a = system.inputs[a].index(to_a.dst_var)
        slot_b = system.inputs[b].index(to_b.dst_var)
        bonds.append(Bond(name, (a, b),
                          np.array([system.index[(a, to_b.src_var)], system.index[(b, to_a.src_var)]]),
                          np.array([system.in_off[a] + slot_a, system.in_off[b] + slot_b]), (slot_a, slot_b)))
    return bonds


@dataclass
class BondRecord:
    """Per-bond statistics of a run (``rtol``, ``atol``: the run's tolerances)."""

    rtol: float
    atol: float
    max_scaled: float = 0.0  # largest eps of a step
    max_residual: float = 0.0  # [J] largest |dE| of a step
    residual_sum: float = 0.0  # [J] sum of dE (signed): the energy the coupling created at the bond
    abs_residual_sum: float = 0.0  # [J] sum of |dE|
    energy: float = 0.0  # [J] sum of E: the energy the bond carried
    over: int = 0  # steps with eps > 1

    def add(self, residual: float, carried: float, scaled: float) -> None:
        self.max_scaled = max(self.max_scaled, scaled)
        self.max_residual = max(self.max_residual, abs(residual))
        self.residual_sum += residual
        self.abs_residual_sum += abs(residual)
        self.energy += carried
        self.over += scaled > 1.0

    @property
    def run_scaled(self) -> float:
        """The run's net residual against the same tolerance: ``|sum dE| / (atol + rtol * sum E)``
        (0 for no residual, inf for a residual against a zero tolerance: ``atol`` 0 and no energy)."""
        scale = self.atol + self.rtol * self.energy
        if scale > 0:
            return abs(self.residual_sum) / scale
        return math.inf if self.residual_sum else 0.0

    def as_dict(self) -> dict:
        return {"max_scaled_residual": self.max_scaled, "max_energy_residual_J": self.max_residual,
                "energy_residual_sum_J": self.residual_sum, "abs_energy_residual_sum_J": self.abs_residual_sum,
                "energy_J": self.energy, "run_scaled_residual": self.run_scaled,
                "steps_over_tolerance": self.over}


@dataclass
class EccoStats(AdaptiveStats):
    bonds: dict[str, BondRecord] = field(default_factory=dict)
    order: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {**super().as_dict(), "stepping_order": self.order,
                "bonds": {n: b.as_dict() for n, b in self.bonds.items()}}


class EccoStepper(AdaptiveStepper):
    """The stepping of ``ecco`` (module docstring): adaptive's Gauss-Seidel step with linear inputs,
    never rolled back, its size chosen from the bonds' energy residual; its bonds, statistics and
    endings (the steps: :class:`cosim.master.adaptive_engine.CompiledEcco`)."""

    needs_rollback = False
    #: the compiled loop of exactly this class (:class:`cosim.master.adaptive_engine.CompiledEcco`)
    native_loop = "ecco"

    def __init__(self, system, order: Sequence[int], options: dict[str, float], start_ns: int, stop_ns: int,
                 grid_ns: int = 0):
        super().__init__(system, order, options, start_ns, stop_ns, grid_ns)
        self.bonds = find_bonds(system)
        if not self.bonds:
            raise UserError("master algorithm ecco controls its step from the energy residual of power bonds "
                            "('a.flange <-> b.flange'), and this scene has none; use adaptive, or gauss_seidel "
                            "with a fixed step")
        self.stats = EccoStats(order=[system.slaves[i].name for i in self.order],
                               bonds={b.name: BondRecord(options["rtol"], options["atol"]) for b in self.bonds})
        self._out_idx = np.array([b.out_idx for b in self.bonds])  # (bonds, 2)
        self._in_idx = np.array([b.in_idx for b in self.bonds])
        self.err_prev = options["safety"]
        #: steps in a row over tolerance at h_min after which the run ends as unstable (option floor_steps; 0: never)
        self.patience = int(options.get("floor_steps", 100))

    def _end(self, code: int, bad: int = -1, st: int = 0, value: float = math.nan, count: int = 0) -> None:
        """End the run for end code ``code`` (:class:`cosim.master.entries.EccoEnd`), as its loop
        returned it: ``bad`` the slave (the bond for NOT_FINITE and
        FLOOR_PATIENCE), ``st`` its FMI status; at the floor ``value`` the bond's eps, ``count`` the
        steps over tolerance there."""
        sysm, t = self.system, self.t
        if code == EccoEnd.STOP_REQUESTED:
            self.end("stopped", f"{sysm.slaves[bad].name} asked to terminate the simulation at t = {t:.9g} s")
        elif code == EccoEnd.SLAVE_FAILED:
            sl = sysm.slaves[bad]
            name = Status(st).name if st in Status._value2member_map_ else str(st)
            self.end("failed", f"{sl.name} returned {name} in the step from t = {t:.9g} s (ecco does not roll back)"
                     + (f": {sl.last_message}" if sl.last_message else ""))
        elif code in (EccoEnd.GET_STATE, EccoEnd.SET_STATE):  # (event mode: worded as adaptive's)
            super()._end(code, bad, st)
        elif code == EccoEnd.NOT_FINITE:
            u0 = sysm.v[self._in_idx]
            self.end("unstable", f"the energy residual of bond {self.bonds[bad].name} is not finite in the step from "
                                 f"t = {t:.9g} s (y = {sysm.v[self._out_idx[bad]]}, u = {u0[bad]})")
        else:
            self.end("unstable", f"the energy residual of bond {self.bonds[bad].name} stayed over its tolerance for "
                                 f"{count} steps at the step floor h_min = {self.opt['h_min']:g} s (scaled "
                                 f"{value:.3g} at t = {t:.9g} s)")


@register
class Ecco(MasterAlgorithm):
    """Registry entry of the power-bond master (module docstring): :class:`EccoStepper` driven by
    the one run loop (:func:`cosim.master.algorithms.adaptive.variable_stepper`); its steps are
    never retried, so a run can be paced in real time."""

    name = "ecco"
    variable_step = True
    ends_steps_at_events = True
    event_policy = ("an event of an FMI 3.0 event-mode component is a step boundary for the whole coupling: the "
                    "step is retaken to the event time, then the event iteration (where every component can roll "
                    "back; otherwise events are handled inside each component's steps)")
    options = OPTIONS
    stepper = EccoStepper
    stepper_for = staticmethod(variable_stepper)
