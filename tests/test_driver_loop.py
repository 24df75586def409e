"""The one driver loop (cosim/master/stepper.py) over every stepper: step observers see each step
(its start, its size and the values after it) of fixed- and variable-step runs, on the compiled
and the Python engines, without changing a bit of the trace; a stop request before a block ends
the run as "stopped" with its reason; a step observer can end a run.

Independent checks: the steps an observer sees must tile the run exactly (sum of h = the stop
time, each t the previous t + h), and the values it sees after each step must be the row the trace
recorded at t + h (recording every step); the analytic pair of test_master gives the exact
values of the Gauss-Seidel map."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosim.master import CoupledSystem, Link, simulate
from cosim.run.execute import build_components, couple
from cosim.scenario import load
from cosim.scenario.recipes import slave_description
from cosim.slaves.fmu_slave import FmuSlave
from cosim.slaves.linear import LinearSlave
from cosim.trace.observer import Observer
from cosim.trace.traces import MemoryTrace

PID_STEP = Path(__file__).resolve().parents[1] / "scenarios" / "pid_step.yaml"


class Steps(Observer):
    """A step observer: every step's (t, h, recorded values after it)."""

    def __init__(self, stop_after: int | None = None):
        self.seen: list[tuple[float, float, np.ndarray]] = []
        self.stop_after = stop_after

    def start(self, columns, meta):
        self.columns = columns

    def initial(self, info):
        assert info.h == 0.0 and info.k == 0
        self.v0 = info.v[info.system.record_idx[:len(self.columns) - 1]].copy()

    def step(self, info):
        self.seen.append((info.t, info.h, info.v[info.system.record_idx[:len(self.columns) - 1]].copy()))
        if self.stop_after is not None and len(self.seen) >= self.stop_after:
            return f"enough after {len(self.seen)} steps"
        return None

    def record(self, rows):
        pass

    def finish(self, status, reason, stats):
        self.final = stats

    def statistics(self):
        return {"steps_seen": len(self.seen)}


def pid_system(sets: dict) -> tuple:
    scene = load(PID_STEP, {"stop_time": 0.05, **sets})
    paths = build_components(scene)
    slaves = [FmuSlave(n, paths[n], slave_description(c, paths[n])) for n, c in scene.components.items()]
    return scene, couple(scene, slaves)


def run_pid(sets: dict, engine: str, observers=()):
    scene, system = pid_system(sets)
    mem = MemoryTrace()
    stats = simulate(system, scene.master.algorithm, step_ns=scene.master.step_ns, n_steps=scene.n_steps,
                     observers=[mem, *observers], start_values=[c.start_values() for c in scene.components.values()],
                     engine=engine, inputs=scene.master.inputs, options=scene.master.options or None,
                     record=scene.master.record)
    return mem.trace, stats


@pytest.mark.parametrize("algorithm, engine", [("gauss_seidel", "compiled"), ("gauss_seidel", "oracle"),
                                               ("adaptive", "compiled"), ("adaptive", "oracle"),
                                               ("ecco", "oracle")])
def test_a_step_observer_sees_every_step_and_changes_no_bit(algorithm, engine):
    sets = {"master.algorithm": algorithm, "master.record": "steps"}  # a row at every step, to compare with
    plain, _ = run_pid(sets, engine)
    obs = Steps()
    trace, stats = run_pid(sets, engine, [obs])
    assert stats.engine == engine and stats.status == "ok"
    assert np.array_equal(trace.data, plain.data)  # one-step blocks: the same steps, bit for bit
    t = np.array([s[0] for s in obs.seen])
    h = np.array([s[1] for s in obs.seen])
    assert len(obs.seen) == len(trace.time) - 1  # every step is recorded here (interval = step or every accepted)
    assert t[0] == 0.0 and np.allclose(t[1:], t[:-1] + h[:-1], rtol=0, atol=1e-12)
    assert math.isclose(t[-1] + h[-1], 0.05, abs_tol=1e-12)
    after = np.array([s[2] for s in obs.seen])
    assert np.array_equal(after, trace.data[1:, 1:])  # the values after each step are that step's row
    assert np.array_equal(obs.v0, trace.data[0, 1:])  # and the initial values the first row
    assert obs.final["Steps"] == {"steps_seen": len(obs.seen)}  # its own figures in the statistics
    if algorithm != "gauss_seidel":
        assert len(set(np.round(h, 12))) > 10  # variable steps


def test_a_step_observer_can_end_the_run():
    obs = Steps(stop_after=7)
    trace, stats = run_pid({}, "compiled", [obs])
    assert stats.status == "failed" and stats.reason == "enough after 7 steps"
    assert len(trace.time) == 8 and trace.time[-1] == pytest.approx(7e-3)


def pair() -> CoupledSystem:
    a = LinearSlave("a", [[-1.0]], [[1.0]], [[1.0]], x0=[1.0])
    b = LinearSlave("b", [[-3.0]], [[1.0]], [[0.8]], [[0.5]], x0=[-0.4])
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]"), Link(1, "y[1]", 0, "u[1]")], [(0, "y[1]"), (1, "y[1]")])


def test_a_stop_request_ends_the_run_before_the_next_block_and_keeps_the_exact_values():
    """Asked before each block (one step per block with a step observer present), the request
    after the 5th step stops the run there; the rows are the exact Gauss-Seidel map's."""
    h = 0.1
    obs = Steps()
    mem = MemoryTrace()
    stats = simulate(pair(), "gauss_seidel", step_ns=100_000_000, n_steps=20, observers=[mem, obs],
                     stop=lambda: "operator stop" if len(obs.seen) == 5 else None)
    assert stats.status == "stopped" and stats.reason == "operator stop" and stats.steps_done == 5
    assert len(mem.trace.time) == 6
    # Gauss-Seidel: a steps with u_a = y_b(t_k), then b with u_b = y_a(t_k+1) (zero-order hold, exact)
    ea, eb = math.exp(-h), math.exp(-3 * h)
    xa, xb = 1.0, -0.4
    yb = 0.8 * xb + 0.5 * xa
    for k in range(5):
        xa = ea * xa + (1 - ea) * yb
        xb = eb * xb + (1 - eb) / 3 * xa
        yb = 0.8 * xb + 0.5 * xa
    assert mem.trace.data[-1, 1:] == pytest.approx([xa, yb], rel=1e-12)
