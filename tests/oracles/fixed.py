"""The Python twins of the fixed-step kernel (``cosim/master/fastloop.c``: Jacobi, Gauss-Seidel,
Jacobi with extrapolated inputs), a test oracle: each class is the product's algorithm (its state,
the event iteration, the completion after a stop request, the endings' wording: written once,
in ``cosim/``) with the Python steps the kernel's are compared with, bit for bit.  They run through
the product's one seam, a runner (:func:`cosim.master.stepper.python_runner` over
:meth:`cosim.master.algorithm.Algorithm.step`), registered as the engine ``oracle``
(:mod:`oracles`)."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cosim.master.algorithm import MAX_EVENTS_PER_STEP, _ns
from cosim.master.algorithms import gauss_seidel, iterative, jacobi, jacobi_extrapolated
from cosim.master.algorithms.jacobi_extrapolated import WEIGHTS
from cosim.master.stepper import StepResult
from cosim.slaves.slave import FAILING, Status

from .iterative import Iterative


class EventSteps:
    """``Algorithm._event_step`` in Python: a step with FMI 3.0 event-mode slaves, ended at the
    earliest early return (``event_step`` in ``fastloop.c``)."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self._reached: dict[int, float] = {}  # the time [s] each slave reached in the current event step
        self._stops: set[int] = set()  # slaves whose request to stop stands in the current event step

    def _event_step(self) -> bool:
        """:meth:`step` with event-mode slaves: from the current point (a grid point or an event) to
        the next grid point, cut at the earliest time an event-mode slave returned early.  Jacobi
        steps the event-mode slaves first and the others only to that time (:meth:`_events_first`);
        Gauss-Seidel steps in its order, the slaves after an early return only to its time
        (:meth:`_events_in_order`); a slave that stepped past the event is rolled back and stepped
        to it, or (when it cannot roll back) noted in :attr:`late_events` and left at the grid
        point until the others catch up.  A stop request does not cut the step: it ends as any, at
        the grid point or the event, and the run ends there (a request whose doStep is rolled back
        goes with it, the retake decides)."""
        slaves = self.system.slaves
        t, t_end = self.t, self.time_at(self.k + 1)
        h = t_end - t if self.t_event is not None else self.h
        # what may step past an event: under Gauss-Seidel any slave, under Jacobi only the event-mode ones
        may_pass = [i for i in range(len(slaves)) if self.sequential or i in self.event_slaves]
        saved = [i for i in may_pass if slaves[i].can_rollback and i not in self._ahead] \
            if len(self.event_slaves) > 1 or (self.sequential and len(slaves) > 1) else []
        for i in saved:
            slaves[i].save_state()
        self._reached.clear()
        self._stops.clear()
        do = self._do
        if self._ahead:  # they reached the grid point in the step an event cut: they wait there
            self._do = [(lambda _t, _h: Status.OK) if i in self._ahead else f for i, f in enumerate(do)]
        try:
            bad = self._events_in_order(t, h) if self.sequential else self._events_first(t, h)
        finally:
            self._do = do
        if self.status != "running":
            return False
        if bad is not None:
            self._fail(bad[0], bad[1], t)
            return False
        ends = {i: slaves[i].step_end() for i in self.event_slaves if i not in self._ahead}
        tol = 1e-12 * (1.0 + abs(t_end))
        early = sorted((r, i) for i, (r, _) in ends.items() if r < t + h - tol)
        if not early:
            self._events_in_step = 0
            self._ahead.clear()
            if self._stops:
                self.stopped_by(min(self._stops), t)
                return False
            self.k, self.t_event = self.k + 1, None
            asking = [i for i, (_, ev) in ends.items() if ev]
            if asking:
                self.pending_event = StepResult(self.t_ns, True, asking[0], "event")
            return True
        t_e, who = early[0]
        self._events_in_step += 1
        if self._events_in_step > MAX_EVENTS_PER_STEP:
            self.chattering(who, t_e)
            return False
        for j in range(len(slaves)):
            if j == who or j in self._ahead or (j in ends and ends[j][0] <= t_e + tol) or \
                    (j not in ends and self._reached.get(j, t + h) <= t_e + tol):  # stepped only to t_e already
                continue
            if j in saved:  # stepped past the event: back (its inputs with it), and to the event time
                slaves[j].restore_state()
                self._stops.discard(j)
                st = self._advance(j, t, t_e - t)
                if self.stop_requested(j, st):
                    self._stops.add(j)
                elif st in FAILING:
                    self._fail(j, st, t)
                    return False
            else:
                self._ahead.add(j)
                self.late(j, who, t_e, self._reached.get(j, t + h))
        for j in range(len(slaves)):
            st = self._io(j, self._pull[j])
            if st in FAILING:
                self._fail(j, st, t)
                return False
        if self._stops:
            self.stopped_by(min(self._stops), t, t_e)
            return False
        self.t_event = t_e
        self.pending_event = StepResult(self.t_ns, True, who, "event")
        return True

    def _fails_step(self, i: int, st: int) -> bool:
        """True when slave ``i``'s doStep status ``st`` fails the step; a stop request is noted
        (:attr:`_stops`) and the step goes on."""
        if self.stop_requested(i, st):
            self._stops.add(i)
            return False
        return st in FAILING


    def _events_in_order(self, t: float, h: float) -> tuple[int, int] | None:
        """A Gauss-Seidel step with event-mode slaves: in :attr:`order`, each slave from the
        freshest outputs; once an event-mode slave has returned early, the slaves after it step only
        to that time (:attr:`_reached`), so only those before it can have stepped past the event
        (the order puts event-mode slaves first where the coupling allows); ``(slave, status)`` of a
        failing call, or None."""
        slaves, reached, tol = self.system.slaves, t + h, 1e-12 * (1.0 + abs(t + h))
        for i in self.order:
            self._gather[i]()
            st = self._io(i, self._push[i])
            if st in FAILING:
                return i, st
            hi = min(h, reached - t)
            if hi > tol:  # (an event at t itself: nothing to step)
                st = self._advance(i, t, hi)
                if self._fails_step(i, st):
                    return i, st
            self._reached[i] = t + hi
            if i in self.event_slaves and i not in self._ahead:
                reached = min(reached, slaves[i].step_end()[0])
            st = self._io(i, self._pull[i])
            if st in FAILING:
                return i, st
        return None

    def _events_first(self, t: float, h: float) -> tuple[int, int] | None:
        """A Jacobi step with event-mode slaves: every input from the outputs at ``t``, the
        event-mode slaves step first, the others then only to the earliest time one of them
        reached (no rollback needed, nothing late); ``(slave, status)`` of a failing call, or None."""
        slaves, n = self.system.slaves, len(self.system.slaves)
        for i in range(n):
            self._gather[i]()
            st = self._io(i, self._push[i])
            if st in FAILING:
                return i, st
        first = [i for i in self.event_slaves if i not in self._ahead]
        for i in first:
            st = self._advance(i, t, h)
            if self._fails_step(i, st):
                return i, st
        reached = min([slaves[i].step_end()[0] for i in first], default=t + h)
        for i in range(n):
            if i not in first:
                hi = min(h, reached - t)
                if hi > 1e-12 * (1.0 + abs(t + h)):  # (an event at t itself: nothing to step)
                    st = self._advance(i, t, hi)
                    if self._fails_step(i, st):
                        return i, st
                self._reached[i] = t + hi
        for i in range(n):
            st = self._io(i, self._pull[i])
            if st in FAILING:
                return i, st
        return self._exchange() if self.exchange else None


def _parts(alg) -> tuple:
    """An algorithm's per-slave calls and counters, as its step's loops use them."""
    return alg._gather, alg._push, alg._do, alg._pull, alg.slave_ns, alg.calls


class Jacobi(EventSteps, jacobi.Jacobi):
    """Jacobi's Python steps (algorithm code 0 of ``fastloop.c``)."""

    def _step_impl(self, t, h):
        gather, push, do, pull, acc, calls = _parts(self)
        n, last = len(do), [_ns()]

        def timed(i: int, st: int) -> int:  # the wall time since the last call, booked to slave i
            tn = _ns()
            acc[i] += tn - last[0]
            last[0] = tn
            return st
        for i in range(n):
            gather[i]()
            st = timed(i, push[i]())
            if st in FAILING:
                return i, st
        for i in range(n):
            st = timed(i, do[i](t, h))
            calls[i] += 1
            if st in FAILING or st == Status.STOP_REQUESTED:
                return i, st
        for i in range(n):
            st = timed(i, pull[i]())
            if st in FAILING:
                return i, st
        return self._exchange() if self.exchange else None


class GaussSeidel(EventSteps, gauss_seidel.GaussSeidel):
    """Gauss-Seidel's Python steps (algorithm code 1 of ``fastloop.c``)."""

    def _step_impl(self, t, h):
        gather, push, do, pull, acc, calls = _parts(self)
        tp = _ns()
        for i in self.order:
            gather[i]()
            st = push[i]()
            if st not in FAILING:
                st = do[i](t, h)
                calls[i] += 1
                if st not in FAILING and st != Status.STOP_REQUESTED:
                    st = pull[i]()
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING or st == Status.STOP_REQUESTED:
                return i, st
        return None


def extrapolator(buf: np.ndarray) -> Callable[[], None]:
    """A function that replaces the freshly gathered inputs in ``buf`` (the values at ``t_k``) by
    their extrapolated step mean and remembers the gathered ones: call it once per macro step."""
    past: list[np.ndarray] = []  # the gathered values at t_k-1, t_k-2

    def extrapolate() -> None:
        now = buf.copy()
        w = WEIGHTS[len(past)]
        np.multiply(now, w[0], out=buf)
        for wj, u in zip(w[1:], past):
            np.add(buf, wj * u, out=buf)
        past.insert(0, now)
        del past[2:]
    return extrapolate


class JacobiExtrapolated(EventSteps, jacobi_extrapolated.JacobiExtrapolated):
    """Jacobi with extrapolated inputs in Python (algorithm code 3 of ``fastloop.c``): Jacobi's step,
    each dynamic slave's gathered inputs replaced by their extrapolated step mean."""

    _step_impl = Jacobi._step_impl

    def __init__(self, system, step_ns, **kw):
        super().__init__(system, step_ns, **kw)
        exchange = set(self.exchange)
        for i in range(len(system.slaves)):
            if i not in exchange and len(system.in_buf[i]):
                self._gather[i] = self._extrapolating(self._gather[i], extrapolator(system.in_buf[i]))

    @staticmethod
    def _extrapolating(gather: Callable[[], None], extrapolate: Callable[[], None]) -> Callable[[], None]:
        def gather_extrapolated() -> None:
            gather()
            extrapolate()
        return gather_extrapolated


#: the oracle class of each product algorithm with a kernel (the others run their own Python loop)
ORACLES = {jacobi.Jacobi: Jacobi, gauss_seidel.GaussSeidel: GaussSeidel,
           jacobi_extrapolated.JacobiExtrapolated: JacobiExtrapolated, iterative.Iterative: Iterative}


def oracle_algorithm(cls: type) -> type:
    """The class whose Python steps run ``cls``: its oracle, or ``cls`` itself when its Python loop
    is product code (an algorithm registered without a kernel)."""
    if cls in ORACLES:
        return ORACLES[cls]
    if cls.native_code is not None:
        raise LookupError(f"no test oracle for {cls.name} (kernel code {cls.native_code}): add one to ORACLES")
    return cls
