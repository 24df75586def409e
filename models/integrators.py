"""Embedded integrators: the one-communication-step map of a :class:`~models.block.Block`.

These are the exact CasADi functions that :mod:`fmus` code-generates into an FMU, so a test can
evaluate in Python precisely what the FMU runs in C.

Conventions
-----------
- Inputs follow ``u(tau) = u + du tau`` over a communication step (``tau`` from 0 to ``h``):
  ``du = 0`` is the zero-order hold; a master that knows the inputs' slopes (FMI 2.0
  ``fmi2SetRealInputDerivatives``, first order) passes them as ``du``.  Blocks are autonomous
  (time does not appear in ``ode``/``out``).
- The step *kernel* has the signature ``(x, u, p, h, du) -> (x_next, ok, err)``:

  ``rk4``
      classic explicit Runge-Kutta of order 4 with ``block.substeps`` equal substeps of ``h/substeps``;
      ``ok`` is 1 when ``x_next`` is finite.
  ``radau``
      implicit Radau IIA, 3 stages, order 5 (stiffly accurate, L-stable), ``block.substeps`` equal
      substeps.  The stage equations are solved by simplified Newton with the Jacobian taken and
      the iteration matrix factorised once per step (a symbolic sparse QR, see
      :func:`radau_stages`); the iteration stops once a correction is below ``NEWTON_STEP`` of
      the tolerance, or after ``max_iter`` iterations, and the kernel then takes one more
      Newton correction ``dZ`` at the returned point and accepts only if every component
      satisfies ``|dZ_j| <= atol + rtol (|x_j| + |Z_j|)`` (``err`` is the largest such ratio,
      ``ok`` = :func:`radau_accepts` (err) and finite).  ``rtol``/``atol`` are the block's
      parameters ``solver.rtol``/``solver.atol`` when it declares them.  The FMU runs
      :func:`radau_memory_kernel`, which keeps the factors and the last stages from one call to
      the next (Python callers of :attr:`Stepper.kernel` get the memoryless kernel).
  ``exact``
      for a block whose ``ode`` is affine in ``x`` and ``u`` (``dx/dt = A x + B u + c`` with
      ``A, B, c`` functions of the parameters only): the exact solution over the step for inputs
      ``u + du tau``, from the matrix exponential of an augmented matrix (:func:`exact_kernel`).
      Stable and exact at any step; ``err`` is 0.
  ``discrete``
      ``ode`` is the update map ``x[k+1] = f(x[k], u, p)``; the kernel applies it once (one sample)
      and ignores ``h`` and ``du`` (a sampled block reads its inputs at the samples).  A
      communication step of ``h = n * sample_period`` applies it ``n`` times (see
      :meth:`Stepper.samples`); any other ``h`` is refused.
  ``none``
      no states: ``x_next`` is empty and ``ok`` is 1.

- ``err`` is 0 for the explicit kernels.
- ``ok`` is 0.0 or 1.0.  A caller (the FMU) that gets ``ok = 0`` must discard ``x_next`` and keep
  the state it had before the step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from .block import Block, BlockError

#: Newton acceptance test of the Radau kernel: ``|dZ_j| <= ATOL + RTOL (|x_j| + |Z_j|)``;
#: defaults of the block parameters ``solver.rtol``/``solver.atol`` (:func:`tolerances`).
RADAU_RTOL = 1e-9
RADAU_ATOL = 1e-10
#: Names of the tolerance parameters a block with an implicit integrator may declare.
SOLVER_RTOL, SOLVER_ATOL = "solver.rtol", "solver.atol"
#: A Radau step is accepted when its error ratio ``err`` is at most this (:func:`radau_accepts`).
RADAU_ACCEPT_RATIO = 1.0
#: Simplified-Newton iterations per Radau substep (linear problems converge in one).
RADAU_MAX_ITER = 30
#: The Newton iteration stops once a correction is below this fraction of ``ATOL + RTOL |x|``.
#: Not lower: with joint springs of 1e8 N/m the corrections of a converged iteration stagnate at
#: 0.05-0.2 of the tolerance (round-off), and at 0.1 a fifth of the multibody mechanism's 0.1 ms
#: steps ran to ``RADAU_MAX_ITER`` (mean 9.7 iterations; 3.0 at 0.3, same states to 1e-8).
#: Acceptance is judged separately, on one more correction (module docstring).
NEWTON_STEP = 0.3

_S6 = math.sqrt(6.0)
#: Radau IIA (s = 3) Butcher tableau; ``b`` equals the last row of ``A`` (stiffly accurate).
RADAU_A = np.array([
    [(88 - 7 * _S6) / 360, (296 - 169 * _S6) / 1800, (-2 + 3 * _S6) / 225],
    [(296 + 169 * _S6) / 1800, (88 + 7 * _S6) / 360, (-2 - 3 * _S6) / 225],
    [(16 - _S6) / 36, (16 + _S6) / 36, 1 / 9],
])
RADAU_C = np.array([(4 - _S6) / 10, (4 + _S6) / 10, 1.0])



def _radau_transformation() -> tuple[np.ndarray, np.ndarray]:
    """``T`` and ``L = T^-1 A^-1 T = [[g, 0, 0], [0, a, b], [0, -b, a]]``, the real block form of
    the inverse Radau matrix (Hairer & Wanner's Radau5 transformation): in these coordinates the
    simplified-Newton matrix splits into an ``n x n`` and a ``2n x 2n`` block."""
    Ai = np.linalg.inv(RADAU_A)
    w, V = np.linalg.eig(Ai)
    i = int(np.argmin(np.abs(w.imag)))
    j = next(k for k in range(3) if k != i and w[k].imag > 0)
    T = np.column_stack([V[:, i].real, V[:, j].real, V[:, j].imag])
    L = np.zeros((3, 3))
    L[0, 0] = w[i].real
    L[1, 1] = L[2, 2] = w[j].real
    L[1, 2], L[2, 1] = w[j].imag, -w[j].imag
    assert np.allclose(np.linalg.solve(T, Ai @ T), L, atol=1e-12)
    return T, L


RADAU_T, RADAU_L = _radau_transformation()

#: Relative tolerance of "h is a multiple of the sample period" (shared with the C wrapper).
SAMPLE_TOL = 1e-9


class IntegratorError(BlockError):
    """A step that cannot be taken as asked (e.g. ``h`` not a multiple of the sample period)."""


def _all_finite(v: ca.SX | ca.MX):
    """1 if every entry of ``v`` is finite (NaN and inf propagate through the sum), else 0."""
    if v.numel() == 0:
        return 1
    return ca.sum1(ca.fabs(ca.vec(v))) < ca.inf


def _syms(block: Block, kind=ca.MX, nx: int | None = None) -> tuple:
    """Symbols ``x, u, p, h, du`` of a kernel's arguments."""
    nu = block.u.numel()
    return tuple(kind.sym(n, s) for n, s in (("x", block.x.numel() if nx is None else nx), ("u", nu),
                                              ("p", block.p.numel()), ("h", 1), ("du", nu)))


def _kernel(block: Block, args: tuple, x_next, ok, err) -> ca.Function:
    return ca.Function(f"{block.name}_step", list(args), [x_next, ok, err], ["x", "u", "p", "h", "du"],
                       ["x_next", "ok", "err"])


def _substeps(block: Block, sub: ca.Function, x, u, p, h, du) -> tuple:
    """``block.substeps`` calls of ``sub(x, u_j, p, h/m, du) -> (x_next, ...)``, substep ``j``
    starting from the input ``u_j = u + du j h/m``; returns the last substep's outputs, with
    ``ok`` the minimum and ``err`` the maximum over substeps when ``sub`` has them."""
    m = block.substeps
    if m == 1:
        res = sub(x, u, p, h, du)
        return tuple(res) if isinstance(res, (list, tuple)) else (res,)
    hs = h / m
    starts = ca.repmat(u, 1, m) + ca.mtimes(du, ca.DM(np.arange(m)).T) * hs
    acc = sub.mapaccum(f"{sub.name()}_acc", m)
    res = acc(x, starts, ca.repmat(p, 1, m), ca.repmat(hs, 1, m), ca.repmat(du, 1, m))
    res = res if isinstance(res, (list, tuple)) else [res]
    out = [res[0][:, -1]]
    if len(res) == 3:
        out += [ca.mmin(res[1]), ca.mmax(res[2])]
    return tuple(out)


def rk4_kernel(block: Block) -> ca.Function:
    """``(x, u, p, h, du) -> (x_next, ok, err)``: RK4 with ``block.substeps`` substeps; the
    stages see the input at their own times (``u``, ``u + du h/2``, ``u + du h``)."""
    f = block.functions()["ode"]
    xs, us, ps, hs, dus = _syms(block, ca.SX)
    k1 = f(xs, us, ps)
    k2 = f(xs + hs / 2 * k1, us + hs / 2 * dus, ps)
    k3 = f(xs + hs / 2 * k2, us + hs / 2 * dus, ps)
    k4 = f(xs + hs * k3, us + hs * dus, ps)
    sub = ca.Function(f"{block.name}_rk4_sub", [xs, us, ps, hs, dus], [xs + hs / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    args = _syms(block)
    (xn,) = _substeps(block, sub, *args)
    return _kernel(block, args, xn, _all_finite(xn), ca.MX(0))


def _radau_residual(block: Block) -> ca.Function:
    """``(Z, x, u, p, h) -> R``: the stage equations ``Z_i - h sum_j a_ij f(x + Z_j, u, p)`` with
    the three stage increments stacked in ``Z`` (3 nx)."""
    n = block.x.numel()
    f = block.functions()["ode"]
    # MX calls of the SX ode function: one copy of f in the generated code
    xs, us, ps, hs = (ca.MX.sym(nm, s) for nm, s in (("x", n), ("u", block.u.numel()),
                                                      ("p", block.p.numel()), ("h", 1)))
    Z = ca.MX.sym("Z", 3 * n)
    Zi = [Z[i * n:(i + 1) * n] for i in range(3)]
    F = [f(xs + Zi[i], us, ps) for i in range(3)]
    R = ca.vertcat(*[Zi[i] - hs * sum(float(RADAU_A[i, j]) * F[j] for j in range(3)) for i in range(3)])
    return ca.Function(f"{block.name}_radau_res", [Z, xs, us, ps, hs], [R], ["Z", "x", "u", "p", "h"], ["R"])


def radau_accepts(err):
    """The Radau kernel's acceptance test on its error ratio ``err`` (a CasADi expression or a
    number): the step is taken when ``err <= RADAU_ACCEPT_RATIO`` (and ``err`` is finite)."""
    return err <= RADAU_ACCEPT_RATIO


def tolerances(block: Block, p) -> tuple:
    """``(rtol, atol)`` of ``block``'s implicit solver: its parameters ``solver.rtol`` and
    ``solver.atol`` (entries of ``p``) when it declares them, else the module defaults."""
    names = [prm.name for prm in block.params]
    out = []
    for name, default in ((SOLVER_RTOL, RADAU_RTOL), (SOLVER_ATOL, RADAU_ATOL)):
        out.append(p[names.index(name)] if name in names else default)
    return tuple(out)


def _newton_factors(block: Block) -> tuple[ca.Function, ca.Function, ca.Function]:
    """``factor(J_nz, h) -> F`` and ``solve(F, r) -> W`` for the simplified-Newton matrix
    ``L (x) I - h I (x) J0`` of :func:`radau_stages`, plus ``J0`` itself.

    The matrix splits into the real block ``g I - h J0`` (n x n) and the complex pair's real block
    ``[[a I - h J0, b I], [-b I, a I - h J0]]`` (2n x 2n).  Both are factorised by a sparse
    Householder QR (``casadi.qr_sparse``) done *symbolically*: the factorisation is an SX
    expression of ``J0``'s nonzeros and ``h`` whose structure (fill-in, ordering) is fixed when the
    code is generated, and ``F`` packs the nonzeros of its factors.  ``solve`` applies them (two
    Householder sweeps and triangular solves, no refactorisation), so a Newton iteration costs
    one ODE evaluation per stage and one ``solve``."""
    n = block.x.numel()
    jac = ca.jacobian(block.ode, block.x)
    sp = jac.sparsity()
    J_nz = ca.vertcat(*jac.nonzeros()) if jac.nnz() else ca.SX(0, 1)
    fx = ca.Function(f"{block.name}_ode_jac", [block.x, block.u, block.p], [J_nz], ["x", "u", "p"], ["J_nz"])
    g, a, b = float(RADAU_L[0, 0]), float(RADAU_L[1, 1]), float(RADAU_L[1, 2])
    Jn = ca.SX.sym("J_nz", sp.nnz())
    hs = ca.SX.sym("h")
    J = ca.SX(sp, Jn) if sp.nnz() else ca.SX(n, n)
    I = ca.SX.eye(n)
    Mr = g * I - hs * J
    # the complex pair's block with real and imaginary parts interleaved state by state: the
    # fill-in of its QR is 20 % lower (measured on the multibody mechanism: 99k against 119k ops)
    inter = [int(k) for k in np.arange(2 * n).reshape(2, n).T.ravel()]
    back = [int(k) for k in np.argsort(inter)]
    Mc = ca.blockcat([[a * I - hs * J, b * I], [-b * I, a * I - hs * J]])[inter, inter]
    r = ca.SX.sym("r", 3 * n)
    factors = [ca.qr_sparse(M, True) for M in (Mr, Mc)]
    F = ca.vertcat(*[ca.vertcat(*m.nonzeros()) for fac in factors for m in fac[:3]])
    factor = ca.Function(f"{block.name}_radau_factor", [Jn, hs], [F], ["J_nz", "h"], ["F"])
    Fs = ca.SX.sym("F", F.numel())
    k, sols = 0, []
    for (V, R, beta, prinv, pc), rhs in zip(factors, (r[:n], r[n:][inter])):
        packed = []
        for m in (V, R, beta):
            packed.append(ca.SX(m.sparsity(), Fs[k:k + m.nnz()]))
            k += m.nnz()
        sols.append(ca.qr_solve(rhs, *packed, prinv, pc))
    solve = ca.Function(f"{block.name}_radau_solve", [Fs, r], [ca.vertcat(sols[0], sols[1][back])],
                        ["F", "r"], ["W"])
    return fx, factor, solve


def radau_stages(block: Block, *, rtol=None, atol=None, max_iter: int = RADAU_MAX_ITER) -> ca.Function:
    """``(x, u, p, h, du) -> (Z, ok, err)``: the converged stage increments of one Radau IIA step
    (stage ``i`` sees the input ``u + du c_i h``), with the acceptance flag and ratio of the
    module docstring.

    Simplified Newton from ``Z = 0`` as in Hairer & Wanner's Radau5: the ODE Jacobian
    ``J0 = df/dx`` is taken once, at the start of the step, and the stage equations are solved in
    the coordinates ``Z = (T (x) I) W`` that make the iteration matrix block diagonal,
    ``L (x) I - h I (x) J0`` (one ``n x n`` and one ``2n x 2n`` block).  The matrix is
    factorised **once per step** (:func:`_newton_factors`); every iteration reuses the factors.
    The loop is ``max_iter`` calls of a conditional iteration (``casadi.Function.conditional``):
    once a correction is below ``NEWTON_STEP * sc`` (``sc = atol + rtol |x|``) the remaining
    calls skip their body, so a converged step pays for the iterations it used only.

    Acceptance uses one more simplified-Newton correction ``dZ`` at the returned point, i.e. the
    error left in ``Z``, not the raw residual: a residual of a stiff component carries round-off
    of order ``eps * k * |x|`` that the iteration matrix damps away.  ``err`` is the largest
    ``|dZ_j| / (atol + rtol (|x_j| + |Z_j|))`` and the step is accepted by :func:`radau_accepts`.

    ``rtol``/``atol`` (numbers) override the tolerances; by default they are the block's
    parameters ``solver.rtol``/``solver.atol`` when declared (:func:`tolerances`), else
    ``RADAU_RTOL``/``RADAU_ATOL``."""
    fx, factor, solve = _newton_factors(block)
    given = _stages_given_factors(block, solve, factor.size1_out(0), rtol=rtol, atol=atol, max_iter=max_iter)
    x, u, p, h, du = _syms(block)
    Z, ok, err, _ = given(x, u, p, h, du, factor(fx(x, u, p), h), ca.MX.zeros(3 * block.x.numel()))
    return ca.Function(f"{block.name}_radau_stages", [x, u, p, h, du], [Z, ok, err],
                       ["x", "u", "p", "h", "du"], ["Z", "ok", "err"])


def _stages_given_factors(block: Block, solve: ca.Function, n_factors: int, *, rtol=None, atol=None,
                          max_iter: int = RADAU_MAX_ITER, tag: str = "") -> ca.Function:
    """``(x, u, p, h, du, F, Z0) -> (Z, ok, err, iterations)``: the simplified-Newton solve of
    :func:`radau_stages` from the stage increments ``Z0`` (0, or a prediction) with the factors
    ``F`` of the iteration matrix given (made by ``_newton_factors``' ``factor`` at this step or
    an earlier one)."""
    n, nu, npar = block.x.numel(), block.u.numel(), block.p.numel()
    f = block.functions()["ode"]
    Tk, Tik, Lk = (ca.sparsify(ca.DM(np.kron(m, np.eye(n)))) for m in (RADAU_T, np.linalg.inv(RADAU_T), RADAU_L))

    def residual(W, xs, us, ps, hs, dus):
        """``(L (x) I) W - h (T^-1 (x) I) F(x + (T (x) I) W)`` and the stage increments ``Z``."""
        Z = ca.mtimes(Tk, W)
        F = ca.vertcat(*[f(xs + Z[i * n:(i + 1) * n], us + float(RADAU_C[i]) * hs * dus, ps) for i in range(3)])
        return ca.mtimes(Lk, W) - hs * ca.mtimes(Tik, F), Z

    # the residual as straight-line code (the products with the constant T, T^-1, L unrolled)
    Wx, xx, ux, px, hx, dux = (ca.SX.sym(nm, s) for nm, s in (("W", 3 * n), ("x", n), ("u", nu), ("p", npar),
                                                               ("h", 1), ("du", nu)))
    res_fn = ca.Function(f"{block.name}_radau_res{tag}", [Wx, xx, ux, px, hx, dux],
                         list(residual(Wx, xx, ux, px, hx, dux)))
    # one conditional simplified-Newton iteration: (W, x, u, p, h, du, F, sc) -> (dW, going)
    W, xs, us, ps, hs, dus = (ca.MX.sym(nm, s) for nm, s in (("W", 3 * n), ("x", n), ("u", nu), ("p", npar),
                                                               ("h", 1), ("du", nu)))
    Fs, scs = ca.MX.sym("F", n_factors), ca.MX.sym("sc", 3 * n)
    G, _ = res_fn(W, xs, us, ps, hs, dus)
    dW = -solve(Fs, G)
    going = ca.mmax(ca.fabs(dW) / scs) > NEWTON_STEP
    body = ca.Function(f"{block.name}_radau_iter{tag}", [W, xs, us, ps, hs, dus, Fs, scs], [dW, going])
    iterate = ca.Function.conditional(f"{block.name}_radau_iter{tag}_if", body)

    x, u, p, h, du = _syms(block)
    fac, Z0 = ca.MX.sym("F", n_factors), ca.MX.sym("Z0", 3 * n)
    tol_r, tol_a = tolerances(block, p)
    tol_r = tol_r if rtol is None else rtol
    tol_a = tol_a if atol is None else atol
    scale = ca.repmat(tol_a + tol_r * ca.fabs(x), 3, 1)
    Wk, going, iterations = ca.mtimes(Tik, Z0), ca.MX(1), ca.MX(0)
    for _ in range(int(max_iter)):
        iterations = iterations + going
        dWk, going = iterate(going, Wk, x, u, p, h, du, fac, scale)
        Wk = Wk + dWk
    # one more correction with the same factors: the error left in Z
    Gk, Zsol = res_fn(Wk, x, u, p, h, du)
    dZ = ca.mtimes(Tk, solve(fac, Gk))
    r = ca.fabs(dZ) / (scale + tol_r * ca.fabs(Zsol))
    err = ca.mmax(r)
    ok = ca.logic_and(ca.logic_and(radau_accepts(err), _all_finite(r)), _all_finite(Zsol))
    return ca.Function(f"{block.name}_radau_stages_given{tag}", [x, u, p, h, du, fac, Z0],
                       [Zsol, ok, err, iterations], ["x", "u", "p", "h", "du", "F", "Z0"], ["Z", "ok", "err", "iterations"])


def radau_substep(block: Block, **newton) -> ca.Function:
    """One Radau IIA step ``(x, u, p, h, du) -> (x_next, ok, err)``; ``x_next = x + Z_3`` since
    the method is stiffly accurate."""
    n = block.x.numel()
    stages = radau_stages(block, **newton)
    x, u, p, h, du = _syms(block)
    Z, ok, err = stages(x, u, p, h, du)
    return ca.Function(f"{block.name}_radau_sub", [x, u, p, h, du], [x + Z[2 * n:3 * n], ok, err],
                       ["x", "u", "p", "h", "du"], ["x_next", "ok", "err"])


def radau_kernel(block: Block, **newton) -> ca.Function:
    """``(x, u, p, h, du) -> (x_next, ok, err)``: Radau IIA with ``block.substeps`` substeps.

    ``ok`` is the minimum over substeps and ``err`` the maximum."""
    args = _syms(block)
    return _kernel(block, args, *_substeps(block, radau_substep(block, **newton), *args))


#: Pade degree and the largest ``||X||_1`` it is used at (Higham 2005, theta_7): below it the
#: [7/7] approximant of ``exp(X)`` is exact to double precision (backward error < 2^-53).
PADE_DEGREE, PADE_THETA = 7, 0.9504178996162932
#: Squarings of the exact kernel come in groups of 2^j, j < SQUARING_BITS (one conditional call
#: per bit of their number ``s``): at most 2^6 - 1 = 63 squarings bring any ``||N h||_1`` below
#: ~8e18 into the Pade range; a larger one (or a non-finite one) makes the step fail (``ok`` = 0).
SQUARING_BITS = 6
EXPM_MAX_SQUARINGS = 2 ** SQUARING_BITS - 1


#: Simplified-Newton iterations a step tries with the factors of an earlier step
#: (:func:`radau_memory_kernel`) before it factorises afresh and starts again.
RADAU_REUSE_MAX_ITER = 8
#: A step that needed more iterations than this with reused factors gets fresh ones next step.
RADAU_REUSE_SLOW = 4


def _extrapolation() -> np.ndarray:
    """``E`` (3 x 3) with ``Z_next = (E (x) I) Z``: the stage increments of the next step
    predicted from this step's by its collocation polynomial ``q`` (degree 3, ``q(0) = 0``,
    ``q(c_i) = Z_i``): ``Z_next,i = q(1 + c_i) - q(1)`` (time in units of the step)."""
    nodes = np.concatenate([[0.0], RADAU_C])
    E = np.zeros((3, 3))
    for i in range(3):
        tau = 1.0 + RADAU_C[i]
        for j in range(3):
            others = [nodes[k] for k in range(4) if k != j + 1]
            E[i, j] = np.prod([(tau - o) / (nodes[j + 1] - o) for o in others])
    E[:, 2] -= 1.0
    return E


RADAU_E = _extrapolation()


def radau_memory_size(block: Block) -> int:
    """Length of the factor memory ``F`` of :func:`radau_memory_kernel` for ``block``."""
    return _newton_factors(block)[1].size1_out(0)


def radau_memory_kernel(block: Block, **newton) -> ca.Function:
    """``(x, u, p, h, du, F, hF, Zp, hZ) -> (x_next, ok, err, F_new, Z, info)``: :func:`radau_kernel`
    with memory from one call to the next (what the FMU runs): the factorised iteration matrix
    ``F``, valid for the substep ``hF``, and the last substep's stage increments ``Zp``, taken
    with the substep ``hZ`` (0: none).

    A substep first tries (at most ``RADAU_REUSE_MAX_ITER`` simplified-Newton iterations) from the
    stages predicted by the last substep's collocation polynomial (:data:`RADAU_E`) with the
    kept factors: the Jacobian of an earlier point slows the convergence, not the solution it
    converges to, and the acceptance test is the same.  When there are no valid factors or that
    attempt is not accepted, it does exactly what :func:`radau_kernel` does: Jacobian at its
    start, factorisation (``F_new``), iteration from zero.  ``info = (refreshed, hF_next,
    factorisations, iterations)``: ``refreshed`` is 1 when ``F_new`` holds new factors (the
    caller keeps them as the next ``F``); ``hF_next`` is the substep the kept factors are valid
    for, 0 after an attempt that needed more than ``RADAU_REUSE_SLOW`` iterations (fresh ones
    next time); ``factorisations`` and ``iterations`` count this call's work.  ``Z`` is the
    last substep's stages (the next ``Zp``, with ``hZ`` = the substep).

    As in Hairer & Wanner's RADAU5, which keeps the Jacobian and its LU factors while the
    iteration converges fast and starts it from the extrapolated collocation polynomial: the
    multibody mechanism's iteration matrix changes little over a step, and factorising it was
    most of a step's cost."""
    n = block.x.numel()
    fx, factor, solve = _newton_factors(block)
    nF = factor.size1_out(0)
    reuse = _stages_given_factors(block, solve, nF, max_iter=RADAU_REUSE_MAX_ITER, tag="_reuse",
                                  **{k: v for k, v in newton.items() if k != "max_iter"})
    fresh = _stages_given_factors(block, solve, nF, tag="_fresh", **newton)
    attempt = ca.Function.conditional(f"{block.name}_radau_reuse_if", reuse)
    redo = ca.Function.conditional(f"{block.name}_radau_fresh_if", fresh)
    xs, us, ps, hs = (ca.MX.sym(nm, s) for nm, s in (("x", n), ("u", block.u.numel()), ("p", block.p.numel()),
                                                      ("h", 1)))
    refactor = ca.Function.conditional(f"{block.name}_radau_refactor_if", ca.Function(
        f"{block.name}_radau_refactor", [xs, us, ps, hs], [factor(fx(xs, us, ps), hs)]))
    Ek = ca.sparsify(ca.DM(np.kron(RADAU_E, np.eye(n))))

    x, u, p, h, du = _syms(block)
    F, hF, Zp, hZ = ca.MX.sym("F", nF), ca.MX.sym("hF"), ca.MX.sym("Zp", 3 * n), ca.MX.sym("hZ")
    valid = ca.logic_and(hF == h, h > 0)
    guess = ca.if_else(hZ == h, ca.mtimes(Ek, Zp), ca.MX.zeros(3 * n))
    ZA, okA, errA, itA = attempt(valid, x, u, p, h, du, F, guess)
    need = ca.logic_not(ca.logic_and(valid, okA == 1))
    F_new = refactor(need, x, u, p, h)
    ZB, okB, errB, itB = redo(need, x, u, p, h, du, F_new, ca.MX.zeros(3 * n))
    Z, ok, err = (ca.if_else(need, b, a) for a, b in ((ZA, ZB), (okA, okB), (errA, errB)))
    slow = ca.logic_and(ca.logic_not(need), itA > RADAU_REUSE_SLOW)
    info = ca.vertcat(need, ca.if_else(slow, 0.0, h), need, itA + itB)
    names_in, names_out = ["x", "u", "p", "h", "du", "F", "hF", "Zp", "hZ"], ["x_next", "ok", "err", "F_new", "Z", "info"]
    sub = ca.Function(f"{block.name}_radau_memory_sub", [x, u, p, h, du, F, hF, Zp, hZ],
                      [x + Z[2 * n:3 * n], ok, err, F_new, Z, info], names_in, names_out)
    if block.substeps == 1:
        return ca.Function(f"{block.name}_step", [x, u, p, h, du, F, hF, Zp, hZ], sub(x, u, p, h, du, F, hF, Zp, hZ),
                           names_in, names_out)
    m = block.substeps
    hk = h / m
    xk, okk, errk, Fk, hFk, Zk, hZk = x, ca.MX(1), ca.MX(0), F, hF / m, Zp, hZ / m  # memory in substeps
    kept_new, refreshed, count, iters = ca.MX.zeros(nF), ca.MX(0), ca.MX(0), ca.MX(0)
    for j in range(m):
        xk, okj, errj, Fj, Zk, infoj = sub(xk, u + du * (j * hk), p, hk, du, Fk, hFk, Zk, hZk)
        okk, errk = ca.fmin(okk, okj), ca.fmax(errk, errj)
        Fk = ca.if_else(infoj[0], Fj, Fk)
        kept_new = ca.if_else(infoj[0], Fj, kept_new)
        refreshed, hFk, hZk = ca.fmax(refreshed, infoj[0]), infoj[1], hk
        count, iters = count + infoj[2], iters + infoj[3]
    return ca.Function(f"{block.name}_step", [x, u, p, h, du, F, hF, Zp, hZ],
                       [xk, okk, errk, kept_new, Zk, ca.vertcat(refreshed, hFk * m, count, iters)], names_in, names_out)
    # (hF and hZ are kept in units of the communication step h: a call with another h starts afresh)


#: CasADi operations whose value jumps where an operand crosses a value (relations, floor, ceil,
#: sign): their derivative is zero, so a Jacobian free of ``x`` does not make an expression that
#: reads ``x`` through them affine (``if x > 1 then 2 else 1``).
_JUMPS = {ca.OP_LT, ca.OP_LE, ca.OP_EQ, ca.OP_NE, ca.OP_FLOOR, ca.OP_CEIL, ca.OP_SIGN}


def _switches_on(expr: ca.SX, args: list[ca.SX], inputs: set[int]) -> bool:
    """Whether ``expr`` (a function of ``args``) reads one of ``args[i]``, ``i`` in ``inputs``,
    through a jump (:data:`_JUMPS`, or the condition of an if-expression)."""
    f = ca.Function("switches", args, [expr])
    dep: dict[int, bool] = {}
    for k in range(f.n_instructions()):
        op, ins, outs = f.instruction_id(k), f.instruction_input(k), f.instruction_output(k)
        if op == ca.OP_INPUT:
            dep[outs[0]] = ins[0] in inputs
            continue
        if op in (ca.OP_OUTPUT, ca.OP_CONST):
            if op == ca.OP_CONST:
                dep[outs[0]] = False
            continue
        read = [dep.get(i, False) for i in ins]
        if (op in _JUMPS and any(read)) or (op == ca.OP_IF_ELSE_ZERO and read and read[0]):
            return True
        for o in outs:
            dep[o] = any(read)
    return False


def affine_parts(block: Block) -> tuple[ca.SX, ca.SX, ca.SX] | None:
    """``(A, B, c)`` with ``ode = A x + B u + c`` when the block's ``ode`` is affine in ``x`` and
    ``u`` (its Jacobians depend on the parameters only, and no relation on ``x`` or ``u``
    switches it), else ``None``."""
    xu = ca.vertcat(block.x, block.u)
    A = ca.jacobian(block.ode, block.x)
    B = ca.jacobian(block.ode, block.u)
    if ca.depends_on(A, xu) or ca.depends_on(B, xu):
        return None
    others = [v for v in ca.symvar(block.ode) if not ca.depends_on(v, xu)]  # parameters, modes
    if _switches_on(block.ode, [xu, ca.vertcat(*others) if others else ca.SX(0, 1)], {0}):
        return None
    c = ca.substitute(block.ode, xu, ca.DM.zeros(xu.numel()))
    return A, B, c


def _pade_expm(X: ca.SX) -> ca.SX:
    """The [7/7] Pade approximant of ``exp(X)`` (accurate for ``||X||_1 <= PADE_THETA``)."""
    m = PADE_DEGREE
    coef = [math.factorial(2 * m - k) * math.factorial(m) / (math.factorial(2 * m) * math.factorial(k)
                                                             * math.factorial(m - k)) for k in range(m + 1)]
    eye = ca.SX.eye(X.size1())
    Pk, num, den = eye, coef[0] * eye, coef[0] * eye
    for k in range(1, m + 1):
        Pk = ca.mtimes(Pk, X)
        num = num + coef[k] * Pk
        den = den + (-1) ** k * coef[k] * Pk
    return ca.solve(den, num)


#: Sweeps of the diagonal balancing applied before the exponential (:func:`_balance`).
BALANCE_SWEEPS = 3


def _balance(X: ca.SX) -> tuple[ca.SX, ca.SX]:
    """``(D^-1 X D, d)`` with ``D = diag(d)``: Parlett-Reinsch balancing (each sweep makes every
    row's off-diagonal 1-norm equal its column's) with a fixed number of sweeps.  A badly scaled matrix (the motor's 1e8 N/m
    bond beside its 1e-6 m deflection) loses digits in the Pade approximant and its squarings
    (5e-5 relative, measured); balanced, the step agrees with the eigen-decomposition solution
    to 1e-14."""
    m = X.size1()
    e = [[X[i, j] for j in range(m)] for i in range(m)]
    d = [ca.SX(1.0) for _ in range(m)]
    for _ in range(BALANCE_SWEEPS):
        for i in range(m):
            c = sum(ca.fabs(e[j][i]) for j in range(m) if j != i)
            r = sum(ca.fabs(e[i][j]) for j in range(m) if j != i)
            f = ca.if_else(ca.logic_and(c > 0, r > 0), ca.sqrt(r / c), 1.0)
            fi = 1.0 / f
            for j in range(m):
                if j != i:
                    e[j][i] = e[j][i] * f
                    e[i][j] = e[i][j] * fi
            d[i] = d[i] * f
    X = ca.vertcat(*[ca.horzcat(*row) for row in e])
    return X, ca.vertcat(*d)


def exact_kernel(block: Block) -> ca.Function:
    """``(x, u, p, h, du) -> (x_next, ok, err)``: the exact step of an affine block.

    With ``dx/dt = A x + B (u + du tau) + c`` the augmented state ``z = (x, 1, tau)`` obeys
    ``dz/dt = N z``, ``N = [[A, B u + c, B du], [0, 0, 0], [0, 1, 0]]``, so
    ``x(h) = [exp(N h) z(0)]_x`` with ``z(0) = (x, 1, 0)``.  ``N h`` is balanced
    (:func:`_balance`), then its exponential is evaluated by scaling and squaring: ``s = max(0, ceil(log2(||N h||_1 / PADE_THETA)))`` squarings of the [7/7] Pade
    approximant of ``exp(N h / 2^s)`` (Higham's method with one fixed degree).  The squarings are
    grouped by the bits of ``s`` (``2^j`` squarings when bit ``j`` is set) in conditional calls
    (``casadi.Function.conditional``), so a step pays only for the ``s`` squarings it needs.  Exact (to round-off) and stable at any ``h``, whatever the block's time constants:
    why the linear blocks (PID, DC motor) use it.  ``err`` is 0; ``ok`` is 0 when the state is
    not finite or ``s > EXPM_MAX_SQUARINGS``.

    The exponential is evaluated at every call, not cached per step size: it depends on the
    inputs through ``B u + c`` (the augmented matrix is ``n + 2`` square, 4 for the PID), and
    costs about a microsecond, less than one Radau step of the same block."""
    parts = affine_parts(block)
    if parts is None:
        raise BlockError(f"block {block.name}: integrator 'exact' needs an ode affine in the states and "
                         f"inputs; this one is not (use radau)")
    A, B, c = parts
    n = block.x.numel()
    _, _, _, hs, dus = _syms(block, ca.SX)
    us, ps = block.u, block.p
    Ns = ca.blockcat([[A, B @ us + c, B @ dus], [ca.SX(2, n), ca.SX(ca.DM([[0, 0], [1, 0]]))]]) * hs
    Nf = ca.Function(f"{block.name}_exact_matrix", [us, ps, hs, dus], [Ns])
    X = ca.SX.sym("X", n + 2, n + 2)
    Xb, d = _balance(X)
    norm = ca.mmax(ca.sum1(ca.fabs(Xb)))
    s = ca.fmax(0, ca.ceil(ca.log(norm / PADE_THETA) / math.log(2.0)))
    # exp(N h) = D exp(D^-1 N h D) D^-1, and D commutes with the squarings
    pade = ca.Function(f"{block.name}_exact_pade", [X], [_pade_expm(Xb / 2 ** s), s, d])
    x, u, p, h, du = _syms(block)
    E, sq, d = pade(Nf(u, p, h, du))
    # 2^j squarings for every bit j of s: at most SQUARING_BITS conditional calls; group j calls
    # group j-1 twice (the generated code holds one squaring, not 63 unrolled ones)
    keep = ca.Function(f"{block.name}_exact_keep", [X], [X])
    group = ca.Function(f"{block.name}_exact_square0", [X], [ca.mtimes(X, X)])
    Xm = ca.MX.sym("X", n + 2, n + 2)
    for j in range(SQUARING_BITS):
        if j:
            group = ca.Function(f"{block.name}_exact_square{j}", [Xm], [prev(prev(Xm))])
        E = ca.Function.conditional(f"{block.name}_exact_bit{j}", [keep], group)(ca.fmod(ca.floor(sq / 2 ** j), 2), E)
        prev = group
    # [D E D^-1 (x, 1, 0)]_x
    xn = d[:n] * (ca.mtimes(E[:n, :n], x / d[:n]) + E[:n, n] / d[n])
    ok = ca.logic_and(_all_finite(xn), sq <= EXPM_MAX_SQUARINGS)
    return _kernel(block, (x, u, p, h, du), xn, ok, ca.MX(0))


def discrete_kernel(block: Block) -> ca.Function:
    """``(x, u, p, h, du) -> (x_next, ok, err)``: one application of the update map (``h`` and
    ``du`` unused)."""
    args = _syms(block, ca.SX)
    xn = block.functions()["ode"](*args[:3])
    return _kernel(block, args, xn, _all_finite(xn), ca.SX(0))


def none_kernel(block: Block) -> ca.Function:
    """``(x, u, p, h, du) -> (x_next, ok, err)`` for a block without states."""
    return _kernel(block, _syms(block, ca.SX, nx=0), ca.SX(0, 1), ca.SX(1), ca.SX(0))


@dataclass
class Stepper:
    """The step kernel of ``block`` and the functions an FMU needs besides it.

    ``step(x, u, p, h, du)`` runs ``samples(h)`` kernel calls, as the FMU does, and returns
    ``(x_next, ok)``; on failure ``x_next`` is the unchanged ``x``.

    For a block with events, the kernels are those of its continuous view
    (:meth:`Block.continuous_view`: ``p' = [p; m]``, one substep): :attr:`block` is that view and
    :attr:`events` the declaration; the FMU's core takes the substeps, locates crossings and
    applies updates itself, so :meth:`step` refuses such a block.
    """

    block: Block
    events: Block | None = None

    def __post_init__(self) -> None:
        blk = self.block
        blk.check()
        if blk.has_events:
            self.events, self.block = blk, blk.continuous_view()
        if blk.integrator == "none" and blk.x.numel():
            raise BlockError(f"block {blk.name}: integrator 'none' but {blk.x.numel()} states "
                             f"({', '.join(v.name for v in blk.states)}); choose rk4, radau or discrete")
        if blk.integrator != "none" and blk.x.numel() == 0:
            raise BlockError(f"block {blk.name}: integrator {blk.integrator!r} but the block has no "
                             f"states; use integrator='none'")

    @cached_property
    def kernel(self) -> ca.Function:
        """``(x, u, p, h, du) -> (x_next, ok, err)`` (see the module docstring)."""
        kind = self.block.integrator
        return {"rk4": rk4_kernel, "radau": radau_kernel, "discrete": discrete_kernel,
                "exact": exact_kernel, "none": none_kernel}[kind](self.block)

    @cached_property
    def memory_kernel(self) -> ca.Function | None:
        """The kernel the FMU runs when it keeps memory between steps (Radau's factors,
        :func:`radau_memory_kernel`), else None (the FMU runs :attr:`kernel`)."""
        return radau_memory_kernel(self.block) if self.block.integrator == "radau" else None

    @cached_property
    def out(self) -> ca.Function:
        """``(x, u, p) -> y``."""
        return self.block.functions()["out"]

    @cached_property
    def start(self) -> ca.Function:
        """``p -> x0``."""
        return self.block.functions()["start"]

    @cached_property
    def out_jacobian(self) -> ca.Function:
        """``(x, u, p) -> [dy/dx, dy/du, dy/dp]``: a dense ``ny x (nx + nu + np)`` matrix, the
        partial derivatives the FMU's directional-derivative call returns."""
        b = self.block
        J = ca.jacobian(b.out, ca.vertcat(b.x, b.u, b.p)) if b.out.numel() else ca.SX(0, b.x.numel() + b.u.numel() + b.p.numel())
        return ca.Function(f"{b.name}_out_jac", [b.x, b.u, b.p], [ca.densify(J)], ["x", "u", "p"], ["J"])

    def samples(self, h: float) -> int:
        """Kernel calls for a communication step ``h`` [s]: ``h / sample_period`` for a discrete
        block (refused unless a whole multiple), else 1."""
        if not (h > 0 and math.isfinite(h)):
            raise IntegratorError(f"block {self.block.name}: communication step h = {h} must be positive and finite")
        if self.block.integrator != "discrete":
            return 1
        ts = float(self.block.sample_period)
        n = round(h / ts)
        if n < 1 or abs(n * ts - h) > SAMPLE_TOL * max(h, ts):
            raise IntegratorError(f"block {self.block.name}: communication step h = {h} s is not a whole "
                                  f"multiple of the sample period {ts} s")
        return n

    def step(self, x, u, p, h: float, du=None) -> tuple[np.ndarray, bool]:
        """Advance the state by one communication step ``h`` [s] with inputs ``u + du tau``
        (``du`` None: held); ``(x_next, ok)``."""
        if self.events is not None:
            raise IntegratorError(f"block {self.block.name}: has events; its steps are taken by the FMU's core "
                                  f"(fmus), which locates crossings and applies updates")
        x0 = np.asarray(x, dtype=float).reshape(-1)
        du = np.zeros(self.block.u.numel()) if du is None else du
        xk = x0
        for _ in range(self.samples(h)):
            xn, ok, _err = self.kernel(xk, u, p, h, du)
            if float(ok) != 1.0:
                return x0.copy(), False
            xk = np.asarray(xn, dtype=float).reshape(-1)
        return xk, True


def step_jacobian(block: Block, **newton) -> ca.Function:
    """``(x, u, p, h) -> (dx_next/dx, dx_next/du)`` of one communication step with held inputs.

    For Radau the derivatives come from the implicit function theorem at the converged stages
    (``dZ = -R_Z^-1 (R_x dx + R_u du)``, chained over substeps), never by differentiating through
    the rootfinder, which would blow up the generated code.  For RK4 they are the algorithmic
    derivatives of the explicit map; for a discrete block, of one sample."""
    b = block
    nx, nu = b.x.numel(), b.u.numel()
    x, u, p, h = (ca.MX.sym(nm, s) for nm, s in (("x", nx), ("u", nu), ("p", b.p.numel()), ("h", 1)))
    du0 = ca.MX.zeros(nu)
    if b.integrator != "radau":
        xn = Stepper(b).kernel(x, u, p, h, du0)[0]
        return ca.Function(f"{b.name}_step_jac", [x, u, p, h], [ca.jacobian(xn, x), ca.jacobian(xn, u)],
                           ["x", "u", "p", "h"], ["A", "B"])
    stages = radau_stages(b, **newton)
    res = _radau_residual(b)
    Zs, xs, us, ps, hs = (ca.MX.sym(nm, s) for nm, s in (("Z", 3 * nx), ("x", nx), ("u", nu),
                                                          ("p", b.p.numel()), ("h", 1)))
    R = res(Zs, xs, us, ps, hs)
    sens = ca.Function(f"{b.name}_radau_sens", [Zs, xs, us, ps, hs],
                       [ca.jacobian(R, Zs), ca.jacobian(R, xs), ca.jacobian(R, us)])
    hk = h / b.substeps
    A, B, xk = ca.MX.eye(nx), ca.MX(nx, nu), x
    for _ in range(b.substeps):
        Zk = stages(xk, u, p, hk, du0)[0]
        RZ, Rx, Ru = sens(Zk, xk, u, p, hk)
        dZ = -ca.solve(RZ, ca.horzcat(Rx, Ru))
        Ax = ca.MX.eye(nx) + dZ[2 * nx:3 * nx, :nx]
        Bu = dZ[2 * nx:3 * nx, nx:]
        A, B = Ax @ A, Ax @ B + Bu
        xk = xk + Zk[2 * nx:3 * nx]
    return ca.Function(f"{b.name}_step_jac", [x, u, p, h], [A, B], ["x", "u", "p", "h"], ["A", "B"])
