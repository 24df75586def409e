"""FMI 3.0 event mode in the variable-step kernels (cosim/master/adaptive_engine.c): ``adaptive`` and
``ecco`` cut a step at the earliest early return of an event-mode FMU (every slave rolled back and
the step retaken to the event, counted as a cut), return after a step at whose end a component
asks for event handling, and the one ``EventIteration`` runs in Python, the inputs' history moved by
the jump (``AdaptiveStepper.after_events``).  Each scene against the Python loop bit for bit (times,
values, steps, cuts, events, doStep counts, the ending and its message), as tests/test_event_kernel.py
does for the fixed-step kernel; the independent checks (FMPy event for event, the analytic impacts)
are tests/test_event_mode.py's and tests/test_event_kernel.py's, which run on these kernels now."""
from __future__ import annotations

import numpy as np
import pytest

from engine_pair import assert_same as assert_pair
from engine_pair import both

VARIABLE = ("adaptive", "ecco")


def assert_same(py, cc) -> None:
    """What tests/engine_pair.py compares, and the variable steps' statistics."""
    assert_pair(py, cc)
    keys = ("accepted_steps", "rejected_steps", "rollbacks", "smallest_step", "largest_step", "discards",
            "steps_cut_at_events", "bonds")
    assert [py.stats.get(k) for k in keys] == [cc.stats.get(k) for k in keys]  # ecco: its bonds' figures


def _bonded(fmu: str, stop: float, fault: int = 2) -> dict:
    """Two lags (tests/data/me_lag's FMI3cs, event mode) in a loop joined as a power bond (a's
    input the effort, its state the flow): ``fault`` 2 in a makes an event at each of its solver
    steps from 0.5 s."""
    comps = {"a": {"fmu": fmu, "params": {"k": 1.0, "g": -1.0, "fault": fault}, "start": {"x": 1.0},
                   "flanges": {"p": {"effort": "u", "flow": "x"}}},
             "b": {"fmu": fmu, "params": {"k": 2.0, "g": 1.0}, "flanges": {"p": {"effort": "x", "flow": "u"}}}}
    return {"name": "bonded", "components": comps, "connections": ["a.p <-> b.p"], "stop_time": stop,
            "outputs": ["a.x", "b.x"]}


@pytest.mark.parametrize("model,outputs", [("BouncingBall", ["h", "v"]), ("Stair", ["counter"])])
def test_one_event_mode_fmu_under_adaptive_equals_the_python_loop(reference_fmus, model, outputs):
    scene = {"name": "ev", "components": {"m": {"fmu": str(reference_fmus[f"3.0/{model}"])}},
             "outputs": [f"m.{o}" for o in outputs]}
    py, cc = both(scene, algorithm="adaptive", step=0.01)
    assert_same(py, cc)
    assert cc.status == {"BouncingBall": "ok", "Stair": "stopped"}[model], cc.reason  # Stair terminates at 9 s
    assert cc.stats["events"]["handled"] == int((np.diff(cc.trace.time) == 0).sum()) >= 5


def test_a_coupled_fmu_rolled_back_to_the_event_under_adaptive_equals_the_python_loop(reference_fmus):
    """Feedthrough, fed by the ball: every bounce cuts the step for both, the step retaken to it."""
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/Feedthrough"])}}
    scene = {"name": "pair", "components": comps, "connections": ["ball.v -> f.Float64_continuous_input"],
             "stop_time": 1.2, "outputs": ["ball.v", "f.Float64_continuous_output"]}
    py, cc = both(scene, algorithm="adaptive", output_interval=0.05)
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["handled"] == 4
    assert cc.stats["steps_cut_at_events"] >= 4


@pytest.mark.parametrize("algorithm", VARIABLE)
def test_a_bouncing_ball_cuts_the_steps_of_a_bonded_loop_as_in_the_python_loop(lag_fmus, reference_fmus, algorithm):
    """The bonded lags (no fault) beside BouncingBall: each bounce cuts the step of all three, the
    lags rolled back and retaken to it, the event iteration between; ecco's bond figures equal."""
    scene = _bonded(str(lag_fmus["3cs"]), 1.2, fault=0)
    scene["components"]["ball"] = {"fmu": str(reference_fmus["3.0/BouncingBall"])}
    scene["outputs"] += ["ball.h"]
    py, cc = both(scene, algorithm=algorithm)
    assert_same(py, cc)
    assert cc.status == "ok", cc.reason
    assert cc.stats["events"]["handled"] == 4 and cc.stats["steps_cut_at_events"] > 0


@pytest.mark.parametrize("algorithm", VARIABLE)
def test_an_event_at_every_step_is_no_chattering_while_the_steps_advance(lag_fmus, algorithm):
    """The bonded lags, fault 2 in a: an event at each of a's solver steps from 0.5 s, every
    accepted step ending at one, each step of positive length: the run goes on (as the fixed-step
    loop does), more than 1000 events in all, the same in both engines."""
    py, cc = both(_bonded(str(lag_fmus["3cs"]), 0.52), algorithm=algorithm)
    assert_same(py, cc)
    assert cc.status == "ok", cc.reason
    assert cc.stats["events"]["handled"] > 1000


@pytest.mark.parametrize("algorithm", VARIABLE)
def test_more_than_1000_events_within_one_output_interval_end_the_run_as_chattering(lag_fmus, algorithm):
    """The same events counted against a 1 s output interval: more than 1000 within it end the run
    as chattering (the message written once, in Python: the kernel returns each event)."""
    py, cc = both(_bonded(str(lag_fmus["3cs"]), 0.52), algorithm=algorithm, output_interval=1.0)
    assert_same(py, cc)
    assert cc.status == "failed" and "within one output interval" in cc.reason and "(chattering)" in cc.reason
    assert cc.stats["events"]["handled"] == 1000


@pytest.mark.parametrize("algorithm", VARIABLE)
@pytest.mark.parametrize("fault,status", [(3, "event_iteration_failed"), (1, "unstable")])
def test_a_misbehaving_event_mode_fmu_ends_the_kernels_run_as_the_python_loops(lag_fmus, algorithm, fault, status):
    """An event iteration that does not settle; a NaN state the guard stops."""
    py, cc = both(_bonded(str(lag_fmus["3cs"]), 1.0, fault), algorithm=algorithm)
    assert_same(py, cc)
    assert cc.status == status


@pytest.mark.parametrize("algorithm", VARIABLE)
def test_every_step_recorded_keeps_the_event_rows_as_in_the_python_loop(lag_fmus, reference_fmus, algorithm):
    """``record: steps`` (a row at every accepted step, no output grid): the left limit is the
    step's own row, the right limit follows; the same rows as the Python loop."""
    scene = _bonded(str(lag_fmus["3cs"]), 1.2, fault=0)
    scene["components"]["ball"] = {"fmu": str(reference_fmus["3.0/BouncingBall"])}
    scene["outputs"] += ["ball.h", "ball.v"]
    py, cc = both(scene, algorithm=algorithm, record="steps")
    assert_same(py, cc)
    assert cc.status == "ok" and len(cc.trace.time) == cc.stats["accepted_steps"] + 1 + 4


def test_a_callback_fmu_rolls_back_through_its_own_state_under_adaptive(reference_fmus):
    """Feedthrough with its Int32 output recorded is a callback slave (typed ports); stepped before
    the ball, it passes each bounce and is restored through the trampolines around its own
    save_state/restore_state."""
    comps = {"ft": {"fmu": str(reference_fmus["3.0/Feedthrough"]), "start": {"Int32_input": 7}},
             "ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])}}
    scene = {"name": "typed", "components": comps, "connections": ["ball.v -> ft.Float64_continuous_input"],
             "stop_time": 1.2, "outputs": ["ball.v", "ft.Float64_continuous_output", "ft.Int32_output"]}
    py, cc = both(scene, algorithm="adaptive", order=["ft", "ball"])
    assert_same(py, cc)
    assert cc.status == "ok" and cc.stats["events"]["handled"] == 4 and np.all(cc.trace["ft.Int32_output"] == 7)
