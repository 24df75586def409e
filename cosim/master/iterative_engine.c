/* The compiled engine of master.algorithm: iterative (cosim/master/iterative_engine.py), its one
   implementation.  Its Python twin, checked against bit for bit, is the test oracle
   tests/oracles/iterative.py: Iterative._solve, with FMI 3.0 event mode Iterative._event_step
   (tests/test_native.py, tests/test_general_kernel.py, tests/test_iterative_event_kernel.py). */
#include "native.h"

/* Iterative._run_slave: from its saved state at t (restored if it ran in this step) with inputs
   ending at ends (NULL: it has none); outputs read into v.  c->step 0 (the start time): only its
   inputs set and its outputs read.  c->status set for a state error. */
static int run_slave(rpr_slave *s, it_ctl *c, double *v, double t, double h, const double *ends) {
    int st = 0, j;
    double *buf = v + s->in_off;
    int64_t t0 = c->timing ? now_ns() : 0;
    if (c->step && s->has_last) {
        st = restore_state(s);
        if (failing(st)) { c->status = IT_RESTORE; return st; }
        c->rollbacks++;
    }
    if (ends) {
        if (c->step && s->interp) {
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
    if (!failing(st) && c->step) {
        st = do_step(s, t, h);
        if (!failing(st) && st != ST_STOP_REQUESTED && ends && s->interp) {
            for (j = 0; j < s->n_in; ++j) buf[j] = ends[j];  /* the outputs at t+h see the inputs at t+h */
            st = set_inputs(s, buf);
        }
    }
    if (!failing(st) && st != ST_STOP_REQUESTED) st = get_outputs(s, v);
    if (c->timing) s->ns += now_ns() - t0;
    if (ends) for (j = 0; j < s->n_in; ++j) s->last_in[j] = ends[j];
    s->has_last = 1;
    return st;
}

static inline int ended(int st) { return failing(st) || st == ST_STOP_REQUESTED; }

/* the non-cut inputs of ends through their connections' transformations (Iterative._ends: the
   sources' values as CoupledSystem.source_values gives them; a cut input's z is one already);
   a function of its own, so that pass() stays as it is without transformations */
static void transform_ends(const rpr_slave *s, double *ends) {
    int32_t j;
    for (j = 0; j < s->n_in; ++j) if (s->cut[j] < 0) ends[j] = through(s, j, ends[j]);
}

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
            if (c->step && !s->has_last) {
                st = run_slave(s, c, v, t, h, NULL);
                if (ended(st) || c->status) { *bad_st = st; return i; }
            }
            continue;
        }
        for (j = 0; j < s->n_in; ++j) c->ends[j] = s->cut[j] >= 0 ? z[s->cut[j]] : v[s->in_src[j]];
        if (s->in_factor) transform_ends(s, c->ends);
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

/* Iterative._local_jacobian (step): L (n_feed x ncols, row-major) of slave s from its directional
   derivatives (column by column), else (none: no dir_der, or a callback slave's answers
   CB_NO_DERIVATIVES) from finite differences of its step; -1 or the failing slave's status in
   *bad_st (a finite-difference step that failed) */
static int local_jacobian(rpr_slave *s, it_ctl *c, double *v, double t, double h, int32_t ncols, int32_t *bad_st) {
    int32_t q, k, j;
    if (c->jac_auto && s->dir_der) {
        int64_t t0 = c->timing ? now_ns() : 0;
        int st = 0;
        for (q = 0; q < s->n_feed; ++q) c->unknown[q] = s->out_vr[s->feed[q]];
        for (k = 0; k < ncols; ++k) c->known[k] = s->in_vr[c->cols[k]];
        for (k = 0; k < ncols && !failing(st) && st != CB_NO_DERIVATIVES; ++k) {
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
        if (st != CB_NO_DERIVATIVES) { c->directional++; return 0; }
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
        c->fd_steps += c->step;
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
            else if (c->dv_has[s->in_src[j]]) {   /* through the connection's factor */
                double f = s->in_factor ? s->in_factor[j] : 1.0;
                for (b = 0; b < m; ++b) c->du[j * m + b] = c->dv[s->in_src[j] * m + b] * f;
            }
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

/* Iterative._solve from t over h (c->step 0: the start point, nothing stepped): IT_OK, IT_FAILED (a
   slave's call: *bad, *bad_st, a stop request among them), IT_DIVERGED, IT_NOT_CONVERGED (c->fail_it,
   c->fail_err), or a state error (c->status).  The passes of a step that ended otherwise than
   unstable go to c->passes[c->n_passes++] (Iterative._record_passes; the unstable one's are
   recorded with its message, Iterative._unstable; a failing Jacobian's nowhere, as in Python). */
static int solve_step(rpr_slave *S, int32_t n, const int32_t *order, it_ctl *c, double *v, int64_t nv, double t,
                      double h, int32_t *bad, int32_t *bad_st) {
    int32_t m = c->m, i, a, b, it, fresh_j = 0, has_old = 0, has_first = 0;
    double r_first = 0.0, err_old = 0.0;
    for (i = 0; i < n; ++i) S[i].has_last = 0;
    for (i = 0; i < n && c->step; ++i) {
        if (!S[i].n_in) continue;
        { int st = save_state(&S[i]); if (failing(st)) { *bad = i; *bad_st = st; return IT_SAVE; } }
    }
    for (a = 0; a < m; ++a) c->zi[a] = c->z[a];
    if (c->step && c->linear && c->has_z_prev) for (a = 0; a < m; ++a) c->zi[a] = 2.0 * c->z[a] - c->z_prev[a];
    for (it = 1; it <= c->max_iter; ++it) {
        double err, size;
        *bad = pass(S, n, order, 0, c, v, t, h, c->zi, bad_st);
        if (*bad >= 0) { c->passes[c->n_passes++] = it; return c->status ? c->status : IT_FAILED; }
        for (a = 0; a < m; ++a) {
            double z = c->zi[a], g = v[c->cut_src[a]] * c->cut_factor[a] + c->cut_offset[a];
            c->g[a] = g;
            c->r[a] = g - z;
            c->e[a] = fabs(c->r[a]) / (c->atol + c->rtol * np_max(fabs(z), fabs(g)));
        }
        err = m ? nan_max(c->e, m, 0) : 0.0;
        size = m ? nan_max(c->r, m, 1) : 0.0;
        if (!isfinite(err) || (has_first && size > c->growth * r_first)) {
            c->fail_it = it; c->fail_err = err;
            return IT_DIVERGED;
        }
        if (err <= 1.0) {
            c->passes[c->n_passes++] = it;
            if (c->step) {
                for (a = 0; a < m; ++a) c->z_prev[a] = c->z[a];
                c->has_z_prev = 1;
            }
            for (a = 0; a < m; ++a) c->z[a] = c->zi[a];
            return IT_OK;
        }
        if (it == c->max_iter) { c->fail_it = it; c->fail_err = err; return IT_NOT_CONVERGED; }
        if (!has_first) { r_first = size; has_first = 1; }
        if (c->newton) {
            if (!c->has_J || (has_old && err > 0.5 * err_old && !fresh_j)) {
                *bad = jacobian(S, n, order, c, v, nv, t, h, bad_st);
                if (*bad >= 0) return c->status ? c->status : IT_FAILED;
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

/* Iterative._accept: the inputs the slaves ended the step (or the start) with are their inputs at
   the new point */
static void accept(rpr_slave *S, int32_t n) {
    int32_t i, j;
    for (i = 0; i < n; ++i)
        if (S[i].has_last && S[i].n_in) for (j = 0; j < S[i].n_in; ++j) S[i].start_in[j] = S[i].last_in[j];
}

/* The iteration's state at a step's start, kept for a retake to an event (keep 1) or put back (0):
   v, z, z_prev, J and every slave's inputs at t (Iterative._event_step's `kept`) */
static void keep_point(rpr_slave *S, int32_t n, it_ctl *c, double *v, int64_t nv, int keep) {
    int32_t m = c->m, i, j;
    int64_t x, off = 0;
#define KEEP(a, b) do { if (keep) (b) = (a); else (a) = (b); } while (0)
    for (x = 0; x < nv; ++x) KEEP(v[x], c->v_kept[x]);
    for (x = 0; x < m; ++x) { KEEP(c->z[x], c->z_kept[x]); KEEP(c->z_prev[x], c->z_prev_kept[x]); }
    for (x = 0; x < (int64_t)m * m; ++x) KEEP(c->J[x], c->J_kept[x]);
    KEEP(c->has_z_prev, c->has_z_prev_kept);
    KEEP(c->has_J, c->has_J_kept);
    for (i = 0; i < n; ++i)
        for (j = 0; j < S[i].n_in; ++j, ++off) KEEP(S[i].start_in[j], c->start_kept[off]);
#undef KEEP
}

/* One step with FMI 3.0 event-mode slaves (Iterative._event_step) from the current point (grid
   point k, or the event ev->t_event that cut step k; *t_out) to the next grid point: every slave's
   state saved, the coupling iterated over the step; where an event-mode slave returned early, at
   the earliest such time t_e, every slave restored, the iteration's state put back and the
   coupling iterated again over [t, t_e] (*h_out: the step iterated last; a stop request in the
   first iteration goes with the step when an event cuts it).  Returns solve_step's
   code; ev->status FX_RUNNING (the grid point), FX_GRID_EVENT (and slave ev->who asks for event
   handling there), FX_EVENT (cut at ev->t_e by ev->who; with a failing code, the retake failed)
   or FX_CHATTERING (more than ev->max_events events in the step, or no progress: t_e at the
   step's start). */
static int event_step(rpr_slave *S, int32_t n, const int32_t *order, it_ctl *c, fx_ctl *ev, double *v, int64_t nv,
                      int64_t k, int64_t start_ns, int64_t step_ns, double *t_out, double *h_out, int32_t *bad,
                      int32_t *bad_st) {
    double t_end = (double)(start_ns + (k + 1) * step_ns) / 1e9;
    double t = ev->has_t_event ? ev->t_event : (double)(start_ns + k * step_ns) / 1e9, tol, t_e = 0.0;
    int32_t i, who = -1;
    int res, st;
    *t_out = t;
    *h_out = t_end - t;
    ev->status = FX_RUNNING;
    keep_point(S, n, c, v, nv, 1);
    for (i = 0; i < n; ++i) {
        st = save_state(&S[i]);
        if (failing(st)) { *bad = i; *bad_st = st; return IT_SAVE; }
    }
    res = solve_step(S, n, order, c, v, nv, t, t_end - t, bad, bad_st);
    /* a stop request goes with a step an event cuts (the retake decides) */
    if (res != IT_OK && !(res == IT_FAILED && *bad_st == ST_STOP_REQUESTED)) return res;
    if (res == IT_OK) accept(S, n);
    tol = 1e-12 * (1.0 + fabs(t_end));
    for (i = 0; i < n; ++i) {  /* the earliest early return (the first slave of equal ones) of those stepped */
        double r;
        if (!S[i].event_mode || !S[i].has_last) continue;
        r = step_end(&S[i]);
        if (r < t_end - tol && (who < 0 || r < t_e)) { who = i; t_e = r; }
    }
    if (who < 0 && res != IT_OK) return res;
    if (who < 0) {  /* the grid point: an event-mode slave may ask for event handling there */
        ev->has_t_event = 0;
        ev->events_in_step = 0;
        ev->who = -1;
        for (i = 0; i < n && ev->who < 0; ++i) if (S[i].event_mode && event_asked(&S[i])) ev->who = i;
        ev->status = ev->who >= 0 ? FX_GRID_EVENT : FX_RUNNING;
        return IT_OK;
    }
    ev->who = who;
    ev->t_e = t_e;
    if (++ev->events_in_step > ev->max_events || t_e <= t) { ev->status = FX_CHATTERING; return IT_OK; }
    for (i = 0; i < n; ++i) {
        st = restore_state(&S[i]);
        if (failing(st)) { *bad = i; *bad_st = st; return IT_RESTORE; }
    }
    keep_point(S, n, c, v, nv, 0);
    *h_out = t_e - t;
    ev->status = FX_EVENT;  /* (a stop request in the retake: the run ends at the event) */
    res = solve_step(S, n, order, c, v, nv, t, t_e - t, bad, bad_st);
    if (res != IT_OK) return res;
    accept(S, n);
    ev->has_t_event = 1;
    ev->t_event = t_e;
    return IT_OK;
}

/* The start point (Iterative.start): the coupling iterated at t without stepping (h = 0); solve_step's
   code (a failing slave in c->bad_slave, c->bad_status) */
int32_t rpr_iter_start(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, it_ctl *c, double t) {
    int32_t bad = -1, bad_st = 0;
    int res;
    c->status = IT_OK;
    c->n_passes = 0;
    c->step = 0;
    res = solve_step(S, n, order, c, v, nv, t, 0.0, &bad, &bad_st);
    c->step = 1;
    if (res == IT_OK) accept(S, n);
    c->bad_slave = bad;
    c->bad_status = bad_st;
    return res;
}

/* Up to nsteps macro steps from step index k0 (as rpr_run: rows every rec_every-th step; returns
   the steps completed; c->status says why it ended early).  With event-mode slaves (ev: their
   state across calls) each step is event_step's, and a call also returns at an event (ev->status;
   the event iteration runs in Python). */
int64_t rpr_iter_run(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, it_ctl *c, int64_t k0,
                     int64_t nsteps, int64_t start_ns, int64_t step_ns, const int64_t *rec_idx, int32_t n_rec, int64_t rec_every,
                     double *rec, int64_t *n_rows, int64_t budget_ns, fx_ctl *ev) {
    int64_t k, done = 0, rows = 0, t_start = (c->timing || budget_ns > 0) ? now_ns() : 0, slave_ns0 = slaves_ns(S, n);
    int32_t i, bad, bad_st, pos;
    double h = (double)step_ns / 1e9;
    c->status = IT_OK;
    c->bad_slave = -1;
    c->n_passes = 0;
    c->step = 1;
    if (ev) ev->status = FX_RUNNING;
    for (k = k0; k < k0 + nsteps; ++k) {
        double t = (double)(start_ns + k * step_ns) / 1e9, h_s = h;
        int res;
        if (ev) res = event_step(S, n, order, c, ev, v, nv, k, start_ns, step_ns, &t, &h_s, &bad, &bad_st);
        else if ((res = solve_step(S, n, order, c, v, nv, t, h, &bad, &bad_st)) == IT_OK) accept(S, n);
        if (res == IT_FAILED && bad_st == ST_STOP_REQUESTED) {
            /* Algorithm.complete_after_stop: the stopping slave's outputs, the rest of the pass over the
               step being iterated (Iterative._finish_step); the step is counted by Iterative.stopped_by */
            int st = get_outputs(&S[bad], v);
            c->bad_slave = bad; c->bad_status = bad_st;
            if (failing(st)) { c->status = IT_FAILED; c->bad_status = st; break; }
            for (pos = 0; order[pos] != bad; ++pos) {}
            i = pass(S, n, order, pos + 1, c, v, t, h_s, c->zi, &bad_st);
            if (i >= 0 && bad_st != ST_STOP_REQUESTED) { c->status = c->status ? c->status : IT_FAILED; c->bad_slave = i;
                                               c->bad_status = bad_st; break; }
            c->status = IT_STOPPED;
            break;
        }
        if (res != IT_OK) { c->status = res; c->bad_slave = bad; c->bad_status = bad_st; break; }
        if (ev && (ev->status == FX_EVENT || ev->status == FX_CHATTERING)) break;  /* k stays: a cut step */
        ++done;
        if (ev && ev->status == FX_GRID_EVENT) break;  /* its row, the left limit, written by Python */
        if ((k + 1) % rec_every == 0) record_row(rec + rows++ * (n_rec + 1), start_ns + (k + 1) * step_ns, v, rec_idx, n_rec);
        if (budget_ns > 0 && (done & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
    *n_rows = rows;
    if (c->timing) c->master_ns += (now_ns() - t_start) - (slaves_ns(S, n) - slave_ns0);
    return done;
}
