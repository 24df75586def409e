"""Scalar measures of a recorded signal ``x(t)`` over a run, for the results table.

With ``t0`` the first and ``T`` the last recorded instant, and ``e(t) = x(t) - r(t)`` the error
against the signal's target ``r`` (a number, another recorded signal, or the reference trace's
same signal interpolated linearly onto the run's instants):

=================  =====================================================================  ========
measure            definition                                                             unit
=================  =====================================================================  ========
``max``, ``min``   largest / smallest value of ``x``                                       x
``max_abs``        largest ``|x|``                                                         x
``rms``            ``sqrt(1/(T-t0) * integral x^2 dt)`` (trapezoidal rule)                 x
``at`` (t)         ``x(t)``, linear between recorded instants (nan outside the run)        x
``end_error``      ``|e(T)|``                                                              x
``max_error``      largest ``|e|``                                                         x
``rms_error``      RMS of ``e`` (as ``rms``)                                               x
``overshoot``      ``100 * max(0, max_t (x - r_T) * sign(s)) / |s|`` with the step         %
                   ``s = r_T - x(t0)`` (nan when ``s = 0``)
``settling_time``  time after ``t0`` from which ``|e| <= band * |s|`` holds to the end;     s
                   the crossing is interpolated linearly; ``inf`` when the last sample is
                   outside the band (not settled within the run)
=================  =====================================================================  ========

With a reference, ``e`` and everything after it is evaluated on the instants both traces cover.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..trace.traces import Trace

MEASURES = ("max", "min", "max_abs", "rms", "end_error", "max_error", "rms_error", "overshoot", "settling_time")
#: Measures of the error against a target (a number, a signal or the reference).
NEEDS_TARGET = frozenset({"end_error", "max_error", "rms_error", "overshoot", "settling_time"})
_trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 names it trapz


@dataclass(frozen=True)
class MetricSpec:
    """One measure of one signal: ``measure`` (see the module docstring), ``arg`` (the instant of
    ``at`` [s]), ``target`` (number, signal name, ``"reference"`` or None) and ``band`` (the
    settling band as a fraction of the step)."""

    signal: str
    measure: str
    arg: float | None = None
    target: Any = None
    band: float = 0.02
    where: tuple[str, int] = ("", 0)

    @property
    def column(self) -> str:
        """The results table's column: ``signal:measure`` or ``signal:at(t)``."""
        return f"{self.signal}:at({self.arg:g})" if self.measure == "at" else f"{self.signal}:{self.measure}"


def rms(t: np.ndarray, x: np.ndarray) -> float:
    """Root mean square of ``x`` over ``t`` (trapezoidal rule; ``|x|`` for one sample)."""
    if len(t) < 2:
        return float(abs(x[0])) if len(x) else math.nan
    return float(math.sqrt(_trapezoid(x * x, t) / (t[-1] - t[0])))


def overshoot(x: np.ndarray, r_end: float) -> float:
    """Overshoot beyond the final target ``r_end`` in percent of the step from ``x[0]``."""
    step = r_end - x[0]
    if step == 0:
        return math.nan
    return float(100.0 * max(0.0, float(np.max((x - r_end) * math.copysign(1.0, step)))) / abs(step))


def settling_time(t: np.ndarray, err: np.ndarray, band_abs: float) -> float:
    """Time after ``t[0]`` from which ``|err| <= band_abs`` to the end (crossing interpolated
    linearly; ``inf`` if the last sample is outside the band, 0 if no sample ever is)."""
    out = np.flatnonzero(np.abs(err) > band_abs)
    if len(out) == 0:
        return 0.0
    k = int(out[-1])
    if k == len(t) - 1:
        return math.inf
    a, b = abs(err[k]), abs(err[k + 1])
    frac = (a - band_abs) / (a - b) if a != b else 0.0
    return float(t[k] + frac * (t[k + 1] - t[k]) - t[0])


def _target(spec: MetricSpec, trace: Trace, t: np.ndarray, keep: np.ndarray, reference: Trace | None) -> np.ndarray:
    if spec.target == "reference":
        return np.interp(t, reference.time, reference[spec.signal])
    if isinstance(spec.target, str):
        return trace[spec.target][keep]
    return np.full(len(t), float(spec.target))


def measure(spec: MetricSpec, trace: Trace, reference: Trace | None = None) -> float:
    """The value of ``spec`` on ``trace`` (nan when the trace has no rows)."""
    t_all, x_all = trace.time, trace[spec.signal]
    if len(t_all) == 0:
        return math.nan
    m = spec.measure
    if m in ("max", "min", "max_abs", "rms", "at"):
        if m == "max":
            return float(np.max(x_all))
        if m == "min":
            return float(np.min(x_all))
        if m == "max_abs":
            return float(np.max(np.abs(x_all)))
        if m == "rms":
            return rms(t_all, x_all)
        if not t_all[0] - 1e-12 <= spec.arg <= t_all[-1] + 1e-12:
            return math.nan
        return float(np.interp(spec.arg, t_all, x_all))
    keep = np.ones(len(t_all), bool)
    if spec.target == "reference":
        keep = (t_all >= reference.time[0] - 1e-12) & (t_all <= reference.time[-1] + 1e-12)
        if not keep.any():
            return math.nan
    t, x = t_all[keep], x_all[keep]
    r = _target(spec, trace, t, keep, reference)
    e = x - r
    if m == "end_error":
        return float(abs(e[-1]))
    if m == "max_error":
        return float(np.max(np.abs(e)))
    if m == "rms_error":
        return rms(t, e)
    if m == "overshoot":
        return overshoot(x, float(r[-1]))
    step = float(r[-1] - x[0])
    if step == 0:
        return math.nan
    return settling_time(t, e, spec.band * abs(step))


def compute(specs: Sequence[MetricSpec], trace: Trace, reference: Trace | None = None) -> dict[str, float]:
    """Every metric of ``specs`` on ``trace``, by column name."""
    return {s.column: measure(s, trace, reference) for s in specs}


__all__ = ["MEASURES", "NEEDS_TARGET", "MetricSpec", "compute", "measure", "overshoot", "rms", "settling_time"]
