"""FMI 3.0 event mode in the fixed-step kernel (cosim/master/fastloop.c, ``event_step``): a step
ends at the earliest early return of an event-mode FMU, the kernel returns ``FX_EVENT``, the one
``EventIteration`` runs in Python and the kernel goes on with the rest of the step.  Each scene
against the Python loop bit for bit (times, values, events, late events, doStep counts, the
ending and its message), beside the independent checks of tests/test_event_mode.py (FMPy event
for event, the coupled FMU at the event's time) that run on this kernel now."""
from __future__ import annotations

import numpy as np
import pytest

from cosim.run.execute import run
from cosim.scenario import from_dict
from engine_pair import assert_same, both

FIXED = ("jacobi", "gauss_seidel")

@pytest.mark.parametrize("algorithm", FIXED)
@pytest.mark.parametrize("model,step,outputs", [("BouncingBall", 0.01, ["h", "v"]), ("Stair", 0.2, ["counter"])])
def test_one_event_mode_fmu_equals_the_python_loop(reference_fmus, algorithm, model, step, outputs):
    scene = {"name": "ev", "components": {"m": {"fmu": str(reference_fmus[f"3.0/{model}"])}},
             "outputs": [f"m.{o}" for o in outputs]}
    py, cc = both(scene, algorithm=algorithm, step=step)
    assert_same(py, cc)
    assert cc.stats["events"]["handled"] == {"BouncingBall": 24, "Stair": 9}[model]


@pytest.mark.parametrize("algorithm", FIXED)
def test_a_coupled_fmu_rolled_back_to_the_event_equals_the_python_loop(reference_fmus, algorithm):
    """Feedthrough, fed by the ball, stepped past a bounce (Gauss-Seidel) is restored through its
    FMU state and stepped to the bounce; under Jacobi it steps only to the bounce."""
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/Feedthrough"])}}
    scene = {"name": "pair", "components": comps, "connections": ["ball.v -> f.Float64_continuous_input"],
             "stop_time": 1.2, "outputs": ["ball.v", "f.Float64_continuous_output"]}
    py, cc = both(scene, algorithm=algorithm)
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["handled"] == 4


@pytest.mark.parametrize("order", [["f", "ball"], ["ball", "f"]])
def test_a_component_that_cannot_roll_back_is_late_as_in_the_python_loop(reference_fmus, order):
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/VanDerPol"]), "rollback": False}}
    scene = {"name": "late", "components": comps, "stop_time": 0.6, "outputs": ["ball.h", "f.x0"]}
    py, cc = both(scene, algorithm="gauss_seidel", order=order)
    assert_same(py, cc)
    late = cc.stats["events"]["late"]
    assert [(e["component"], e["event_of"]) for e in late] == ([("f", "ball")] if order[0] == "f" else [])


@pytest.mark.parametrize("algorithm", FIXED)
def test_two_event_mode_fmus_roll_back_to_the_earlier_event(reference_fmus, algorithm):
    """Two balls dropped from different heights: each bounce cuts the step for both; the one that
    stepped past the other's bounce is restored through its FMU state (under Jacobi as well: two
    event-mode components step first)."""
    ball = str(reference_fmus["3.0/BouncingBall"])
    comps = {"a": {"fmu": ball}, "b": {"fmu": ball, "start": {"h": 0.6}}}
    scene = {"name": "two", "components": comps, "stop_time": 1.5, "outputs": ["a.h", "a.v", "b.h", "b.v"]}
    py, cc = both(scene, algorithm=algorithm)
    assert_same(py, cc)
    t = cc.trace.time
    assert cc.stats["events"]["handled"] == int((np.diff(t) == 0).sum()) >= 4


@pytest.mark.parametrize("fault,step,status", [(2, 0.05, "failed"), (3, 0.01, "event_iteration_failed"),
                                               (1, 0.01, "unstable")])
def test_a_misbehaving_event_mode_fmu_ends_the_kernels_run_as_the_python_loops(lag_fmus, fault, step, status):
    """tests/data/me_lag as an FMI 3.0 event-mode FMU: chattering (more than 1000 events in a step:
    the kernel's FX_CHATTERING, the message written once), an event iteration that does not settle,
    a NaN state the guard stops."""
    scene = {"name": "hostile", "components": {"a": {"fmu": str(lag_fmus["3cs"]), "params": {"fault": fault},
                                                     "start": {"x": 1.0}}},
             "stop_time": 1.0, "outputs": ["a.x"]}
    py, cc = both(scene, algorithm="jacobi", step=step)
    assert_same(py, cc)
    assert cc.status == status


def test_events_in_a_coupled_loop_of_event_mode_fmus_equal_the_python_loop(lag_fmus):
    """Two event-mode lags in a loop (tests/data/me_lag's FMI3cs), fault 2 in one: an event at each of
    its solver steps from 0.5 s, the other rolled back to each (Gauss-Seidel) or stepped only to it
    (Jacobi)."""
    fmu = str(lag_fmus["3cs"])
    comps = {"a": {"fmu": fmu, "params": {"k": 1.0, "g": -1.0, "fault": 2}, "start": {"x": 1.0}},
             "b": {"fmu": fmu, "params": {"k": 2.0, "g": 1.0}}}
    scene = {"name": "loop", "components": comps, "connections": ["a.x -> b.u", "b.x -> a.u"], "stop_time": 0.52,
             "outputs": ["a.x", "b.x"]}
    for algorithm in FIXED:
        py, cc = both(scene, algorithm=algorithm)
        assert_same(py, cc)
        assert cc.status == "ok" and cc.stats["events"]["handled"] > 100


@pytest.mark.parametrize("algorithm", FIXED)
def test_a_callback_fmu_rolls_back_through_its_own_state_as_in_the_python_loop(reference_fmus, algorithm):
    """Feedthrough with its Int32 output recorded is a callback slave (typed ports); stepped before
    the ball, it passes each bounce and is restored through the trampolines around its own
    save_state/restore_state, then stepped to the bounce."""
    comps = {"ft": {"fmu": str(reference_fmus["3.0/Feedthrough"]), "start": {"Int32_input": 7}},
             "ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])}}
    scene = {"name": "typed", "components": comps, "connections": ["ball.v -> ft.Float64_continuous_input"],
             "stop_time": 1.2, "outputs": ["ball.v", "ft.Float64_continuous_output", "ft.Int32_output"]}
    py, cc = both(scene, algorithm=algorithm, order=["ft", "ball"])
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["late"] == [] and np.all(cc.trace["ft.Int32_output"] == 7)


@pytest.mark.parametrize("algorithm", FIXED)
def test_a_multirate_component_keeps_the_scenes_events_inside_dostep(reference_fmus, algorithm):
    """A component stepped at rate 2 takes its sub-steps at the macro step's own sub-instants, which
    an event cannot cut (it once was stepped twice over a cut step, and VanDerPol refused the
    second communication point): in such a scene no component is in event mode.  The run is ok,
    equal on both engines, and VanDerPol equals its run alone."""
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/VanDerPol"]), "rate": 2}}
    scene = {"name": "rates", "components": comps, "stop_time": 0.6, "outputs": ["ball.h", "f.x0"]}
    py, cc = both(scene, algorithm=algorithm)
    assert_same(py, cc)
    assert cc.status == "ok", cc.reason
    assert "event_mode" not in cc.stats["events"] and len(np.unique(cc.trace.time)) == len(cc.trace.time)
    alone = run(from_dict({"name": "alone", "components": {"f": comps["f"]}, "stop_time": 0.6, "outputs": ["f.x0"],
                           "master": {"algorithm": algorithm, "step": 0.01, "estimate": False}}))
    assert np.array_equal(alone.trace.time, cc.trace.time) and np.array_equal(alone.trace["f.x0"], cc.trace["f.x0"])


@pytest.mark.parametrize("algorithm", FIXED)
def test_our_fmu_checks_the_kernels_calling_sequence_and_bounces_at_the_analytic_times(reference_fmus, cache,
                                                                                      algorithm):
    """The catalog's pendulum against a stop as an FMI 3.0 event-mode FMU (ours check the calling
    sequence: a communication point that does not follow the previous one, or a step after a
    restored state that does not start at its time, returns Error) beside BouncingBall: each
    one's event cuts the other's step, the one that stepped past it restored through its FMU
    state.  The run is ok, equals the Python loop bit for bit, and the pendulum's impacts are at
    their analytic times among the events."""
    from test_events import analytic_impacts

    from fmus import build_fmu
    from models.blocks import make

    pendulum = build_fmu(make("pendulum", "stop"), fmi_version="3.0", cache_dir=cache)
    comps = {"p": {"fmu": str(pendulum)}, "ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])}}
    scene = {"name": "bounce", "components": comps, "stop_time": 2.5, "outputs": ["p.state.theta", "ball.h"]}
    py, cc = both(scene, algorithm=algorithm)
    assert_same(py, cc)
    assert cc.status == "ok", cc.reason
    t = cc.trace.time
    events = t[1:][np.diff(t) == 0]
    impacts = analytic_impacts(5)
    impacts = impacts[impacts < 2.5]
    assert len(impacts) >= 3 and len(events) > len(impacts) and cc.stats["events"]["late"] == []
    assert np.all(np.min(np.abs(events[None, :] - impacts[:, None]), axis=1) < 1e-9)


@pytest.mark.parametrize("algorithm", FIXED)
def test_an_output_interval_longer_than_the_step_keeps_every_event_row_as_in_the_python_loop(reference_fmus,
                                                                                            algorithm):
    """Rows every 5th step, and two at each event whatever the grid (the kernel records the grid
    rows, Python the event's left limit)."""
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/Feedthrough"])}}
    scene = {"name": "grid", "components": comps, "connections": ["ball.v -> f.Float64_continuous_input"],
             "stop_time": 2.0, "outputs": ["ball.v", "f.Float64_continuous_output"]}
    py, cc = both(scene, algorithm=algorithm, output_interval=0.05)
    assert_same(py, cc)
    t = cc.trace.time
    grid = t[np.abs(t * 20 - np.round(t * 20)) < 1e-9]
    assert np.array_equal(np.unique(grid), np.round(np.arange(0, 2.0001, 0.05), 9))
    assert int((np.diff(t) == 0).sum()) == cc.stats["events"]["handled"] >= 4
