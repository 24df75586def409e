"""The compiled engine of ``master.algorithm: iterative``: its macro steps in C.

The same steps as :class:`cosim.master.algorithms.iterative.Iterative` (the Python loop stays the
reference; ``tests/test_native.py`` checks that both give the same values bit for bit, the same
passes per step, rollbacks, Jacobians and Broyden updates, and the same endings): save every
slave's FMU state, passes over the Gauss-Seidel order with each slave restored and re-stepped
only when its inputs changed, the residual of the cut connections, and the fixed-point or
Newton update (Jacobian by the chain rule from directional derivatives or finite differences,
Broyden's update, the solve of :mod:`cosim.master.dense` in the same order of
operations).  The start-time iteration stays in Python (it runs once, before the loop).

One call runs up to ``nsteps`` macro steps (returning early after its wall-time budget) and
hands back a failure, a stop request (after completing the step, as the Python loop does) or a
step that did not converge, with what the Python side needs to word it alike.
"""
from __future__ import annotations

import ctypes
from ctypes import POINTER, c_int64, c_void_p
from functools import lru_cache

import numpy as np

from ..errors import UserError
from .native import CSlave, SlaveArray, builds, c_struct, compile_loop, ctypes_struct

#: The iteration's options, state, scratch buffers and counters (``it_ctl``), declared once for C and ctypes.
CONTROL_FIELDS = (
    ("int32_t", "m", "cut connections (unknowns)"), ("int32_t", "max_iter", "passes per step"),
    ("int32_t", "newton", "1: Newton, 0: fixed point"), ("int32_t", "jac_auto", "directional derivatives allowed"),
    ("int32_t", "linear", "master.inputs linear: the first guess extrapolates"), ("int32_t", "timing", "time calls"),
    ("int32_t", "has_J", "a Jacobian is kept"), ("int32_t", "has_z_prev", "z at the previous point is known"),
    ("double", "omega", "fixed-point relaxation"), ("double", "rtol", "convergence"), ("double", "atol", "convergence"),
    ("double", "growth", "divergence: residual over this times the first"), ("double", "fd_rel", "FD perturbation"),
    ("double *", "z", "the cut inputs at the current point"), ("double *", "z_prev", "at the previous point"),
    ("double *", "zi", "the iterate"), ("double *", "g", "G(z)"), ("double *", "r", "G(z) - z"),
    ("double *", "e", "the scaled residual"), ("double *", "z_old", "the previous iterate"),
    ("double *", "r_old", "its residual"), ("double *", "dz", "the update"), ("double *", "J", "dG/dz (m x m)"),
    ("double *", "A", "I - J, factorised (m x m)"), ("double *", "w", "work (m)"),
    ("double *", "dv", "chain rule: d v / d z per value (nv x m)"), ("int8_t *", "dv_has", "per value: dv known"),
    ("double *", "du", "chain rule: d inputs / d z of one slave (max_in x m)"),
    ("double *", "L", "a slave's local Jacobian (max_feed x max_in)"), ("int32_t *", "cols", "its columns"),
    ("double *", "ends", "a slave's inputs at t+h"), ("double *", "base_in", "finite differences: its inputs"),
    ("double *", "base_out", "finite differences: its feeding outputs"),
    ("double *", "saved_out", "finite differences: its outputs"), ("uint32_t *", "known", "directional: inputs"),
    ("uint32_t *", "unknown", "directional: outputs"), ("double *", "seed", "directional: seed"),
    ("double *", "sens", "directional: result"),
    ("const int64_t *", "cut_src", "per unknown, its source in v"), ("const double *", "cut_factor", "transformation"),
    ("const double *", "cut_offset", "transformation"), ("int32_t *", "passes", "passes of each step of the call"),
    ("int64_t", "rollbacks", "statistics"), ("int64_t", "jacobians", "statistics"),
    ("int64_t", "directional", "statistics"), ("int64_t", "broyden", "statistics"),
    ("int64_t", "fd_steps", "statistics"),
    ("int32_t", "status", "why a call returned early: 0 running, 1 a slave failed, 2 stopped (step completed), "
                          "3 diverged, 4 not converged, 5 saving a state failed, 6 restoring it failed, "
                          "7 a directional derivative failed"),
    ("int32_t", "bad_slave", "the slave of that status"), ("int32_t", "bad_status", "its FMI status"),
    ("int32_t", "fail_it", "passes of the step that did not converge"), ("double", "fail_err", "its residual"),
    ("int64_t", "master_ns", "wall time in this loop outside the slaves' calls (with timing)"),
)

CControl = ctypes_struct("it_ctl", CONTROL_FIELDS)

SOURCE = c_struct("it_ctl", CONTROL_FIELDS) + r"""
enum { IT_OK = 0, IT_FAILED = 1, IT_STOPPED = 2, IT_DIVERGED = 3, IT_NOT_CONVERGED = 4, IT_SAVE = 5,
       IT_RESTORE = 6, IT_DIRECTIONAL = 7 };

/* Iterative._run_slave: from its saved state at t (restored if it ran in this step) with inputs
   ending at ends (NULL: it has none); outputs read into v.  c->status set for a state error. */
static int run_slave(rpr_slave *s, it_ctl *c, double *v, double t, double h, const double *ends) {
    int st = 0, j;
    double *buf = v + s->in_off;
    int64_t t0 = c->timing ? now_ns() : 0;
    if (s->has_last) {
        st = restore_state(s);
        if (failing(st)) { c->status = IT_RESTORE; return st; }
        c->rollbacks++;
    }
    if (ends) {
        if (s->interp) {
            for (j = 0; j < s->n_in; ++j) buf[j] = s->start_in[j];
            for (j = 0; j < s->n_in; ++j) s->slope[j] = ends[j] - s->start_in[j];
            for (j = 0; j < s->n_in; ++j) s->slope[j] /= h;
            st = set_inputs(s, buf);
            if (!failing(st)) st = set_slopes(s);
        } else {
            for (j = 0; j < s->n_in; ++j) buf[j] = ends[j];
            st = set_inputs(s, buf);
        }
    }
    if (!failing(st)) {
        st = do_step(s, t, h);
        if (!failing(st) && st != ST_STOP && ends && s->interp) {
            for (j = 0; j < s->n_in; ++j) buf[j] = ends[j];  /* the outputs at t+h see the inputs at t+h */
            st = set_inputs(s, buf);
        }
    }
    if (!failing(st) && st != ST_STOP) st = get_outputs(s, v);
    if (c->timing) s->ns += now_ns() - t0;
    if (ends) for (j = 0; j < s->n_in; ++j) s->last_in[j] = ends[j];
    s->has_last = 1;
    return st;
}

static inline int ended(int st) { return failing(st) || st == ST_STOP; }

/* Iterative._pass from order position start; the failing slave (or -1), *bad_st its status */
static int32_t pass(rpr_slave *S, int32_t n, const int32_t *order, int32_t start, it_ctl *c, double *v, double t,
                    double h, const double *z, int32_t *bad_st) {
    int32_t k, j, i;
    for (k = start; k < n; ++k) {
        rpr_slave *s;
        int st;
        i = order[k];
        s = &S[i];
        if (!s->n_in) {
            if (!s->has_last) {
                st = run_slave(s, c, v, t, h, NULL);
                if (ended(st) || c->status) { *bad_st = st; return i; }
            }
            continue;
        }
        for (j = 0; j < s->n_in; ++j) c->ends[j] = s->cut[j] >= 0 ? z[s->cut[j]] : v[s->in_src[j]];
        if (s->has_last) {
            int same = 1;
            for (j = 0; j < s->n_in; ++j) if (!(c->ends[j] == s->last_in[j])) { same = 0; break; }
            if (same) continue;
        }
        st = run_slave(s, c, v, t, h, c->ends);
        if (ended(st) || c->status) { *bad_st = st; return i; }
    }
    *bad_st = 0;
    return -1;
}

/* left-to-right sum from the first product (cosim.master.dense.dot) */
static double dot_strided(const double *a, int64_t sa, const double *b, int64_t sb, int32_t len) {
    double acc;
    int32_t k;
    if (len <= 0) return 0.0;
    acc = a[0] * b[0];
    for (k = 1; k < len; ++k) acc += a[k * sa] * b[k * sb];
    return acc;
}

/* Iterative._local_jacobian (step): L (n_feed x ncols, row-major) of slave s; -1 or the failing
   slave's status in *bad_st (a finite-difference step that failed) */
static int local_jacobian(rpr_slave *s, it_ctl *c, double *v, double t, double h, int32_t ncols, int32_t *bad_st) {
    int32_t q, k, j;
    if (c->jac_auto && s->dir_der) {
        int64_t t0 = c->timing ? now_ns() : 0;
        int st = 0;
        for (q = 0; q < s->n_feed; ++q) c->unknown[q] = s->out_vr[s->feed[q]];
        for (k = 0; k < ncols; ++k) c->known[k] = s->in_vr[c->cols[k]];
        for (k = 0; k < ncols && !failing(st); ++k) {
            for (j = 0; j < ncols; ++j) c->seed[j] = j == k ? 1.0 : 0.0;
            if (s->fmi3)
                st = ((fmi3GetDirectionalDerivative_t)s->dir_der)(s->inst, c->unknown, (size_t)s->n_feed, c->known,
                                                                  (size_t)ncols, c->seed, (size_t)ncols, c->sens,
                                                                  (size_t)s->n_feed);
            else
                st = ((fmi2GetDirectionalDerivative_t)s->dir_der)(s->inst, c->unknown, (size_t)s->n_feed, c->known,
                                                                  (size_t)ncols, c->seed, c->sens);
            for (q = 0; q < s->n_feed; ++q) c->L[q * ncols + k] = c->sens[q];
        }
        if (c->timing) s->ns += now_ns() - t0;
        if (failing(st)) { c->status = IT_DIRECTIONAL; *bad_st = st; return -1; }
        c->directional++;
        return 0;
    }
    for (j = 0; j < s->n_in; ++j) c->base_in[j] = s->last_in[j];
    for (q = 0; q < s->n_feed; ++q) c->base_out[q] = v[s->out_off + s->feed[q]];
    for (j = 0; j < s->n_out; ++j) c->saved_out[j] = v[s->out_off + j];
    for (k = 0; k < ncols; ++k) {
        int32_t col = c->cols[k];
        double d;
        int st;
        for (j = 0; j < s->n_in; ++j) c->ends[j] = c->base_in[j];
        d = c->fd_rel * py_max(1.0, fabs(c->ends[col]));
        c->ends[col] += d;
        st = run_slave(s, c, v, t, h, c->ends);
        c->fd_steps++;
        if (ended(st) || c->status) { *bad_st = st; return -1; }
        for (q = 0; q < s->n_feed; ++q) c->L[q * ncols + k] = (v[s->out_off + s->feed[q]] - c->base_out[q]) / d;
    }
    for (j = 0; j < s->n_out; ++j) v[s->out_off + j] = c->saved_out[j];
    return 0;
}

/* Iterative._jacobian: dG/dz into c->J by the chain rule along the order; the failing slave or -1 */
static int32_t jacobian(rpr_slave *S, int32_t n, const int32_t *order, it_ctl *c, double *v, int64_t nv,
                        double t, double h, int32_t *bad_st) {
    int32_t m = c->m, k, j, b, q, a;
    int64_t x;
    c->jacobians++;
    for (x = 0; x < nv; ++x) c->dv_has[x] = 0;
    for (k = 0; k < n; ++k) {
        int32_t i = order[k], ncols = 0;
        rpr_slave *s = &S[i];
        if (!s->n_in || !s->n_feed) continue;
        for (j = 0; j < s->n_in * m; ++j) c->du[j] = 0.0;
        for (j = 0; j < s->n_in; ++j) {
            if (s->cut[j] >= 0) c->du[j * m + s->cut[j]] = 1.0;
            else if (c->dv_has[s->in_src[j]])
                for (b = 0; b < m; ++b) c->du[j * m + b] = c->dv[s->in_src[j] * m + b] * 1.0;
        }
        for (j = 0; j < s->n_in; ++j) {
            for (b = 0; b < m; ++b) if (c->du[j * m + b] != 0.0) break;
            if (b < m) c->cols[ncols++] = j;
        }
        if (!ncols) continue;
        if (local_jacobian(s, c, v, t, h, ncols, bad_st) < 0) return i;
        for (q = 0; q < s->n_feed; ++q) {   /* dy = L @ du[cols] */
            int64_t out = s->out_off + s->feed[q];
            for (b = 0; b < m; ++b) {
                double acc = c->L[q * ncols] * c->du[c->cols[0] * m + b];
                for (a = 1; a < ncols; ++a) acc += c->L[q * ncols + a] * c->du[c->cols[a] * m + b];
                c->w[b] = acc;
            }
            for (b = 0; b < m; ++b) c->dv[out * m + b] = c->w[b];
            c->dv_has[out] = 1;
        }
    }
    for (a = 0; a < m; ++a)
        for (b = 0; b < m; ++b)
            c->J[a * m + b] = (c->dv_has[c->cut_src[a]] ? c->dv[c->cut_src[a] * m + b] : 0.0) * c->cut_factor[a];
    return -1;
}

/* cosim.master.dense.solve of (I - J) dz = r into c->dz; 0 when singular */
static int solve_newton(it_ctl *c) {
    int32_t m = c->m, i, j, k, p;
    double *A = c->A, *x = c->dz;
    for (i = 0; i < m; ++i) for (j = 0; j < m; ++j) A[i * m + j] = (i == j ? 1.0 : 0.0) - c->J[i * m + j];
    for (i = 0; i < m; ++i) x[i] = c->r[i];
    for (k = 0; k < m; ++k) {
        double best = fabs(A[k * m + k]);
        p = k;
        for (i = k + 1; i < m; ++i) if (fabs(A[i * m + k]) > best) { p = i; best = fabs(A[i * m + k]); }
        if (!(best > 0.0)) return 0;
        if (p != k) {
            for (j = 0; j < m; ++j) { double tmp = A[k * m + j]; A[k * m + j] = A[p * m + j]; A[p * m + j] = tmp; }
            { double tmp = x[k]; x[k] = x[p]; x[p] = tmp; }
        }
        for (i = k + 1; i < m; ++i) {
            double f = A[i * m + k] / A[k * m + k];
            for (j = k + 1; j < m; ++j) A[i * m + j] -= f * A[k * m + j];
            x[i] -= f * x[k];
        }
    }
    for (i = m - 1; i >= 0; --i) {
        double s = x[i];
        for (j = i + 1; j < m; ++j) s -= A[i * m + j] * x[j];
        x[i] = s / A[i * m + i];
    }
    return 1;
}

static inline double nan_max(const double *a, int32_t m, int absolute) {   /* numpy's max: NaN wins */
    double best = 0.0;
    int32_t k;
    for (k = 0; k < m; ++k) {
        double x = absolute ? fabs(a[k]) : a[k];
        if (isnan(x)) return NAN;
        if (k == 0 || x > best) best = x;
    }
    return best;
}

/* Iterative._solve (step): IT_OK, IT_FAILED/IT_STOPPED-to-be (a slave: *bad), IT_DIVERGED,
   IT_NOT_CONVERGED, or a state error (c->status) */
static int solve_step(rpr_slave *S, int32_t n, const int32_t *order, it_ctl *c, double *v, int64_t nv, double t,
                      double h, int32_t *passes, int32_t *bad, int32_t *bad_st) {
    int32_t m = c->m, i, a, b, it, fresh_j = 0, has_old = 0, has_first = 0;
    double r_first = 0.0, err_old = 0.0;
    for (i = 0; i < n; ++i) S[i].has_last = 0;
    for (i = 0; i < n; ++i) {
        if (!S[i].n_in) continue;
        { int st = save_state(&S[i]); if (failing(st)) { *bad = i; *bad_st = st; return IT_SAVE; } }
    }
    for (a = 0; a < m; ++a) c->zi[a] = c->z[a];
    if (c->linear && c->has_z_prev) for (a = 0; a < m; ++a) c->zi[a] = 2.0 * c->z[a] - c->z_prev[a];
    for (it = 1; it <= c->max_iter; ++it) {
        double err, size;
        *bad = pass(S, n, order, 0, c, v, t, h, c->zi, bad_st);
        if (*bad >= 0) { *passes = it; return c->status ? c->status : IT_FAILED; }
        for (a = 0; a < m; ++a) {
            double z = c->zi[a], g = v[c->cut_src[a]] * c->cut_factor[a] + c->cut_offset[a];
            c->g[a] = g;
            c->r[a] = g - z;
            c->e[a] = fabs(c->r[a]) / (c->atol + c->rtol * np_max(fabs(z), fabs(g)));
        }
        err = m ? nan_max(c->e, m, 0) : 0.0;
        size = m ? nan_max(c->r, m, 1) : 0.0;
        if (!isfinite(err) || (has_first && size > c->growth * r_first)) {
            *passes = it; c->fail_it = it; c->fail_err = err;
            return IT_DIVERGED;
        }
        if (err <= 1.0) {
            *passes = it;
            for (a = 0; a < m; ++a) { c->z_prev[a] = c->z[a]; c->z[a] = c->zi[a]; }
            c->has_z_prev = 1;
            return IT_OK;
        }
        if (it == c->max_iter) { *passes = it; c->fail_it = it; c->fail_err = err; return IT_NOT_CONVERGED; }
        if (!has_first) { r_first = size; has_first = 1; }
        if (c->newton) {
            if (!c->has_J || (has_old && err > 0.5 * err_old && !fresh_j)) {
                *bad = jacobian(S, n, order, c, v, nv, t, h, bad_st);
                if (*bad >= 0) { *passes = -1; return c->status ? c->status : IT_FAILED; }
                c->has_J = 1;
                fresh_j = 1;
            } else if (has_old) {   /* Broyden */
                double den;
                for (a = 0; a < m; ++a) { c->dz[a] = c->zi[a] - c->z_old[a]; c->w[a] = c->r[a] - c->r_old[a]; }
                den = dot_strided(c->dz, 1, c->dz, 1, m);
                if (den > 0) {
                    for (a = 0; a < m; ++a) {   /* jf = J - I; w = dr - jf @ dz */
                        double acc = (c->J[a * m] - (a == 0 ? 1.0 : 0.0)) * c->dz[0];
                        for (b = 1; b < m; ++b) acc += (c->J[a * m + b] - (a == b ? 1.0 : 0.0)) * c->dz[b];
                        c->A[a] = c->w[a] - acc;
                    }
                    for (a = 0; a < m; ++a)
                        for (b = 0; b < m; ++b) c->J[a * m + b] = c->J[a * m + b] + c->A[a] * c->dz[b] / den;
                    c->broyden++;
                }
            }
            if (!solve_newton(c)) for (a = 0; a < m; ++a) c->dz[a] = c->r[a];
        } else {
            for (a = 0; a < m; ++a) c->dz[a] = c->omega * c->r[a];
        }
        for (a = 0; a < m; ++a) { c->z_old[a] = c->zi[a]; c->r_old[a] = c->r[a]; }
        err_old = err;
        has_old = 1;
        for (a = 0; a < m; ++a) c->zi[a] = c->zi[a] + c->dz[a];
    }
    return IT_NOT_CONVERGED;  /* not reached: max_iter >= 1 */
}

/* Up to nsteps macro steps from step index k0 (as rpr_run: rows every rec_every-th step; returns
   the steps completed; c->status says why it ended early) */
int64_t rpr_iter_run(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, it_ctl *c, int64_t k0,
                     int64_t nsteps, int64_t step_ns, const int64_t *rec_idx, int32_t n_rec, int64_t rec_every,
                     double *rec, int64_t *n_rows, int64_t budget_ns) {
    int64_t k, done = 0, rows = 0, t_start = (c->timing || budget_ns > 0) ? now_ns() : 0, slave_ns0 = slaves_ns(S, n);
    int32_t i, j, bad, bad_st, pos;
    double h = (double)step_ns / 1e9;
    c->status = 0;
    c->bad_slave = -1;
    for (k = k0; k < k0 + nsteps; ++k) {
        double t = (double)(k * step_ns) / 1e9;
        int res = solve_step(S, n, order, c, v, nv, t, h, &c->passes[done], &bad, &bad_st);
        if (res == IT_FAILED && bad_st == ST_STOP) {
            /* Algorithm.complete_after_stop: the stopping slave's outputs, the rest of the pass */
            int st = get_outputs(&S[bad], v);
            c->bad_slave = bad; c->bad_status = bad_st;
            if (failing(st)) { c->status = IT_FAILED; c->bad_status = st; break; }
            for (pos = 0; order[pos] != bad; ++pos) {}
            i = pass(S, n, order, pos + 1, c, v, t, h, c->zi, &bad_st);
            if (i >= 0 && bad_st != ST_STOP) { c->status = c->status ? c->status : IT_FAILED; c->bad_slave = i;
                                               c->bad_status = bad_st; break; }
            c->status = IT_STOPPED;
            ++done;
            break;
        }
        if (res != IT_OK) { c->status = res; c->bad_slave = bad; c->bad_status = bad_st; break; }
        for (i = 0; i < n; ++i)   /* Iterative._accept */
            if (S[i].has_last && S[i].n_in) for (j = 0; j < S[i].n_in; ++j) S[i].start_in[j] = S[i].last_in[j];
        ++done;
        if ((k + 1) % rec_every == 0) record_row(rec + rows++ * (n_rec + 1), (k + 1) * step_ns, v, rec_idx, n_rec);
        if (budget_ns > 0 && (done & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
    *n_rows = rows;
    if (c->timing) c->master_ns += (now_ns() - t_start) - (slaves_ns(S, n) - slave_ns0);
    return done;
}
"""

#: Longest wall time of one call [ns]: it returns to Python (signals, progress) at least this often.
CALL_BUDGET_NS = 250_000_000


@lru_cache(maxsize=1)
def library() -> ctypes.CDLL:
    """Compile (once, cached on disk: :func:`cosim.master.native.compile_loop`) and load the engine."""
    return compile_loop(SOURCE, "rpr_iter", {
        "rpr_iter_run": [POINTER(CSlave), ctypes.c_int32, c_void_p, c_void_p, c_int64, POINTER(CControl), c_int64,
                         c_int64, c_int64, c_void_p, ctypes.c_int32, c_int64, c_void_p, POINTER(c_int64), c_int64]})


class CompiledIterative:
    """Runs :class:`cosim.master.algorithms.iterative.Iterative`'s macro steps in C, with the shape
    of :class:`cosim.master.engine._Compiled` (``run(nsteps, rec_every, rec) -> rows``), updating
    the algorithm's step count, status, counters and statistics as its own loop would."""

    def __init__(self, alg):
        self.lib = library()
        self.alg = alg
        sysm = alg.system
        m, nv = len(alg.cuts), len(sysm.v)
        self.arr = arr = SlaveArray(sysm)
        max_in = max([len(b) for b in sysm.in_buf] + [1])
        max_out = max([len(b) for b in sysm.out_buf] + [1])
        max_feed = max([len(f) for f in alg.feeding] + [1])
        for i, s in enumerate(sysm.slaves):
            c = arr[i]
            c.state = s.state_slot()  # the slave's own FMU state: freed with the instance
            c.get_state, c.set_state = arr.entries[i].get_state, arr.entries[i].set_state
            if alg.opt["jacobian"] == "auto":
                c.dir_der = arr.entries[i].directional_derivative
            n_in = c.n_in
            if n_in:
                cut = np.full(n_in, -1, dtype=np.int64)
                cut[alg.cut_mask[i]] = alg.cut_index[i]
                c.cut = arr.buffer(cut, np.int64)
                c.start_in = arr.buffer(alg.start_in[i].astype(np.float64).copy())
                c.last_in = arr.buffer(np.zeros(n_in))
            if alg.interpolating[i]:
                c.interp, c.set_der = 1, arr.entries[i].set_input_derivatives
                c.orders = arr.buffer(np.ones(n_in, dtype=np.int32), np.int32)
                c.slope = arr.buffer(alg.slopes[i])
            out_pos = {int(k) - sysm.out_off[i] for _, k in alg.feeding[i]}
            feed = np.array(sorted(out_pos), dtype=np.int32)
            c.n_feed = len(feed)
            c.feed = arr.buffer(feed, np.int32)
        self.ctl = ctl = CControl()
        opt = alg.opt
        ctl.m, ctl.max_iter, ctl.newton = m, int(opt["max_iter"]), int(opt["method"] == "newton")
        ctl.jac_auto, ctl.linear = int(opt["jacobian"] == "auto"), int(alg.inputs == "linear")
        ctl.timing = int(alg.timing)
        ctl.omega, ctl.rtol, ctl.atol = opt["omega"], opt["rtol"], opt["atol"]
        from .algorithms.iterative import FD_REL, GROWTH_LIMIT

        ctl.growth, ctl.fd_rel = GROWTH_LIMIT, FD_REL
        for name in ("rollbacks", "jacobians", "directional", "broyden", "fd_steps"):  # the start's, counted on
            setattr(ctl, name, getattr(alg, name))
        buf = arr.buffer
        self.z = np.array(alg.z, dtype=np.float64)
        self.z_prev = np.zeros(m) if alg.z_prev is None else np.array(alg.z_prev, dtype=np.float64)
        ctl.has_z_prev = int(alg.z_prev is not None)
        if alg.J is not None:
            self.J = np.ascontiguousarray(alg.J, dtype=np.float64)
            ctl.has_J = 1
        else:
            self.J = np.zeros((m, m))
        self.e = np.zeros(m)
        self.zi = np.zeros(m)
        ctl.z, ctl.z_prev, ctl.J, ctl.e, ctl.zi = buf(self.z), buf(self.z_prev), buf(self.J), buf(self.e), buf(self.zi)
        for name in ("g", "r", "z_old", "r_old", "dz", "w"):
            setattr(ctl, name, buf(np.zeros(max(m, 1))))
        ctl.A = buf(np.zeros(max(m * m, m, 1)))
        ctl.dv, ctl.dv_has = buf(np.zeros(nv * max(m, 1))), buf(np.zeros(nv, dtype=np.int8), np.int8)
        ctl.du, ctl.L = buf(np.zeros(max_in * max(m, 1))), buf(np.zeros(max_feed * max_in))
        ctl.cols = buf(np.zeros(max_in, dtype=np.int32), np.int32)
        for name, size in (("ends", max_in), ("base_in", max_in), ("base_out", max_feed), ("saved_out", max_out),
                           ("seed", max_in), ("sens", max_feed)):
            setattr(ctl, name, buf(np.zeros(size)))
        ctl.known, ctl.unknown = buf(np.zeros(max_in, dtype=np.uint32), np.uint32), buf(
            np.zeros(max_feed, dtype=np.uint32), np.uint32)
        ctl.cut_src, ctl.cut_factor = buf(alg.cut_src, np.int64), buf(alg.cut_factor.astype(np.float64))
        ctl.cut_offset = buf(alg.cut_offset.astype(np.float64))
        self.passes = np.zeros(0, dtype=np.int32)
        self.order = np.array(alg.order, dtype=np.int32)
        self.rec_idx = sysm.record_idx
        self.n_rows = c_int64()
        self.budget_ns = CALL_BUDGET_NS

    def run(self, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
        alg, sysm, ctl = self.alg, self.alg.system, self.ctl
        if len(self.passes) < nsteps:
            self.passes = np.zeros(nsteps, dtype=np.int32)
            ctl.passes = self.passes.ctypes.data
        ctl.master_ns = 0
        t_fail = alg.t
        done = int(self.lib.rpr_iter_run(
            self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, len(sysm.v),
            ctypes.byref(ctl), alg.k, nsteps, alg.step_ns,
            self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx), rec_every, rec.ctypes.data,
            ctypes.byref(self.n_rows), self.budget_ns))
        code = int(ctl.status)
        counted = done if code in (0, 2) else done + 1  # the step that ended the run counts its passes too
        alg.passes += [int(p) for p in self.passes[:counted] if p >= 0]
        for i, c in enumerate(self.arr.arr):
            alg.calls[i], alg.slave_ns[i] = c.calls, c.ns
        for name in ("rollbacks", "jacobians", "directional", "broyden", "fd_steps"):
            setattr(alg, name, int(getattr(ctl, name)))
        alg.master_ns += ctl.master_ns
        rows = int(self.n_rows.value)
        if code == 2:
            alg.k += done - 1
            alg.stopped_by(ctl.bad_slave, alg.t)
            rec[rows, 0] = alg.t
            np.take(sysm.v, sysm.record_idx, out=rec[rows, 1:])
            return rows + 1
        alg.k += done
        t_fail = alg.t
        bad, st = int(ctl.bad_slave), int(ctl.bad_status)
        if code == 1:
            alg._fail(bad, st, t_fail)
        elif code in (3, 4):
            what = ("the coupling iteration diverged" if code == 3 else
                    f"the coupling iteration did not converge within max_iter = {int(ctl.max_iter)} passes")
            alg.passes.pop()  # _unstable records the step's passes itself
            alg._unstable(int(ctl.fail_it), True, t_fail, self.e.copy(), what, float(ctl.fail_err))
        elif code:
            from ..slaves.slave import Status

            s = sysm.slaves[bad]
            what = {5: "getting the FMU state", 6: "setting the FMU state", 7: "get directional derivative"}[code]
            name = Status(st).name if st in Status._value2member_map_ else str(st)
            raise UserError(f"{s.name}: {what} failed ({name})" + (f": {s.last_message}" if s.last_message else ""))
        return rows


def available() -> bool:
    """True when the engine's library can be built and loaded here."""
    return builds(library)


__all__ = ["CompiledIterative", "available", "library"]
