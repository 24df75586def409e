"""The fixed-step kernel (cosim/master/fastloop.c) on the scenes it once refused: slaves without C
entry points (Python slaves, called through trampolines, cosim/master/callbacks.py), connections
with a linear transformation, a start time other than 0, and jacobi_extrapolated's extrapolated
inputs.  Each against the Python loop bit for bit and against an independent source: the exact
solution of the linear pair (its matrix exponential), the time invariance of the pair (a later
start gives the same values), the hand-computed transformation."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from cosim.master import CoupledSystem, Link, simulate
from cosim.run.execute import run as run_scene
from cosim.slaves.linear import LinearSlave
from cosim.slaves.slave import Status
from cosim.trace.traces import MemoryTrace

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
FIXED = ("jacobi", "gauss_seidel", "jacobi_extrapolated")
A_, B_, C_ = 1.0, 3.0, 0.8


def pair(factor: float = 1.0, offset: float = 0.0, cls=LinearSlave) -> CoupledSystem:
    """x_a' = -a x_a + u_a, x_b' = -b x_b + u_b with u_b = factor x_a + offset, u_a = c x_b."""
    a = cls("a", [[-A_]], [[1.0]], [[1.0]], x0=[1.0])
    b = cls("b", [[-B_]], [[1.0]], [[C_]], x0=[-0.4])
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]", factor=factor, offset=offset), Link(1, "y[1]", 0, "u[1]")],
                         [(0, "y[1]"), (1, "x[1]"), (1, "u[1]")])


def run(system: CoupledSystem, alg: str, engine: str, n: int = 200, step_ns: int = 10_000_000, **kw):
    mem = MemoryTrace()
    stats = simulate(system, alg, step_ns=step_ns, n_steps=n, observers=[mem], engine=engine, **kw)
    return mem.trace, stats


@pytest.mark.parametrize("alg", FIXED)
@pytest.mark.parametrize("factor, offset", [(1.0, 0.0), (0.37, 0.0), (-1.5, 0.25)])
@pytest.mark.parametrize("start_ns", [0, 2_500_000_001])
def test_python_slaves_transformed_and_late_start_equal_the_python_loop(alg, factor, offset, start_ns):
    py, s1 = run(pair(factor, offset), alg, "oracle", start_ns=start_ns)
    cc, s2 = run(pair(factor, offset), alg, "compiled", start_ns=start_ns)
    assert (s1.engine, s2.engine) == ("oracle", "compiled") and s2.status == "ok"
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    assert {k: x["do_step_calls"] for k, x in s1.slaves.items()} == {k: x["do_step_calls"] for k, x in s2.slaves.items()}


@pytest.mark.parametrize("alg", FIXED)
def test_a_late_start_shifts_the_times_only(alg):
    """The pair is time invariant: from t0 = 2.5 s the values are those from 0, the times t0 + k h
    (integer nanoseconds, so exactly the grid's)."""
    t0_ns = 2_500_000_000
    base, _ = run(pair(), alg, "compiled", n=50)
    late, st = run(pair(), alg, "compiled", n=50, start_ns=t0_ns)
    assert st.engine == "compiled" and st.status == "ok"
    assert np.array_equal(base.data[:, 1:], late.data[:, 1:])
    assert np.array_equal(late.time, np.array([(t0_ns + k * 10_000_000) / 1e9 for k in range(51)]))


@pytest.mark.parametrize("alg", FIXED)
def test_the_kernel_applies_the_transformation_as_the_exact_solution_says(alg):
    """u_b = f x_a + o: the coupled linear system x' = M x + [0, o] has an exact solution; every
    algorithm converges to it (first order for Jacobi and Gauss-Seidel: within 2 % at 10 ms), and
    the recorded input is f y_a + o of the row before (Jacobi) or of the same row (Gauss-Seidel)."""
    f, o = -1.5, 0.25
    tr, st = run(pair(f, o), alg, "compiled", n=100)
    assert st.engine == "compiled" and st.status == "ok"
    M = np.array([[-A_, C_], [f, -B_]])
    aug = np.zeros((3, 3))
    aug[:2, :2], aug[1, 2] = M, o
    ref = (scipy.linalg.expm(aug * 1.0) @ np.array([1.0, -0.4, 1.0]))[:2]
    assert abs(tr.data[-1, 1] - ref[0]) < 2e-2 * abs(ref[0])
    assert abs(tr.data[-1, 2] - ref[1]) < 2e-2 * abs(ref[1])
    ya, ub = tr.data[:, 0 + 1], tr.data[:, 2 + 1]
    if alg == "gauss_seidel":  # a steps first: b's input is a's fresh output
        assert np.array_equal(ub[1:], ya[1:] * f + o)
    elif alg == "jacobi":  # the output read at t_k
        assert np.array_equal(ub[1:], ya[:-1] * f + o)


def test_jacobi_extrapolated_in_the_kernel_is_second_order():
    """The compiled jacobi_extrapolated against the exact pair: the error falls at order 2."""
    errors = []
    for h_ms in (40, 20, 10):
        tr, st = run(pair(), "jacobi_extrapolated", "compiled", n=1000 // h_ms, step_ns=h_ms * 1_000_000)
        assert st.engine == "compiled" and st.status == "ok"
        ref = scipy.linalg.expm(np.array([[-A_, C_], [1.0, -B_]])) @ np.array([1.0, -0.4])
        errors.append(max(abs(tr.data[-1, 1] - ref[0]), abs(tr.data[-1, 2] - ref[1])))
    orders = [math.log2(a / b) for a, b in zip(errors, errors[1:])]
    assert all(1.85 < p < 2.15 for p in orders), errors


class Exploding(LinearSlave):
    """Raises in its 6th doStep (a Python model's error)."""

    def do_step(self, t, h):
        self.steps = getattr(self, "steps", 0) + 1
        if self.steps == 6:
            raise ZeroDivisionError(f"model error at t = {t:.3f}")
        return super().do_step(t, h)


class Stopping(LinearSlave):
    """Asks to end the simulation in its 6th doStep (FMI 3.0 terminateSimulation)."""

    def do_step(self, t, h):
        self.steps = getattr(self, "steps", 0) + 1
        st = super().do_step(t, h)
        return Status.STOP_REQUESTED if self.steps == 6 else st


@pytest.mark.parametrize("alg", FIXED)
def test_a_python_slaves_exception_comes_out_of_the_kernel_as_it_would_from_the_python_loop(alg):
    for engine in ("oracle", "compiled"):
        system = pair(cls=Exploding)
        with pytest.raises(ZeroDivisionError, match="model error at t = 0.050"):
            run(system, alg, engine)
        assert system.slaves[0].steps == 6  # the kernel made no call after the failing one


@pytest.mark.parametrize("alg", FIXED)
def test_a_python_slaves_stop_request_ends_the_run_as_in_the_python_loop(alg):
    py, s1 = run(pair(cls=Stopping), alg, "oracle")
    cc, s2 = run(pair(cls=Stopping), alg, "compiled")
    assert s2.engine == "compiled" and s1.status == s2.status == "stopped" and s1.reason == s2.reason
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    assert cc.time[-1] == pytest.approx(0.06, abs=1e-12)


def typed_run(reference_fmus, fmi: str, master: dict, engine: str):
    """VanDerPol feeding Reference FMU Feedthrough, whose Int32, Boolean and String outputs are
    recorded (so Feedthrough is a callback slave, its typed part converted in Python), run with
    ``master`` on ``engine``."""
    from cosim.scenario import from_dict

    return run_scene(from_dict({"name": "typed", "stop_time": 0.5, "components": {
        "vdp": {"fmu": str(reference_fmus[f"{fmi}/VanDerPol"])},
        "ft": {"fmu": str(reference_fmus[f"{fmi}/Feedthrough"]), "start": {"String_input": "abc", "Int32_input": 7}}},
        "connections": ["vdp.x0 -> ft.Float64_continuous_input"], "master": {**master, "engine": engine},
        "outputs": ["vdp.x0", "ft.Float64_continuous_output", "ft.Int32_output", "ft.Boolean_output",
                    "ft.String_output"]}))


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_typed_ports_run_in_the_kernel_as_in_the_python_loop(reference_fmus, fmi):
    """Feedthrough with Int32, Boolean and String outputs recorded: that FMU
    becomes a callback slave (its typed part converted in Python), VanDerPol stays a direct FMU;
    the compiled trace, text included, equals the Python loop's."""
    py, cc = (typed_run(reference_fmus, fmi, {"algorithm": "gauss_seidel", "step": 0.01, "order": ["vdp", "ft"]}, e)
              for e in ("oracle", "compiled"))
    assert (py.stats["engine"], cc.stats["engine"]) == ("oracle", "compiled") and cc.status == "ok", cc.reason
    assert np.array_equal(py.trace.time, cc.trace.time) and np.array_equal(py.trace.data, cc.trace.data)
    assert py.trace.text == cc.trace.text and cc.trace.text
    assert np.all(cc.trace["ft.Int32_output"] == 7) and cc.trace.text["ft.String_output"] == [(0.0, "abc")]


def bonded_pair(cls=LinearSlave) -> CoupledSystem:
    """The linear pair with its two links one power bond (ecco needs one): effort x_a, flow c x_b."""
    a = cls("a", [[-A_]], [[1.0]], [[1.0]], x0=[1.0])
    b = cls("b", [[-B_]], [[1.0]], [[C_]], x0=[-0.4])
    bond = "a.y[1] <-> b.y[1]"
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]", bond=bond), Link(1, "y[1]", 0, "u[1]", bond=bond)],
                         [(0, "y[1]"), (1, "x[1]")])


def test_ecco_runs_python_slaves_in_its_kernel_as_in_the_python_loop():
    """ecco never rolls back: its kernel (adaptive_engine.c) calls Python slaves through callbacks,
    the same steps and values as its Python loop, and within 1 % of the exact solution at t = 1 s."""
    py, s1 = run(bonded_pair(), "ecco", "oracle", n=100)
    cc, s2 = run(bonded_pair(), "ecco", "compiled", n=100)
    assert (s1.engine, s2.engine) == ("oracle", "compiled") and s2.status == "ok", s2.reason
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    ref = scipy.linalg.expm(np.array([[-A_, C_], [1.0, -B_]])) @ np.array([1.0, -0.4])
    assert cc.time[-1] == 1.0
    assert abs(cc.data[-1, 1] - ref[0]) < 1e-2 * abs(ref[0]) and abs(cc.data[-1, 2] - ref[1]) < 1e-2 * abs(ref[1])


def test_ecco_passes_a_python_slaves_exception_on():
    system = bonded_pair(cls=Exploding)
    with pytest.raises(ZeroDivisionError, match="model error"):
        run(system, "ecco", "compiled", n=100)
    assert system.slaves[0].steps == 6


def test_adaptive_rolls_python_slaves_back_in_its_kernel_as_in_the_python_loop():
    """adaptive saves and restores every slave's state around a rejected step: a Python slave does
    it through its own save_state/restore_state behind the FMU state trampolines.  The same
    accepted and rejected steps, the same values as its Python loop, and within its tolerance's
    reach of the exact solution at t = 1 s."""
    opts = {"rtol": 1e-3}  # a tolerance at which the first proposal is rejected (measured: one rollback)
    py, s1 = run(bonded_pair(), "adaptive", "oracle", n=5, step_ns=200_000_000, options=opts)
    cc, s2 = run(bonded_pair(), "adaptive", "compiled", n=5, step_ns=200_000_000, options=opts)
    assert (s1.engine, s2.engine) == ("oracle", "compiled") and s2.status == "ok", s2.reason
    assert s2.adaptive["rollbacks"] > 0 and s1.adaptive == s2.adaptive
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    ref = scipy.linalg.expm(np.array([[-A_, C_], [1.0, -B_]])) @ np.array([1.0, -0.4])
    assert cc.time[-1] == 1.0 and abs(cc.data[-1, 1] - ref[0]) < 1e-2 * abs(ref[0])


# --- the variable-step kernel (adaptive_engine.c): transformed connections and typed ports -----------

def bonded_trio(factor: float, offset: float) -> CoupledSystem:
    """The bonded pair and a third lag c fed by a's output through a transformation:
    x_c' = -x_c + (factor y_a + offset)."""
    sysm = bonded_pair()
    c = LinearSlave("c", [[-1.0]], [[1.0]], [[1.0]], x0=[0.2])
    return CoupledSystem([*sysm.slaves, c], [*sysm.links, Link(0, "y[1]", 2, "u[1]", factor=factor, offset=offset)],
                         [(0, "y[1]"), (1, "x[1]"), (2, "x[1]"), (2, "u[1]")])


def _exact_trio(f: float, o: float, t: float) -> np.ndarray:
    """The exact states (x_a, x_b, x_c) of :func:`bonded_trio` at ``t`` [s] (the offset as a fourth,
    constant state)."""
    M = np.zeros((4, 4))
    M[:3, :3] = [[-A_, C_, 0.0], [1.0, -B_, 0.0], [f, 0.0, -1.0]]
    M[2, 3] = o
    return (scipy.linalg.expm(M * t) @ np.array([1.0, -0.4, 0.2, 1.0]))[:3]


@pytest.mark.parametrize("alg", ["adaptive", "ecco"])
@pytest.mark.parametrize("factor, offset", [(0.37, 0.0), (-1.5, 0.25)])
def test_variable_step_kernel_runs_transformed_connections_as_the_python_loop(alg, factor, offset):
    """A connection with a factor and an offset no longer sends adaptive or ecco to their Python
    loops: the kernel gives the same steps and values bit for bit, the recorded input of c is the
    transformation of a's output at the same row, and the states are within 1 % of the exact
    solution at t = 1 s."""
    opts = {"rtol": 1e-3} if alg == "adaptive" else None
    kw = dict(n=5, step_ns=200_000_000, options=opts)
    py, s1 = run(bonded_trio(factor, offset), alg, "oracle", **kw)
    cc, s2 = run(bonded_trio(factor, offset), alg, "compiled", **kw)
    assert (s1.engine, s2.engine) == ("oracle", "compiled") and s2.status == "ok", s2.reason
    assert s1.adaptive == s2.adaptive and s2.adaptive["accepted_steps"] > 5
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    assert np.array_equal(cc.data[1:, 4], cc.data[1:, 1] * factor + offset)  # a steps before c (Gauss-Seidel)
    ref = _exact_trio(factor, offset, 1.0)
    assert cc.time[-1] == 1.0
    assert np.all(np.abs(cc.data[-1, [1, 2, 3]] - ref) < 1e-2 * np.abs(ref)), (cc.data[-1], ref)


@pytest.mark.parametrize("alg", ["adaptive", "ecco"])
def test_variable_step_kernel_applies_the_transformation_to_linear_inputs(alg):
    """FMUs that follow their inputs' slopes (pid_step, a motor's voltage through 0.8 u + 0.1):
    the kernel transforms the input and its slope as the Python loop does, bit for bit, with the
    same accepted and rejected steps."""
    from cosim.scenario import load

    sets = {"master.algorithm": alg, "stop_time": 0.05}
    if alg == "ecco":
        sets["components.mech.rollback"] = False
    sc = load(SCENARIOS / "pid_step.yaml", sets)
    text = Path(sc.path).read_text().replace("pid1.y -> motor1.u", "pid1.y -> motor1.u * 0.8 + 0.1")
    py, cc = (_scene_text_run(text, sets, engine) for engine in ("oracle", "compiled"))
    assert (py.stats["engine"], cc.stats["engine"]) == ("oracle", "compiled") and cc.status == "ok", cc.reason
    assert np.array_equal(py.trace.data, cc.trace.data)
    keys = ("accepted_steps", "rejected_steps", "rollbacks", "smallest_step", "largest_step")
    assert {k: py.stats.get(k) for k in keys} == {k: cc.stats.get(k) for k in keys}
    plain = run_scene(SCENARIOS / "pid_step.yaml", sets, engine="compiled")
    assert not np.array_equal(plain.trace["motor1.i"], cc.trace["motor1.i"])  # the transformation acts


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_typed_ports_run_in_the_adaptive_kernel_as_in_the_python_loop(reference_fmus, fmi):
    """adaptive with Feedthrough's Int32, Boolean and String outputs recorded (a callback slave,
    rolled back through its own save_state/restore_state): the compiled trace, text included,
    equals the Python loop's, with the same rejections."""
    py, cc = (typed_run(reference_fmus, fmi, {"algorithm": "adaptive", "output_interval": 0.05}, e)
              for e in ("oracle", "compiled"))
    assert (py.stats["engine"], cc.stats["engine"]) == ("oracle", "compiled") and cc.status == "ok", cc.reason
    assert np.array_equal(py.trace.time, cc.trace.time) and np.array_equal(py.trace.data, cc.trace.data)
    assert py.stats["rejected_steps"] == cc.stats["rejected_steps"]
    assert py.trace.text == cc.trace.text and cc.trace.text["ft.String_output"] == [(0.0, "abc")]
    assert np.all(cc.trace["ft.Int32_output"] == 7)
    assert np.array_equal(cc.trace["ft.Float64_continuous_output"], cc.trace["vdp.x0"])  # feedthrough, unchanged


def test_typed_ports_run_in_the_ecco_kernel_as_in_the_python_loop(reference_fmus):
    """ecco on pid_step with a Feedthrough FMU (typed outputs recorded) on a PID's output: bit for bit."""
    from cosim.scenario import load

    sets = {"master.algorithm": "ecco", "stop_time": 0.02, "components.mech.rollback": False}
    sc = load(SCENARIOS / "pid_step.yaml", sets)
    text = Path(sc.path).read_text().replace(
        "components:\n", f"components:\n  ft: {{fmu: {reference_fmus['3.0/Feedthrough']}, "
                         "start: {String_input: abc, Int32_input: 7}}\n", 1).replace(
        "connections:\n", "connections:\n  - pid1.y -> ft.Float64_continuous_input\n", 1).replace(
        "outputs:\n", "outputs:\n  - ft.Int32_output\n  - ft.String_output\n  - ft.Float64_continuous_output\n", 1)
    py, cc = (_scene_text_run(text, sets, engine) for engine in ("oracle", "compiled"))
    assert (py.stats["engine"], cc.stats["engine"]) == ("oracle", "compiled") and cc.status == "ok", cc.reason
    assert np.array_equal(py.trace.data, cc.trace.data) and py.trace.text == cc.trace.text
    assert cc.trace.text["ft.String_output"] == [(0.0, "abc")]
    assert np.array_equal(cc.trace["ft.Float64_continuous_output"], cc.trace["pid1.y"])


def _scene_text_run(text: str, sets: dict, engine: str):
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "s.yaml"
        p.write_text(text)
        return run_scene(p, sets, engine=engine)


# --- iterative's kernel (iterative_engine.c): Python slaves, transformed connections, typed ports -----

D_A, D_B = 0.5, 0.4


def loop_pair(factor: float, offset: float, cls=LinearSlave) -> CoupledSystem:
    """An algebraic loop driven by a source: y_a = x_a + d_a u_a, y_b = c x_b + d_b u_b, with
    u_b = factor y_a + offset, u_a = y_b; x_b' = -b x_b + u_b + x_s, the source x_s' = -x_s
    (x_s(0) = 1, the others 0: with offset 0 the start is consistent, so Newton's first Jacobian
    is built in the first step, by the kernel)."""
    src = cls("s", [[-1.0]], np.zeros((1, 0)), [[1.0]], x0=[1.0])
    a = cls("a", [[-A_]], [[1.0]], [[1.0]], [[D_A]], x0=[0.0])
    b = cls("b", [[-B_]], [[1.0, 1.0]], [[C_]], [[D_B, 0.0]], x0=[0.0])
    return CoupledSystem([src, a, b], [Link(1, "y[1]", 2, "u[1]", factor=factor, offset=offset),
                                       Link(2, "y[1]", 1, "u[1]"), Link(0, "y[1]", 2, "u[2]")],
                         [(1, "x[1]"), (2, "x[1]"), (1, "y[1]"), (2, "y[1]"), (1, "u[1]"), (2, "u[1]")])


def _exact_loop(f: float, o: float, t: float) -> np.ndarray:
    """The states (x_a, x_b) of :func:`loop_pair` at ``t`` [s] with the loop solved by hand:
    u_a = (c x_b + d_b f x_a + d_b o) / (1 - d_a d_b f), u_b = f (x_a + d_a u_a) + o."""
    den = 1.0 - D_A * D_B * f
    ua = np.array([D_B * f, C_, 0.0, D_B * o]) / den  # u_a as a row over (x_a, x_b, x_s, 1)
    ub = f * (np.array([1.0, 0.0, 0.0, 0.0]) + D_A * ua) + np.array([0.0, 0.0, 0.0, o])
    M = np.zeros((4, 4))
    M[0] = np.array([-A_, 0.0, 0.0, 0.0]) + ua
    M[1] = np.array([0.0, -B_, 1.0, 0.0]) + ub
    M[2, 2] = -1.0
    return (scipy.linalg.expm(M * t) @ np.array([0.0, 0.0, 1.0, 1.0]))[:2]


ITER_OPTIONS = {"newton": {}, "finite_difference": {"jacobian": "finite_difference"},
                "fixed_point": {"method": "fixed_point", "omega": 0.7}}
ITER_KEYS = ("iterations_total", "start_iterations", "rollbacks", "jacobians", "directional_derivatives",
             "finite_difference_steps", "broyden_updates")


@pytest.mark.parametrize("method", sorted(ITER_OPTIONS))
@pytest.mark.parametrize("factor, offset", [(1.0, 0.0), (-1.5, 0.0), (0.6, 0.25)])
@pytest.mark.parametrize("inputs", ["hold", "linear"])
def test_iterative_kernel_runs_python_slaves_and_transformed_loops_as_the_python_loop(method, factor, offset, inputs):
    """Python slaves in an algebraic loop through a transformed connection: the kernel calls them
    back, Newton's Jacobian from their output_jacobian behind the directional-derivative
    trampoline (the factor in the chain rule), or from finite differences of their steps; the
    same values bit for bit, the same passes, Jacobians and Broyden updates as the Python loop."""
    kw = dict(n=50, options=ITER_OPTIONS[method], inputs=inputs)
    py, s1 = run(loop_pair(factor, offset), "iterative", "oracle", **kw)
    cc, s2 = run(loop_pair(factor, offset), "iterative", "compiled", **kw)
    assert (s1.engine, s2.engine) == ("oracle", "compiled") and s2.status == "ok", s2.reason
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)
    assert {k: s1.extra[k] for k in ITER_KEYS} == {k: s2.extra[k] for k in ITER_KEYS}
    assert s2.extra["rollbacks"] > 0
    if offset == 0.0 and method != "fixed_point":  # a consistent start: the Jacobians were the kernel's
        assert s2.extra["start_iterations"] == 1 and s2.extra["jacobians"] > 0
    if method == "newton":
        assert s2.extra["directional_derivatives"] > 0 and s2.extra["finite_difference_steps"] == 0
    elif method == "finite_difference":
        assert s2.extra["directional_derivatives"] == 0
        assert s2.extra["finite_difference_steps"] > 0 or offset != 0.0


def test_the_iterative_kernel_solves_the_transformed_loop():
    """Independent of the Python loop: at every row the loop's equations hold (u_b the
    transformation of y_a as computed, u_a = y_b to the convergence tolerance), and the states
    converge to the exact solution of the loop solved by hand at first order (held inputs)."""
    f, o = -1.5, 0.25
    errors = []
    for h_ms in (20, 10):
        tr, st = run(loop_pair(f, o), "iterative", "compiled", n=1000 // h_ms, step_ns=h_ms * 1_000_000)
        assert st.engine == "compiled" and st.status == "ok", st.reason
        xa, xb, ya, yb, ua, ub = (tr.data[:, k] for k in range(1, 7))
        assert np.array_equal(ub, ya * f + o)
        assert np.allclose(ua, yb, rtol=1e-7, atol=1e-9)
        assert np.allclose(ya, xa + D_A * ua, rtol=1e-14, atol=0)
        errors.append(np.max(np.abs(np.array([xa[-1], xb[-1]]) - _exact_loop(f, o, 1.0))))
    assert errors[1] < 2e-2 and 1.8 < errors[0] / errors[1] < 2.2, errors  # first order in h


class NoJacobian(LinearSlave):
    """A Python slave that provides no output Jacobian (Slave's default): Newton takes finite differences."""

    def output_jacobian(self, outputs, inputs):
        return None


def test_iterative_kernel_falls_back_to_finite_differences_for_a_python_slave_without_jacobian():
    py, s1 = run(loop_pair(0.8, 0.0, cls=NoJacobian), "iterative", "oracle", n=30)
    cc, s2 = run(loop_pair(0.8, 0.0, cls=NoJacobian), "iterative", "compiled", n=30)
    assert s2.extra["start_iterations"] == 1  # every Jacobian the kernel's
    assert s2.engine == "compiled" and s2.status == "ok", s2.reason
    assert np.array_equal(py.data, cc.data)
    assert {k: s1.extra[k] for k in ITER_KEYS} == {k: s2.extra[k] for k in ITER_KEYS}
    assert s2.extra["finite_difference_steps"] > 0 and s2.extra["directional_derivatives"] == 0


def test_iterative_kernel_passes_a_python_slaves_exception_and_stop_request_on():
    steps = []
    for engine in ("oracle", "compiled"):
        system = loop_pair(1.0, 0.0, cls=Exploding)
        with pytest.raises(ZeroDivisionError, match="model error"):
            run(system, "iterative", engine, n=50)
        steps.append([getattr(s, "steps", 0) for s in system.slaves])
    assert steps[0] == steps[1] and max(steps[1]) == 6  # the kernel made no call after the failing one
    py, s1 = run(loop_pair(1.0, 0.0, cls=Stopping), "iterative", "oracle", n=50)
    cc, s2 = run(loop_pair(1.0, 0.0, cls=Stopping), "iterative", "compiled", n=50)
    assert s2.engine == "compiled" and s1.status == s2.status == "stopped" and s1.reason == s2.reason
    assert np.array_equal(py.time, cc.time) and np.array_equal(py.data, cc.data)


def test_iterative_kernel_runs_a_transformed_fmu_loop_as_the_python_loop():
    """force_loop (three algebraic loops of FMUs, Newton from their directional derivatives) with
    one controller's voltage through 0.9 u + 0.05: bit for bit, the same passes and Jacobians."""
    from cosim.scenario import load

    sets = {"master.algorithm": "iterative", "stop_time": 0.05}
    sc = load(SCENARIOS / "force_loop.yaml", sets)
    text = Path(sc.path).read_text().replace("fc1.y -> motor1.u", "fc1.y -> motor1.u * 0.9 + 0.05")
    py, cc = (_scene_text_run(text, sets, engine) for engine in ("oracle", "compiled"))
    assert (py.stats["engine"], cc.stats["engine"]) == ("oracle", "compiled") and cc.status == "ok", cc.reason
    assert np.array_equal(py.trace.data, cc.trace.data)
    assert {k: py.stats[k] for k in ITER_KEYS} == {k: cc.stats[k] for k in ITER_KEYS}
    assert cc.stats["directional_derivatives"] > 0


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_typed_ports_run_in_the_iterative_kernel_as_in_the_python_loop(reference_fmus, fmi):
    py, cc = (typed_run(reference_fmus, fmi, {"algorithm": "iterative", "step": 0.01, "inputs": "linear"}, e)
              for e in ("oracle", "compiled"))
    assert (py.stats["engine"], cc.stats["engine"]) == ("oracle", "compiled") and cc.status == "ok", cc.reason
    assert np.array_equal(py.trace.time, cc.trace.time) and np.array_equal(py.trace.data, cc.trace.data)
    assert py.trace.text == cc.trace.text and cc.trace.text["ft.String_output"] == [(0.0, "abc")]
    assert np.array_equal(cc.trace["ft.Float64_continuous_output"], cc.trace["vdp.x0"])
