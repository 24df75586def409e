"""Tests every registered master algorithm must pass (parametrised over the registry), and the
error-controlled algorithm against independent references: the exact solution of a linear pair,
and the monolithic CVODES solution of the thesis's closed-loop scene."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from cosim.errors import UserError
from cosim.master import ALGORITHMS, CoupledSystem, Link, simulate
from cosim.scenario import SceneError, load
from cosim.slaves.linear import LinearSlave
from cosim.slaves.slave import Status
from cosim.trace.traces import MemoryTrace, Trace

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
A_, B_, C_ = 1.0, 3.0, 0.8
XA0, XB0 = 1.0, -0.4


def pair(cls=LinearSlave) -> CoupledSystem:
    """x_a' = -a x_a + c x_b, x_b' = -b x_b + x_a, cut into two exact linear slaves.  The two links
    are declared one power bond (effort x_a, flow c x_b: the power each side computes, output times
    input, is x_a c x_b on both), which the power-bond algorithm (ecco) needs and the others ignore."""
    a = cls("a", [[-A_]], [[1.0]], [[1.0]], x0=[XA0])
    b = cls("b", [[-B_]], [[1.0]], [[C_]], x0=[XB0])
    bond = "a.y[1] <-> b.y[1]"
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]", bond=bond), Link(1, "y[1]", 0, "u[1]", bond=bond)],
                         [(0, "y[1]"), (1, "x[1]")])


def exact(t: float) -> np.ndarray:
    return scipy.linalg.expm(np.array([[-A_, C_], [1.0, -B_]]) * t) @ np.array([XA0, XB0])


def simulate_pair(alg: str, system: CoupledSystem | None = None, step_ns: int = 10_000_000, n: int = 100,
                  record: str = "grid"):
    mem = MemoryTrace()
    stats = simulate(system or pair(), alg, step_ns=step_ns, n_steps=n, observers=[mem], record=record)
    return mem.trace, stats


@pytest.mark.parametrize("alg", sorted(ALGORITHMS))
def test_every_algorithm_converges_to_the_exact_solution(alg):
    """Step 10 ms to t = 1 s: every algorithm ends at the stop time exactly, ok, and within 1 % of
    the exact solution of the coupled pair (a first-order coupling errs by ~0.5 % here)."""
    tr, stats = simulate_pair(alg)
    assert stats.status == "ok", stats.reason
    assert tr.time[0] == 0.0 and tr.time[-1] == 1.0 and np.all(np.diff(tr.time) > 0)
    ref = exact(1.0)
    assert abs(tr.data[-1, 1] - ref[0]) < 1e-2 * abs(ref[0])
    assert abs(tr.data[-1, 2] - ref[1]) < 1e-2 * max(abs(ref[1]), 0.1)


def transformed_pair() -> CoupledSystem:
    """The same coupled pair with both connections scaled (``dst = factor * src``) and the
    slaves' gains scaled back: the same exact solution only if the master applies the factors."""
    a = LinearSlave("a", [[-A_]], [[1.0]], [[4.0]], x0=[XA0])
    b = LinearSlave("b", [[-B_]], [[2.0]], [[C_]], x0=[XB0])
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]", factor=0.125), Link(1, "y[1]", 0, "u[1]", factor=1.0)],
                         [(0, "x[1]"), (1, "x[1]")])


@pytest.mark.parametrize("alg", sorted(ALGORITHMS))
def test_every_algorithm_applies_the_connections_factors(alg):
    """a's output is 4 x_a, scaled by 1/8 into b, whose input gain is 2: b sees x_a as in the
    plain pair; without the factor b would see 4 x_a and end far from the exact solution."""
    if alg == "ecco":
        pytest.skip("ecco needs power bonds, which a transformed connection is not")
    tr, stats = simulate_pair(alg, transformed_pair())
    assert stats.status == "ok", stats.reason
    ref = exact(1.0)
    assert abs(tr.data[-1, 1] - ref[0]) < 1e-2 * abs(ref[0])
    assert abs(tr.data[-1, 2] - ref[1]) < 1e-2 * max(abs(ref[1]), 0.1)


class Discarding(LinearSlave):
    """Refuses every step from t >= 0.3 s on."""

    def do_step(self, t, h):
        if t + h > 0.3 + 1e-12:
            self.messages.append("[DISCARD] the test slave refuses steps past 0.3 s")
            return Status.DISCARD
        return super().do_step(t, h)


@pytest.mark.parametrize("alg", sorted(ALGORITHMS))
def test_every_algorithm_ends_a_run_the_slave_refuses_with_its_reason(alg):
    """No hang and no 'ok': the run stops near 0.3 s with the slave's name and message."""
    tr, stats = simulate_pair(alg, pair(Discarding))
    assert stats.status in ("failed", "unstable")
    assert "a" in stats.reason and "refuses steps past 0.3 s" in stats.reason or "h_min" in stats.reason
    assert 0.25 <= tr.time[-1] <= 0.3 + 1e-12


def test_adaptive_is_accurate_on_the_exact_pair_and_reports_its_steps():
    tr, stats = simulate_pair("adaptive", record="steps")  # a row at every accepted step
    d = stats.as_dict()
    assert d["accepted_steps"] == len(tr.time) - 1 and d["rejected_steps"] >= 0
    assert d["smallest_step"] <= d["largest_step"] <= 0.05
    ts = np.linspace(0, 1, 11)
    for t in ts[1:]:
        k = int(np.argmin(np.abs(tr.time - t)))
        np.testing.assert_allclose(tr.data[k, 1:], exact(tr.time[k]), atol=2e-4)


def test_adaptive_refuses_a_slave_that_cannot_roll_back():
    class Fixed(LinearSlave):
        @property
        def can_rollback(self) -> bool:
            return False

    with pytest.raises(UserError, match="needs rollback.*cannot roll back"):
        simulate_pair("adaptive", pair(Fixed))


def test_linear_slave_restores_its_saved_state_exactly():
    s = LinearSlave("s", [[-1.0, 2.0], [0.0, -3.0]], [[1.0], [1.0]], [[1.0, 0.0]], x0=[1.0, 2.0])
    s.instantiate()
    s.save_state()
    s.do_step(0.0, 0.1)
    after = s.x.copy()
    s.restore_state()
    assert np.array_equal(s.x, [1.0, 2.0])
    s.do_step(0.0, 0.1)
    assert np.array_equal(s.x, after)


@pytest.fixture(scope="module")
def two_mass_fmu_slaves():
    from cosim.run.execute import build_components
    from cosim.slaves.fmu_slave import FmuSlave

    scene = load(SCENARIOS / "two_mass.yaml")
    paths = build_components(scene)
    return scene, paths, FmuSlave


def test_fmu_state_rollback_is_bit_exact(two_mass_fmu_slaves):
    """Save, step twice, restore, step twice again: identical outputs (FMI get/set FMU state)."""
    scene, paths, FmuSlave = two_mass_fmu_slaves
    s = FmuSlave("mass1", paths["mass1"])
    assert s.can_rollback
    s.instantiate()
    s.set_start({"x0": 0.3, "v0": -1.0})
    s.enter_initialization(0.0, 1.0)
    s.exit_initialization()
    out, inp = np.zeros(2), np.array([0.7])
    s.bind(np.array([s.vr("f")], dtype=np.uint32), inp, np.array([s.vr("x"), s.vr("v")], dtype=np.uint32), out)
    s.push()
    s.save_state()
    runs = []
    for _ in range(2):
        for k in range(2):
            assert s.do_step(0.01 * k, 0.01) == Status.OK
        s.pull()
        runs.append(out.copy())
        s.restore_state()
    assert np.array_equal(runs[0], runs[1]) and runs[0][0] != 0.3
    s.terminate()
    s.free()


@pytest.mark.parametrize("options, message", [
    ({"rtl": 1e-3}, "unknown option 'rtl'; did you mean 'rtol'?"),
    ({"rtol": 2.0}, "rtol = 2.0 is outside"),
    ({"h_min": 0.1, "h_max": 0.01}, "h_min = 0.1 s is larger than h_max"),
    ({"rtol": "[1, 2]"}, "rtol = [1, 2] must be a number"),
    ({"rtol": "{a: 1}"}, "rtol = {'a': 1} must be a number"),
])
def test_master_options_are_checked_against_the_algorithm_declaration(tmp_path, options, message):
    scene = tmp_path / "opts.yaml"
    body = ", ".join(f"{k}: {v}" for k, v in options.items())
    scene.write_text(f"include: {SCENARIOS / 'two_mass.yaml'}\nmaster:\n  algorithm: adaptive\n"
                     f"  options: {{{body}}}\n")
    with pytest.raises(SceneError) as exc:
        load(scene)
    assert message in str(exc.value) and "opts.yaml:4" in str(exc.value)


def test_fixed_step_algorithms_have_no_options():
    with pytest.raises(SceneError, match="master algorithm jacobi has no options"):
        load(SCENARIOS / "two_mass.yaml", {"master.options": {"rtol": 1e-3}})


# --- the thesis's closed-loop scene against its monolithic reference --------------------------
@pytest.fixture(scope="module")
def pid_step_adaptive():
    from cosim.run.reference import reference
    from cosim.run.execute import run

    scene = SCENARIOS / "pid_step.yaml"
    res = run(scene, {"master.algorithm": "adaptive", "master.record": "steps"})  # every accepted step a row
    # The reference at the instants that matter: every microsecond through the start transient
    # (the motors' 0.44 ms electrical time constant), every 0.1 ms after (interpolation error
    # below 1e-6 of range there).
    fine = reference(scene, {"stop_time": 0.02, "master.step": 1e-6, "master.output_interval": 1e-6})
    coarse = reference(scene, {"master.step": 1e-4, "master.output_interval": 1e-4})
    return res, fine.trace, coarse.trace


def _window(tr: Trace, a: float, b: float) -> Trace:
    keep = (tr.time >= a) & (tr.time <= b)
    return Trace(tr.columns, tr.data[keep])


def test_adaptive_pid_step_within_a_thousandth_of_range_everywhere(pid_step_adaptive):
    """Issue 10's acceptance: at the default tolerance every recorded variable stays within 1e-3
    of its range of the monolithic CVODES solution over the whole run, start transient included
    (measured at rtol 3e-5: worst 8.4e-4 on platform.y, whose range is only ~0.7 mm)."""
    from cosim.analysis.trace_diff import compare

    res, fine, coarse = pid_step_adaptive
    assert res.status == "ok", res.reason
    assert res.trace.time[-1] == 5.0
    span = {n: np.ptp(coarse[n]) for n in coarse.names}
    worst: dict[str, float] = {}
    for ref, a, b in ((fine, 0.0, 0.02), (coarse, 0.02, 5.0)):
        for d in compare(_window(res.trace, a, b), ref):
            if span[d.name] > 0:
                worst[d.name] = max(worst.get(d.name, 0.0), d.max_abs / span[d.name])
    assert len(worst) >= 20
    bad = {n: e for n, e in worst.items() if e > 1e-3}
    assert not bad, bad


def test_adaptive_pid_step_resolves_the_start_and_grows_later(pid_step_adaptive):
    """Steps of microseconds through the first millisecond (the motors' electrical transient),
    at least 5 ms once the platform moves slowly (issue 10; measured: up to 5.3 ms after 3 s; the
    PIDs' and motors' exact kernels are stable at any step)."""
    res = pid_step_adaptive[0]
    h = np.diff(res.trace.time)
    t = res.trace.time[1:]
    assert h[t <= 1e-3].max() < 5e-5
    assert h[t >= 3.0].max() >= 5e-3
    assert res.stats["rollbacks"] == res.stats["rejected_steps"]
