/* The compiled inner loop of the fixed-step master, Jacobi and Gauss-Seidel (cosim/master/fastloop.py).
   The Python oracle it is checked against bit for bit: tests/oracles.py. */
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

#define CHECK(expr, who) do { int st_ = (expr); if (st_ > ST_WARNING) { *fail_slave = (who); \
    *fail_status = st_; goto out; } } while (0)
#define TICK(i) do { if (timing) { int64_t t_ = now_ns(); S[i].ns += t_ - tprev; tprev = t_; } } while (0)

/* Run up to nsteps macro steps from step index k0 (t_k = start_ns + k step_ns).  algorithm 0 =
   Jacobi (memoryless slaves then evaluated in `order`), 1 = Gauss-Seidel (slaves in `order`),
   3 = Jacobi with each slave's inputs extrapolated (`weights`; the slaves with `past`).  After
   every `rec_every`-th step a row (t, v[rec_idx]...) is appended to rec.  Returns the number of
   steps completed; on a failure *fail_slave >= 0.  With budget_ns > 0 it also returns (early, no
   failure) once that much wall time has passed, so that Python can handle signals between calls. */
int64_t rpr_run(rpr_slave *S, int32_t n, const int32_t *order, int32_t algorithm, const double *weights, double *v,
                int64_t k0, int64_t nsteps, int64_t start_ns, int64_t step_ns, int32_t timing,
                const int64_t *rec_idx, int32_t n_rec, int64_t rec_every, double *rec, int64_t *n_rows,
                int32_t *fail_slave, int32_t *fail_status, int64_t *master_ns, int64_t budget_ns) {
    int64_t k, done = 0, rows = 0, t_start = (timing || budget_ns > 0) ? now_ns() : 0, tprev = t_start;
    int64_t slave_ns0 = 0, slave_ns1 = 0;
    int32_t i, c;
    double h = (double)step_ns / 1e9, inv_h = 1.0 / h;
    for (i = 0; i < n; ++i) slave_ns0 += S[i].ns;
    *fail_slave = -1;
    *fail_status = 0;
    for (k = k0; k < k0 + nsteps; ++k) {
        int64_t t_ns = start_ns + k * step_ns;
        double t = (double)t_ns / 1e9;
        if (timing) tprev = now_ns();  /* time since the last slave call is the master's own */
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
