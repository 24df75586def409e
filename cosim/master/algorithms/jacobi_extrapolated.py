"""Fixed-step Jacobi with second-order input extrapolation: each slave's inputs over the step
``t_k -> t_k+1`` are held at the mean, over that step, of the quadratic through the values its
sources gave at ``t_k-2``, ``t_k-1`` and ``t_k`` (docs/how-to/add-an-algorithm.md).

That mean is ``(23 u_k - 16 u_k-1 + 5 u_k-2) / 12`` (the Adams-Bashforth 3 weights: the
integral of the extrapolating quadratic over the next step), ``(3 u_k - u_k-1) / 2`` at the
second step and ``u_k`` at the first.  A held input equal to the step mean of the true input to
O(h^3) leaves a local error of O(h^3) in the states, so the coupling converges at order 2 where
plain Jacobi (``inputs: hold``, the input's value at ``t_k``) converges at order 1, with no input
derivatives: it also serves FMUs that cannot interpolate their inputs (``inputs: linear`` needs
``canInterpolateInputs``).

Its steps: algorithm code 3 of ``fastloop.c`` (the gathered inputs' last two values kept per slave,
``past``); its Python twin, the test oracle, in ``tests/oracles/fixed.py``."""
from __future__ import annotations

from ...errors import UserError
from ..algorithm import register
from .jacobi import Jacobi

#: weights of u_k, u_k-1, u_k-2 in the held input, by how many past values there are (1, 2, 3)
WEIGHTS = ((1.0,), (1.5, -0.5), (23 / 12, -16 / 12, 5 / 12))


@register
class JacobiExtrapolated(Jacobi):
    """Jacobi (:class:`cosim.master.algorithms.jacobi.Jacobi`: all inputs from the outputs at
    ``t_k``, then all slaves step) with each dynamic slave's inputs extrapolated to their step mean
    (module docstring); memoryless slaves (evaluated within the exchange) take their inputs as
    they are.  Inputs held (``inputs: hold``); one rate; FMI 3.0 events inside the steps."""

    name = "jacobi_extrapolated"
    native_code = 3  # fastloop.c: Jacobi's push with extrapolate()
    multirate = False
    ends_steps_at_events = False
    event_policy = ("events are handled inside each component's steps and reach the others at the next "
                    "communication point (FMI 3.0 event mode not used); an input's extrapolation runs across them")

    def __init__(self, system, step_ns, **kw):
        if kw.get("inputs", "hold") != "hold":
            raise UserError(f"master algorithm {self.name} extrapolates the inputs itself: use inputs: hold, "
                            f"not {kw['inputs']!r}")
        super().__init__(system, step_ns, **kw)
