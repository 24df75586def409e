/* The compiled engines of the variable-step masters adaptive and ecco (cosim/master/adaptive_engine.py). */
#include "native.h"

static int slave_step(rpr_slave *s, double *v, double t, double h) {
    int st = set_inputs(s, v + s->in_off);
    if (!failing(st) && s->interp && s->n_in) st = set_slopes(s);
    if (failing(st)) return st;
    st = do_step(s, t, h);
    if (failing(st) || st == ST_STOP_REQUESTED) return st;
    return get_outputs(s, v);
}

/* One Gauss-Seidel step of h from t with linear inputs (AdaptiveStepper._attempt's stepping):
   each input interpolated from a source that stepped before, extrapolated from the last two
   points otherwise (s->guess: the extrapolation to t+h, in the source's units), then through the
   connection's transformation; returns -1, or the failing slave with
   *bad_st its status. */
static int32_t gs_step(rpr_slave *S, int32_t n, const int32_t *order, double *v, double h_prev, int32_t timing,
                       double t, double h, int32_t *bad_st) {
    int32_t k, j;
    int64_t tprev = timing ? now_ns() : 0;  /* one clock read per slave, as the fixed-step loop */
    for (k = 0; k < n; ++k) {
        rpr_slave *s = &S[order[k]];
        double *in = v + s->in_off;
        int st;
        for (j = 0; j < s->n_in; ++j) {
            double now = v[s->in_src[j]];
            if (s->interp) {
                double ext = h_prev > 0 ? (s->cur[j] - s->prev[j]) / h_prev : 0.0;
                s->slope[j] = s->fresh[j] ? (now - s->cur[j]) / h : ext;
                in[j] = s->fresh[j] ? s->cur[j] : now;
                s->guess[j] = now + ext * h;
            } else {
                in[j] = now;
                s->guess[j] = now;
            }
            if (s->in_factor) {   /* the input (and its slope) through its connection's transformation */
                in[j] = through(s, j, in[j]);
                if (s->interp) s->slope[j] = s->slope[j] * s->in_factor[j];
            }
        }
        st = slave_step(s, v, t, h);
        if (timing) { int64_t t1 = now_ns(); s->ns += t1 - tprev; tprev = t1; }
        if (failing(st) || st == ST_STOP_REQUESTED) { *bad_st = st; return order[k]; }
    }
    *bad_st = 0;
    return -1;
}

/* AdaptiveStepper._attempt: the step and its scaled coupling error, or INFINITY with *bad set to
   the failing slave. */
static double attempt(rpr_slave *S, int32_t n, const int32_t *order, double *v, const double *lo,
                      const double *hi, ad_ctl *c, double t, double h, int32_t *bad, int32_t *bad_st) {
    int32_t k, j;
    double err = 0.0, weight = h / c->h_ref;
    *bad = gs_step(S, n, order, v, c->h_prev, c->timing, t, h, bad_st);
    if (*bad >= 0) return INFINITY;
    for (k = 0; k < n; ++k) {
        rpr_slave *s = &S[order[k]];
        for (j = 0; j < s->n_in; ++j) {
            int64_t src = s->in_src[j];
            double actual, span, tol, e;
            if (s->fresh[j]) continue;
            actual = v[src];
            span = np_max(hi[src], actual) - np_min(lo[src], actual);
            tol = c->atol + c->rtol * span;
            e = fabs(actual - s->guess[j]) * weight / tol;
            if (isnan(e)) e = INFINITY;
            err = py_max(err, e);
        }
    }
    return err;
}

/* the one step-size rule of adaptive and ecco (its Python twin: _propose in tests/oracles/variable.py): the next step after an
   accepted step h (h_ns [ns]; h_tried the step it was to be) is h times the controller's factor
   fac, bounded by fac_min/fac_max and h_min/h_max; a step cut short to land on the stop time does
   not shrink the proposal */
static inline double propose(double h, int64_t h_ns, double h_tried, double fac, double fac_min, double fac_max,
                             double h_min, double h_max) {
    fac = py_min(fac_max, py_max(fac_min, fac));
    if (h_ns < round_ns(h_tried * 1e9)) fac = py_max(fac, 1.0);
    return py_min(h_max, py_max(h_min, h * fac));
}

/* plan_ns (the oracle's _plan_ns): the step [ns] from t_ns for the proposal h: the rest of the way to
   the next output point (on the grid from start_ns; the stop time at most) when the proposal
   reaches it, else that way split into the fewest equal steps no longer than the proposal (ceiling
   divisions, the last step landing); without a grid, the proposal clipped to the stop time */
static int64_t plan_ns(double h, int64_t t_ns, int64_t start_ns, int64_t grid_ns, int64_t stop_ns) {
    int64_t want = round_ns(h * 1e9), target = stop_ns, left, n;
    if (grid_ns > 0) {
        int64_t k = (t_ns - start_ns) / grid_ns + 1;   /* t_ns >= start_ns: the floor division */
        int64_t at = start_ns + k * grid_ns;
        target = at < stop_ns ? at : stop_ns;
    }
    left = target - t_ns;
    if (want >= left) return left > 1 ? left : 1;
    if (grid_ns <= 0) return want > 1 ? want : 1;
    n = (left + (want > 1 ? want : 1) - 1) / (want > 1 ? want : 1);
    n = (left + n - 1) / n;
    return n > 1 ? n : 1;
}

/* is t_ns an output point (AdaptiveStepper._on_output)? */
static inline int on_output(int64_t t_ns, int64_t start_ns, int64_t grid_ns, int64_t stop_ns) {
    return grid_ns <= 0 || t_ns >= stop_ns || (t_ns - start_ns) % grid_ns == 0;
}

/* the sources' values at the new point become the current ones (AdaptiveStepper._commit) */
static void shift_history(rpr_slave *S, int32_t n, const double *v) {
    int32_t i, j;
    for (i = 0; i < n; ++i) {
        rpr_slave *s = &S[i];
        for (j = 0; j < s->n_in; ++j) {
            s->prev[j] = s->cur[j];
            s->cur[j] = v[s->in_src[j]];
        }
    }
}

/* ---- FMI 3.0 event mode (AdaptiveStepper's events, docs/explanation/events.md) ---------------------- */

/* After a step to t1_ns: the earliest time [ns] an event-mode slave returned early inside it
   (the oracle's _early_return), or t1_ns when every one reached its end */
static int64_t early_return(const rpr_slave *S, int32_t n, int64_t t1_ns) {
    int64_t early = t1_ns;
    int32_t i;
    for (i = 0; i < n; ++i) {
        if (!S[i].event_mode) continue;
        {
            int64_t e = round_ns(step_end(&S[i]) * 1e9);
            if (e < early) early = e;
        }
    }
    return early;
}

/* every slave back to its saved state and v to v_saved (a step retaken); the failing slave or -1 */
static int32_t roll_back(rpr_slave *S, int32_t n, double *v, const double *v_saved, int64_t nv, int32_t *bad_st) {
    int32_t i;
    for (i = 0; i < n; ++i) {
        int st = restore_state(&S[i]);
        if (failing(st)) { *bad_st = st; return i; }
    }
    memcpy(v, v_saved, (size_t)nv * sizeof(double));
    return -1;
}

/* every slave's state saved and v into v_saved; the failing slave or -1 */
static int32_t save_all(rpr_slave *S, int32_t n, const double *v, double *v_saved, int64_t nv, int32_t *bad_st) {
    int32_t i;
    memcpy(v_saved, v, (size_t)nv * sizeof(double));
    for (i = 0; i < n; ++i) {
        int st = save_state(&S[i]);
        if (failing(st)) { *bad_st = st; return i; }
    }
    return -1;
}

/* After an accepted step (AdaptiveStepper._note_event): 1 when an event-mode slave asks for event
   handling at its end (Python counts it and runs the event iteration), else 0 with the count of
   events in a row reset */
static int event_at_end(const rpr_slave *S, int32_t n, int32_t *events_here) {
    int32_t i;
    for (i = 0; i < n; ++i)
        if (S[i].event_mode && event_asked(&S[i])) return 1;
    *events_here = 0;
    return 0;
}

static int64_t rpr_adapt_loop(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv,
                              double *v_saved, double *lo, double *hi, ad_ctl *c, const int64_t *rec_idx,
                              int32_t n_rec, double *rec, int64_t *h_rec, int64_t max_steps, int64_t budget_ns,
                              int64_t t_start) {
    int64_t rows = 0, steps = 0, h_ns = 0;
    int32_t j, bad, bad_st;
    double h = 0.0, err = 0.0, p;
    c->status = AD_RUNNING;
    while (c->t_ns < c->stop_ns && steps < max_steps) {
        double t = (double)c->t_ns / 1e9;
        int64_t cut = -1;   /* an event's time [ns] the step is retaken to (-1: none) */
        int at_event;
        bad = save_all(S, n, v, v_saved, nv, &bad_st);
        if (bad >= 0) { c->status = AD_GET_STATE; c->bad_slave = bad; c->bad_status = bad_st; return rows; }
        for (;;) {
            double shrink;
            h_ns = cut < 0 ? plan_ns(c->h, c->t_ns, c->start_ns, c->grid_ns, c->stop_ns) : cut - c->t_ns;
            h = (double)h_ns / 1e9;
            err = attempt(S, n, order, v, lo, hi, c, t, h, &bad, &bad_st);
            p = (c->any_interp && c->h_prev > 0) ? c->p_lin : c->p_hold;
            if (bad >= 0 && bad_st == ST_STOP_REQUESTED) {
                c->status = AD_STOP_REQUESTED; c->bad_slave = bad; c->bad_status = bad_st;
                return rows;
            }
            if (bad < 0 && c->n_event) {
                int64_t early = early_return(S, n, c->t_ns + h_ns);
                if (early < c->t_ns + h_ns) {  /* an event inside the step: it ends there for every slave */
                    if (early <= c->t_ns) { c->status = AD_NO_PROGRESS; c->t_e_ns = early; return rows; }
                    cut = early;
                    c->event_cuts++;
                    bad = roll_back(S, n, v, v_saved, nv, &bad_st);
                    if (bad >= 0) { c->status = AD_SET_STATE; c->bad_slave = bad; c->bad_status = bad_st; return rows; }
                    continue;
                }
            }
            if (bad < 0 && (err <= 1.0 || c->h_prev == 0)) break;
            cut = -1;   /* retried smaller: the event, if still inside, is found again */
            c->rejected++;
            if (bad >= 0) c->discards++;
            {
                int32_t st, who = roll_back(S, n, v, v_saved, nv, &st);
                if (who >= 0) { c->status = AD_SET_STATE; c->bad_slave = who; c->bad_status = st; return rows; }
            }
            c->rollbacks++;
            shrink = !isfinite(err) ? c->fac_min : py_max(c->fac_min, c->safety * pow(err, -1.0 / p));
            if (h <= c->h_min * (1 + 1e-12)) {
                c->status = AD_STEP_FLOOR; c->bad_slave = bad; c->bad_status = bad_st; c->last_err = err;
                return rows;
            }
            c->h = py_max(c->h_min, h * py_min(shrink, 0.9));
        }
        /* accepted */
        c->accepted++;
        c->h_min_taken = py_min(c->h_min_taken, h);
        c->h_max_taken = py_max(c->h_max_taken, h);
        shift_history(S, n, v);
        for (j = 0; j < nv; ++j) {
            hi[j] = np_max(hi[j], v[j]);
            lo[j] = np_min(lo[j], v[j]);
        }
        c->t_ns += h_ns;
        c->h_prev = h;
        at_event = c->n_event && event_at_end(S, n, &c->events_here);
        if (cut < 0) {   /* a step cut short at an event says nothing new of the error: keep the proposal */
            double e = py_max(err, 1e-10), fac;
            fac = c->safety * pow(e, -c->k_i / p) * pow(c->err_prev, c->k_p / p);
            c->err_prev = e;
            c->h = propose(h, h_ns, c->h, fac, c->fac_min, c->fac_max, c->h_min, c->h_max);
        }
        if (on_output(c->t_ns, c->start_ns, c->grid_ns, c->stop_ns))
            record_row(rec + (rows++) * (n_rec + 1), c->t_ns, v, rec_idx, n_rec);
        h_rec[steps++] = h_ns;
        if (at_event) { c->status = AD_EVENT; return rows; }
        if (budget_ns > 0 && (steps & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
    return rows;
}

/* Up to max_steps accepted steps, until the stop time, the wall-time budget, or an event for
   Python (c->status != 0).  Each accepted step appends its step [ns] to h_rec, and one that ends
   on an output point (t, v[rec_idx]...) to rec.  Returns the number of rows; with timing, adds the loop's own time
   outside the slaves' calls to c->master_ns. */
int64_t rpr_adapt_run(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, double *v_saved,
                      double *lo, double *hi, ad_ctl *c, const int64_t *rec_idx, int32_t n_rec, double *rec,
                      int64_t *h_rec, int64_t max_steps, int64_t budget_ns) {
    int64_t t_start = (budget_ns > 0 || c->timing) ? now_ns() : 0, slave_ns0 = slaves_ns(S, n), rows;
    rows = rpr_adapt_loop(S, n, order, v, nv, v_saved, lo, hi, c, rec_idx, n_rec, rec, h_rec, max_steps, budget_ns,
                          t_start);
    if (c->timing) c->master_ns += (now_ns() - t_start) - (slaves_ns(S, n) - slave_ns0);
    return rows;
}

/* ecco's steps (the oracle's EccoStepper.step): steps (never retried) sized from the bonds' energy residual, up to max_steps
   steps, the stop time, the budget or an event for Python (c->status != 0); rows and h_rec as
   rpr_adapt_run's. */
static int64_t rpr_ecco_loop(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, double *v_saved,
                             ec_ctl *c,
                             const int64_t *rec_idx, int32_t n_rec, double *rec, int64_t *h_rec, int64_t max_steps,
                             int64_t budget_ns, int64_t t_start) {
    int64_t rows = 0, steps = 0;
    int32_t b, k, bad, bad_st;
    c->status = EC_RUNNING;
    while (c->t_ns < c->stop_ns && steps < max_steps) {
        double t = (double)c->t_ns / 1e9, h, hh, err, fac;
        int64_t h_ns, cut = -1;   /* cut: an event's time [ns] the step was retaken to (-1: none) */
        int at_event;
        if (c->ending) { c->status = EC_FLOOR_PATIENCE; c->bad_slave = c->end_bond; return rows; }
        h_ns = plan_ns(c->h, c->t_ns, c->start_ns, c->grid_ns, c->stop_ns);
        for (k = 0; k < 2 * c->n_bonds; ++k) c->y0[k] = v[c->out_idx[k]];
        if (c->n_event) {   /* (the run uses event mode only where every slave can roll back) */
            bad = save_all(S, n, v, v_saved, nv, &bad_st);
            if (bad >= 0) { c->status = EC_GET_STATE; c->bad_slave = bad; c->bad_status = bad_st; return rows; }
        }
        for (;;) {
            int64_t early;
            h = (double)h_ns / 1e9;
            bad = gs_step(S, n, order, v, c->h_prev, c->timing, t, h, &bad_st);
            if (bad >= 0) {
                c->status = (bad_st == ST_STOP_REQUESTED || (bad_st == ST_DISCARD && stop_asked(&S[bad]))) ? EC_STOP_REQUESTED : EC_SLAVE_FAILED;
                c->bad_slave = bad; c->bad_status = bad_st;
                return rows;
            }
            early = c->n_event ? early_return(S, n, c->t_ns + h_ns) : c->t_ns + h_ns;
            if (early >= c->t_ns + h_ns) break;
            if (early <= c->t_ns) { c->status = EC_NO_PROGRESS; c->t_e_ns = early; return rows; }
            cut = early;   /* an event inside the step: retaken to end there */
            h_ns = early - c->t_ns;
            c->event_cuts++;
            bad = roll_back(S, n, v, v_saved, nv, &bad_st);
            if (bad >= 0) { c->status = EC_SET_STATE; c->bad_slave = bad; c->bad_status = bad_st; return rows; }
        }
        hh = 0.5 * h;
        for (b = 0; b < c->n_bonds; ++b) {   /* bond_energy */
            double u0a = v[c->in_idx[2 * b]], u0b = v[c->in_idx[2 * b + 1]];
            rpr_slave *sa = &S[c->side[2 * b]], *sb = &S[c->side[2 * b + 1]];
            double ka = sa->interp ? sa->slope[c->slot[2 * b]] : 0.0;
            double kb = sb->interp ? sb->slope[c->slot[2 * b + 1]] : 0.0;
            double u1a = u0a + ka * h, u1b = u0b + kb * h;
            double p0a = c->y0[2 * b] * u0a, p0b = c->y0[2 * b + 1] * u0b;
            double p1a = v[c->out_idx[2 * b]] * u1a, p1b = v[c->out_idx[2 * b + 1]] * u1b;
            double residual = hh * ((p0a - p0b) + (p1a - p1b));
            double carried = hh * np_max(fabs(p0a) + fabs(p1a), fabs(p0b) + fabs(p1b));
            c->scaled[b] = fabs(residual) / (c->atol + c->rtol * carried);
            c->y0[2 * b] = residual;        /* kept for the statistics below */
            c->y0[2 * b + 1] = carried;
        }
        for (b = 0; b < c->n_bonds; ++b) {
            if (!isfinite(c->scaled[b])) { c->status = EC_NOT_FINITE; c->bad_slave = b; return rows; }
        }
        for (b = 0; b < c->n_bonds; ++b) {   /* BondRecord.add */
            double r = c->y0[2 * b], x = c->scaled[b];
            c->max_scaled[b] = py_max(c->max_scaled[b], x);
            c->max_residual[b] = py_max(c->max_residual[b], fabs(r));
            c->residual_sum[b] += r;
            c->abs_residual_sum[b] += fabs(r);
            c->energy[b] += c->y0[2 * b + 1];
            c->over[b] += x > 1.0;
        }
        /* AdaptiveStepper._commit */
        c->accepted++;
        c->h_min_taken = py_min(c->h_min_taken, h);
        c->h_max_taken = py_max(c->h_max_taken, h);
        shift_history(S, n, v);
        c->t_ns += h_ns;
        c->h_prev = h;
        at_event = c->n_event && event_at_end(S, n, &c->events_here);
        if (cut >= 0) {   /* a step cut short at an event: the controller keeps its proposal */
            if (on_output(c->t_ns, c->start_ns, c->grid_ns, c->stop_ns))
                record_row(rec + (rows++) * (n_rec + 1), c->t_ns, v, rec_idx, n_rec);
            h_rec[steps++] = h_ns;
            if (at_event) { c->status = EC_EVENT; return rows; }
            continue;
        }
        err = c->scaled[0];
        for (b = 1; b < c->n_bonds; ++b) err = c->scaled[b] > err ? c->scaled[b] : err;
        err = py_max(err, 1e-10);
        c->at_floor = (err > 1.0 && h <= c->h_min * (1 + 1e-12)) ? c->at_floor + 1 : 0;
        if (c->floor_patience > 0 && c->at_floor >= c->floor_patience) {
            int32_t kmax = 0;
            for (b = 1; b < c->n_bonds; ++b) if (c->scaled[b] > c->scaled[kmax]) kmax = b;
            c->ending = 1; c->end_bond = kmax; c->end_scaled = c->scaled[kmax];
        }
        fac = pow(c->safety / err, c->k_i) * pow(c->err_prev / err, c->k_p);
        c->err_prev = err;
        c->h = propose(h, h_ns, c->h, fac, c->fac_min, c->fac_max, c->h_min, c->h_max);
        if (on_output(c->t_ns, c->start_ns, c->grid_ns, c->stop_ns))
            record_row(rec + (rows++) * (n_rec + 1), c->t_ns, v, rec_idx, n_rec);
        h_rec[steps++] = h_ns;
        if (at_event) { c->status = EC_EVENT; return rows; }
        if (budget_ns > 0 && (steps & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
    return rows;
}

int64_t rpr_ecco_run(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, double *v_saved, ec_ctl *c,
                     const int64_t *rec_idx, int32_t n_rec, double *rec, int64_t *h_rec, int64_t max_steps,
                     int64_t budget_ns) {
    int64_t t_start = (budget_ns > 0 || c->timing) ? now_ns() : 0, slave_ns0 = slaves_ns(S, n), rows;
    rows = rpr_ecco_loop(S, n, order, v, nv, v_saved, c, rec_idx, n_rec, rec, h_rec, max_steps, budget_ns, t_start);
    if (c->timing) c->master_ns += (now_ns() - t_start) - (slaves_ns(S, n) - slave_ns0);
    return rows;
}
