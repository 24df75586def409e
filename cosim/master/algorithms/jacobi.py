"""Fixed-step Jacobi: every slave takes its inputs from outputs read at ``t_k``, then all step
(conventions in :mod:`cosim.master`; compiled variant code 0 in :mod:`cosim.master.fastloop`)."""
from __future__ import annotations

from ...slaves.slave import FAILING, Status
from ..algorithm import Algorithm, _ns, register


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

    def _step_impl(self, t, h):
        gather, push, do, pull, acc, calls = (self._gather, self._push, self._do, self._pull, self.slave_ns,
                                               self.calls)
        n = len(do)
        tp = _ns()
        for i in range(n):
            gather[i]()
            st = push[i]()
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING:
                return i, st
        for i in range(n):
            st = do[i](t, h)
            calls[i] += 1
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING or st == Status.STOP_REQUESTED:
                return i, st
        for i in range(n):
            st = pull[i]()
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING:
                return i, st
        return self._exchange() if self.exchange else None

    def _finish_step(self, i, t, h):
        for j in range(i + 1, len(self._do)):
            st = self._advance(j, t, h)
            if st in FAILING:
                return j, st
        for j in range(len(self._pull)):
            st = self._io(j, self._pull[j])
            if st in FAILING:
                return j, st
        return self._exchange()
