"""The embedded integrators (models.integrators) against analytic solutions, their known order,
the RK4 stability function and finite differences.  The small test blocks defined here are
reused by the FMU tests (tests/test_fmus.py)."""
from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
import scipy.linalg

from models import integrators as I
from models.block import Block, BlockError, Param, Var


# --- test blocks ------------------------------------------------------------------------------
def msd_block(*, m: float = 1.0, k: float = 100.0, c: float = 2.0, s0: float = 0.01,
              integrator: str = "radau", substeps: int = 1, name: str = "msd") -> Block:
    """Mass-spring-damper ``m a = f - k s - c v``; input ``f`` [N]; outputs ``s``, ``v`` and the
    acceleration ``a`` (direct feedthrough from ``f``); the start position is the parameter ``s0``
    (so the states have a calculated start)."""
    p = ca.SX.sym("p", 4)
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 1)
    acc = (u[0] - p[1] * x[0] - p[2] * x[1]) / p[0]
    return Block.build(
        name, description="mass-spring-damper test block",
        params=[Param("m", m, "kg", 1e-6, math.inf, "mass"), Param("k", k, "N/m", 0.0, math.inf, "stiffness"),
                Param("c", c, "N.s/m", 0.0, math.inf, "damping"), Param("s0", s0, "m", description="start position")],
        inputs=[Var("f", "N", "applied force")],
        outputs=[Var("body.s", "m", "position"), Var("body.v", "m/s", "velocity"),
                 Var("body.a", "m/s2", "acceleration")],
        states=[Var("s", "m"), Var("v", "m/s")],
        p=p, u=u, x=x, ode=ca.vertcat(x[1], acc), out=ca.vertcat(x[0], x[1], acc),
        start=ca.vertcat(p[3], 0.0), integrator=integrator, substeps=substeps)


def stiff_block(*, integrator: str = "radau", substeps: int = 1) -> Block:
    """The thesis's parasitic joint: 1 kg on a 1e8 N/m spring with 2000 N s/m damping."""
    return msd_block(m=1.0, k=1e8, c=2000.0, s0=1e-3, integrator=integrator, substeps=substeps, name="stiff")


def lag_block(*, T: float = 0.05, Ts: float = 0.01) -> Block:
    """Sampled first-order lag ``T y' + y = u``, exact ZOH update ``y+ = a y + (1 - a) u``,
    ``a = exp(-Ts/T)``, every ``Ts`` seconds; the time constant is tunable, the start is 0
    (an exact start value)."""
    p = ca.SX.sym("p", 1)
    x = ca.SX.sym("x", 1)
    u = ca.SX.sym("u", 1)
    a = ca.exp(-Ts / p[0])
    return Block.build("lag", description="sampled first-order lag",
                       params=[Param("T", T, "s", 1e-6, math.inf, "time constant")],
                       inputs=[Var("u", "V")], outputs=[Var("y", "V")], states=[Var("y_state", "V")],
                       p=p, u=u, x=x, ode=a * x + (1 - a) * u, out=x, start=ca.DM([0.0]),
                       integrator="discrete", sample_period=Ts)


def gain_block(K: float = 2.5) -> Block:
    """Stateless gain ``y = K u`` with a structural (fixed) gain."""
    p = ca.SX.sym("p", 1)
    u = ca.SX.sym("u", 1)
    return Block.build("gain", description="static gain", params=[Param("K", K, "1", structural=True)],
                       inputs=[Var("u", "V")], outputs=[Var("y", "V")], states=[], p=p, u=u,
                       x=ca.SX.sym("x", 0), ode=ca.SX(0, 1), out=p[0] * u, start=ca.SX(0, 1),
                       integrator="none")


def msd_exact(t: float, *, m: float, k: float, c: float, s0: float, v0: float = 0.0, f: float = 0.0) -> np.ndarray:
    """(s, v) at time t for a constant force, by the matrix exponential of the augmented system."""
    A = np.array([[0.0, 1.0, 0.0], [-k / m, -c / m, f / m], [0.0, 0.0, 0.0]])
    return (scipy.linalg.expm(A * t) @ np.array([s0, v0, 1.0]))[:2]


def run_stepper(block: Block, h: float, n: int, f: float = 0.0) -> np.ndarray:
    st = I.Stepper(block)
    p = block.param_defaults
    x = np.asarray(st.start(p), dtype=float).ravel()
    for _ in range(n):
        x, ok = st.step(x, [f], p, h)
        assert ok
    return x


# --- accuracy and order -------------------------------------------------------------------------
@pytest.mark.parametrize("integrator,order", [("rk4", 4), ("radau", 5)])
def test_observed_order_matches_the_method(integrator, order):
    """Global error at t = 1 s against the matrix exponential; halving h divides it by 2^order."""
    errs = []
    for h in (0.05, 0.025):
        x = run_stepper(msd_block(integrator=integrator), h, round(1.0 / h), f=3.0)
        errs.append(np.linalg.norm(x - msd_exact(1.0, m=1, k=100, c=2, s0=0.01, f=3.0)))
    observed = math.log2(errs[0] / errs[1])
    assert abs(observed - order) < 0.35, (errs, observed)


def msd_ramp_exact(t: float, f0: float, df: float, *, m=1.0, k=100.0, c=2.0, s0=0.01) -> np.ndarray:
    """(s, v) at time t under the force ``f0 + df t``: matrix exponential of (s, v, f, df/dt)."""
    A = np.zeros((4, 4))
    A[0, 1], A[1, 0], A[1, 1], A[1, 2], A[2, 3] = 1.0, -k / m, -c / m, 1 / m, 1.0
    return (scipy.linalg.expm(A * t) @ np.array([s0, 0.0, f0, df]))[:2]


@pytest.mark.parametrize("integrator,order", [("rk4", 4), ("radau", 5)])
def test_a_ramp_input_is_followed_to_the_method_order(integrator, order):
    """Inputs ``u + du tau`` inside the step (the linear-input convention): each stage must see
    the input at its own time (RK4 at 0, h/2, h; Radau at c_i h), or the error falls only like
    h or h^2.  Global error at t = 1 s against the exact solution under the ramp."""
    f0, df = 3.0, 40.0
    errs = []
    for h in (0.05, 0.025):
        st, blk = I.Stepper(msd_block(integrator=integrator)), msd_block(integrator=integrator)
        x = np.array([0.01, 0.0])
        for k in range(round(1.0 / h)):
            x, ok = st.step(x, [f0 + df * k * h], blk.param_defaults, h, du=[df])
            assert ok
        errs.append(np.linalg.norm(x - msd_ramp_exact(1.0, f0, df)))
    observed = math.log2(errs[0] / errs[1])
    assert abs(observed - order) < 0.35, (errs, observed)


@pytest.mark.parametrize("substeps", [1, 4])
def test_radau_accuracy_against_the_analytic_solution(substeps):
    h = 0.01
    x = run_stepper(msd_block(integrator="radau", substeps=substeps), h, 100, f=3.0)
    exact = msd_exact(1.0, m=1, k=100, c=2, s0=0.01, f=3.0)
    # order 5: the error falls as (h / substeps)^5 (about 1e-9 at h w = 0.1 here)
    assert np.max(np.abs(x - exact)) < 2e-9 / substeps ** 5


def test_substeps_are_equal_steps_of_h_over_n():
    a = run_stepper(msd_block(integrator="rk4", substeps=5), 0.05, 4)
    b = run_stepper(msd_block(integrator="rk4", substeps=1), 0.01, 20)
    np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)


# --- stiffness: SPEC §6 -----------------------------------------------------------------------
def rk4_amplification(h: float) -> float:
    """|R(h lambda)| of RK4 for the stiff block's eigenvalues (the stability function, by hand)."""
    lam = np.roots([1.0, 2000.0, 1e8])
    z = h * lam
    return float(np.max(np.abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24)))


@pytest.mark.parametrize("substeps", [1, 2, 5, 10])
def test_rk4_on_the_stiff_joint_diverges_exactly_where_its_stability_function_says(substeps):
    blk = stiff_block(integrator="rk4", substeps=substeps)
    st = I.Stepper(blk)
    p = blk.param_defaults
    x = np.array([1e-3, 0.0])
    failed = False
    for _ in range(50):
        x, ok = st.step(x, [0.0], p, 1e-3)
        if not ok or abs(x[0]) > 1.0:
            failed = True
            break
    unstable = rk4_amplification(1e-3 / substeps) > 1.0
    assert failed == unstable
    if substeps == 1:
        assert unstable  # SPEC §6: RK4 at one 1 ms step diverges


def test_radau_is_stable_on_the_stiff_joint_at_1ms():
    blk = stiff_block()
    st = I.Stepper(blk)
    p = blk.param_defaults
    x = np.array([1e-3, 0.0])
    peak = 0.0
    for _ in range(50):
        x, ok = st.step(x, [0.0], p, 1e-3)
        assert ok
        peak = max(peak, abs(x[0]))
    assert peak <= 1e-3 and abs(x[0]) < 1e-9  # the true solution decays like exp(-1000 t)


def test_radau_accepts_stiff_springs_far_from_the_origin():
    """Two 1 kg bodies 1.5 m and 1.8 m from the origin joined by a 1e8 N/m spring, body 1 pushed
    with 1 N: the spring force carries round-off ~eps k |x| ~ 3e-8 N, far above the Newton
    tolerance on the raw residual; the correction-based acceptance must still take every step.
    The centre of mass moves exactly as x_cm(t) = 1.65 + t^2 / 4 (a quadratic, which Radau
    IIA reproduces up to round-off)."""
    p = ca.SX.sym("p", 2)
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 1)
    F = p[0] * (x[1] - x[0] - 0.3) + p[1] * (x[3] - x[2])
    blk = Block.build("pair", params=[Param("k", 1e8), Param("c", 2000.0)], inputs=[Var("f")],
                      outputs=[Var("cm")], states=[Var("p1"), Var("p2"), Var("v1"), Var("v2")], p=p, u=u, x=x,
                      ode=ca.vertcat(x[2], x[3], F + u[0], -F), out=(x[0] + x[1]) / 2,
                      start=ca.DM([1.5, 1.8, 0.0, 0.0]), integrator="radau")
    st = I.Stepper(blk)
    xk = np.array([1.5, 1.8, 0.0, 0.0])
    for k in range(1, 101):
        xk, ok = st.step(xk, [1.0], blk.param_defaults, 1e-3)
        assert ok
    assert (xk[0] + xk[1]) / 2 == pytest.approx(1.65 + 0.1 ** 2 / 4, abs=1e-12)


@pytest.mark.parametrize("substeps", [1, 10])
def test_radau_reports_non_convergence_instead_of_a_wrong_state(substeps):
    """``z' = -k z^3``: one Newton iteration cannot meet the tolerance (ok = 0, a ratio > 1); the
    default iteration count converges, and the result matches the exact ``1/sqrt(1 + 2 k t)``
    to the method's accuracy."""
    p = ca.SX.sym("p", 1)
    x = ca.SX.sym("x", 1)
    u = ca.SX.sym("u", 0)
    blk = Block.build("cubic", params=[Param("k", 10.0)], inputs=[], outputs=[Var("y")], states=[Var("z")],
                      p=p, u=u, x=x, ode=-p[0] * x ** 3, out=x, start=ca.DM([1.0]), integrator="radau",
                      substeps=substeps)
    _, ok, err = I.radau_kernel(blk, max_iter=1)([1.0], [], [10.0], 0.1, [])
    assert float(ok) == 0.0 and float(err) > 1.0
    xn, ok, err = I.radau_kernel(blk)([1.0], [], [10.0], 0.1, [])
    assert float(ok) == 1.0 and float(err) <= 1.0
    exact = 1 / math.sqrt(1 + 2 * 10.0 * 0.1)
    assert abs(float(xn) - exact) < (3e-4 if substeps == 1 else 1e-8)


def cubic_block(k: float = 10.0) -> Block:
    """``z' = -k z^3`` from ``z = 1`` (exact ``1/sqrt(1 + 2 k t)``)."""
    p, x = ca.SX.sym("p", 1), ca.SX.sym("x", 1)
    return Block.build("cubic", params=[Param("k", k)], inputs=[], outputs=[Var("y")], states=[Var("z")],
                       p=p, u=ca.SX.sym("u", 0), x=x, ode=-p[0] * x ** 3, out=x, start=ca.DM([1.0]),
                       integrator="radau")


@pytest.mark.parametrize("ratio", [0.98, 1.02])
@pytest.mark.parametrize("kind", ["atol", "rtol"])
def test_radau_accepts_a_step_exactly_up_to_its_tolerance(kind, ratio):
    """The acceptance threshold itself: ``ok`` iff the error estimate ``err`` is at most 1.

    One simplified-Newton iteration (``max_iter=1``) leaves a stage error that does not depend on
    the tolerance (the iteration is affine invariant), while ``err`` is that error over
    ``atol`` (``rtol = 0``): so ``atol`` places ``err`` just below or just above 1.  Independently
    of the kernel's own estimate, the step's true error -- its distance from the converged Radau
    step -- is then about ``ratio * atol``: a step is accepted exactly when it is within its
    tolerance.  (Relies on ``radau_kernel(block, rtol=, atol=, max_iter=)`` returning
    ``(x_next, ok, err)``.)  The same with a relative tolerance alone (``atol = 0``): then the
    scale is ``rtol (|x| + |Z|)`` per component."""
    blk, x0, args = cubic_block(), 1.0, ([1.0], [], [10.0], 0.1, [])

    def kernel(tol: float):
        tols = {"atol": tol, "rtol": 0.0} if kind == "atol" else {"atol": 0.0, "rtol": tol}
        return I.radau_kernel(blk, max_iter=1, **tols)

    _, _, err_ref = kernel(1e-10)(*args)
    tol = 1e-10 * float(err_ref) / ratio
    xn, ok, err = kernel(tol)(*args)
    assert float(err) == pytest.approx(ratio, rel=1e-6)
    assert float(ok) == (1.0 if ratio < 1 else 0.0)
    converged, ok_c, _ = I.radau_kernel(blk)(*args)
    assert float(ok_c) == 1.0
    xn, converged = float(xn), float(converged)
    scale = tol if kind == "atol" else tol * (abs(x0) + abs(xn - x0))
    true_ratio = abs(xn - converged) / scale
    assert 0.5 * ratio < true_ratio < 2.0 * ratio, true_ratio


def test_radau_discards_a_step_too_large_for_simplified_newton():
    """A stiff, strongly nonlinear step (the state falls 80 % within the step) defeats the
    simplified Newton iteration: the kernel must say so, not return an unconverged state."""
    p = ca.SX.sym("p", 1)
    x = ca.SX.sym("x", 1)
    blk = Block.build("cubic", params=[Param("k", 1e4)], inputs=[], outputs=[Var("y")], states=[Var("z")],
                      p=p, u=ca.SX.sym("u", 0), x=x, ode=-p[0] * x ** 3, out=x, start=ca.DM([1.0]),
                      integrator="radau")
    _, ok, err = I.radau_kernel(blk)([1.0], [], [1e4], 1e-3, [])
    assert float(ok) == 0.0 and float(err) > 1.0


# --- discrete and none ------------------------------------------------------------------------
def test_discrete_lag_matches_the_continuous_step_response_at_samples():
    blk = lag_block(T=0.05, Ts=0.01)
    st = I.Stepper(blk)
    x = np.zeros(1)
    for k in range(1, 11):
        x, ok = st.step(x, [1.0], blk.param_defaults, 0.02)  # two samples per communication step
        assert ok
        assert x[0] == pytest.approx(1 - math.exp(-2 * k * 0.01 / 0.05), rel=1e-12)


@pytest.mark.parametrize("h", [0.015, 0.005, 0.0])
def test_discrete_refuses_a_step_that_is_not_a_multiple_of_the_sample_period(h):
    st = I.Stepper(lag_block(Ts=0.01))
    with pytest.raises(I.IntegratorError, match="lag"):
        st.step([0.0], [1.0], [0.05], h)


def test_none_integrator_with_states_is_refused():
    blk = msd_block()
    blk.integrator = "none"
    with pytest.raises(BlockError, match="msd.*'none'"):
        I.Stepper(blk)


# --- derivatives ------------------------------------------------------------------------------
@pytest.mark.parametrize("integrator,substeps", [("radau", 1), ("radau", 3), ("rk4", 2)])
def test_step_jacobian_matches_central_differences(integrator, substeps):
    """Implicit-function-theorem sensitivities of the step vs central differences (nonlinear
    block: a pendulum-like spring, so the Jacobian depends on the state)."""
    p = ca.SX.sym("p", 1)
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 1)
    blk = Block.build("pend", params=[Param("g", 9.81)], inputs=[Var("tau")], outputs=[Var("th")],
                      states=[Var("q"), Var("w")], p=p, u=u, x=x,
                      ode=ca.vertcat(x[1], -p[0] * ca.sin(x[0]) + u[0] - 0.3 * x[1]), out=x[0],
                      start=ca.DM([0.5, 0.0]), integrator=integrator, substeps=substeps)
    J = I.step_jacobian(blk)
    kern = I.Stepper(blk).kernel
    x0, u0, p0, h = np.array([0.7, -0.4]), np.array([0.2]), np.array([9.81]), 0.05
    A, B = (np.asarray(m) for m in J(x0, u0, p0, h))
    eps = 1e-6
    fd_A = np.column_stack([(np.asarray(kern(x0 + eps * e, u0, p0, h, 0)[0]) - np.asarray(kern(x0 - eps * e, u0, p0, h, 0)[0])).ravel()
                            / (2 * eps) for e in np.eye(2)])
    fd_B = ((np.asarray(kern(x0, u0 + eps, p0, h, 0)[0]) - np.asarray(kern(x0, u0 - eps, p0, h, 0)[0])) / (2 * eps)).reshape(2, 1)
    np.testing.assert_allclose(A, fd_A, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(B, fd_B, rtol=1e-6, atol=1e-8)


def test_output_jacobian_is_the_analytic_one():
    blk = msd_block(m=2.0, k=50.0, c=3.0)
    J = np.asarray(I.Stepper(blk).out_jacobian([0.1, 0.2], [1.0], blk.param_defaults))
    # columns: s, v, f, m, k, c, s0 ; rows: s, v, a
    a = (1.0 - 50 * 0.1 - 3 * 0.2) / 2.0
    expected = np.array([[1, 0, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0, 0],
                         [-25.0, -1.5, 0.5, -a / 2.0, -0.05, -0.1, 0.0]])
    np.testing.assert_allclose(J, expected, rtol=1e-14, atol=1e-15)
