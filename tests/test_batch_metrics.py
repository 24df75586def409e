"""Batch metrics against hand computation on traces of known analytic shape: the step response
of an underdamped second-order system (overshoot exp(-pi z / sqrt(1 - z^2)), peak at pi / wd,
settling found by a root finder on the closed form), a sine over whole periods (RMS A / sqrt 2)
and its error against a shifted copy."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from cosim.batch.metrics import MetricSpec, compute, measure
from cosim.trace.traces import Trace

Z, WN, T_END, DT = 0.3, 10.0, 3.0, 1e-4
WD = WN * math.sqrt(1 - Z * Z)


def step_response(t):
    """Unit step response of wn^2 / (s^2 + 2 z wn s + wn^2) from rest."""
    return 1 - np.exp(-Z * WN * t) * (np.cos(WD * t) + Z / math.sqrt(1 - Z * Z) * np.sin(WD * t))


def settling_exact(band: float) -> float:
    """The last instant where |y - 1| = band, by bracketing on a fine grid and brentq."""
    g = lambda t: float(abs(step_response(np.array([t]))[0] - 1) - band)  # noqa: E731
    ts = np.linspace(0, T_END, 300001)
    outside = np.abs(step_response(ts) - 1) > band
    k = np.flatnonzero(outside)[-1]
    return brentq(g, ts[k], ts[k + 1], xtol=1e-12)


@pytest.fixture(scope="module")
def trace() -> Trace:
    t = np.arange(0, round(T_END / DT) + 1) * DT
    y = 0.3 + 0.2 * step_response(t)  # from 0.3 to 0.5: a step of 0.2
    s = 2.0 * np.sin(2 * np.pi * 2.0 * t)  # two hertz, six whole periods
    target = np.full_like(t, 0.5)
    return Trace(["time", "y", "s", "target"], np.column_stack([t, y, s, target]))


def analytic_overshoot() -> float:
    return 100 * math.exp(-math.pi * Z / math.sqrt(1 - Z * Z))


CASES = [
    ("max of y", MetricSpec("y", "max"), 0.3 + 0.2 * (1 + math.exp(-math.pi * Z / math.sqrt(1 - Z * Z))), 1e-7),  # the peak lies between samples
    ("min of s", MetricSpec("s", "min"), -2.0, 1e-9),
    ("max_abs of s", MetricSpec("s", "max_abs"), 2.0, 1e-9),
    ("rms of s", MetricSpec("s", "rms"), 2.0 / math.sqrt(2), 1e-9),
    ("y at 0.12345 s", MetricSpec("y", "at", 0.12345), 0.3 + 0.2 * float(step_response(np.array([0.12345]))[0]), 1e-8),
    ("overshoot %", MetricSpec("y", "overshoot", target=0.5), analytic_overshoot(), 1e-7),
    ("overshoot against a target signal", MetricSpec("y", "overshoot", target="target"), analytic_overshoot(), 1e-7),
    ("2 % settling time", MetricSpec("y", "settling_time", target=0.5, band=0.02), settling_exact(0.02), 1e-6),
    ("5 % settling time", MetricSpec("y", "settling_time", target=0.5, band=0.05), settling_exact(0.05), 1e-6),
    ("end error", MetricSpec("y", "end_error", target=0.5), 0.2 * abs(float(step_response(np.array([T_END]))[0]) - 1), 1e-12),
    ("max error against the target", MetricSpec("y", "max_error", target=0.5), 0.2, 1e-12),
]


@pytest.mark.parametrize("spec, expected, tol", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_metric_matches_hand_computation(trace, spec, expected, tol):
    assert measure(spec, trace) == pytest.approx(expected, rel=tol, abs=tol * 1e-3)


def test_errors_against_a_reference_trace(trace):
    """Against a reference shifted by 0.01 sin(2 pi t), sampled on other instants: the maximum
    error is 0.01, its RMS over three whole periods 0.01 / sqrt 2, the end error 0."""
    tr = np.linspace(0, T_END, 7001)
    ref = Trace(["time", "y"], np.column_stack([tr, 0.3 + 0.2 * step_response(tr) + 0.01 * np.sin(2 * np.pi * tr)]))
    got = compute([MetricSpec("y", m, target="reference") for m in ("max_error", "rms_error", "end_error")],
                  trace, ref)
    assert got["y:max_error"] == pytest.approx(0.01, rel=1e-4)
    assert got["y:rms_error"] == pytest.approx(0.01 / math.sqrt(2), rel=1e-4)
    assert got["y:end_error"] == pytest.approx(0.0, abs=1e-6)


def test_not_settled_is_infinite_and_no_step_is_nan():
    t = np.linspace(0, 1, 101)
    rising = Trace(["time", "x"], np.column_stack([t, t]))
    assert measure(MetricSpec("x", "settling_time", target=2.0), rising) == math.inf
    assert math.isnan(measure(MetricSpec("x", "overshoot", target=0.0), Trace(["time", "x"], np.zeros((3, 2)))))
    assert math.isnan(measure(MetricSpec("x", "at", 2.0), rising))
