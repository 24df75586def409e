"""Fixed-step Jacobi: every slave takes its inputs from outputs read at ``t_k``, then all step
(conventions in :mod:`cosim.master`; its steps: algorithm code 0 of ``fastloop.c``,
:mod:`cosim.master.fastloop`; its Python twin, the test oracle, in ``tests/oracles/fixed.py``)."""
from __future__ import annotations

from ...slaves.slave import FAILING
from ..algorithm import Algorithm, register


@register
class Jacobi(Algorithm):
    """All slaves take inputs from outputs read at ``t_k``, then all step in parallel (in
    principle), then all outputs are read (see :mod:`cosim.master` for the delay convention); a
    memoryless slave (a ``sum`` block) is then evaluated on them, so it adds no delay."""

    name = "jacobi"
    native_code = 0
    multirate = True
    ends_steps_at_events = True
    event_policy = ("a step ends at the earliest event of an FMI 3.0 event-mode component for the whole coupling "
                    "(the event-mode components step first, the others only to that time), event iteration across "
                    "the coupling, two trace rows at each event, then the rest of the step; other components handle "
                    "their events inside their steps")
    #: needs no stepping order: a cycle of direct feedthrough runs with the one-step coupling delay
    delays_algebraic_loops = True

    def _finish_step(self, i, t, h):
        """After slave ``i`` asked to stop (both engines): the slaves after it step, every output is read."""
        for j in range(i + 1, len(self._do)):
            st = self._advance(j, t, h)
            if st in FAILING:
                return j, st
        for j in range(len(self._pull)):
            st = self._io(j, self._pull[j])
            if st in FAILING:
                return j, st
        return self._exchange()
