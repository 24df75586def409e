"""The exact kernel of linear blocks (models.integrators.exact_kernel) and the factor-once Radau
kernel, against independent solutions: the eigen-decomposition of the block's linear ODE, a
tight scipy Radau integration, and the step sizes where RK4 must fail."""
from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from models import integrators as I
from models.block import BlockError
from models.blocks import make

LINEAR = [("pid", "continuous", {}), ("dc_motor", "full", {}), ("dc_motor", "full", {"rotor": "state"}),
          ("dc_motor", "quasistatic", {"rotor": "state"})]


def _affine_numbers(blk):
    A, B, c = I.affine_parts(blk)
    f = ca.Function("abc", [blk.p], [A, B, c])
    return tuple(np.asarray(m, dtype=float) for m in f(blk.param_defaults))


def _eigen_step(A, B, c, x0, u, du, h):
    """x(h) of dx/dt = A x + B (u + du t) + c by diagonalisation (distinct eigenvalues)."""
    lam, V = np.linalg.eig(A)
    Vi = np.linalg.inv(V)
    y0, g, k = Vi @ x0, Vi @ (B @ u + c.ravel()), Vi @ (B @ du)
    e = np.exp(lam * h)
    with np.errstate(divide="ignore", invalid="ignore"):
        g1 = np.where(lam == 0, h, (e - 1) / lam)
        g2 = np.where(lam == 0, h * h / 2, (e - 1 - lam * h) / lam ** 2)
    return (V @ (e * y0 + g * g1 + k * g2)).real


@pytest.mark.parametrize("model,fidelity,opts", LINEAR, ids=lambda v: str(v))
def test_linear_blocks_default_to_the_exact_kernel(model, fidelity, opts):
    assert make(model, fidelity, **opts).integrator == "exact"


@pytest.mark.parametrize("h", [1e-3, 1e-2, 0.1])
@pytest.mark.parametrize("model,fidelity,opts", LINEAR, ids=lambda v: str(v))
def test_exact_step_equals_the_eigen_decomposition_solution(model, fidelity, opts, h):
    blk = make(model, fidelity, **opts)
    A, B, c = _affine_numbers(blk)
    rng = np.random.default_rng(7)
    x0, u, du = rng.normal(size=A.shape[0]), rng.normal(size=B.shape[1]), 10 * rng.normal(size=B.shape[1])
    xn, ok, err = I.Stepper(blk).kernel(x0, u, blk.param_defaults, h, du)
    ref = _eigen_step(A, B, c, x0, u, du, h)
    assert float(ok) == 1.0 and float(err) == 0.0
    np.testing.assert_allclose(np.asarray(xn).ravel(), ref, rtol=1e-10, atol=1e-12 * np.max(np.abs(ref)))


@pytest.mark.parametrize("integrator,stable", [("exact", True), ("radau", True), ("rk4", False)])
def test_pid_filter_at_a_10ms_step(integrator, stable):
    """The 1 ms derivative filter at a 10 ms step: exact and Radau stay bounded and follow the
    filter's exact step response (w -> s), RK4 (stable only up to 2.8 Tf) blows up."""
    blk = make("pid", "continuous", integrator=integrator)
    st = I.Stepper(blk)
    x = np.zeros(2)
    u = np.array([0.05, 0.0])  # a 5 cm error held: w follows it with the 1 ms filter
    for _ in range(100):
        x, ok = st.step(x, u, blk.param_defaults, 1e-2)
        if not ok:
            break
    if stable:
        assert ok and abs(x[1] - 0.05) < 1e-12
        if integrator == "exact":
            assert x[0] == pytest.approx(80.0 * 0.05 * 1.0, rel=1e-12)  # I = Ki e t after 1 s
    else:
        assert not ok or abs(x[1]) > 1.0


@pytest.mark.parametrize("h", [1e-3, 1e-2])
def test_motor_at_a_large_step_matches_a_tight_reference(h):
    blk = make("dc_motor", "full")
    f = blk.functions()["ode"]
    p = blk.param_defaults
    u = np.array([6.0, 0.1])
    x = np.zeros(1)
    st = I.Stepper(blk)
    for _ in range(10):
        x, ok = st.step(x, u, p, h)
        assert ok
    ref = solve_ivp(lambda t, z: np.asarray(f(z, u, p)).ravel(), (0, 10 * h), [0.0], method="Radau",
                    rtol=1e-12, atol=1e-14).y[:, -1]
    assert x[0] == pytest.approx(ref[0], rel=1e-9)


def test_exact_refuses_a_nonlinear_block():
    blk = make("pid", "continuous", anti_windup="clamp")
    assert blk.integrator == "radau"  # auto picks Radau for the nonlinear law
    with pytest.raises(BlockError, match="affine"):
        I.Stepper(dataclasses.replace(blk, integrator="exact")).kernel


def test_radau_blocks_declare_their_tolerances_as_parameters():
    blk = make("mechanism", "multibody")
    names = [p.name for p in blk.params]
    assert I.SOLVER_RTOL in names and I.SOLVER_ATOL in names
    assert I.SOLVER_RTOL not in [p.name for p in make("mechanism", "rigid").params]


def test_radau_tolerance_parameters_reach_the_acceptance_test():
    """With no Newton iteration the acceptance correction is the whole stage increment: the
    motor's current rises by ~0.024 A in 1 us at 6 V (6 V / 0.251 mH * 1 us), which fails the
    default tolerances and passes ``solver.atol = 1`` A -- the parameters, not constants, decide."""
    blk = make("dc_motor", "full", integrator="radau")
    names = [q.name for q in blk.params]
    p = blk.param_defaults.copy()
    kern = I.radau_kernel(blk, max_iter=0)
    args = ([0.0], [6.0, 0.0])
    _, ok, err = kern(*args, p, 1e-6, [0.0, 0.0])
    assert float(ok) == 0.0 and float(err) > I.RADAU_ACCEPT_RATIO
    p[names.index(I.SOLVER_ATOL)] = 1.0
    _, ok, err = kern(*args, p, 1e-6, [0.0, 0.0])
    assert float(ok) == 1.0 and float(err) == pytest.approx(6.0 / 0.251e-3 * 1e-6, rel=0.01)


@pytest.mark.parametrize("err,accepted", [(1.0 - 1e-12, True), (1.0, True), (1.0 + 1e-12, False)])
def test_radau_acceptance_threshold(err, accepted):
    assert bool(I.radau_accepts(err)) is accepted
