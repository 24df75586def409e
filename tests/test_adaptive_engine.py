"""The compiled adaptive engine (cosim/master/adaptive_engine.py) against its reference
implementation, the Python loop of cosim/master/algorithms/adaptive.py: the same accepted and
rejected steps, the same values bit for bit, the same statistics and the same ending, on scenes
that exercise rollbacks, Discards from a slave's own integrator, the step floor and a stop request."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.errors import UserError
from cosim.run.execute import run

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
RK4_MOTORS = {f"components.motor{i}.options.integrator": "rk4" for i in (1, 2, 3)}

CASES = {
    # rollbacks from the coupling error, linear inputs, through the start transient
    "pid_step": ("pid_step.yaml", {"stop_time": 0.4}),
    # RK4 motors beyond their stability limit (a loose tolerance lets the steps grow): the states
    # blow up, slaves return Discard, every retry is rolled back until the step floor (guards off:
    # since adaptive runs are guarded, the rated guard would stop the blown-up motors first; every
    # accepted step recorded, no landing on the 1 ms output grid, which would keep the steps short)
    "motors_rk4_discards": ("pid_step.yaml", {"stop_time": 0.2, **RK4_MOTORS, "guards": "off", "master.record": "steps",
                                              "master.options": {"rtol": 1e-2, "h_ref": 10.0}}),
    # a step floor above what the start needs: the run ends as unstable with the reason
    "pid_step_floor": ("pid_step.yaml", {"stop_time": 0.1, "master.options": {"h_min": 2e-4, "h_init": 2e-4}}),
    # another pair of FMUs: two oscillators cut at a spring
    "two_mass": ("two_mass.yaml", {"stop_time": 2.0}),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def both(request):
    scene, sets = CASES[request.param]
    sets = {"master.algorithm": "adaptive", **sets}
    py = run(SCENARIOS / scene, sets, engine="oracle")
    c = run(SCENARIOS / scene, sets, engine="compiled")
    return request.param, py, c


def test_the_compiled_engine_ran(both):
    _, py, c = both
    assert (py.stats["engine"], c.stats["engine"]) == ("oracle", "compiled")


def test_same_steps_and_values_bit_for_bit(both):
    """Identical traces (every accepted instant and every recorded value, compared exactly)."""
    _, py, c = both
    assert py.trace.data.shape == c.trace.data.shape
    assert np.array_equal(py.trace.data, c.trace.data, equal_nan=True)


def test_same_statistics_and_ending(both):
    name, py, c = both
    keys = ("status", "reason", "accepted_steps", "rejected_steps", "rollbacks", "discards", "smallest_step",
            "largest_step", "simulated_s")
    assert {k: py.stats[k] for k in keys} == {k: c.stats[k] for k in keys}
    assert ({s: d["do_step_calls"] for s, d in py.stats["slaves"].items()}
            == {s: d["do_step_calls"] for s, d in c.stats["slaves"].items()})
    if name == "motors_rk4_discards":
        assert c.stats["discards"] > 0 and c.status == "unstable" and "returned DISCARD" in c.reason
    elif name == "pid_step_floor":
        assert c.status == "unstable" and "step floor" in c.reason and "coupling error" in c.reason
    else:
        assert c.status == "ok" and c.stats["rollbacks"] > 0


def test_compiled_engine_refuses_what_it_cannot_run():
    """engine compiled with a scene the C loop cannot carry (an FMI 3.0 event-mode component for a
    loop not declared to end its steps at events) is one clear error, not a silent fallback; auto
    takes the Python loop.  The adaptive loop, declared so since it does
    (tests/test_variable_event_kernel.py), takes it.  (A connection with a factor, once refused, runs
    in the kernel: tests/test_general_kernel.py.)"""
    from dataclasses import replace

    from cosim.master import CoupledSystem, Link
    from cosim.master.algorithms.adaptive import AdaptiveStepper
    from cosim.master.engine import choose_engine, variable_loop
    from cosim.slaves.linear import LinearSlave

    a, b = LinearSlave("a", [[-1.0]], [[1.0]], [[1.0]]), LinearSlave("b", [[-3.0]], [[1.0]], [[1.0]])
    system = CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]", factor=1.5), Link(1, "y[1]", 0, "u[1]")])
    loop = variable_loop("adaptive", AdaptiveStepper)
    assert choose_engine(system, "compiled", loop) == "compiled"
    a.event_mode = True
    assert loop.events and choose_engine(system, "compiled", loop) == "compiled"
    without = replace(loop, events=False)
    with pytest.raises(UserError, match="compiled for adaptive does not end its steps at events"):
        choose_engine(system, "compiled", without)
    with pytest.raises(UserError, match="auto for adaptive does not end its steps at events"):
        choose_engine(system, "auto", without)  # no Python loop to fall back on: the oracle is a test's


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_a_stop_request_ends_both_engines_alike(reference_fmus, fmi):
    """The Modelica Reference FMU Stair asks to stop at t = 9 s (FMI 3.0 terminateSimulation, FMI 2.0
    Discard + fmi2Terminated): both loops end "stopped" with the same reason, at the same instants."""
    from cosim.scenario import from_dict

    scene = {"name": "stair", "outputs": [], "components": {"s": {"fmu": str(reference_fmus[f"{fmi}/Stair"])}},
             "master": {"algorithm": "adaptive"}}
    py = run(from_dict(scene), engine="oracle")
    c = run(from_dict(scene), engine="compiled")
    assert (py.stats["engine"], c.stats["engine"]) == ("oracle", "compiled")
    if fmi == "3.0":  # the Python loop runs Stair in event mode (the compiled one cannot): it stops in the
        # event iteration at the 9 s event itself, as FMPy does (test_event_mode.py), the compiled loop at the
        # end of the step in which doStep asked to terminate
        assert c.status == py.status == "stopped" and "asked to terminate" in c.reason
        assert py.reason == "stopped by s at t = 9 s: it asked to terminate the simulation in its event iteration"
        assert py.trace.time[-1] == 9.0 and c.trace.time[-1] < 9.0 + 1e-9
        return
    assert c.status == py.status == "stopped" and c.reason == py.reason and "asked to terminate" in c.reason
    assert np.array_equal(py.trace.data, c.trace.data) and c.trace.time[-1] < 9.0 + 1e-9
