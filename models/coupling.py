"""Macro-step maps of fixed-step co-simulation of linear blocks: the analytic stability test.

For blocks that are linear time-invariant, ``dx/dt = A x + B u``, ``y = C x`` (no direct
feedthrough on connected outputs), a fixed-step master algorithm turns one communication step
into a linear map ``Z_k+1 = M(h) Z_k`` of the slaves' states and the input history it keeps.  The
co-simulation is stable exactly when the spectral radius ``rho(M) < 1``; this module builds ``M``
from the blocks' own equations (the same CasADi expressions the FMUs are generated from, linearised
by automatic differentiation) with each slave integrated exactly (matrix exponential), so it is an
independent account of what the master should do, not a replay of the master's code.

Conventions (as documented in :mod:`cosim.master`):

- ``jacobi``: every input takes its source output at ``t_k``; every slave steps.
- ``gauss_seidel``: slaves step in ``order``; an input whose source already stepped takes the
  source's output at ``t_k+1``, the others at ``t_k``.
- ``inputs="hold"``: inputs constant over the step.  ``inputs="linear"``: an input from a source that
  already stepped is interpolated between ``y_k`` and ``y_k+1``; the others are extrapolated from
  ``y_k-1`` and ``y_k``; the slave integrates the ramp exactly.
- multirate (``rates``): slave ``i`` crosses the macro step in ``rates[i]`` exact sub-steps of
  ``h / rates[i]``, its input on sub-step ``j`` being the macro step's held value or its line
  restarted at the sub-instant (``u0 + u1 (j h / r + s)``); its outputs are exchanged at the macro
  instants only.

``Z = [x_1, ..., x_n, y_k-1 of every connection]`` (the history part only matters for ``linear``).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np
from scipy.linalg import expm

from .block import Block


@dataclass(frozen=True)
class LinearSlave:
    """``dx/dt = A x + B u``, ``y = C x + D u`` about the origin, with input and output names."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]


@dataclass(frozen=True)
class Link:
    """``slaves[src].outputs[out] -> slaves[dst].inputs[inp]`` by index."""

    src: int
    out: int
    dst: int
    inp: int


def linearize(block: Block, params: Mapping[str, float] | None = None, *, tol: float = 1e-9) -> LinearSlave:
    """The block's Jacobians at the origin with parameters ``params`` (defaults otherwise).

    Raises ValueError if the block is not linear in ``x`` and ``u`` (Jacobians that change between
    the origin and a random point, relative tolerance ``tol``)."""
    p = block.param_vector(**dict(params or {}))
    jac = _jacobians(block)
    nx, nu = block.x.numel(), block.u.numel()
    at0 = [np.array(m, dtype=float) for m in jac(np.zeros(nx), np.zeros(nu), p)]
    rng = np.random.default_rng(0)
    at1 = [np.array(m, dtype=float) for m in jac(rng.normal(size=nx), rng.normal(size=nu), p)]
    for a, b in zip(at0, at1):
        if not np.allclose(a, b, rtol=tol, atol=tol * (1 + np.abs(a).max(initial=0))):
            raise ValueError(f"block {block.name} is not linear: its Jacobians depend on the operating point")
    A, B, C, D = (m.reshape(r, c) for m, (r, c) in zip(at0, [(nx, nx), (nx, nu), (len(block.outputs), nx),
                                                               (len(block.outputs), nu)]))
    return LinearSlave(A, B, C, D, tuple(v.name for v in block.inputs), tuple(v.name for v in block.outputs))


_JACOBIANS: dict[int, tuple[Block, ca.Function]] = {}


def _jacobians(block: Block) -> ca.Function:
    """``(x, u, p) -> (df/dx, df/du, dh/dx, dh/du)`` of ``block``, built once per block."""
    hit = _JACOBIANS.get(id(block))
    if hit is None or hit[0] is not block:
        fn = ca.Function("lin", [block.x, block.u, block.p],
                         [ca.jacobian(block.ode, block.x), ca.jacobian(block.ode, block.u),
                          ca.jacobian(block.out, block.x), ca.jacobian(block.out, block.u)])
        hit = _JACOBIANS[id(block)] = (block, fn)
    return hit[1]


def ramp_discretization(A: np.ndarray, B: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact step of ``dx/dt = A x + B (u0 + u1 tau)`` over ``tau in [0, h]``:
    ``x(h) = Phi x(0) + G0 u0 + G1 u1`` (matrix exponential of the augmented system)."""
    n, m = B.shape
    aug = np.zeros((n + 2 * m, n + 2 * m))
    aug[:n, :n], aug[:n, n:n + m], aug[n:n + m, n + m:] = A, B, np.eye(m)
    E = expm(aug * h)
    return E[:n, :n], E[:n, n:n + m], E[:n, n + m:]


def rk4_ramp_discretization(A: np.ndarray, B: np.ndarray, h: float, substeps: int = 1
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(Phi, G0, G1)`` as :func:`ramp_discretization`, for ``substeps`` classic RK4 steps of
    ``h / substeps`` instead of the exact solution (stages at ``0, h/2, h/2, h`` of each substep,
    the input ramp evaluated at the stages' times): the map of a slave whose embedded integrator
    is RK4, so that a master's sub-steps change the result and can be checked."""
    n, m = B.shape
    hs = h / substeps
    I = np.eye(n)

    def one(x, u0, u1):  # one RK4 substep on columns: x (n, k), input u0 + u1 tau
        k1 = A @ x + B @ u0
        k2 = A @ (x + hs / 2 * k1) + B @ (u0 + hs / 2 * u1)
        k3 = A @ (x + hs / 2 * k2) + B @ (u0 + hs / 2 * u1)
        k4 = A @ (x + hs * k3) + B @ (u0 + hs * u1)
        return x + hs / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    # linear in (x, u0, u1): push the identity through each part
    cols = [(I, np.zeros((m, n)), np.zeros((m, n))), (np.zeros((n, m)), np.eye(m), np.zeros((m, m))),
            (np.zeros((n, m)), np.zeros((m, m)), np.eye(m))]
    out = []
    for x, u0, u1 in cols:
        for j in range(substeps):
            x = one(x, u0 + u1 * (j * hs), u1)
        out.append(x)
    return out[0], out[1], out[2]


def macro_map(slaves: Sequence[LinearSlave], links: Sequence[Link], h: float, algorithm: str = "jacobi",
              inputs: str = "hold", order: Sequence[int] | None = None,
              rates: Sequence[int] | None = None, discretization=ramp_discretization) -> np.ndarray:
    """The matrix ``M`` of one macro step (module docstring).  Unconnected inputs are held at
    zero (they only add a constant term, which does not change stability).  ``rates``: sub-steps
    per macro step of each slave (default one each); ``discretization(A, B, h) -> (Phi, G0, G1)``
    steps a slave under a ramp input (default exact, :func:`ramp_discretization`)."""
    if algorithm not in ("jacobi", "gauss_seidel"):
        raise ValueError(f"no analytic macro-step map for algorithm {algorithm!r}")
    if inputs not in ("hold", "linear"):
        raise ValueError(f"inputs must be 'hold' or 'linear', got {inputs!r}")
    for ln in links:
        if np.any(slaves[ln.src].D[ln.out] != 0):
            raise ValueError(f"output {slaves[ln.src].outputs[ln.out]} has direct feedthrough: no analytic map")
    n = len(slaves)
    sizes = [s.A.shape[0] for s in slaves]
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    nz = int(offs[-1]) + len(links)
    hist0 = int(offs[-1])  # Z[hist0 + c] = y_k-1 of link c

    def pick(i: int) -> np.ndarray:  # rows of Z selecting x_i
        sel = np.zeros((sizes[i], nz))
        sel[:, offs[i]:offs[i + 1]] = np.eye(sizes[i])
        return sel

    now = [pick(i) for i in range(n)]  # x_i at t_k as a map of Z_k
    cur = list(now)  # x_i at the latest time it reached in this macro step
    stepped = [False] * n
    seq = list(order) if order is not None else list(range(n))
    sequential = algorithm == "gauss_seidel"
    new = [None] * n
    for i in seq:
        sl = slaves[i]
        Phi, G0, G1 = discretization(sl.A, sl.B, h)
        U0 = np.zeros((sl.B.shape[1], nz))
        U1 = np.zeros((sl.B.shape[1], nz))
        for c, ln in enumerate(links):
            if ln.dst != i:
                continue
            yk = slaves[ln.src].C[ln.out] @ now[ln.src]
            if sequential and stepped[ln.src]:
                yk1 = slaves[ln.src].C[ln.out] @ cur[ln.src]
                if inputs == "hold":
                    U0[ln.inp] = yk1
                else:
                    U0[ln.inp], U1[ln.inp] = yk, (yk1 - yk) / h
            else:
                U0[ln.inp] = yk
                if inputs == "linear":
                    prev = np.zeros(nz)
                    prev[hist0 + c] = 1.0
                    U1[ln.inp] = (yk - prev) / h
        r = int(rates[i]) if rates is not None else 1
        if r == 1:
            new[i] = Phi @ now[i] + G0 @ U0 + G1 @ U1
        else:  # r exact sub-steps along the same input line u(tau) = U0 + U1 tau
            Phi, G0, G1 = discretization(sl.A, sl.B, h / r)
            x = now[i]
            for j in range(r):
                x = Phi @ x + G0 @ (U0 + U1 * (j * h / r)) + G1 @ U1
            new[i] = x
        if sequential:
            cur[i], stepped[i] = new[i], True
    M = np.zeros((nz, nz))
    for i in range(n):
        M[offs[i]:offs[i + 1]] = new[i]
    for c, ln in enumerate(links):
        M[hist0 + c] = slaves[ln.src].C[ln.out] @ now[ln.src]
    return M


def spectral_radius(M: np.ndarray) -> float:
    """``max |eig(M)|``."""
    return float(np.max(np.abs(np.linalg.eigvals(M)))) if M.size else 0.0


def monolithic_map(slaves: Sequence[LinearSlave], links: Sequence[Link], h: float) -> np.ndarray:
    """The exact map over ``h`` of the coupled system integrated as one ODE (the reference the
    co-simulation approximates; its spectral radius is ``exp(h max Re(lambda))``)."""
    sizes = [s.A.shape[0] for s in slaves]
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    A = np.zeros((offs[-1], offs[-1]))
    for i, s in enumerate(slaves):
        A[offs[i]:offs[i + 1], offs[i]:offs[i + 1]] = s.A
    for ln in links:
        d, s = ln.dst, ln.src
        A[offs[d]:offs[d + 1], offs[s]:offs[s + 1]] += np.outer(slaves[d].B[:, ln.inp], slaves[s].C[ln.out])
    return expm(A * h)
