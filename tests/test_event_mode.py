"""FMI 3.0 co-simulation with event mode and early return across the coupling
(docs/explanation/events.md): the Reference FMUs BouncingBall and Stair against FMPy's
``simulate_fmu(use_event_mode=True, early_return_allowed=True)`` event for event, and a coupled pair
where one FMU's event changes the other's input at the same instant (not a step late)."""
from __future__ import annotations

import numpy as np
import pytest

from cosim.run.execute import run
from cosim.scenario import from_dict

fmpy = pytest.importorskip("fmpy")


def _events(t: np.ndarray) -> np.ndarray:
    """The times written twice (left and right limit of an event)."""
    return t[1:][np.diff(t) == 0]


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss_seidel", "iterative", "adaptive"])
@pytest.mark.parametrize("model,step,outputs", [("BouncingBall", 0.01, ["h", "v"]), ("Stair", 0.2, ["counter"])])
def test_event_mode_equals_fmpy_event_for_event(reference_fmus, model, step, outputs, algorithm):
    path = reference_fmus[f"3.0/{model}"]
    res = run(from_dict({"name": "ev", "components": {"m": {"fmu": str(path)}}, "outputs": [f"m.{o}" for o in outputs],
                         "master": {"algorithm": algorithm, "step": step}}))
    ref = fmpy.simulate_fmu(str(path), use_event_mode=True, early_return_allowed=True, output_interval=step,
                            output=outputs)
    if model == "Stair":  # it asks to stop in its event iteration at 9 s; FMPy takes one more step after that
        assert res.status == "stopped" and "at t = 9 s" in res.reason, res.reason
        ref = ref[ref["time"] <= 9.0 + 1e-9]
    else:
        assert res.status == "ok", res.reason
    t = res.trace.time
    assert len(t) == len(ref) and np.max(np.abs(t - ref["time"])) < 1e-12
    ev = _events(t)
    if algorithm == "adaptive":  # its time is counted in whole nanoseconds: the event time rounded to one
        np.testing.assert_allclose(ev, _events(np.asarray(ref["time"])), rtol=0, atol=1e-12)
    else:
        np.testing.assert_array_equal(ev, _events(np.asarray(ref["time"])))
    assert len(ev) == {"BouncingBall": 24, "Stair": 9}[model] and res.stats["events"]["handled"] == len(ev)
    for o in outputs:
        theirs = np.asarray(ref[o], dtype=float)
        assert np.max(np.abs(res.trace[f"m.{o}"] - theirs)) <= 1e-9 * np.ptp(theirs), o


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss_seidel", "iterative", "adaptive"])
def test_an_event_reaches_the_coupled_fmu_at_its_time(reference_fmus, algorithm):
    """BouncingBall's velocity drives Feedthrough: at each bounce the right-limit row has the new
    velocity in both (the event iteration exchanged it); Feedthrough, stepped past the bounce, was
    rolled back to it.  Without event mode (held inputs are needed for event mode, so the fixed-step
    algorithms, whose compiled loops end their steps at events too, run without it with ``inputs:
    linear``) the bounce reaches Feedthrough a step later.  Adaptive's compiled loop ends its steps
    at events as well: its run is the Python loop's, bit for bit."""
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/Feedthrough"])}}
    scene = {"name": "pair", "components": comps, "connections": ["ball.v -> f.Float64_continuous_input"],
             "stop_time": 1.2, "outputs": ["ball.v", "f.Float64_continuous_output"]}
    res = run(from_dict({**scene, "master": {"algorithm": algorithm, "step": 0.01, "estimate": False}}))
    assert res.status == "ok", res.reason
    t, v, y = res.trace.time, res.trace["ball.v"], res.trace["f.Float64_continuous_output"]
    right = np.r_[False, np.diff(t) == 0]
    bounces = right & (v > 0) & (np.r_[0.0, v[:-1]] < 0)
    assert bounces.sum() == 2  # at 0.453 and 1.089 s
    np.testing.assert_array_equal(y[bounces], v[bounces])
    assert res.stats["events"]["late"] == []
    if algorithm == "adaptive":
        py = run(from_dict({**scene, "master": {"algorithm": algorithm, "step": 0.01, "estimate": False,
                                                "engine": "oracle"}}))
        assert res.stats["engine"] == "compiled" and py.stats["engine"] == "oracle"
        assert np.array_equal(py.trace.time, t) and np.array_equal(py.trace.data, res.trace.data)
        return
    plain = run(from_dict({**scene, "master": {"algorithm": algorithm, "step": 0.01, "estimate": False,
                                               "inputs": "linear"}}))
    tp, vp, yp = plain.trace.time, plain.trace["ball.v"], plain.trace["f.Float64_continuous_output"]
    first = int(np.argmax(vp > 0))  # the first row after the first bounce
    assert len(_events(tp)) == 0 and tp[first] == pytest.approx(0.46)
    assert yp[first] < 0 if algorithm == "jacobi" else yp[first] > 0  # Jacobi: the bounce a step late


def test_a_component_that_cannot_roll_back_gets_the_event_late_and_the_sidecar_says_so(reference_fmus):
    """Gauss-Seidel steps VanDerPol (no rollback here) past the bounce before the ball returns
    early: it gets the bounce at the next grid point, and the sidecar says so.  Jacobi steps the
    event-mode ball first and VanDerPol only to the bounce: nothing late."""
    comps = {"ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])},
             "f": {"fmu": str(reference_fmus["3.0/VanDerPol"]), "rollback": False}}
    scene = {"name": "late", "components": comps, "stop_time": 0.6, "outputs": ["ball.h", "f.x0"]}
    res = run(from_dict({**scene, "master": {"algorithm": "jacobi", "step": 0.01, "estimate": False}}))
    assert res.status == "ok" and res.stats["events"]["late"] == [], res.reason
    res = run(from_dict({**scene, "master": {"algorithm": "gauss_seidel", "step": 0.01, "estimate": False,
                                             "order": ["f", "ball"]}}))
    assert res.status == "ok", res.reason
    late = res.stats["events"]["late"]
    assert [(e["component"], e["event_of"]) for e in late] == [("f", "ball")]
    assert late[0]["t"] == pytest.approx(0.453) and late[0]["reached"] == pytest.approx(0.46)
    assert res.stats["events"]["notes"] == ["f had stepped past ball's event at t = 0.453 s and cannot roll back: the "
                                            "event reached it at the next communication point, t = 0.46 s"]
    t = res.trace.time
    # the bounce, and the FMU's second early return a step of its own later (as under FMPy)
    assert list(_events(t)) == pytest.approx([0.453, 0.454]) and np.all(np.diff(t) >= 0)


@pytest.mark.parametrize("algorithm,says", [
    ("jacobi", "events: a step ends at the earliest event of an FMI 3.0 event-mode component for the whole coupling"),
    ("adaptive", "events: an event of an FMI 3.0 event-mode component is a step boundary for the whole coupling"),
    ("iterative", "events: a step ends at the earliest event of an FMI 3.0 event-mode component for the whole "
                  "coupling: every component is rolled back and the coupling iterated again to the event time"),
])
def test_run_check_says_what_the_algorithm_does_with_events(reference_fmus, tmp_path, capsys, algorithm, says):
    from cosim import cli

    scene = tmp_path / "s.yaml"
    scene.write_text(f"name: s\ncomponents:\n  s: {{fmu: {reference_fmus['3.0/BouncingBall']}}}\n"
                     f"master: {{algorithm: {algorithm}, step: 0.01}}\nstop_time: 1\n")
    assert cli.main(["run", str(scene), "--check"]) == 0
    assert says in capsys.readouterr().out


@pytest.mark.parametrize("n,edges,first,order", [
    (3, [(0, 1)], [2], [2, 0, 1]),  # independent of the others: first
    (3, [(0, 1)], [1], [0, 1, 2]),  # fed by 0 without feedback: after it (stepping it first would cut 0 -> 1)
    (2, [(0, 1), (1, 0)], [1], [1, 0]),  # a loop: either order cuts one edge, the event-reporting one first
    (3, [(0, 1), (1, 2), (2, 0)], [], [0, 1, 2]),  # none: the fewest-cut order as before
])
def test_gauss_seidel_puts_event_reporting_slaves_first_where_the_coupling_allows(n, edges, first, order):
    from cosim.master import gauss_seidel_order

    assert gauss_seidel_order(n, edges, first) == order
    cuts = lambda o: sum(o.index(a) > o.index(b) for a, b in edges)  # noqa: E731
    assert cuts(gauss_seidel_order(n, edges, first)) == cuts(gauss_seidel_order(n, edges))


def test_gauss_seidel_steps_the_event_mode_fmu_first_so_nothing_is_late(reference_fmus):
    """The default order steps the ball (event mode) before VanDerPol (cannot roll back), which then
    steps only to each bounce: no event late, and VanDerPol equals its run alone at the grid points
    (its own dynamics do not depend on where its steps were cut: FMPy's CS run at the same step)."""
    comps = {"f": {"fmu": str(reference_fmus["3.0/VanDerPol"]), "rollback": False},
             "ball": {"fmu": str(reference_fmus["3.0/BouncingBall"])}}
    scene = {"name": "first", "components": comps, "stop_time": 0.6, "outputs": ["ball.h", "f.x0"],
             "master": {"algorithm": "gauss_seidel", "step": 0.01, "estimate": False}}
    res = run(from_dict(scene))
    assert res.status == "ok", res.reason
    assert res.stats["events"]["late"] == [] and res.stats["events"]["handled"] >= 1
    t = res.trace.time
    assert list(_events(t)) == pytest.approx([0.453, 0.454])  # the bounce at its own time, as in the late test


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss_seidel", "adaptive", "iterative"])
def test_the_sidecar_says_what_every_algorithm_does_with_events(reference_fmus, algorithm):
    """Every algorithm's run of an FMU with events carries its event policy (``events.mode``), the
    one ``run --check`` prints; a plain FMU's run says nothing about events."""
    from cosim.master.algorithm import algorithm as alg

    ball = run(from_dict({"name": "s", "components": {"s": {"fmu": str(reference_fmus["3.0/BouncingBall"])}},
                          "stop_time": 0.2, "outputs": ["s.h"],
                          "master": {"algorithm": algorithm, "step": 0.01, "estimate": False}}))
    assert ball.status == "ok", ball.reason
    assert ball.stats["events"]["mode"] == alg(algorithm).event_policy
    plain = run(from_dict({"name": "p", "components": {"p": {"fmu": str(reference_fmus["3.0/VanDerPol"])}},
                           "stop_time": 0.2, "outputs": ["p.x0"],
                           "master": {"algorithm": algorithm, "step": 0.01, "estimate": False}}))
    assert plain.status == "ok" and "events" not in plain.stats, plain.reason



def test_the_tolerance_choice_gives_event_mode_fmus_an_algorithm_that_ends_steps_at_events(lag_fmus, reference_fmus):
    """A loop of two lags that can roll back: the choice is adaptive either way; as FMI 3.0
    event-mode FMUs (tests/data/me_lag's FMI3cs.xml) it keeps adaptive because adaptive ends its
    steps at events, with held inputs (event mode needs them), and the chosen run is in event mode."""
    from cosim.master import ALGORITHMS
    from cosim.run.choose import kind

    def pair(fmu):
        return from_dict({"name": "auto", "stop_time": 1.0, "outputs": ["a.x", "b.x"],
                          "components": {"a": {"fmu": str(fmu), "params": {"k": 1.0, "g": -1.0}, "start": {"x": 1.0}},
                                         "b": {"fmu": str(fmu), "params": {"k": 2.0, "g": 1.0}}},
                          "connections": ["a.x -> b.u", "b.x -> a.u"], "master": {"tolerance": 1e-3, "step": 0.01}})

    assert kind(pair(lag_fmus["3"]))[0] == "adaptive"
    scene = pair(lag_fmus["3cs"])
    alg, why = kind(scene)
    assert ALGORITHMS[alg].ends_steps_at_events
    res = run(scene)
    assert res.status == "ok"
    assert res.stats["choice"]["algorithm"] == alg and res.stats["choice"]["settings"]["inputs"] == "hold"
    assert res.stats["events"]["event_mode"] == ["a", "b"]
