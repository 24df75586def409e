"""The fit's solver and statistics.

Solver: SciPy's trust-region reflective least squares (``scipy.optimize.least_squares``, method
``trf``: bounds, Jacobian scaling) with the exact Jacobian of :mod:`.problem`; a library, not an
optimiser of ours.  Gauss-Newton-type steps need only the residuals' Jacobian, which the CasADi
model gives exactly; an NLP solver (IPOPT) would need the Hessian of the sum of squares or a
quasi-Newton one, and does no better on a small, well-scaled least-squares problem.

Statistics at the estimate, from the Jacobian ``J`` of the weighted residuals (each column scaled
to unit length, so that the ranks and correlations depend neither on units nor on a value at 0):

- each signal's noise variance from its own residuals (``sigma_s^2 = mean r_s^2 * n / (n - p)``),
  so a signal with a larger noise (relative to its range) counts for less in the covariance;
- covariance ``A^+ B A^+`` with ``A = J^T J`` and ``B = sum_s sigma_s^2 J_s^T J_s`` (the sandwich
  form, exact for independent noise of a different level per signal);
- a 95 % interval ``+-1.96`` standard deviations;
- parameters the data cannot tell apart: a singular value of ``J`` below ``RANK_TOL`` of the
  largest (a direction the residuals do not see: each parameter it moves by more than
  ``NULL_WEIGHT`` gets an infinite interval), and every pair whose correlation exceeds
  ``CORRELATED`` in magnitude.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .problem import Problem, Unknown

Z95 = 1.959963984540054
RANK_TOL = 1e-7
CORRELATED = 0.95
#: Weight (in the unit-length columns' space) above which an unseen direction moves a parameter.
NULL_WEIGHT = 1e-4
#: How far inside a bound a start on it is moved (relative), as the trust region needs.
INSIDE = 1e-9


@dataclass
class Estimate:
    unknown: Unknown
    value: float
    half_width: float  # of the 95 % interval (inf: not identifiable from these data)

    @property
    def relative(self) -> float:
        return self.half_width / abs(self.value) if self.value else float("inf")


@dataclass
class FitResult:
    problem: Problem
    theta: np.ndarray
    estimates: list[Estimate]
    rms_start: float  # weighted residual RMS (relative to each signal's range) at the start
    rms_end: float
    signal_rms_start: np.ndarray  # per signal, in its unit
    signal_rms_end: np.ndarray
    correlation: np.ndarray
    confounded: list[tuple[str, str, float]]  # pairs the data cannot tell apart (|correlation| > CORRELATED)
    unseen: list[list[str]]  # parameters of each direction the residuals do not see
    evaluations: int
    jacobians: int
    wall_s: float
    message: str
    at_bound: list[str] = field(default_factory=list)


def _inside(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    pad = INSIDE * np.maximum(1.0, np.abs(x))
    return np.minimum(np.maximum(x, np.where(np.isfinite(lo), lo + pad, -np.inf)),
                      np.where(np.isfinite(hi), hi - pad, np.inf))


def solve(problem: Problem, *, start: np.ndarray | None = None, max_evaluations: int = 100,
          log: Callable[[str], None] | None = None) -> FitResult:
    """Least squares from ``start`` (default: the scene's values) within the catalog bounds."""
    from scipy.optimize import least_squares

    unk = problem.unknowns
    lo = np.array([u.lower for u in unk], dtype=float)
    hi = np.array([u.upper for u in unk], dtype=float)
    x0 = _inside(np.array(problem.start if start is None else start, dtype=float), lo, hi)
    count = {"f": 0, "j": 0}

    def fun(th):
        count["f"] += 1
        r = problem.residual(th)
        if log and (count["f"] <= 3 or count["f"] % 5 == 0):
            log(f"fit: evaluation {count['f']}, weighted RMS residual {np.sqrt(np.mean(r ** 2)):.4g}")
        return r

    def jac(th):
        count["j"] += 1
        return problem.residual_jacobian(th)

    t0 = time.perf_counter()
    r0 = problem.residual(x0)
    sol = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12,
                        gtol=1e-12, max_nfev=max_evaluations)
    wall = time.perf_counter() - t0
    theta = sol.x
    r = problem.residual(theta)
    J = problem.residual_jacobian(theta)
    half, corr, unseen = _statistics(problem, theta, r, J)
    m, n = len(problem.signals), len(problem.time)
    names = [u.path for u in unk]
    confounded = [(names[a], names[b], float(corr[a, b])) for a in range(len(unk)) for b in range(a + 1, len(unk))
                  if abs(corr[a, b]) > CORRELATED]
    at_bound = [names[k] for k in range(len(unk)) if sol.active_mask[k] != 0]
    per = lambda res: np.sqrt(np.mean(res.reshape(m, n) ** 2, axis=1)) * problem.scale  # noqa: E731
    return FitResult(problem, theta, [Estimate(u, float(theta[k]), float(half[k])) for k, u in enumerate(unk)],
                     float(np.sqrt(np.mean(r0 ** 2))), float(np.sqrt(np.mean(r ** 2))), per(r0), per(r), corr,
                     confounded, [[names[k] for k in d] for d in unseen], count["f"], count["j"], wall, sol.message,
                     at_bound)


def _statistics(problem: Problem, theta: np.ndarray, r: np.ndarray, J: np.ndarray):
    """95 % half-widths, correlation matrix, and the parameters of each unseen direction."""
    m, n, p = len(problem.signals), len(problem.time), len(theta)
    norms = np.linalg.norm(J, axis=0)
    d = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)  # unit-free columns (Jacobi scaling)
    Js = J * d
    U, S, Vt = np.linalg.svd(Js, full_matrices=False)
    keep = S > RANK_TOL * S[0] if len(S) and S[0] > 0 else np.zeros(len(S), dtype=bool)
    A_pinv = (Vt[keep].T / S[keep] ** 2) @ Vt[keep]
    dof = max(1, m * n - p)
    sigma2 = np.mean(r.reshape(m, n) ** 2, axis=1) * (m * n) / dof
    B = sum(sigma2[s] * Js[s * n:(s + 1) * n].T @ Js[s * n:(s + 1) * n] for s in range(m))
    cov = A_pinv @ B @ A_pinv
    std = np.sqrt(np.maximum(np.diag(cov), 0.0)) * d
    null = Vt[~keep]
    unseen = [sorted(np.flatnonzero(np.abs(v) > NULL_WEIGHT)) for v in null]
    half = Z95 * std
    if len(null):  # any parameter the unseen directions move at all: no interval
        half[np.linalg.norm(null, axis=0) > NULL_WEIGHT] = np.inf
    dn = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = np.clip(cov / np.outer(dn, dn), -1.0, 1.0)
    for v, direction in zip(Vt[~keep], unseen):  # unseen: its parameters move together, fully
        for a in direction:
            for b in direction:
                if a != b:
                    corr[a, b] = float(np.sign(v[a] * v[b]))
    return half, corr, unseen


__all__ = ["CORRELATED", "Estimate", "FitResult", "solve"]
