"""A stop request (FMI 3.0 terminateSimulation) in a step of jacobi and gauss_seidel with an FMI 3.0
event-mode component (docs/explanation/events.md, "A stop request in a step"): the step ends
as any step, at the grid point or at the event that cut it, and the run ends there.  BouncingBall
(the Reference FMUs) bounces at 0.453 s and returns early once more at 0.454 s (as under FMPy); a
Python lag fed by its velocity asks to stop in its ``at``-th doStep, a Python clock (x = t, exact)
beside them.  Each run against the test oracle bit for bit (tests/oracles/fixed.py), and
independently: the clock's value is the last row's time, the run equals the run without the
request up to that row, and every component took as many doSteps as the lag."""
from __future__ import annotations

import numpy as np
import pytest

from cosim.master import CoupledSystem, Link, simulate
from cosim.slaves.fmu_slave import FmuSlave
from cosim.slaves.linear import LinearSlave
from cosim.slaves.slave import Status
from cosim.trace.traces import MemoryTrace

FIXED = ("jacobi", "gauss_seidel")
STEP_NS, N_STEPS = 10_000_000, 60
#: the lag's doStep that asks to stop -> (the step's start, where it ends) [s]: the step the bounce
#: cuts; the step from the bounce, cut by the ball's second early return; the step from that event
#: to the grid point; an ordinary step
STOPS = {46: (0.45, 0.453), 47: (0.453, 0.454), 48: (0.454, 0.46), 50: (0.47, 0.48)}


class Stopping(LinearSlave):
    """Asks to stop the simulation in its ``at``-th doStep (after taking it)."""

    at = 0

    def do_step(self, t, h):
        self.steps = getattr(self, "steps", 0) + 1
        st = super().do_step(t, h)
        return Status.STOP_REQUESTED if self.steps == self.at else st


class StoppingBall(FmuSlave):
    """BouncingBall called back through Python (no C entry points) that asks to stop in its
    ``at``-th doStep, as an FMU setting terminateSimulation there would."""

    at = 0

    def native(self):
        return None

    def do_step(self, t, h):
        self.steps = getattr(self, "steps", 0) + 1
        st = super().do_step(t, h)
        return Status.STOP_REQUESTED if self.steps == self.at else st


def _system(ball: str, at: int = 0, ball_first: bool = True, ball_at: int = 0,
            lag_cls: type = Stopping) -> CoupledSystem:
    """The ball's velocity into a lag (x' = -2 x + u, a ``lag_cls``) asking to stop in its
    ``at``-th doStep (0: never), and a clock (x1 = t); ``ball_first``: the ball is slave 0 (else
    the lag is, and the ball 1); ``ball_at``: the ball asks to stop in that doStep."""
    lag = type("Lag", (lag_cls,), {"at": at})("lag", [[-2.0]], [[1.0]], [[1.0]], x0=[0.0])
    clock = LinearSlave("clock", [[0.0, 1.0], [0.0, 0.0]], [[0.0], [0.0]], [[1.0, 0.0]], x0=[0.0, 1.0])
    b = type("Ball", (StoppingBall,), {"at": ball_at})("ball", ball) if ball_at else FmuSlave("ball", ball)
    slaves = [b, lag, clock] if ball_first else [lag, b, clock]
    bi, li = (0, 1) if ball_first else (1, 0)
    return CoupledSystem(slaves, [Link(bi, "v", li, "u[1]")], [(bi, "h"), (bi, "v"), (li, "x[1]"), (2, "x[1]")])


def _run(system: CoupledSystem, algorithm: str, engine: str, **kw):
    mem = MemoryTrace()
    stats = simulate(system, algorithm, step_ns=STEP_NS, n_steps=N_STEPS, observers=[mem], engine=engine, **kw)
    assert stats.engine == engine
    return mem.trace, stats


def _calls(stats) -> dict[str, int]:
    return {k: s["do_step_calls"] for k, s in stats.slaves.items()}


def _both(make, algorithm: str, **kw):
    """The oracle's and the kernel's run of a fresh ``make()`` each, asserted bit for bit alike."""
    (py, s1), (cc, s2) = (_run(make(), algorithm, e, **kw) for e in ("oracle", "compiled"))
    assert (s1.status, s1.reason, s1.steps_done) == (s2.status, s2.reason, s2.steps_done)
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    assert s1.extra.get("events") == s2.extra.get("events") and _calls(s1) == _calls(s2)
    return cc, s2


def _assert_prefix_of_the_free_run(ball: str, algorithm: str, cc, end: float, order=None, **kw) -> None:
    """The stopped run's rows are the run without a stop request (``kw``: its system, ``order``:
    the stepping order) up to its row at ``end`` (at an event: the left limit), bit for bit, and
    the clock there reads ``end``."""
    free, fs = _run(_system(ball, **kw), algorithm, "compiled", order=order)
    assert fs.status == "ok", fs.reason
    m = int(np.flatnonzero(np.isclose(free.time, end, rtol=0, atol=1e-12))[0]) + 1
    assert np.array_equal(cc.time, free.time[:m]) and np.array_equal(cc.data, free.data[:m])
    assert cc["clock.x[1]"][-1] == pytest.approx(end, rel=0, abs=1e-12)
    assert np.allclose(cc["clock.x[1]"], cc.time, rtol=0, atol=1e-12)  # every row: the clock at its time


@pytest.mark.parametrize("algorithm", FIXED)
@pytest.mark.parametrize("ball_first", [True, False])
@pytest.mark.parametrize("at", sorted(STOPS))
def test_a_stop_request_ends_the_run_where_its_step_ends(reference_fmus, algorithm, ball_first, at):
    """The run ends where the step the lag asked in ends, every component there (the clock reads
    the row's time), the row stamped with it, the message naming it and the step's start; no
    component stepped twice or past it, whichever is slave 0."""
    ball = str(reference_fmus["3.0/BouncingBall"])
    start, end = STOPS[at]
    cc, st = _both(lambda: _system(ball, at, ball_first), algorithm)
    assert st.status == "stopped" and st.reason.startswith(
        f"stopped by lag at t = {end:g} s: it asked to terminate the simulation in the step from t = {start:g} s"), \
        st.reason
    assert cc.time[-1] == pytest.approx(end, rel=0, abs=1e-12) and cc.time[-2] < cc.time[-1]  # one row: left limit
    assert st.steps_done == round(end * 1e9) // STEP_NS  # grid steps completed (a cut one is not)
    assert _calls(st) == {"ball": at, "lag": at, "clock": at}  # each component once in every step taken
    _assert_prefix_of_the_free_run(ball, algorithm, cc, end, ball_first=ball_first)


@pytest.mark.parametrize("at,status", [(46, "ok"), (47, "stopped")])
def test_a_stop_request_rolled_back_with_its_step_goes_with_it(reference_fmus, at, status):
    """Gauss-Seidel in the order lag, ball, clock: the lag steps over the whole step from 0.45 s
    (its 46th doStep), the bounce at 0.453 s cuts it, and the lag is rolled back and stepped to the
    bounce (its 47th).  A request in the 46th goes with the step rolled back (the run goes on, equal
    to the run without it); one in the retake ends the run at the bounce."""
    ball = str(reference_fmus["3.0/BouncingBall"])
    cc, st = _both(lambda: _system(ball, at), "gauss_seidel", order=[1, 0, 2])
    assert st.status == status, st.reason
    free, fs = _run(_system(ball), "gauss_seidel", "compiled", order=[1, 0, 2])
    if status == "ok":
        assert np.array_equal(cc.time, free.time) and np.array_equal(cc.data, free.data)
        assert _calls(st) == _calls(fs)
        return
    assert st.reason.startswith("stopped by lag at t = 0.453 s: it asked to terminate the simulation in the step "
                                "from t = 0.45 s"), st.reason
    assert _calls(st) == {"ball": 46, "lag": 47, "clock": 46}  # the lag's retake, nothing else twice
    _assert_prefix_of_the_free_run(ball, "gauss_seidel", cc, 0.453, order=[1, 0, 2])


@pytest.mark.parametrize("algorithm", FIXED)
@pytest.mark.parametrize("at", [46, 48])
def test_a_stop_request_of_the_event_mode_component_ends_the_run_where_its_step_ends(reference_fmus, algorithm, at):
    """The ball itself asks to stop: in the step its bounce cuts (it returned early at 0.453 s:
    the run ends there) or in the step from its second early return to the grid point."""
    ball = str(reference_fmus["3.0/BouncingBall"])
    start, end = STOPS[at]
    cc, st = _both(lambda: _system(ball, ball_at=at), algorithm)
    assert st.status == "stopped" and st.reason.startswith(
        f"stopped by ball at t = {end:g} s: it asked to terminate the simulation in the step from t = {start:g} s"), \
        st.reason
    assert _calls(st) == {"ball": at, "lag": at, "clock": at}
    _assert_prefix_of_the_free_run(ball, algorithm, cc, end)


class Fixed(Stopping):
    """The lag without rollback (as hardware or an FMU without state)."""

    can_rollback = property(lambda self: False)


def test_a_late_component_stays_at_the_grid_point_and_is_noted_when_the_run_ends_at_the_event(reference_fmus):
    """Gauss-Seidel in the order lag, ball, clock, the lag unable to roll back: it steps over the
    whole step from 0.45 s and asks to stop there (its 46th doStep); the bounce cuts the step at
    0.453 s, where the run ends (the ball and the clock there), the lag late at 0.46 s and noted so,
    as at any event."""
    ball = str(reference_fmus["3.0/BouncingBall"])
    cc, st = _both(lambda: _system(ball, 46, lag_cls=Fixed), "gauss_seidel", order=[1, 0, 2])
    assert st.status == "stopped" and st.reason.startswith(
        "stopped by lag at t = 0.453 s: it asked to terminate the simulation in the step from t = 0.45 s"), st.reason
    assert [(e["component"], e["event_of"], e["t"], e["reached"]) for e in st.extra["events"]["late"]] == \
        [("lag", "ball", pytest.approx(0.453, abs=1e-12), pytest.approx(0.46, abs=1e-12))]
    assert _calls(st) == {"ball": 46, "lag": 46, "clock": 46}
    _assert_prefix_of_the_free_run(ball, "gauss_seidel", cc, 0.453, order=[1, 0, 2], lag_cls=Fixed)
