"""Jacobi with second-order input extrapolation (cosim/master/algorithms/jacobi_extrapolated.py,
the walk-through of docs/how-to/add-an-algorithm.md) against independent sources: the exact
step mean of a quadratic input (calculus), the exact solution of a linear pair (matrix
exponential) and the monolithic CVODES reference of the two-mass scene.  Each shows the
coupling error falling at order 2 with the step where plain Jacobi's falls at order 1, and
smaller than plain Jacobi's at the same step."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cosim.analysis.trace_diff import compare
from cosim.errors import UserError
from cosim.master import ALGORITHMS
from oracles.fixed import extrapolator  # fastloop.c's extrapolation in Python (bit for bit: test_general_kernel.py)
from cosim.run.execute import run
from cosim.run.reference import reference

from test_accuracy import TWO_MASS
from test_algorithms import exact, pair, simulate_pair


def _orders(errors: list[float]) -> list[float]:
    """Observed orders between successive step halvings."""
    return [math.log2(a / b) for a, b in zip(errors, errors[1:])]


def test_it_is_registered_as_a_fixed_step_algorithm():
    cls = ALGORITHMS["jacobi_extrapolated"]
    assert not cls.variable_step and cls.native_code == 3 and cls.delays_algebraic_loops


def test_the_held_input_is_the_exact_step_mean_of_a_quadratic():
    """u(t) = 2 - 3 t + 5 t^2 sampled at t = 0, h, 2h: from the third step on, the value held over
    [t_k, t_k + h] is its integral over that step divided by h (the extrapolating quadratic is u)."""
    h = 0.1
    u = lambda t: 2 - 3 * t + 5 * t ** 2  # noqa: E731
    U = lambda t: 2 * t - 1.5 * t ** 2 + 5 / 3 * t ** 3  # noqa: E731 - its antiderivative
    buf = np.zeros(1)
    extrapolate = extrapolator(buf)
    held = []
    for k in range(5):
        buf[0] = u(k * h)
        extrapolate()
        held.append(buf[0])
    assert held[0] == u(0.0)  # one value: held as it is
    assert held[1] == pytest.approx(1.5 * u(h) - 0.5 * u(0.0), abs=1e-15)  # two: the linear one's mean
    for k in range(2, 5):
        assert held[k] == pytest.approx((U((k + 1) * h) - U(k * h)) / h, rel=1e-13)


def test_the_error_on_the_exact_linear_pair_falls_at_order_two():
    """Final-state error against expm at t = 1 s, steps 40, 20, 10, 5 ms."""
    errors = {}
    for alg in ("jacobi", "jacobi_extrapolated"):
        errors[alg] = []
        for h_ms in (40, 20, 10, 5):
            tr, stats = simulate_pair(alg, pair(), step_ns=h_ms * 1_000_000, n=1000 // h_ms)
            assert stats.status == "ok", stats.reason
            ref = exact(1.0)
            errors[alg].append(max(abs(tr.data[-1, 1] - ref[0]), abs(tr.data[-1, 2] - ref[1])))
    assert all(0.9 < p < 1.2 for p in _orders(errors["jacobi"])), errors
    assert all(1.85 < p < 2.15 for p in _orders(errors["jacobi_extrapolated"])), errors
    assert all(e2 < e1 / 5 for e1, e2 in zip(errors["jacobi"], errors["jacobi_extrapolated"])), errors


def test_two_mass_against_the_monolithic_reference(tmp_path, cache):
    """The two-mass scene (FMUs, CVODES inside) over 2 s at steps 4, 2, 1 ms, recorded every 4 ms,
    against the monolithic CVODES reference: order 2 against plain Jacobi's order 1, and at each
    step at least 50 times more accurate (plain Jacobi is near its stability limit at 4 ms)."""
    scene = tmp_path / "two_mass.yaml"
    errors: dict[str, list[float]] = {}
    ref = None
    for alg in ("jacobi", "jacobi_extrapolated"):
        errors[alg] = []
        for h in (4e-3, 2e-3, 1e-3):
            master = f"{{algorithm: {alg}, step: {h}, inputs: hold, tolerance: none, output_interval: 4e-3}}"
            scene.write_text(TWO_MASS.format(stop=2.0, master=master, rollback=""))
            res = run(scene, cache_dir=cache)
            assert res.status == "ok", res.reason
            ref = ref or reference(res.scene)
            errors[alg].append(max(d.max_abs for d in compare(res.trace, ref.trace)))
    assert all(0.9 < p < 1.3 for p in _orders(errors["jacobi"])), errors
    assert all(1.7 < p < 2.2 for p in _orders(errors["jacobi_extrapolated"])), errors
    assert all(e2 < e1 / 50 for e1, e2 in zip(errors["jacobi"], errors["jacobi_extrapolated"])), errors


def test_it_refuses_linear_inputs():
    from cosim.master import simulate

    with pytest.raises(UserError, match="jacobi_extrapolated extrapolates the inputs itself"):
        simulate(pair(), "jacobi_extrapolated", step_ns=10_000_000, n_steps=10, observers=[], inputs="linear")
