/* The compiled inner loop of the fixed-step master, Jacobi, Gauss-Seidel and Jacobi with extrapolated
   inputs (cosim/master/fastloop.py): their one implementation.  Its Python twin, the test oracle it is
   checked against bit for bit, is tests/oracles/fixed.py: Jacobi._step_impl, GaussSeidel._step_impl and,
   with FMI 3.0 event mode, EventSteps._event_step (tests/test_general_kernel.py, tests/test_event_kernel.py). */
#include "native.h"

/* the slave's inputs from their sources in v, each through its connection's linear
   transformation where it has one (CoupledSystem.gather: v[src] * factor + offset) */
static inline void gather(const rpr_slave *s, const double *v, double *in) {
    int j;
    if (s->in_factor) for (j = 0; j < s->n_in; ++j) in[j] = v[s->in_src[j]] * s->in_factor[j] + s->in_offset[j];
    else for (j = 0; j < s->n_in; ++j) in[j] = v[s->in_src[j]];
}

/* jacobi_extrapolated: the gathered inputs (u_k) replaced by their extrapolated step mean,
   sum of w[m] u_k-m over the past values there are (weights: row n_past of W, 3 x 3), and
   remembered (cosim.master.algorithms.jacobi_extrapolated) */
static inline void extrapolate(rpr_slave *s, double *in, const double *W) {
    int j;
    const double *w = W + 3 * s->n_past;
    double *p1 = s->past, *p2 = s->past + s->n_in;
    for (j = 0; j < s->n_in; ++j) {
        double now = in[j], x = now * w[0];
        if (s->n_past >= 1) x = x + w[1] * p1[j];
        if (s->n_past >= 2) x = x + w[2] * p2[j];
        p2[j] = p1[j];
        p1[j] = now;
        in[j] = x;
    }
    if (s->n_past < 2) s->n_past++;
}

static inline int push(rpr_slave *s, double *v, double inv_h, const double *W) {
    int j, st;
    double *in = v + s->in_off;
    if (!s->n_in) return set_inputs(s, in);  /* a callback slave's typed inputs */
    gather(s, v, in);
    if (s->past) extrapolate(s, in, W);
    if (!s->interp) return set_inputs(s, in);
    for (j = 0; j < s->n_in; ++j) {
        double now = in[j];
        s->slope[j] = (now - s->hist[j]) * inv_h;
        if (s->fresh[j]) in[j] = s->hist[j];
        s->hist[j] = now;
    }
    st = set_inputs(s, in);
    if (st > ST_WARNING) return st;
    return set_slopes(s);
}

/* a memoryless slave evaluated within Jacobi's exchange: its inputs from their sources now (held,
   no slope), then its outputs (Algorithm._exchange) */
static inline int exchange(rpr_slave *s, double *v) {
    int st;
    double *in = v + s->in_off;
    gather(s, v, in);
    st = set_inputs(s, in);
    if (st > ST_WARNING) return st;
    return get_outputs(s, v);
}

/* one macro step from t_ns of a slave at rate > 1: sub-steps at the exact sub-instants, its
   inputs held or set on the macro step's line before every later sub-step (cosim.master.multirate) */
static inline int advance(rpr_slave *s, double *v, int64_t t_ns, double t, double h) {
    int32_t j, m;
    int st;
    double hs, *in;
    if (s->rate <= 1) return do_step(s, t, h);
    hs = (double)s->sub_ns / 1e9;
    in = v + s->in_off;
    if (s->interp) for (m = 0; m < s->n_in; ++m) s->base[m] = in[m];
    st = do_step(s, (double)t_ns / 1e9, hs);
    for (j = 1; j < s->rate; ++j) {
        if (st > ST_WARNING) return st;
        if (s->interp) {
            double tau = (double)(j * s->sub_ns) / 1e9;
            for (m = 0; m < s->n_in; ++m) in[m] = s->slope[m] * tau + s->base[m];
            st = set_inputs(s, in);
            if (st > ST_WARNING) return st;
            st = set_slopes(s);
            if (st > ST_WARNING) return st;
        }
        st = do_step(s, (double)(t_ns + j * s->sub_ns) / 1e9, hs);
    }
    return st;
}

/* ---- FMI 3.0 event mode (Algorithm._event_step, docs/explanation/events.md) ---------------------------- */

/* one slave's call timed into its wall time (Algorithm._io / _advance) */
#define TIMED(i, expr) do { int64_t t0_ = timing ? now_ns() : 0; st = (expr); \
    if (timing) S[i].ns += now_ns() - t0_; } while (0)
#define FAIL(who, status) do { *fail_slave = (who); *fail_status = (status); return FX_RUNNING; } while (0)

/* doStep of slave i in an event step: a slave at the grid point already (ahead) waits there, its
   call counted as the Python loop counts it */
static inline int step_ev(rpr_slave *s, double *v, int64_t t_ns, double t, double h) {
    if (s->ahead) { s->calls++; return ST_OK; }
    return advance(s, v, t_ns, t, h);
}

static inline int can_save(const rpr_slave *s) { return s->get_state && s->set_state && s->state; }

/* a slave's stop request stands in this event step: the step ends as any, then the run (FX_STOPPED) */
static inline int stop_stands(const rpr_slave *S, int32_t n) {
    int32_t i;
    for (i = 0; i < n; ++i) if (S[i].stop) return 1;
    return 0;
}

/* Gauss-Seidel's event step (the oracle's _events_in_order): in order, each slave from the freshest
   outputs; once an event-mode slave returned early, the slaves after it step only to its time */
static int events_in_order(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t t_ns, double t,
                           double h, int32_t timing, int32_t *fail_slave, int32_t *fail_status) {
    double reached = t + h, tol = 1e-12 * (1.0 + fabs(t + h));
    int32_t c, i;
    int st;
    for (c = 0; c < n; ++c) {
        double hi;
        i = order[c];
        TIMED(i, push(&S[i], v, 1.0 / h, NULL));
        if (st > ST_WARNING) FAIL(i, st);
        hi = py_min(h, reached - t);
        if (hi > tol) {  /* (an event at t itself: nothing to step) */
            TIMED(i, step_ev(&S[i], v, t_ns, t, hi));
            if (st == ST_STOP_REQUESTED) S[i].stop = 1;  /* the step goes on: it ends the run where it ends */
            else if (st > ST_WARNING) FAIL(i, st);
        }
        S[i].reached = t + hi;
        if (S[i].event_mode && !S[i].ahead) reached = py_min(reached, step_end(&S[i]));
        TIMED(i, get_outputs(&S[i], v));
        if (st > ST_WARNING) FAIL(i, st);
    }
    return FX_RUNNING;
}

/* Jacobi's event step (the oracle's _events_first): every input from the outputs at t, the event-mode
   slaves step first, the others only to the earliest time one of them reached */
static int events_first(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t t_ns, double t,
                        double h, int32_t timing, int32_t *fail_slave, int32_t *fail_status) {
    double reached = t + h;
    int32_t c, i, have = 0;
    int st;
    for (i = 0; i < n; ++i) {
        TIMED(i, push(&S[i], v, 1.0 / h, NULL));
        if (st > ST_WARNING) FAIL(i, st);
    }
    for (i = 0; i < n; ++i) {
        if (!S[i].event_mode || S[i].ahead) continue;
        TIMED(i, advance(&S[i], v, t_ns, t, h));
        if (st == ST_STOP_REQUESTED) S[i].stop = 1;  /* the step goes on: it ends the run where it ends */
        else if (st > ST_WARNING) FAIL(i, st);
    }
    for (i = 0; i < n; ++i) {  /* Python's min over the list of the first ones (t + h when none) */
        if (!S[i].event_mode || S[i].ahead) continue;
        if (!have || step_end(&S[i]) < reached) reached = step_end(&S[i]);
        have = 1;
    }
    for (i = 0; i < n; ++i) {
        double hi;
        if (S[i].event_mode && !S[i].ahead) continue;
        hi = py_min(h, reached - t);
        if (hi > 1e-12 * (1.0 + fabs(t + h))) {
            TIMED(i, step_ev(&S[i], v, t_ns, t, hi));
            if (st == ST_STOP_REQUESTED) S[i].stop = 1;
            else if (st > ST_WARNING) FAIL(i, st);
        }
        S[i].reached = t + hi;
    }
    for (i = 0; i < n; ++i) {
        TIMED(i, get_outputs(&S[i], v));
        if (st > ST_WARNING) FAIL(i, st);
    }
    for (c = 0; c < n; ++c) {  /* memoryless slaves, in order (Algorithm._exchange) */
        i = order[c];
        if (!S[i].memoryless) continue;
        TIMED(i, exchange(&S[i], v));
        if (st > ST_WARNING) FAIL(i, st);
    }
    return FX_RUNNING;
}

/* One step with event-mode slaves (Algorithm._event_step) from the current point (the grid point
   k, or the event c->t_event that cut step k) to the next grid point, cut at the earliest early
   return.  FX_RUNNING: the step reached the grid point (or a call failed: *fail_slave >= 0);
   FX_GRID_EVENT: it did, and slave c->who asks for event handling there; FX_EVENT: it was cut at c->t_e by c->who (the slaves that stepped past rolled
   back and stepped to it, or, when they cannot roll back, marked ahead); FX_CHATTERING, FX_FAILED;
   FX_STOPPED: a slave asked to stop in the step (its `stop`; one whose doStep was rolled back asks again
   in the retake or not at all), the step ended as above at the grid point or at c->t_e (has_t_event),
   where the run ends. */
static int event_step(rpr_slave *S, int32_t n, const int32_t *order, int32_t algorithm, double *v, int64_t k,
                      int64_t start_ns, int64_t step_ns, int32_t timing, fx_ctl *c, int32_t *fail_slave,
                      int32_t *fail_status) {
    int64_t t_ns = start_ns + k * step_ns;
    double t_end = (double)(start_ns + (k + 1) * step_ns) / 1e9;
    double t = c->has_t_event ? c->t_event : (double)t_ns / 1e9;
    double h = c->has_t_event ? t_end - t : (double)step_ns / 1e9, tol, t_e = 0.0;
    int32_t i, j, who = -1, seq = algorithm == 1;
    /* what may step past an event: under Gauss-Seidel any slave, under Jacobi the event-mode ones */
    int32_t save = c->n_event > 1 || (seq && n > 1);
    int st;
#define SAVED(s) (save && (seq || (s)->event_mode) && can_save(s) && !(s)->ahead)
    for (i = 0; i < n; ++i) {
        if (!SAVED(&S[i])) continue;
        st = save_state(&S[i]);
        if (failing(st)) { *fail_slave = i; *fail_status = st; return FX_FAILED; }
    }
    for (i = 0; i < n; ++i) { S[i].reached = t + h; S[i].stop = 0; }
    st = seq ? events_in_order(S, n, order, v, t_ns, t, h, timing, fail_slave, fail_status)
             : events_first(S, n, order, v, t_ns, t, h, timing, fail_slave, fail_status);
    if (*fail_slave >= 0) return st;
    tol = 1e-12 * (1.0 + fabs(t_end));
    for (i = 0; i < n; ++i) {  /* the earliest early return (the first slave of equal ones) */
        double r;
        if (!S[i].event_mode || S[i].ahead) continue;
        r = step_end(&S[i]);
        if (r < t + h - tol && (who < 0 || r < t_e)) { who = i; t_e = r; }
    }
    if (who < 0) {  /* the grid point: an event-mode slave may ask for event handling there */
        c->who = -1;
        for (i = 0; i < n && c->who < 0; ++i)
            if (S[i].event_mode && !S[i].ahead && event_asked(&S[i])) c->who = i;
        for (i = 0; i < n; ++i) S[i].ahead = 0;
        c->has_t_event = 0;
        c->events_in_step = 0;
        return stop_stands(S, n) ? FX_STOPPED : c->who >= 0 ? FX_GRID_EVENT : FX_RUNNING;
    }
    c->who = who;
    c->t_e = t_e;
    if (++c->events_in_step > c->max_events) return FX_CHATTERING;
    for (j = 0; j < n; ++j) {
        rpr_slave *s = &S[j];
        if (j == who || s->ahead || (s->event_mode ? step_end(s) : s->reached) <= t_e + tol) continue;
        if (SAVED(s)) {  /* stepped past the event: back (its inputs with it), and to the event time */
            st = restore_state(s);
            s->stop = 0;  /* its stop request goes with the step rolled back: the retake decides */
            if (!failing(st)) TIMED(j, advance(s, v, t_ns, t, t_e - t));
            if (st == ST_STOP_REQUESTED) s->stop = 1;
            else if (failing(st)) { *fail_slave = j; *fail_status = st; return FX_FAILED; }
        } else {
            s->ahead = 1;  /* late: it gets the event at the grid point (s->reached for the note) */
        }
    }
#undef SAVED
    for (j = 0; j < n; ++j) {
        TIMED(j, get_outputs(&S[j], v));
        if (failing(st)) { *fail_slave = j; *fail_status = st; return FX_FAILED; }
    }
    c->has_t_event = 1;
    c->t_event = t_e;
    return stop_stands(S, n) ? FX_STOPPED : FX_EVENT;
}

#define CHECK(expr, who) do { int st_ = (expr); if (st_ > ST_WARNING) { *fail_slave = (who); \
    *fail_status = st_; goto out; } } while (0)
#define TICK(i) do { if (timing) { int64_t t_ = now_ns(); S[i].ns += t_ - tprev; tprev = t_; } } while (0)

/* Run up to nsteps macro steps from step index k0 (t_k = start_ns + k step_ns).  algorithm 0 =
   Jacobi (memoryless slaves then evaluated in `order`), 1 = Gauss-Seidel (slaves in `order`),
   3 = Jacobi with each slave's inputs extrapolated (`weights`; the slaves with `past`).  After
   every `rec_every`-th step a row (t, v[rec_idx]...) is appended to rec.  Returns the number of
   steps completed; on a failure *fail_slave >= 0.  With event-mode slaves (ev: their state across
   calls) each step is event_step's, and a call also returns at an event (ev->status).  With
   budget_ns > 0 it also returns (early, no failure) once that much wall time has passed, so that
   Python can handle signals between calls. */
int64_t rpr_run(rpr_slave *S, int32_t n, const int32_t *order, int32_t algorithm, const double *weights, double *v,
                int64_t k0, int64_t nsteps, int64_t start_ns, int64_t step_ns, int32_t timing,
                const int64_t *rec_idx, int32_t n_rec, int64_t rec_every, double *rec, int64_t *n_rows,
                int32_t *fail_slave, int32_t *fail_status, int64_t *master_ns, int64_t budget_ns, fx_ctl *ev) {
    int64_t k, done = 0, rows = 0, t_start = (timing || budget_ns > 0) ? now_ns() : 0, tprev = t_start;
    int64_t slave_ns0 = 0, slave_ns1 = 0;
    int32_t i, c;
    double h = (double)step_ns / 1e9, inv_h = 1.0 / h;
    for (i = 0; i < n; ++i) slave_ns0 += S[i].ns;
    *fail_slave = -1;
    *fail_status = 0;
    if (ev) ev->status = FX_RUNNING;
    for (k = k0; k < k0 + nsteps; ++k) {
        int64_t t_ns = start_ns + k * step_ns;
        double t = (double)t_ns / 1e9;
        if (timing) tprev = now_ns();  /* time since the last slave call is the master's own */
        if (ev) {  /* event mode: a step ends at an event (the event iteration runs in Python) */
            ev->status = event_step(S, n, order, algorithm, v, k, start_ns, step_ns, timing, ev, fail_slave,
                                    fail_status);
            /* (FX_STOPPED: the step is not counted, Python ends the run where it ended) */
            if (*fail_slave >= 0 || (ev->status != FX_RUNNING && ev->status != FX_GRID_EVENT)) goto out;
            ++done;
            if (ev->status == FX_GRID_EVENT) goto out;  /* its row, the left limit, written by Python */
            if ((k + 1) % rec_every == 0) record_row(rec + rows++ * (n_rec + 1), t_ns + step_ns, v, rec_idx, n_rec);
            if (budget_ns > 0 && (done & 15) == 0 && now_ns() - t_start > budget_ns) break;
            continue;
        }
        if (algorithm != 1) {
            for (i = 0; i < n; ++i) { CHECK(push(&S[i], v, inv_h, weights), i); TICK(i); }
            for (i = 0; i < n; ++i) { CHECK(advance(&S[i], v, t_ns, t, h), i); TICK(i); }
            for (i = 0; i < n; ++i) { CHECK(get_outputs(&S[i], v), i); TICK(i); }
            for (c = 0; c < n; ++c) {  /* memoryless slaves, in order: their inputs now, outputs at once */
                i = order[c];
                if (!S[i].memoryless) continue;
                CHECK(exchange(&S[i], v), i);
                TICK(i);
            }
        } else {
            for (c = 0; c < n; ++c) {
                i = order[c];
                CHECK(push(&S[i], v, inv_h, weights), i);
                CHECK(advance(&S[i], v, t_ns, t, h), i);
                CHECK(get_outputs(&S[i], v), i);
                TICK(i);
            }
        }
        ++done;
        if ((k + 1) % rec_every == 0) record_row(rec + rows++ * (n_rec + 1), t_ns + step_ns, v, rec_idx, n_rec);
        if (budget_ns > 0 && (done & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
out:
    *n_rows = rows;
    if (timing) {
        for (i = 0; i < n; ++i) slave_ns1 += S[i].ns;
        *master_ns += (now_ns() - t_start) - (slave_ns1 - slave_ns0);
    }
    return done;
}
