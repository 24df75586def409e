"""FMI 3.0 event mode in iterative's kernel (cosim/master/iterative_engine.c, ``event_step``): a step
cut at the earliest early return of an event-mode FMU, every component rolled back through its FMU
state (a callback slave through its own save_state/restore_state) and the coupling iterated again
to the event time; the kernel returns ``FixedEnd.EVENT`` (``GRID_EVENT`` at a grid point,
``CHATTERING``), the one ``EventIteration`` runs in Python.  Each scene against the Python loop
(``Iterative._event_step``) bit for bit: times, values, events, doStep counts, passes, rollbacks,
Jacobians, the ending and its message.  Beside them the independent checks: the pendulum's impacts
at their analytic times, the coupled component's value at each event the event-mode one's, the
start-time iteration's values against the loop solved by hand."""
from __future__ import annotations

import numpy as np
import pytest

from cosim.master import CoupledSystem, Link, simulate
from cosim.slaves.fmu_slave import FmuSlave
from cosim.slaves.linear import LinearSlave
from cosim.slaves.slave import Status
from cosim.trace.traces import MemoryTrace
from engine_pair import assert_same as assert_pair
from engine_pair import both

#: the iteration's own statistics, equal in both engines
ITER_KEYS = ("iterations_mean", "iterations_max", "iterations_total", "start_iterations", "rollbacks", "jacobians",
             "directional_derivatives", "finite_difference_steps", "broyden_updates", "cut_connections")


def assert_same(py, cc) -> None:
    """What tests/engine_pair.py compares, and the iteration's statistics."""
    assert_pair(py, cc)
    assert [py.stats.get(k) for k in ITER_KEYS] == [cc.stats.get(k) for k in ITER_KEYS]
    assert py.stats["engine"] == "oracle" and cc.stats["engine"] == "compiled"


def _events(t: np.ndarray) -> np.ndarray:
    """The times written twice (left and right limit of an event)."""
    return t[1:][np.diff(t) == 0]


def _ball_feeding(reference_fmus, stop: float, **feedthrough) -> dict:
    """BouncingBall's velocity into Feedthrough (``f``, its settings ``feedthrough``) to ``stop`` [s]."""
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/Feedthrough"]), **feedthrough}}
    return {"name": "pair", "components": comps, "connections": ["ball.v -> f.Float64_continuous_input"],
            "stop_time": stop, "outputs": ["ball.v", "f.Float64_continuous_output"]}


@pytest.mark.parametrize("model,step,outputs", [("BouncingBall", 0.01, ["h", "v"]), ("Stair", 0.2, ["counter"])])
def test_one_event_mode_fmu_equals_the_python_loop(reference_fmus, model, step, outputs):
    """BouncingBall's bounces cut the steps; Stair's time events fall on grid points (the step
    reaches the grid point and the kernel returns ``GRID_EVENT``) until it asks to stop in its
    event iteration at 9 s."""
    scene = {"name": "ev", "components": {"m": {"fmu": str(reference_fmus[f"3.0/{model}"])}},
             "outputs": [f"m.{o}" for o in outputs]}
    py, cc = both(scene, algorithm="iterative", step=step)
    assert_same(py, cc)
    assert cc.status == {"BouncingBall": "ok", "Stair": "stopped"}[model], cc.reason
    assert cc.stats["events"]["handled"] == {"BouncingBall": 24, "Stair": 9}[model] == len(_events(cc.trace.time))
    if model == "Stair":  # every event on the grid: no step cut
        assert np.allclose(_events(cc.trace.time), np.arange(1.0, 10.0), rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", ["newton", "fixed_point"])
def test_a_coupled_fmu_rolled_back_to_the_event_equals_the_python_loop(reference_fmus, method):
    """Feedthrough fed by the ball, stepped past each bounce in the first iteration: both rolled
    back through their FMU states and the coupling iterated again to the bounce."""
    py, cc = both(_ball_feeding(reference_fmus, 1.2), algorithm="iterative", options={"method": method})
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["handled"] == 4 and cc.stats["events"]["late"] == []
    t, v, y = cc.trace.time, cc.trace["ball.v"], cc.trace["f.Float64_continuous_output"]
    assert np.array_equal(y, v)  # the coupling at every row, the event's right limit included


def test_two_event_mode_fmus_roll_back_to_the_earlier_event(reference_fmus):
    """Two balls dropped from different heights: each bounce cuts the step for both."""
    ball = str(reference_fmus["3.0/BouncingBall"])
    comps = {"a": {"fmu": ball}, "b": {"fmu": ball, "start": {"h": 0.6}}}
    scene = {"name": "two", "components": comps, "stop_time": 1.5, "outputs": ["a.h", "a.v", "b.h", "b.v"]}
    py, cc = both(scene, algorithm="iterative")
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["handled"] == len(_events(cc.trace.time)) >= 4


@pytest.mark.parametrize("options", [{}, {"method": "fixed_point", "omega": 0.8}, {"jacobian": "finite_difference"}])
def test_events_in_a_loop_of_event_mode_fmus_equal_the_python_loop(lag_fmus, options):
    """Two event-mode lags in a loop (one cut connection, iterated), fault 2 in one: an event at each
    of its solver steps from 0.5 s, both rolled back to each and the loop iterated again."""
    fmu = str(lag_fmus["3cs"])
    comps = {"a": {"fmu": fmu, "params": {"k": 1.0, "g": -1.0, "fault": 2}, "start": {"x": 1.0}},
             "b": {"fmu": fmu, "params": {"k": 2.0, "g": 1.0}}}
    scene = {"name": "loop", "components": comps, "connections": ["a.x -> b.u", "b.x -> a.u"], "stop_time": 0.52,
             "outputs": ["a.x", "b.x"]}
    py, cc = both(scene, algorithm="iterative", options=options)
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["handled"] > 100, cc.reason
    assert cc.stats["cut_connections"] and cc.stats["rollbacks"] > 0


@pytest.mark.parametrize("fault,step,status,says", [
    (2, 0.05, "failed", "more than 1000 events in the step from t = 0.5 s (chattering)"),
    (3, 0.01, "event_iteration_failed", "did not settle in 100 rounds"),
    (1, 0.01, "unstable", "")])
def test_a_misbehaving_event_mode_fmu_ends_the_kernels_run_as_the_python_loops(lag_fmus, fault, step, status, says):
    """tests/data/me_lag as an FMI 3.0 event-mode FMU: chattering (the kernel's FX_CHATTERING, the
    message Algorithm.chattering's), an event iteration that does not settle, a NaN state the
    guard stops."""
    scene = {"name": "hostile", "components": {"a": {"fmu": str(lag_fmus["3cs"]), "params": {"fault": fault},
                                                     "start": {"x": 1.0}}},
             "stop_time": 1.0, "outputs": ["a.x"]}
    py, cc = both(scene, algorithm="iterative", step=step)
    assert_same(py, cc)
    assert cc.status == status and says in cc.reason, cc.reason


@pytest.mark.parametrize("first", ["a", "b"])
def test_of_two_events_at_the_same_time_the_first_components_is_taken(lag_fmus, first):
    """Two identical lags with fault 2, uncoupled: their events fall at the same instants from 0.5 s;
    the step ends at the first one's in the slaves' order (Python's sorted (time, slave)), which the
    chattering message names."""
    lag = {"fmu": str(lag_fmus["3cs"]), "params": {"fault": 2}, "start": {"x": 1.0}}
    names = [first, "b" if first == "a" else "a"]
    scene = {"name": "twins", "components": {n: dict(lag) for n in names}, "stop_time": 1.0, "outputs": ["a.x", "b.x"]}
    py, cc = both(scene, algorithm="iterative", step=0.05)
    assert_same(py, cc)
    assert cc.status == "failed" and cc.reason.startswith(f"{first}: more than 1000 events"), cc.reason


def test_a_callback_fmu_rolls_back_through_its_own_state_as_in_the_python_loop(reference_fmus):
    """Feedthrough with its Int32 output recorded is a callback slave (typed ports), stepped before
    the ball: restored through the trampolines around its own save_state/restore_state."""
    scene = _ball_feeding(reference_fmus, 1.2, start={"Int32_input": 7})
    scene["outputs"].append("f.Int32_output")
    py, cc = both(scene, algorithm="iterative", order=["f", "ball"])
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["handled"] == 4 and np.all(cc.trace["f.Int32_output"] == 7)


def test_an_output_interval_longer_than_the_step_keeps_every_event_row_as_in_the_python_loop(reference_fmus):
    """Rows every 5th step, and two at each event whatever the grid."""
    py, cc = both(_ball_feeding(reference_fmus, 2.0), algorithm="iterative", output_interval=0.05)
    assert_same(py, cc)
    t = cc.trace.time
    grid = t[np.abs(t * 20 - np.round(t * 20)) < 1e-9]
    assert np.array_equal(np.unique(grid), np.round(np.arange(0, 2.0001, 0.05), 9))
    assert int((np.diff(t) == 0).sum()) == cc.stats["events"]["handled"] >= 4


# --- Python slaves beside an event-mode FMU (callback slaves, simulate's API) -------------------------------

class Failing(LinearSlave):
    """Returns Error (or, ``stop``, asks to end the simulation) in its ``at``-th doStep."""

    at, stop = 0, False

    def do_step(self, t, h):
        self.steps = getattr(self, "steps", 0) + 1
        st = super().do_step(t, h)
        if self.steps == self.at:
            return Status.STOP_REQUESTED if self.stop else Status.ERROR
        return st


def _ball_and_lag(ball: str, cls=LinearSlave) -> CoupledSystem:
    """The ball's velocity into a first-order lag (a Python slave): x' = -2 x + u."""
    lag = cls("lag", [[-2.0]], [[1.0]], [[1.0]], x0=[0.0])
    return CoupledSystem([FmuSlave("ball", ball), lag], [Link(0, "v", 1, "u[1]")],
                         [(0, "h"), (0, "v"), (1, "x[1]")])


def _simulate(system: CoupledSystem, engine: str, n: int = 60, **kw):
    mem = MemoryTrace()
    stats = simulate(system, "iterative", step_ns=10_000_000, n_steps=n, observers=[mem], engine=engine, **kw)
    return mem.trace, stats


def test_a_python_slave_is_rolled_back_to_the_event_as_in_the_python_loop(reference_fmus):
    runs = [_simulate(_ball_and_lag(str(reference_fmus["3.0/BouncingBall"])), e) for e in ("oracle", "compiled")]
    (py, s1), (cc, s2) = runs
    assert (s1.engine, s2.engine, s2.status) == ("oracle", "compiled", "ok"), s2.reason
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    # the bounce, and the FMU's second early return a step of its own later (as under FMPy)
    assert list(_events(cc.time)) == pytest.approx([0.453, 0.454]) and s2.extra["events"]["handled"] == 2
    assert {k: s1.extra[k] for k in ITER_KEYS} == {k: s2.extra[k] for k in ITER_KEYS}
    assert [s["do_step_calls"] for s in s1.slaves.values()] == [s["do_step_calls"] for s in s2.slaves.values()]


@pytest.mark.parametrize("stop", [False, True])
@pytest.mark.parametrize("at,start,end", [(46, 0.45, None), (47, 0.45, 0.453), (50, 0.454, 0.46)])
def test_a_failing_or_stopping_python_slave_around_an_event_ends_the_run_as_the_python_loop(reference_fmus, at, start,
                                                                                          end, stop):
    """The lag's 46th doStep is its first over the step the bounce cuts (from 0.45 s), its 47th the
    one retaken to the bounce at 0.453 s, its 50th the rest of the step after the ball's second
    early return at 0.454 s (its 48th and 49th: the step from the bounce, cut there).  An Error there
    fails the run (Algorithm._fail's message, the step's start).  A stop request completes the
    step being iterated and ends the run where that step ends (the retaken one at the event, not
    completed: Iterative.stopped_by), the row there; in the 46th it goes with the step the bounce
    cuts (the retake, where this lag does not ask again, decides: the run goes on)."""
    out = []
    for engine in ("oracle", "compiled"):
        cls = type("F", (Failing,), {"at": at, "stop": stop})
        out.append(_simulate(_ball_and_lag(str(reference_fmus["3.0/BouncingBall"]), cls), engine))
    (py, s1), (cc, s2) = out
    assert s2.engine == "compiled" and (s1.status, s1.reason) == (s2.status, s2.reason)
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    assert {k: s1.extra[k] for k in ITER_KEYS} == {k: s2.extra[k] for k in ITER_KEYS}
    if stop and end is None:
        assert s2.status == "ok" and s2.steps_done == 60 and s2.extra["events"]["handled"] == 2, s2.reason
    elif stop:
        assert s2.steps_done == (46 if end == 0.46 else 45)
        assert s2.status == "stopped" and s2.reason.startswith(f"stopped by lag at t = {end:g} s: it asked to "
                                                               f"terminate the simulation in the step from t = "
                                                               f"{start:g} s"), s2.reason
        assert cc.time[-1] == pytest.approx(end, abs=1e-12) and cc.time[-2] < cc.time[-1]
    else:
        assert s2.status == "failed" and f"lag returned ERROR in the step from t = {start:g} s (step 45)" in s2.reason


# --- independent checks -----------------------------------------------------------------------------------

def test_our_fmu_checks_the_kernels_calling_sequence_and_bounces_at_the_analytic_times(reference_fmus, cache):
    """The catalog's pendulum against a stop as an FMI 3.0 event-mode FMU (ours check the calling
    sequence: a communication point that does not follow the previous one, or a step after a
    restored state that does not start at its time, returns Error) beside BouncingBall and a
    Feedthrough fed by the pendulum's angle: each event cuts the others' step, every one rolled
    back and the coupling iterated again to it.  The pendulum's impacts are at their analytic
    times (elliptic integrals, tests/test_events.py) among the events to 1e-9 s, and the
    Feedthrough carries the angle at every row, the events' both limits included."""
    from test_events import analytic_impacts

    from fmus import build_fmu
    from models.blocks import make

    pendulum = build_fmu(make("pendulum", "stop"), fmi_version="3.0", cache_dir=cache)
    comps = {"p": {"fmu": str(pendulum)}, "ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/Feedthrough"])}}
    scene = {"name": "bounce", "components": comps, "stop_time": 2.5,
             "connections": ["p.theta -> f.Float64_continuous_input"],
             "outputs": ["p.state.theta", "p.theta", "ball.h", "f.Float64_continuous_output"]}
    py, cc = both(scene, algorithm="iterative")
    assert_same(py, cc)
    assert cc.status == "ok", cc.reason
    events = _events(cc.trace.time)
    impacts = analytic_impacts(5)
    impacts = impacts[impacts < 2.5]
    assert len(impacts) >= 3 and len(events) > len(impacts) and cc.stats["events"]["late"] == []
    assert np.all(np.min(np.abs(events[None, :] - impacts[:, None]), axis=1) < 1e-9)
    assert np.array_equal(cc.trace["f.Float64_continuous_output"], cc.trace["p.theta"])
    assert np.array_equal(cc.trace["p.theta"], cc.trace["p.state.theta"])


D_A, D_B, A_, B_, C_ = 0.5, 0.4, 1.0, 2.0, 0.7


def _loop(f: float, o: float) -> CoupledSystem:
    """An algebraic loop through a transformed connection: y_a = x_a + d_a u_a, y_b = c x_b + d_b u_b,
    u_b = f y_a + o, u_a = y_b; x_a(0) = 1, x_b(0) = -0.5 (the start inconsistent with u = 0)."""
    a = LinearSlave("a", [[-A_]], [[1.0]], [[1.0]], [[D_A]], x0=[1.0])
    b = LinearSlave("b", [[-B_]], [[1.0]], [[C_]], [[D_B]], x0=[-0.5])
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]", factor=f, offset=o), Link(1, "y[1]", 0, "u[1]")],
                         [(0, "u[1]"), (1, "u[1]"), (0, "y[1]"), (1, "y[1]")])


@pytest.mark.parametrize("inputs", ["hold", "linear"])
@pytest.mark.parametrize("options", [{}, {"method": "fixed_point", "omega": 0.9},
                                     {"jacobian": "finite_difference"}])
def test_the_kernels_start_iteration_equals_the_python_one_and_solves_the_loop(options, inputs):
    """The start-time iteration is the kernel's (``rpr_iter_start``, nothing stepped): the first row
    bit for bit the Python loop's, as many passes and Jacobians, and the steps after it (linear
    inputs start their line from the inputs it left); and, independently, the loop solved by hand
    at t = 0: u_a = (c x_b + d_b (f x_a + o)) / (1 - d_a d_b f), u_b = f (x_a + d_a u_a) + o."""
    f, o = -1.5, 0.25
    (py, s1), (cc, s2) = (_simulate(_loop(f, o), e, n=5, options=options, inputs=inputs)
                          for e in ("oracle", "compiled"))
    assert s2.engine == "compiled" and s2.status == "ok", s2.reason
    assert np.array_equal(py.data[0], cc.data[0]) and np.array_equal(py.data, cc.data)
    assert {k: s1.extra[k] for k in ITER_KEYS} == {k: s2.extra[k] for k in ITER_KEYS}
    assert s2.extra["start_iterations"] > 1  # the start was iterated, not taken as it came
    ua = (C_ * -0.5 + D_B * (f * 1.0 + o)) / (1.0 - D_A * D_B * f)
    ub = f * (1.0 + D_A * ua) + o
    np.testing.assert_allclose(cc.data[0, 1:3], [ua, ub], rtol=1e-7, atol=1e-9)


def test_a_start_that_does_not_converge_ends_both_engines_alike():
    """One fixed-point pass allowed: the inconsistent start ends the run as unstable, worded once
    (Iterative._unstable: 'at the start time')."""
    runs = [_simulate(_loop(-1.5, 0.25), e, n=5, options={"method": "fixed_point", "max_iter": 1})
            for e in ("oracle", "compiled")]
    (py, s1), (cc, s2) = runs
    assert s1.status == s2.status == "unstable" and s1.reason == s2.reason, (s1.reason, s2.reason)
    assert "at the start time t = 0 s" in s2.reason and s2.engine == "compiled"
    assert np.array_equal(py.data, cc.data) and s1.extra["start_iterations"] == s2.extra["start_iterations"] == 1


def test_engine_auto_runs_event_mode_scenes_in_the_kernel(reference_fmus):
    """``master.engine`` auto (the default) and compiled choose the kernel for an event-mode scene,
    its components in event mode (the sidecar lists them)."""
    from cosim.run.execute import run
    from cosim.scenario import from_dict

    scene = _ball_feeding(reference_fmus, 0.5)
    for engine in ("auto", "compiled"):
        res = run(from_dict({**scene, "master": {"algorithm": "iterative", "step": 0.01, "estimate": False,
                                                 "engine": engine}}))
        assert res.status == "ok" and res.stats["engine"] == "compiled", res.reason
        assert res.stats["events"]["event_mode"] == ["ball", "f"] and res.stats["events"]["handled"] == 2
