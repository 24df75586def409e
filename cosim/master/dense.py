"""Small dense linear algebra in a fixed order of operations, for the iterative master's Newton
step (a few cut connections: matrices of a few rows).

Every sum runs left to right starting from its first product, and the solve is Gaussian
elimination with partial pivoting (the first largest pivot), so the compiled iterative engine
(:mod:`cosim.master.iterative_engine`), which does the same operations in C, agrees with this
bit for bit; BLAS and LAPACK (numpy's ``@`` and ``linalg.solve``) choose their own order.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def dot(a: Sequence[float], b: Sequence[float]) -> float:
    """``sum(a[k] * b[k])`` from ``k = 0`` (0.0 for empty vectors)."""
    if not len(a):
        return 0.0
    acc = a[0] * b[0]
    for k in range(1, len(a)):
        acc += a[k] * b[k]
    return acc


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` with :func:`dot`'s order in every entry."""
    a, b = np.asarray(a, dtype=float).tolist(), np.asarray(b, dtype=float)
    cols = b.T.tolist()
    return np.array([[dot(row, col) for col in cols] for row in a]).reshape(len(a), b.shape[1])


def matvec(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``a @ x`` with :func:`dot`'s order."""
    xs = np.asarray(x, dtype=float).tolist()
    return np.array([dot(row, xs) for row in np.asarray(a, dtype=float).tolist()])


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """``x`` with ``a x = b`` by Gaussian elimination with partial pivoting (rows swapped to the
    first largest ``|pivot|``), then back substitution; None when a pivot is exactly zero (or not
    a number): the matrix is singular."""
    m = len(b)
    A = np.asarray(a, dtype=float).tolist()
    x = np.asarray(b, dtype=float).tolist()
    for k in range(m):
        p, best = k, abs(A[k][k])
        for i in range(k + 1, m):
            if abs(A[i][k]) > best:
                p, best = i, abs(A[i][k])
        if not best > 0.0:
            return None
        if p != k:
            A[k], A[p] = A[p], A[k]
            x[k], x[p] = x[p], x[k]
        for i in range(k + 1, m):
            f = A[i][k] / A[k][k]
            for j in range(k + 1, m):
                A[i][j] -= f * A[k][j]
            x[i] -= f * x[k]
    for i in range(m - 1, -1, -1):
        s = x[i]
        for j in range(i + 1, m):
            s -= A[i][j] * x[j]
        x[i] = s / A[i][i]
    return np.array(x)


__all__ = ["dot", "matmul", "matvec", "solve"]
