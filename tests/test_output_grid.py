"""Traces on the grid a run promises (issue 32, item 1): every algorithm records at
``master.output_interval`` (a variable-step master lands a step on each output point), the row
count ``run`` announces is the one it writes, runs of one scene at different settings share their
time column, ``master.record: steps`` gives every accepted step instead, both engines of a
variable-step master write the same rows bit for bit, and adaptive's grid rows hold against the
monolithic reference (scipy's LSODA on the scene's assembled ODE, an independent solution)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.run.execute import estimate, run
from cosim.run.reference import reference
from cosim.scenario import load

SCENE = Path(__file__).resolve().parents[1] / "scenarios" / "pid_step.yaml"
#: 40 ms of pid_step, a row every 2 ms: 21 rows at 0, 2, ..., 40 ms
SHORT = {"stop_time": 0.04, "master.output_interval": 2e-3, "master.estimate": False}
GRID = np.arange(21) * 2e-3


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss_seidel", "iterative", "adaptive", "ecco"])
def test_every_algorithm_writes_the_announced_grid(algorithm):
    sets = {**SHORT, "master.algorithm": algorithm}
    scene = load(SCENE, sets)
    announced = estimate(scene)
    res = run(SCENE, sets)
    assert res.status == "ok", res.reason
    t = res.trace.time
    assert len(t) == announced.rows == 21 and f"{announced.rows:,} rows x" in str(announced)
    np.testing.assert_allclose(t, GRID, rtol=0, atol=1e-15)
    if algorithm in ("adaptive", "ecco"):  # it chose more steps than rows: the rows are its landing points
        assert res.stats["steps_done"] > 20


def test_runs_at_different_tolerances_line_up():
    """Two adaptive runs of one scene at different rtol (as a batch's axis would) share the time column."""
    a = run(SCENE, {**SHORT, "master.algorithm": "adaptive", "master.options.rtol": 1e-4})
    b = run(SCENE, {**SHORT, "master.algorithm": "adaptive", "master.options.rtol": 1e-6})
    assert a.stats["steps_done"] != b.stats["steps_done"]
    assert np.array_equal(a.trace.time, b.trace.time)


def test_record_steps_gives_every_accepted_step():
    sets = {**SHORT, "master.algorithm": "adaptive", "master.record": "steps"}
    assert "one row per accepted step" in str(estimate(load(SCENE, sets)))
    res = run(SCENE, sets)
    assert res.status == "ok", res.reason
    t = res.trace.time
    assert len(t) == res.stats["accepted_steps"] + 1 and np.all(np.diff(t) > 0)
    assert not np.isin(np.round(t[1:-1] / 2e-3, 9) % 1, [0.0]).all()  # irregular: not the grid


def test_record_must_be_grid_or_steps(tmp_path):
    from cosim.scenario import SceneError

    with pytest.raises(SceneError, match=r"master.record = 'step'.*did you mean 'steps'"):
        load(SCENE, {"master.record": "step"})


@pytest.mark.parametrize("algorithm", ["adaptive", "ecco"])
def test_both_engines_write_the_same_grid_rows_bit_for_bit(algorithm):
    sets = {"stop_time": 0.1, "master.algorithm": algorithm, "master.estimate": False}
    py = run(SCENE, sets, engine="oracle")
    c = run(SCENE, sets, engine="compiled")
    assert (py.stats["engine"], c.stats["engine"]) == ("oracle", "compiled")
    assert len(c.trace.time) == 101 and np.array_equal(py.trace.data, c.trace.data)
    assert py.stats["accepted_steps"] == c.stats["accepted_steps"]


def test_adaptive_on_the_grid_against_the_monolithic_reference():
    """pid_step's start transient (motors' 0.44 ms time constant) under adaptive at its default rtol:
    every recorded signal within 1e-3 of its range of the monolithic solution at the same instants."""
    sets = {"stop_time": 0.3, "master.algorithm": "adaptive", "master.estimate": False}
    res = run(SCENE, sets)
    ref = reference(SCENE, sets)
    assert res.status == ref.status == "ok", (res.reason, ref.reason)
    np.testing.assert_allclose(res.trace.time, ref.trace.time, rtol=0, atol=1e-15)  # the same instants
    for name in res.trace.columns[1:]:
        x, r = res.trace[name], ref.trace[name]
        assert np.max(np.abs(x - r)) <= 1e-3 * max(np.ptp(r), 1e-4), name
