"""Master algorithms against exact discrete solutions, the continuous solution's first-order
convergence, the compiled loop against the Python loop on real FMUs, integer time, failures,
interrupts and the algorithm registry.

The analytic problem: two first-order systems stepped *exactly* under a zero-order hold
(:class:`cosim.slaves.LinearSlave`), coupled both ways, one of them with direct feedthrough:

    A:  x_a' = -a x_a + u_a,            y_a = x_a
    B:  x_b' = -b x_b + u_b,            y_b = c x_b + d u_b
    y_a -> u_b,  y_b -> u_a

so every macro step is an exact linear map whose form follows from the documented conventions
(Jacobi: inputs from the outputs read at t_k, feedthrough evaluated with the previous inputs;
Gauss-Seidel: A first, then B with A's fresh output).
"""
from __future__ import annotations

import itertools
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from cosim.errors import UserError
from cosim.master import (ALGORITHMS, Algorithm, CoupledSystem, Link, algorithm, find_algebraic_loop,
                          gauss_seidel_order, register, simulate)
from cosim.slaves.fmu_slave import FmuSlave
from cosim.slaves.linear import LinearSlave
from cosim.slaves.slave import Status
from cosim.trace.traces import CsvTrace, MemoryTrace, read_trace

sys.path.insert(0, str(Path(__file__).parent))

A_, B_, C_, D_ = 1.0, 3.0, 0.8, 0.5
XA0, XB0 = 1.0, -0.4


def pair(d: float = D_) -> CoupledSystem:
    a = LinearSlave("a", [[-A_]], [[1.0]], [[1.0]], x0=[XA0])
    b = LinearSlave("b", [[-B_]], [[1.0]], [[C_]], [[d]], x0=[XB0])
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]"), Link(1, "y[1]", 0, "u[1]")],
                         [(0, "y[1]"), (1, "y[1]"), (0, "u[1]"), (1, "x[1]")])


def run(system: CoupledSystem, alg: str, step_ns: int, n: int, **kw):
    mem = MemoryTrace()
    stats = simulate(system, alg, step_ns=step_ns, n_steps=n, observers=[mem], **kw)
    return mem.trace, stats


def expected(alg: str, h: float, n: int, d: float = D_) -> np.ndarray:
    """Rows (y_a, y_b, u_a, x_b) at t_0..t_n from the hand-written step maps of the conventions."""
    ea, eb = math.exp(-A_ * h), math.exp(-B_ * h)
    ga, gb = (1 - ea) / A_, (1 - eb) / B_
    xa, xb = XA0, XB0
    yb = C_ * xb + d * xa  # initial exchange: B's feedthrough sees A's start output
    rows = [(xa, yb, yb, xb)]
    for _ in range(n):
        if alg == "jacobi":
            ua, ub = yb, xa
            xa, xb = ea * xa + ga * ua, eb * xb + gb * ub
            yb = C_ * xb + d * ub  # evaluated with the input held over the step just taken
        else:
            ua = yb
            xa = ea * xa + ga * ua
            ub = xa  # fresh output of A
            xb = eb * xb + gb * ub
            yb = C_ * xb + d * ub
        rows.append((xa, yb, yb, xb))
    return np.array(rows)


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
@pytest.mark.parametrize("d", [0.0, D_], ids=["no-feedthrough", "feedthrough"])
def test_exact_discrete_solution_of_the_coupled_pair(alg, d):
    tr, stats = run(pair(d), alg, 50_000_000, 40)  # h = 0.05 s
    np.testing.assert_allclose(tr.data[:, 1:], expected(alg, 0.05, 40, d), rtol=0, atol=1e-14)
    assert stats.status == "ok" and stats.steps_done == 40
    assert tr.meta["step"] == stats.step == 0.05 and tr.meta["algorithm"] == alg
    assert stats.slaves["a"]["do_step_calls"] == stats.slaves["b"]["do_step_calls"] == 40


def test_jacobi_and_gauss_seidel_differ_by_the_fresh_value():
    """A sanity check that the two conventions are really different maps on this problem."""
    j, _ = run(pair(), "jacobi", 50_000_000, 10)
    g, _ = run(pair(), "gauss_seidel", 50_000_000, 10)
    assert np.max(np.abs(j.data[1:, 1:] - g.data[1:, 1:])) > 1e-3


def continuous(t: float) -> np.ndarray:
    """Monolithic solution: x_a' = -a x_a + c x_b + d x_a, x_b' = -b x_b + x_a."""
    M = np.array([[-A_ + D_, C_], [1.0, -B_]])
    return scipy.linalg.expm(M * t) @ np.array([XA0, XB0])


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
def test_first_order_convergence_to_the_monolithic_solution(alg):
    errs = []
    for k in (1, 2, 4):
        h_ns = 20_000_000 // k
        tr, _ = run(pair(), alg, h_ns, 50 * k)  # to t = 1 s
        errs.append(abs(tr.data[-1, 1] - continuous(1.0)[0]))
    assert errs[0] / errs[1] == pytest.approx(2.0, rel=0.1)
    assert errs[1] / errs[2] == pytest.approx(2.0, rel=0.05)


def test_time_is_an_integer_count_of_nanosecond_steps():
    """t_k = k * step_ns / 1e9 exactly: no accumulated drift even for a step of 0.1 s."""
    seen = []

    class Spy(LinearSlave):
        def do_step(self, t, h):
            seen.append((t, h))
            return super().do_step(t, h)

    s = Spy("s", [[-1.0]], [[1.0]], [[1.0]])
    tr, _ = run(CoupledSystem([s], [], [(0, "y[1]")]), "jacobi", 100_000_000, 1000)
    ts = np.array([t for t, _ in seen])
    assert np.array_equal(ts, np.arange(1000) * 100_000_000 / 1e9)
    assert tr.time[-1] == 100.0
    assert sum(0.1 for _ in range(1000)) != 100.0  # what naive accumulation would give


class Failing(LinearSlave):
    def __init__(self, *a, fail_at: int, status: int = Status.DISCARD, **kw):
        super().__init__(*a, **kw)
        self.fail_at, self.status, self.k = fail_at, status, 0

    def do_step(self, t, h):
        self.k += 1
        if self.k == self.fail_at:
            self.messages.append("[DISCARD] the test slave refuses this step")
            return self.status
        return super().do_step(t, h)


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
@pytest.mark.parametrize("status,expect", [(Status.DISCARD, "failed"), (Status.ERROR, "failed")])
def test_a_failing_slave_stops_the_run_and_keeps_the_partial_trace(tmp_path, status, expect, alg):
    bad = Failing("bad", [[-1.0]], [[1.0]], [[1.0]], fail_at=7, status=status)
    ok = LinearSlave("ok", [[-2.0]], [[1.0]], [[1.0]], x0=[1.0])
    system = CoupledSystem([ok, bad], [Link(0, "y[1]", 1, "u[1]")], [(0, "y[1]"), (1, "y[1]")])
    csv = CsvTrace(tmp_path / "t.csv")
    mem = MemoryTrace()
    stats = simulate(system, alg, step_ns=10_000_000, n_steps=100, observers=[mem, csv])
    assert stats.status == expect and stats.steps_done == 6
    assert "bad" in stats.reason and "t = 0.06 s" in stats.reason
    if expect == "failed":
        assert Status(status).name in stats.reason and "refuses this step" in stats.reason
    back = read_trace(tmp_path / "t.csv")
    assert back.status == expect and back.reason == stats.reason
    assert len(back.data) == 7 and back.time[-1] == pytest.approx(0.06)
    np.testing.assert_array_equal(back.data, mem.trace.data)
    side = json.loads((tmp_path / "t.json").read_text())
    assert side["status"] == expect and side["reason"] == stats.reason and side["rows"] == 7


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss_seidel"])
def test_a_stop_request_completes_the_step_and_records_its_end(tmp_path, algorithm):
    """A slave asking to stop in the step from t = 0.06 s: the others complete that step, the point
    t = 0.07 s is recorded (off the output grid too) and the run ends "stopped by bad at 0.07 s"."""
    bad = Failing("bad", [[-1.0]], [[1.0]], [[1.0]], fail_at=7, status=Status.STOP_REQUESTED)
    ok = LinearSlave("ok", [[-2.0]], [[1.0]], [[1.0]], x0=[1.0])
    ref = LinearSlave("ok", [[-2.0]], [[1.0]], [[1.0]], x0=[1.0])
    system = CoupledSystem([bad, ok], [Link(1, "y[1]", 0, "u[1]")], [(1, "y[1]"), (0, "y[1]")])
    csv = CsvTrace(tmp_path / "t.csv")
    stats = simulate(system, algorithm, step_ns=10_000_000, n_steps=100, record_every=5, observers=[csv],
                     order=[1, 0])
    assert stats.status == "stopped" and stats.steps_done == 7
    assert stats.reason.startswith("stopped by bad at t = 0.07 s: it asked to terminate the simulation in the "
                                   "step from t = 0.06 s")
    back = read_trace(tmp_path / "t.csv")
    assert back.status == "stopped" and list(back.time) == pytest.approx([0.0, 0.05, 0.07])
    for _ in range(7):  # 'ok' completed its seventh step: its exact solution at 0.07 s
        ref.do_step(0.0, 0.01)
    assert back["ok.y[1]"][-1] == pytest.approx(ref.x[0], abs=1e-15)
    assert json.loads((tmp_path / "t.json").read_text())["reason"] == stats.reason


def test_an_interrupt_leaves_the_partial_trace_and_the_reason(tmp_path):
    class Interrupting(MemoryTrace):
        def record(self, rows):
            super().record(rows)
            if self.trace is not None and sum(len(c) for c in self._chunks) > 100:
                raise KeyboardInterrupt

    csv = CsvTrace(tmp_path / "t.csv")
    with pytest.raises(KeyboardInterrupt):
        simulate(pair(), "jacobi", step_ns=1_000_000, n_steps=10_000, observers=[csv, Interrupting()])
    back = read_trace(tmp_path / "t.csv")
    assert back.status == "interrupted" and "KeyboardInterrupt" in back.reason
    assert 100 < len(back.data) < 10_001
    assert json.loads((tmp_path / "t.json").read_text())["status"] == "interrupted"


# --- real FMUs: compiled loop vs Python loop ----------------------------------------------------
@pytest.fixture(scope="module")
def fmu_paths(tmp_path_factory):
    import fmus
    from test_fmu_integrators import gain_block, msd_block

    cache = tmp_path_factory.getbasetemp() / "fmu-cache"
    out = {}
    for v in ("2.0", "3.0"):
        out[("msd", v)] = fmus.build_fmu(msd_block(), fmi_version=v, cache_dir=cache)
        out[("gain", v)] = fmus.build_fmu(gain_block(K=-40.0), fmi_version=v, cache_dir=cache)
    return out


def fmu_system(paths, v_msd: str, v_gain: str) -> CoupledSystem:
    """A mass-spring-damper under feedback force f = -40 s from a gain FMU (feedthrough)."""
    sl = [FmuSlave("m", paths[("msd", v_msd)]), FmuSlave("g", paths[("gain", v_gain)])]
    return CoupledSystem(sl, [Link(0, "body.s", 1, "u"), Link(1, "y", 0, "f")],
                         [(0, "body.s"), (0, "body.v"), (0, "body.a"), (1, "y"), (0, "f")])


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
@pytest.mark.parametrize("versions", [("2.0", "2.0"), ("3.0", "3.0"), ("2.0", "3.0")], ids=["fmi2", "fmi3", "mixed"])
def test_compiled_loop_equals_the_python_loop_bit_for_bit(fmu_paths, alg, versions):
    py, s1 = run(fmu_system(fmu_paths, *versions), alg, 1_000_000, 500, engine="oracle")
    cc, s2 = run(fmu_system(fmu_paths, *versions), alg, 1_000_000, 500, engine="compiled")
    assert (s1.engine, s2.engine) == ("oracle", "compiled")
    assert np.array_equal(py.data, cc.data)
    assert s2.slaves["m"]["do_step_calls"] == 500 and s2.slaves["m"]["wall_s"] > 0


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
@pytest.mark.parametrize("inputs", ["hold", "linear"])
@pytest.mark.parametrize("rates, versions", [((4, 1), ("2.0", "2.0")), ((2, 5), ("2.0", "2.0")),
                                             ((4, 2), ("3.0", "2.0"))], ids=["msd4", "msd2-gain5", "msd4-fmi3"])
def test_compiled_multirate_equals_the_python_loop_bit_for_bit(fmu_paths, alg, inputs, rates, versions):
    """Slaves at several doSteps per macro step (cosim.master.multirate), inputs held or ramped at the
    sub-instants: the same trace in both engines, and each slave's doSteps counted."""
    py, s1 = run(fmu_system(fmu_paths, *versions), alg, 1_000_000, 300, engine="oracle", inputs=inputs, rates=rates)
    cc, s2 = run(fmu_system(fmu_paths, *versions), alg, 1_000_000, 300, engine="compiled", inputs=inputs, rates=rates)
    one, _ = run(fmu_system(fmu_paths, *versions), alg, 1_000_000, 300, engine="compiled", inputs=inputs)
    assert (s1.engine, s2.engine) == ("oracle", "compiled") and s2.status == "ok"
    assert np.array_equal(py.data, cc.data)
    assert not np.array_equal(cc.data, one.data)  # the sub-steps did change the result
    for s, r in zip(("m", "g"), rates):
        assert s1.slaves[s]["do_step_calls"] == s2.slaves[s]["do_step_calls"] == 300 * r


@pytest.mark.parametrize("every", [3, 7])
def test_compiled_loop_records_every_nth_point_like_the_python_loop(fmu_paths, every):
    """Recording every n-th communication point: the same rows (t = 0, n h, 2 n h, ...) in both
    engines, and the same values as the every-point trace at those instants."""
    py, _ = run(fmu_system(fmu_paths, "2.0", "2.0"), "gauss_seidel", 1_000_000, 100, engine="oracle",
                record_every=every)
    cc, _ = run(fmu_system(fmu_paths, "2.0", "2.0"), "gauss_seidel", 1_000_000, 100, engine="compiled",
                record_every=every)
    full, _ = run(fmu_system(fmu_paths, "2.0", "2.0"), "gauss_seidel", 1_000_000, 100, engine="compiled")
    np.testing.assert_allclose(cc.time, np.arange(0, 101, every) * 1e-3, rtol=0, atol=1e-15)
    assert np.array_equal(py.data, cc.data)
    assert np.array_equal(cc.data, full.data[::every])


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
def test_fmu_pair_follows_the_conventions_on_a_linear_problem(fmu_paths, alg):
    """msd (Radau IIA, order 5: exact to ~1e-12 here) under f = -40 s from a gain FMU.  Gauss-Seidel
    steps the msd first and the gain after it, so the msd's force over [t_k, t_k+1] is K s(t_k);
    under Jacobi the gain's output read at t_k was evaluated with its input of the previous
    exchange, so the force is K s(t_k-1): one step of delay through the feedthrough."""
    tr, _ = run(fmu_system(fmu_paths, "2.0", "2.0"), alg, 1_000_000, 300)
    m, k, c, K = 1.0, 100.0, 2.0, -40.0
    M = np.zeros((3, 3))
    M[0, 1], M[1, 0], M[1, 1], M[1, 2] = 1.0, -k / m, -c / m, 1 / m
    E = scipy.linalg.expm(M * 1e-3)
    x = np.array([0.01, 0.0])
    s = [x[0]]
    for j in range(300):
        f = K * (s[j] if alg == "gauss_seidel" else s[max(j - 1, 0)])
        x = E[:2, :2] @ x + E[:2, 2] * f
        s.append(x[0])
    s = np.array(s)
    np.testing.assert_allclose(tr["m.body.s"], s, rtol=0, atol=1e-12)
    lagged = s if alg == "gauss_seidel" else np.concatenate([[s[0]], s[:-1]])
    np.testing.assert_allclose(tr["g.y"], K * lagged, rtol=0, atol=1e-12)


def linear_input_solution(alg: str, n: int, h: float = 1e-3) -> np.ndarray:
    """msd positions at t_0..t_n under f = -40 s with linear inputs, from the conventions (module
    docstring of cosim.master) and the exact step of the msd under a ramp force (augmented
    matrix exponential of (s, v, f, df/dt))."""
    m, k, c, K = 1.0, 100.0, 2.0, -40.0
    M = np.zeros((4, 4))
    M[0, 1], M[1, 0], M[1, 1], M[1, 2], M[2, 3] = 1.0, -k / m, -c / m, 1 / m, 1.0
    E = scipy.linalg.expm(M * h)[:2]
    x = np.array([0.01, 0.0])
    s = [x[0]]
    y = [K * s[0]]  # the gain's output as read at t_0, t_1, ...
    for j in range(n):
        if alg == "gauss_seidel":  # msd first: the gain's output is extrapolated from t_j-1, t_j
            f, df = K * s[j], K * (s[j] - s[max(j - 1, 0)]) / h
        else:  # Jacobi: the gain's output read at t_j, extrapolated through its own input slope
            f, df = y[j], (y[j] - y[max(j - 1, 0)]) / h
            y.append(K * (2 * s[j] - s[j - 1]) if j >= 1 else K * s[0])
        x = E @ np.array([x[0], x[1], f, df])
        s.append(x[0])
    return np.array(s)


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
def test_fmu_pair_with_linear_inputs_follows_the_conventions(fmu_paths, alg):
    """inputs="linear": the msd's force is extrapolated from the gain's last two outputs (the gain
    steps after it), the gain's input is interpolated (Gauss-Seidel) or extrapolated (Jacobi);
    the trajectory equals the hand-written recurrence, in both engines, and is far closer to the
    continuous closed loop than holding."""
    want = linear_input_solution(alg, 300)
    for engine in ("oracle", "compiled"):
        tr, st = run(fmu_system(fmu_paths, "2.0", "2.0"), alg, 1_000_000, 300, inputs="linear", engine=engine)
        assert st.engine == engine
        np.testing.assert_allclose(tr["m.body.s"], want, rtol=0, atol=1e-12)
    held, _ = run(fmu_system(fmu_paths, "2.0", "2.0"), alg, 1_000_000, 300)
    wn = math.sqrt(140.0 - 1.0)  # continuous loop: s'' + 2 s' + 140 s = 0 from (0.01, 0)
    t = np.arange(301) * 1e-3
    exact = 0.01 * np.exp(-t) * (np.cos(wn * t) + np.sin(wn * t) / wn)
    assert np.abs(tr["m.body.s"] - exact).max() < np.abs(held["m.body.s"] - exact).max() / 20


@pytest.mark.parametrize("engine", ["oracle", "compiled"])
def test_a_slave_feeding_itself_extrapolates_its_own_output(fmu_paths, engine):
    """Gauss-Seidel, linear inputs, the msd's position wired to its own force (a spring of
    -1 N/m): the source has not stepped when the slave takes its input, so the input is
    extrapolated -- ``s_k`` with slope ``(s_k - s_k-1) / h`` -- never interpolated."""
    m = FmuSlave("m", fmu_paths[("msd", "2.0")])
    system = CoupledSystem([m], [Link(0, "body.s", 0, "f")], [(0, "body.s")])
    tr, st = run(system, "gauss_seidel", 1_000_000, 200, inputs="linear", engine=engine)
    assert st.engine == engine
    M = np.zeros((4, 4))
    M[0, 1], M[1, 0], M[1, 1], M[1, 2], M[2, 3] = 1.0, -100.0, -2.0, 1.0, 1.0
    E = scipy.linalg.expm(M * 1e-3)[:2]
    x, s = np.array([0.01, 0.0]), [0.01]
    for j in range(200):
        x = E @ np.array([x[0], x[1], s[j], (s[j] - s[max(j - 1, 0)]) / 1e-3])
        s.append(x[0])
    np.testing.assert_allclose(tr["m.body.s"], s, rtol=0, atol=1e-12)


@pytest.mark.parametrize("alg", ["jacobi", "gauss_seidel"])
def test_linear_inputs_leave_fmi3_slaves_holding(fmu_paths, alg):
    """FMI 3.0 has no input derivatives: such slaves keep holding, bit for bit."""
    lin, _ = run(fmu_system(fmu_paths, "3.0", "3.0"), alg, 1_000_000, 100, inputs="linear")
    hold, _ = run(fmu_system(fmu_paths, "3.0", "3.0"), alg, 1_000_000, 100)
    assert np.array_equal(lin.data, hold.data)


def test_a_diverging_fmu_discards_and_the_run_reports_it(tmp_path):
    import fmus
    from test_fmu_integrators import stiff_block

    path = fmus.build_fmu(stiff_block(integrator="rk4"), cache_dir=tmp_path / "cache")
    system = CoupledSystem([FmuSlave("stiff", path)], [], [(0, "body.s")])
    tr, st = run(system, "jacobi", 1_000_000, 1000)
    assert st.status == "failed" and st.engine == "compiled"
    assert "stiff returned DISCARD" in st.reason and "non-finite" in st.reason
    assert 1 < st.steps_done < 1000 and len(tr.data) == st.steps_done + 1
    # the failing step is the one after the last completed: from t = steps_done * h
    assert f"in the step from t = {st.steps_done * 1e-3:.9g} s (step {st.steps_done})" in st.reason


# --- Gauss-Seidel order on more than two slaves, both engines -------------------------------------
def affine_block():
    """Sampled affine map ``x+ = a x + b u`` every 10 ms, output ``y = x`` (no feedthrough), start
    ``x0``; ``a``, ``b``, ``x0`` are tunable, so one FMU serves every slave of the ring."""
    import casadi as ca

    from models.block import Block, Param, Var

    p, x, u = ca.SX.sym("p", 3), ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return Block.build("affine", description="sampled affine map (master tests)",
                       params=[Param("a", 0.9, "1"), Param("b", 0.5, "1"), Param("x0", 0.0, "1")],
                       inputs=[Var("u", "1")], outputs=[Var("y", "1")], states=[Var("x", "1")],
                       p=p, u=u, x=x, ode=p[0] * x + p[1] * u, out=x, start=p[2],
                       integrator="discrete", sample_period=0.01)


# a ring of four slaves declared 0..3 but wired 3 -> 1 -> 2 -> 0 -> 3, each with its own a, b, x0
RING = [(3, 1), (1, 2), (2, 0), (0, 3)]
RING_PARAMS = [(0.9, 0.5, 1.0), (0.7, -0.8, -0.5), (0.95, 0.3, 0.25), (0.6, 1.1, 2.0)]


@pytest.fixture(scope="module")
def affine_fmu(tmp_path_factory):
    import fmus

    return fmus.build_fmu(affine_block(), cache_dir=tmp_path_factory.getbasetemp() / "fmu-cache")


def ring_system(path) -> CoupledSystem:
    slaves = [FmuSlave(f"s{i}", path) for i in range(4)]
    return CoupledSystem(slaves, [Link(a, "y", b, "u") for a, b in RING], [(i, "y") for i in range(4)])


def ring_exact(order, n: int) -> np.ndarray:
    """Outputs at t_0..t_n of the ring under Gauss-Seidel in ``order``, from the convention alone:
    each slave, in turn, takes its source's *current* output (already stepped this macro step or
    not) and applies its own affine map."""
    src = {b: a for a, b in RING}
    y = np.array([x0 for _, _, x0 in RING_PARAMS])
    rows = [y.copy()]
    for _ in range(n):
        for i in order:
            a, b, _ = RING_PARAMS[i]
            y[i] = a * y[i] + b * y[src[i]]
        rows.append(y.copy())
    return np.array(rows)


@pytest.mark.parametrize("engine", ["oracle", "compiled"])
@pytest.mark.parametrize("order", [None, (3, 2, 1, 0), (2, 0, 3, 1)], ids=["default", "reversed", "shuffled"])
def test_gauss_seidel_steps_slaves_in_its_order_not_the_declaration_order(affine_fmu, engine, order):
    """Four FMUs in a ring: every stepping order gives a different exact map.  The default order
    cuts one connection of the ring (0, 3, 1, 2: the declaration order would cut two); an
    explicit order is followed as given, by the compiled loop as by the Python loop."""
    want = [0, 3, 1, 2] if order is None else list(order)
    start = [{"a": a, "b": b, "x0": x0} for a, b, x0 in RING_PARAMS]
    tr, st = run(ring_system(affine_fmu), "gauss_seidel", 10_000_000, 30, engine=engine, order=order,
                 start_values=start)
    assert st.engine == engine and st.status == "ok"
    assert gauss_seidel_order(4, RING) == [0, 3, 1, 2]
    np.testing.assert_allclose(tr.data[:, 1:], ring_exact(want, 30), rtol=1e-13, atol=1e-13)
    # the declaration order is a different map: this test could tell them apart
    assert np.abs(ring_exact(want, 30) - ring_exact(range(4), 30)).max() > 0.1


# --- the compiled loop's own build -----------------------------------------------------------------
@pytest.fixture
def fresh_loop_library(tmp_path, monkeypatch):
    """The loop library forgotten, with an empty cache under ``tmp_path``; forgotten again after."""
    from cosim.master import fastloop

    monkeypatch.setenv("RPR_COSIM_CACHE", str(tmp_path / "fmus"))
    fastloop.library.cache_clear()
    yield fastloop
    fastloop.library.cache_clear()


def test_the_compiled_loop_builds_into_an_empty_cache(fresh_loop_library, tmp_path):
    dll = fresh_loop_library.library()
    assert dll.rpr_run is not None
    assert len(list((tmp_path / "master").glob("rpr_loop_*.so"))) == 1


def test_without_a_c_compiler_the_compiled_loop_says_so(fresh_loop_library, monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    with pytest.raises(UserError, match=r"needs a C compiler .*/nonexistent/cc.*No such file.*\$CC"):
        fresh_loop_library.library()


@pytest.mark.parametrize("alg", ["jacobi", "adaptive"])
def test_without_a_c_compiler_a_run_says_so_before_it_starts(fresh_loop_library, monkeypatch, alg):
    """No silent fallback to a Python loop: a run on a machine without a working C compiler (an
    empty build cache, $CC naming none) ends at its start with one line naming the compiler, before
    any slave is initialised."""
    from cosim.master import adaptive_engine

    monkeypatch.setenv("CC", "/nonexistent/cc")
    adaptive_engine.library.cache_clear()

    def initialize(*a, **kw):
        raise AssertionError("the slaves were initialised before the compiler was checked")
    monkeypatch.setattr(sys.modules["cosim.master.simulate"], "initialize", initialize)
    system = pair(0.0)
    try:
        for engine in ("auto", "compiled"):
            with pytest.raises(UserError) as err:
                simulate(system, alg, step_ns=50_000_000, n_steps=4, engine=engine)
            msg = str(err.value)
            assert msg.startswith("a run needs a C compiler for its master loop, and none works here (/nonexistent/cc")
            assert msg.endswith("install gcc or point $CC to a working C compiler") and "\n" not in msg
    finally:
        adaptive_engine.library.cache_clear()


def test_master_engine_python_is_gone():
    """``python`` is no longer an engine (the Python loops are test oracles): one line naming the key
    and what it takes, from the Python API, a scene and the CLI."""
    from cosim.master.engine import PYTHON_GONE

    with pytest.raises(UserError) as err:
        simulate(pair(0.0), "jacobi", step_ns=50_000_000, n_steps=4, engine="python")
    assert str(err.value) == PYTHON_GONE
    assert PYTHON_GONE.startswith("master.engine: python is gone") and "use auto or compiled" in PYTHON_GONE
    with pytest.raises(UserError, match="master.engine must be one of auto, compiled, oracle, got 'fast'"):
        simulate(pair(0.0), "jacobi", step_ns=50_000_000, n_steps=4, engine="fast")


def test_master_engine_python_is_gone_from_the_cli_and_the_scene(tmp_path, capsys):
    from cosim.cli import main
    from cosim.master.engine import PYTHON_GONE
    from cosim.scenario import SceneError, load

    scene = Path(__file__).resolve().parents[1] / "scenarios" / "two_mass.yaml"
    assert main(["run", str(scene), "--engine", "python", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err == f"rpr-cosim run: error: {PYTHON_GONE}\n"  # one line, no traceback
    text = tmp_path / "py.yaml"
    text.write_text(scene.read_text().replace("master: {", "master: {engine: python, ", 1))
    with pytest.raises(SceneError) as exc:
        load(text)
    assert "py.yaml:" in str(exc.value) and PYTHON_GONE in str(exc.value) and "Traceback" not in str(exc.value)


# --- structure ---------------------------------------------------------------------------------
@pytest.mark.parametrize("n,edges,order", [
    (3, [(0, 1), (1, 2)], [0, 1, 2]),
    (3, [(2, 1), (1, 0)], [2, 1, 0]),
    (2, [(0, 1), (1, 0)], [0, 1]),
    # pid_step-like: source 0 -> pid 1; loop pid 1 -> motor 2 -> mech 3 -> motor 2, mech 3 -> pid 1;
    # the fewest cut edges (one: motor -> mech) puts the mechanism first
    (4, [(0, 1), (1, 2), (2, 3), (3, 2), (3, 1)], [0, 3, 1, 2]),
])
def test_gauss_seidel_order_cuts_the_fewest_connections(n, edges, order):
    assert gauss_seidel_order(n, edges) == order


def test_gauss_seidel_order_of_a_large_group_follows_the_greedy_rule():
    """Beyond seven slaves the order is greedy, by out-degree minus in-degree among the slaves
    not yet placed: on a chain of nine closed by one connection back (at least one cut) that
    rule finds the single cut."""
    edges = [(k, k + 1) for k in range(8)] + [(8, 0)]
    order = gauss_seidel_order(9, edges)
    pos = {v: k for k, v in enumerate(order)}
    assert sorted(order) == list(range(9))
    assert sum(pos[a] > pos[b] for a, b in edges) == 1


def test_gauss_seidel_order_cuts_the_fewest_connections_in_a_group_of_seven():
    """Seven slaves in one strongly connected group: the order is searched exhaustively (the
    greedy rule used beyond seven cuts five connections here); the fewest cuts, by brute force
    over all 5040 orders, is four."""
    edges = [(0, 2), (0, 3), (0, 6), (1, 0), (1, 3), (1, 4), (2, 3), (2, 6), (3, 0), (3, 4), (4, 0), (4, 1),
             (4, 2), (4, 5), (5, 2), (6, 0)]

    def cuts(order):
        pos = {v: k for k, v in enumerate(order)}
        return sum(pos[a] > pos[b] for a, b in edges)

    fewest = min(cuts(p) for p in itertools.permutations(range(7)))
    assert fewest == 4
    assert cuts(gauss_seidel_order(7, edges)) == fewest


@pytest.mark.parametrize("edges,has_loop", [
    ([("a.y", "b.u"), ("b.u", "b.y"), ("b.y", "a.u")], False),
    ([("a.y", "b.u"), ("b.u", "b.y"), ("b.y", "a.u"), ("a.u", "a.y")], True),
])
def test_algebraic_loop_detection(edges, has_loop):
    cyc = find_algebraic_loop(edges)
    assert (cyc is not None) == has_loop
    if cyc:
        assert cyc[0] == cyc[-1] and all((a, b) in edges for a, b in zip(cyc, cyc[1:]))


def test_the_master_refuses_an_algebraic_loop_of_feedthrough_slaves():
    a = LinearSlave("a", [[-1.0]], [[1.0]], [[1.0]], [[1.0]])
    b = LinearSlave("b", [[-1.0]], [[1.0]], [[1.0]], [[1.0]])
    system = CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]"), Link(1, "y[1]", 0, "u[1]")], [(0, "y[1]")])
    mem = MemoryTrace()
    with pytest.raises(UserError, match=r"algebraic loop: .*a\.y\[1\] -> b\.u\[1\]"):
        simulate(system, "gauss_seidel", step_ns=1_000_000, n_steps=3, observers=[mem])
    # refused before any step: the observers hear so, with no step counted
    assert mem.trace.status == "failed" and "algebraic loop" in mem.trace.reason
    assert mem.trace.stats["steps_done"] == 0 and mem.trace.stats["steps_planned"] == 3


def test_jacobi_runs_an_algebraic_loop_with_its_one_step_delay():
    """Jacobi needs no order: each output on the loop is read at t_k from inputs of t_k-1."""
    a = LinearSlave("a", [[-1.0]], [[1.0]], [[1.0]], [[0.5]])
    b = LinearSlave("b", [[-1.0]], [[1.0]], [[1.0]], [[0.5]])
    system = CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]"), Link(1, "y[1]", 0, "u[1]")], [(0, "y[1]")])
    mem = MemoryTrace()
    stats = simulate(system, "jacobi", step_ns=1_000_000, n_steps=3, observers=[mem])
    assert stats.status == "ok" and mem.trace.stats["steps_done"] == 3


def test_registry_suggests_the_closest_algorithm():
    with pytest.raises(UserError, match="did you mean 'gauss_seidel'"):
        algorithm("gauss_siedel")
    assert set(ALGORITHMS) >= {"jacobi", "gauss_seidel"}


def test_every_algorithm_module_is_listed_and_registers_its_class():
    """cosim.master.algorithms imports the modules in MODULES: a module added to the package but
    not to the list would never register, so the list must name every module found on disk, and
    each module must contribute an Algorithm subclass to the registry under its name."""
    import pkgutil

    from cosim.master import algorithms

    on_disk = {m.name for m in pkgutil.iter_modules(algorithms.__path__)}
    assert set(algorithms.MODULES) == on_disk
    owners = {cls.__module__.rsplit(".", 1)[-1] for cls in ALGORITHMS.values()}
    assert on_disk <= owners


def test_an_algorithm_without_kernel_or_python_step_is_refused_when_registered():
    """The extension point's contract: no compiled loop and no _step_impl is said at @register,
    naming the class, not as a NotImplementedError at the run's first step."""
    with pytest.raises(TypeError, match=r"'test_nothing' \(.*Nothing\) has no compiled loop .* no _step_impl"):
        @register
        class Nothing(Algorithm):
            name = "test_nothing"
    assert "test_nothing" not in ALGORITHMS


def test_a_registered_algorithm_runs_through_the_same_loop():
    """The extension point: a subclass implementing only _step_impl (here Gauss-Seidel in the
    reverse order) is found by name and produces the map its convention implies."""

    @register
    class Reverse(Algorithm):
        name = "test_reverse_gs"

        def _step_impl(self, t, h):
            for i in reversed(range(len(self._do))):
                self._gather[i]()
                for st in (self._io(i, self._push[i]), self._advance(i, t, h), self._io(i, self._pull[i])):
                    if st >= Status.DISCARD:
                        return i, st
            return None

    try:
        tr, st = run(pair(0.0), "test_reverse_gs", 50_000_000, 20)
        assert st.engine == "python"  # no compiled variant
        # B first with A's old output, then A with B's fresh output
        ea, eb = math.exp(-A_ * 0.05), math.exp(-B_ * 0.05)
        ga, gb = (1 - ea) / A_, (1 - eb) / B_
        xa, xb = XA0, XB0
        for _ in range(20):
            xb = eb * xb + gb * xa
            xa = ea * xa + ga * C_ * xb
        assert tr.data[-1, 1] == pytest.approx(xa, abs=1e-14)
        assert tr.data[-1, 4] == pytest.approx(xb, abs=1e-14)
    finally:
        ALGORITHMS.pop("test_reverse_gs")


def test_a_trace_cut_short_by_a_crash_reads_back_without_its_broken_row(tmp_path):
    csv = CsvTrace(tmp_path / "t.csv", commented=True)  # the form whose status line ends the file
    simulate(pair(), "jacobi", step_ns=1_000_000, n_steps=50, observers=[csv])
    text = (tmp_path / "t.csv").read_text()
    data_end = text.index("# status")
    cut = text[:data_end - 20]  # the writer died in the middle of the last row
    (tmp_path / "t.csv").write_text(cut)
    back = read_trace(tmp_path / "t.csv")
    assert back.status == "" and len(back.data) == 50 and back.time[-1] == pytest.approx(0.049)
    (tmp_path / "bad.csv").write_text(cut[:cut.index("\n0.01")] + "\n0.01,oops,1,2,3\n" + cut[cut.index("\n0.01"):])
    with pytest.raises(UserError, match=r"bad\.csv:\d+: expected 5 numbers separated by commas"):
        read_trace(tmp_path / "bad.csv")
