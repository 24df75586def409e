"""Fixed-step Gauss-Seidel: slaves step one after another in a fixed order, each reading the
freshest outputs (conventions in :mod:`cosim.master`; its steps: algorithm code 1 of ``fastloop.c``,
:mod:`cosim.master.fastloop`; its Python twin, the test oracle, in ``tests/oracles/fixed.py``)."""
from __future__ import annotations

from ...slaves.slave import FAILING
from ..algorithm import Algorithm, register


@register
class GaussSeidel(Algorithm):
    """Slaves step one after another in :attr:`order`; each reads the freshest outputs."""

    name = "gauss_seidel"
    native_code = 1
    sequential = True
    multirate = True
    ends_steps_at_events = True
    event_policy = ("a step ends at the earliest event of an FMI 3.0 event-mode component for the whole coupling "
                    "(event-mode components step first where the coupling allows, the ones after an early return only to its "
                    "time; one stepped past it is rolled back to it, or, when it cannot roll back, gets it at the next "
                    "communication point, listed in the sidecar), "
                    "event iteration across the coupling, two trace rows at each event, then the rest of the step; "
                    "other components handle their events inside their steps")

    def _finish_step(self, i, t, h):
        """After slave ``i`` asked to stop (both engines): its outputs, then the slaves after it in order."""
        st = self._io(i, self._pull[i])
        if st in FAILING:
            return i, st
        for j in self.order[self.order.index(i) + 1:]:
            self._gather[j]()
            st = self._io(j, self._push[j])
            if st not in FAILING:
                st = self._advance(j, t, h)
                if st not in FAILING:
                    st = self._io(j, self._pull[j])
            if st in FAILING:
                return j, st
        return None
