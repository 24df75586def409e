"""The compiled engines of the variable-step masters ``adaptive`` and ``ecco``: their step loops in C.

The same steps as :class:`cosim.master.algorithms.adaptive.AdaptiveStepper` (the Python loop stays the reference
implementation; ``tests/test_adaptive_engine.py`` checks that both take the same steps and produce the
same values, bit for bit): save every slave's FMU state (``fmi2GetFMUstate`` into one state per
slave, allocated by the first call and reused), a Gauss-Seidel step with linear inputs, the
coupling error estimate, the PI controller, and on a rejected step ``fmi2SetFMUstate`` and a retry.
Every operation is done in the same order and precision as the Python loop (no fused
multiply-add: ``-std=c99`` keeps ``-ffp-contract=off``; ``nearbyint`` rounds half to even like
Python's ``round``), which is what makes the two agree exactly.

One call runs until it has recorded ``max_rows`` accepted steps, spent its wall-time budget (so
that Python handles signals between calls), reached the stop time, or met something it leaves
to Python: a stop request, the step floor, or a failing get/set of an FMU state.

``ecco`` (:class:`CompiledEcco`, the loop of :class:`cosim.master.algorithms.ecco.EccoStepper`)
takes the same Gauss-Seidel step with linear inputs, never rolled back, and sizes the next step
from the bonds' energy residual, with the same per-bond statistics and endings.

Timing (per-slave wall time in the run statistics) reads the clock once per slave, as the
fixed-step loop does: a slave's time includes preparing its inputs; the master's own time is the
rest (saving and restoring states, the estimate, the controller, recording).
"""
from __future__ import annotations

import ctypes
import math
from ctypes import POINTER, c_int32, c_int64, c_void_p
from functools import lru_cache

import numpy as np

from ..errors import UserError
from .native import CSlave, SlaveArray, c_struct, compile_loop, ctypes_struct

#: The controller's state and the run's counters (``ad_ctl``), declared once for C and ctypes.
CONTROL_FIELDS = (
    ("int64_t", "t_ns", "current point [ns]"), ("int64_t", "stop_ns", "stop time [ns]"),
    ("double", "h", "the next step tried [s]"), ("double", "h_prev", "the last accepted step [s] (0: none)"),
    ("double", "err_prev", "the last accepted step's error"),
    *[("double", k, "option") for k in ("rtol", "atol", "h_ref", "h_min", "h_max", "safety", "fac_min", "fac_max")],
    ("double", "k_i", "controller gain"), ("double", "k_p", "controller gain"),
    ("double", "p_lin", "order with linear inputs"), ("double", "p_hold", "order with held inputs"),
    ("int32_t", "any_interp", "some slave follows input slopes"), ("int32_t", "timing", "time the slaves' calls"),
    ("int64_t", "accepted", "statistics"), ("int64_t", "rejected", "statistics"),
    ("int64_t", "rollbacks", "statistics"), ("int64_t", "discards", "statistics"),
    ("double", "h_min_taken", "statistics"), ("double", "h_max_taken", "statistics"),
    ("int32_t", "status", "why a call returned early: 0 running, 1 a slave asked to stop, 2 the step floor, "
                          "3 getting an FMU state failed, 4 setting it failed"),
    ("int32_t", "bad_slave", "the slave of that status"), ("int32_t", "bad_status", "its FMI status"),
    ("double", "last_err", "the error at the step floor"),
    ("int64_t", "master_ns", "wall time in this loop outside the slaves' calls (with timing)"),
)

#: ecco's controller state, its bonds (by index into v and the slaves) and their statistics (``ec_ctl``).
ECCO_FIELDS = (
    ("int64_t", "t_ns", "current point [ns]"), ("int64_t", "stop_ns", "stop time [ns]"),
    ("double", "h", "the next step [s]"), ("double", "h_prev", "the last step [s] (0: none)"),
    ("double", "err_prev", "the last step's error"),
    *[("double", k, "option") for k in ("rtol", "atol", "h_min", "h_max", "safety", "fac_min", "fac_max", "k_i",
                                        "k_p")],
    ("int32_t", "timing", "time the slaves' calls"), ("int32_t", "n_bonds", "power bonds"),
    ("const int64_t *", "out_idx", "per bond, v indices of y_a, y_b"),
    ("const int64_t *", "in_idx", "per bond, v indices of u_a, u_b"),
    ("const int32_t *", "side", "per bond, the slaves a, b"), ("const int32_t *", "slot", "per bond, u_a, u_b among "
                                                                                         "their slaves' inputs"),
    ("double *", "y0", "work: the bonds' outputs at the step's start"), ("double *", "scaled", "work: eps per bond"),
    ("double *", "max_scaled", "per bond statistics"), ("double *", "max_residual", "[J]"),
    ("double *", "residual_sum", "[J]"), ("double *", "abs_residual_sum", "[J]"), ("double *", "energy", "[J]"),
    ("int64_t *", "over", "steps over tolerance"),
    ("int64_t", "accepted", "statistics"), ("double", "h_min_taken", "statistics"),
    ("double", "h_max_taken", "statistics"),
    ("int32_t", "floor_patience", "steps over tolerance at h_min before the run ends (0: never)"),
    ("int32_t", "at_floor", "such steps in a row"), ("int32_t", "ending", "the run ends before the next step"),
    ("int32_t", "end_bond", "the bond it ends on"), ("double", "end_scaled", "its eps"),
    ("int32_t", "status", "why a call returned early: 0 running, 1 a slave asked to stop, 5 over tolerance at the "
                          "floor, 6 a slave failed, 7 a residual not finite"),
    ("int32_t", "bad_slave", "the slave of that status (the bond for 7)"), ("int32_t", "bad_status", "its FMI status"),
    ("int64_t", "master_ns", "wall time in this loop outside the slaves' calls (with timing)"),
)

CControl = ctypes_struct("ad_ctl", CONTROL_FIELDS)
CEccoControl = ctypes_struct("ec_ctl", ECCO_FIELDS)

SOURCE = c_struct("ad_ctl", CONTROL_FIELDS) + c_struct("ec_ctl", ECCO_FIELDS) + r"""
static int slave_step(rpr_slave *s, double *v, double t, double h) {
    int st = set_inputs(s, v + s->in_off);
    if (!failing(st) && s->interp && s->n_in) st = set_slopes(s);
    if (failing(st)) return st;
    st = do_step(s, t, h);
    if (failing(st) || st == ST_STOP) return st;
    return get_outputs(s, v);
}

/* One Gauss-Seidel step of h from t with linear inputs (AdaptiveStepper._attempt's stepping):
   each input interpolated from a source that stepped before, extrapolated from the last two
   points otherwise (s->guess: the extrapolation to t+h); returns -1, or the failing slave with
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
        }
        st = slave_step(s, v, t, h);
        if (timing) { int64_t t1 = now_ns(); s->ns += t1 - tprev; tprev = t1; }
        if (failing(st) || st == ST_STOP) { *bad_st = st; return order[k]; }
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

static inline void record(double *rec, int64_t rows, int32_t n_rec, int64_t t_ns, const double *v,
                          const int64_t *rec_idx) {
    double *row = rec + rows * (n_rec + 1);
    int32_t j;
    row[0] = (double)t_ns / 1e9;
    for (j = 0; j < n_rec; ++j) row[j + 1] = v[rec_idx[j]];
}

static inline int64_t round_ns(double x) {   /* Python's round(x): half to even */
    if (!(x < 9.0e18)) return INT64_MAX;
    return (int64_t)nearbyint(x);
}

static int64_t rpr_adapt_loop(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv,
                              double *v_saved, double *lo, double *hi, ad_ctl *c, const int64_t *rec_idx,
                              int32_t n_rec, double *rec, int64_t *h_rec, int64_t max_rows, int64_t budget_ns,
                              int64_t t_start) {
    int64_t rows = 0, h_ns = 0;
    int32_t i, j, bad, bad_st;
    double h = 0.0, err = 0.0, p;
    c->status = 0;
    while (c->t_ns < c->stop_ns && rows < max_rows) {
        double t = (double)c->t_ns / 1e9;
        memcpy(v_saved, v, (size_t)nv * sizeof(double));
        for (i = 0; i < n; ++i) {
            int st = save_state(&S[i]);
            if (failing(st)) { c->status = 3; c->bad_slave = i; c->bad_status = st; return rows; }
        }
        for (;;) {
            int64_t want = round_ns(c->h * 1e9), left = c->stop_ns - c->t_ns;
            double shrink;
            h_ns = want < left ? want : left;
            if (h_ns < 1) h_ns = 1;
            h = (double)h_ns / 1e9;
            err = attempt(S, n, order, v, lo, hi, c, t, h, &bad, &bad_st);
            p = (c->any_interp && c->h_prev > 0) ? c->p_lin : c->p_hold;
            if (bad >= 0 && bad_st == ST_STOP) {
                c->status = 1; c->bad_slave = bad; c->bad_status = bad_st;
                return rows;
            }
            if (bad < 0 && (err <= 1.0 || c->h_prev == 0)) break;
            c->rejected++;
            if (bad >= 0) c->discards++;
            for (i = 0; i < n; ++i) {
                int st = restore_state(&S[i]);
                if (failing(st)) { c->status = 4; c->bad_slave = i; c->bad_status = st; return rows; }
            }
            c->rollbacks++;
            memcpy(v, v_saved, (size_t)nv * sizeof(double));
            shrink = !isfinite(err) ? c->fac_min : py_max(c->fac_min, c->safety * pow(err, -1.0 / p));
            if (h <= c->h_min * (1 + 1e-12)) {
                c->status = 2; c->bad_slave = bad; c->bad_status = bad_st; c->last_err = err;
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
        {
            double e = py_max(err, 1e-10), fac;
            fac = c->safety * pow(e, -c->k_i / p) * pow(c->err_prev, c->k_p / p);
            c->err_prev = e;
            fac = py_min(c->fac_max, py_max(c->fac_min, fac));
            if (h_ns < round_ns(c->h * 1e9)) fac = py_max(fac, 1.0);
            c->h = py_min(c->h_max, py_max(c->h_min, h * fac));
        }
        record(rec, rows, n_rec, c->t_ns, v, rec_idx);
        h_rec[rows++] = h_ns;
        if (budget_ns > 0 && (rows & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
    return rows;
}

/* Accepted steps until max_rows rows are recorded, the stop time, the wall-time budget, or an
   event for Python (c->status != 0).  Each accepted step appends (t, v[rec_idx]...) to rec and
   its step [ns] to h_rec.  Returns the number of rows; with timing, adds the loop's own time
   outside the slaves' calls to c->master_ns. */
int64_t rpr_adapt_run(rpr_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, double *v_saved,
                      double *lo, double *hi, ad_ctl *c, const int64_t *rec_idx, int32_t n_rec, double *rec,
                      int64_t *h_rec, int64_t max_rows, int64_t budget_ns) {
    int64_t t_start = (budget_ns > 0 || c->timing) ? now_ns() : 0, slave_ns0 = slaves_ns(S, n), rows;
    rows = rpr_adapt_loop(S, n, order, v, nv, v_saved, lo, hi, c, rec_idx, n_rec, rec, h_rec, max_rows, budget_ns,
                          t_start);
    if (c->timing) c->master_ns += (now_ns() - t_start) - (slaves_ns(S, n) - slave_ns0);
    return rows;
}

/* EccoStepper.step: steps (never retried) sized from the bonds' energy residual, until max_rows
   rows, the stop time, the budget or an event for Python (c->status != 0); rows and h_rec as
   rpr_adapt_run's. */
static int64_t rpr_ecco_loop(rpr_slave *S, int32_t n, const int32_t *order, double *v, ec_ctl *c,
                             const int64_t *rec_idx, int32_t n_rec, double *rec, int64_t *h_rec, int64_t max_rows,
                             int64_t budget_ns, int64_t t_start) {
    int64_t rows = 0;
    int32_t b, k, bad, bad_st;
    c->status = 0;
    while (c->t_ns < c->stop_ns && rows < max_rows) {
        double t = (double)c->t_ns / 1e9, h, hh, err, fac;
        int64_t want = round_ns(c->h * 1e9), left = c->stop_ns - c->t_ns, h_ns;
        if (c->ending) { c->status = 5; return rows; }
        h_ns = want < left ? want : left;
        if (h_ns < 1) h_ns = 1;
        h = (double)h_ns / 1e9;
        for (k = 0; k < 2 * c->n_bonds; ++k) c->y0[k] = v[c->out_idx[k]];
        bad = gs_step(S, n, order, v, c->h_prev, c->timing, t, h, &bad_st);
        if (bad >= 0) {
            c->status = (bad_st == ST_STOP || (bad_st == ST_DISCARD && stop_asked(&S[bad]))) ? 1 : 6;
            c->bad_slave = bad; c->bad_status = bad_st;
            return rows;
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
            if (!isfinite(c->scaled[b])) { c->status = 7; c->bad_slave = b; return rows; }
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
        fac = py_min(c->fac_max, py_max(c->fac_min, fac));   /* AdaptiveStepper._propose */
        if (h_ns < round_ns(c->h * 1e9)) fac = py_max(fac, 1.0);
        c->h = py_min(c->h_max, py_max(c->h_min, h * fac));
        record(rec, rows, n_rec, c->t_ns, v, rec_idx);
        h_rec[rows++] = h_ns;
        if (budget_ns > 0 && (rows & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
    return rows;
}

int64_t rpr_ecco_run(rpr_slave *S, int32_t n, const int32_t *order, double *v, ec_ctl *c, const int64_t *rec_idx,
                     int32_t n_rec, double *rec, int64_t *h_rec, int64_t max_rows, int64_t budget_ns) {
    int64_t t_start = (budget_ns > 0 || c->timing) ? now_ns() : 0, slave_ns0 = slaves_ns(S, n), rows;
    rows = rpr_ecco_loop(S, n, order, v, c, rec_idx, n_rec, rec, h_rec, max_rows, budget_ns, t_start);
    if (c->timing) c->master_ns += (now_ns() - t_start) - (slaves_ns(S, n) - slave_ns0);
    return rows;
}
"""


#: Longest wall time of one call [ns]: it returns to Python (signals, progress) at least this often.
CALL_BUDGET_NS = 100_000_000


@lru_cache(maxsize=1)
def library() -> ctypes.CDLL:
    """Compile (once, cached on disk: :func:`cosim.master.native.compile_loop`) and load the engine."""
    return compile_loop(SOURCE, "rpr_adapt", {
        "rpr_adapt_run": [POINTER(CSlave), c_int32, c_void_p, c_void_p, c_int64, c_void_p, c_void_p, c_void_p,
                          POINTER(CControl), c_void_p, c_int32, c_void_p, c_void_p, c_int64, c_int64],
        "rpr_ecco_run": [POINTER(CSlave), c_int32, c_void_p, c_void_p, POINTER(CEccoControl), c_void_p, c_int32,
                         c_void_p, c_void_p, c_int64, c_int64]})


def usable(system, rollback: bool = True) -> bool:
    """Whether the compiled engine can run ``system``: FMU slaves with C entry points (and, with
    ``rollback``, FMU state get/set), scalar Float64 connections copied as they are, and a working
    C compiler."""
    if system.typed.active or system.transformed:
        return False
    for s in system.slaves:
        ne = s.native()
        if ne is None or (rollback and not (ne.get_state and ne.set_state)):
            return False
    try:
        library()
    except UserError:
        return False
    return True


class _CompiledVariable:
    """What the compiled adaptive and ecco loops share: the slaves' structs with the stepper's
    input history (fresh inputs, slopes, the sources' last two values), the recorded columns and
    the per-slave counters."""

    def __init__(self, stepper, states: bool):
        self.py = stepper  # the Python stepper: its setup, statistics and messages
        sysm = stepper.system
        self.lib = library()
        self.arr = arr = SlaveArray(sysm, states=states)
        for i in range(len(arr)):
            c = arr[i]
            n_in = c.n_in
            interp = bool(stepper.interp[i]) and n_in > 0
            c.interp, c.set_der = int(interp), arr.entries[i].set_input_derivatives if interp else 0
            cur = np.ascontiguousarray(sysm.v[sysm.in_src[i]], dtype=np.float64)
            if n_in:
                c.orders = arr.buffer(np.ones(n_in, dtype=np.int32), np.int32)
                c.fresh = arr.buffer(stepper.fresh[i].astype(np.int8), np.int8)
                c.cur, c.prev, c.guess = arr.buffer(cur), arr.buffer(cur.copy()), arr.buffer(np.zeros(n_in))
                c.slope = arr.buffer(stepper.slopes[i])
        self.order = np.array(stepper.order, dtype=np.int32)
        self.rec_idx = np.ascontiguousarray(sysm.record_idx, dtype=np.int64)  # recorded, then watched (guards)
        self.h_rec = np.empty(0, dtype=np.int64)
        self.status, self.message = "running", ""

    @property
    def t_ns(self) -> int:
        return int(self.ctl.t_ns)

    @property
    def t(self) -> float:
        return self.ctl.t_ns / 1e9

    @property
    def master_ns(self) -> int:
        """The master's own time in the compiled loop [ns] (outside the slaves' calls)."""
        return int(self.ctl.master_ns)

    @property
    def calls(self) -> list[int]:
        return [int(c.calls) for c in self.arr.arr]

    @property
    def slave_ns(self) -> list[int]:
        return [int(c.ns) for c in self.arr.arr]

    def _rows(self, rec: np.ndarray) -> None:
        if len(self.h_rec) < len(rec):
            self.h_rec = np.empty(len(rec), dtype=np.int64)

    def close(self) -> None:
        """Free the FMU states (before the instances are freed)."""
        self.arr.free_states()


class CompiledAdaptive(_CompiledVariable):
    """Drop-in for :class:`cosim.master.algorithms.adaptive.AdaptiveStepper` whose accepted-step loop runs in C.
    It shares the stepper's setup (order, fresh inputs, options) and exposes the same ``t_ns``,
    ``stats``, ``calls``, ``slave_ns``, ``status`` and ``message``; :meth:`run` replaces the
    Python loop of :class:`cosim.master.algorithms.adaptive.VariableStepper` one block at a time."""

    def __init__(self, stepper, timing: bool = True):
        super().__init__(stepper, states=True)
        opt = stepper.opt
        self.v_saved = np.empty_like(stepper.system.v)
        self.lo, self.hi = stepper.lo, stepper.hi
        self.ctl = ctl = CControl()
        ctl.t_ns, ctl.stop_ns, ctl.h, ctl.h_prev, ctl.err_prev = (stepper.t_ns, stepper.stop_ns, stepper.h,
                                                                   stepper.h_prev, stepper.err_prev)
        for name in ("rtol", "atol", "h_ref", "h_min", "h_max", "safety", "fac_min", "fac_max"):
            setattr(ctl, name, opt[name])
        ctl.k_i, ctl.k_p = stepper.k_i, stepper.k_p
        ctl.p_lin, ctl.p_hold = stepper.order_p_linear, stepper.order_p_hold
        ctl.any_interp, ctl.timing = int(any(stepper.interp)), int(timing)
        ctl.h_min_taken, ctl.h_max_taken = math.inf, 0.0

    @property
    def stats(self):
        st, c = self.py.stats, self.ctl
        st.accepted, st.rejected, st.rollbacks, st.discards = c.accepted, c.rejected, c.rollbacks, c.discards
        st.h_min_taken, st.h_max_taken = c.h_min_taken, c.h_max_taken
        return st

    def run(self, rec: np.ndarray) -> int:
        """Accepted steps into ``rec`` (rows of time and the recorded values) until it is full,
        the stop time, the call's time budget or the end of the run; returns the rows written."""
        sysm, ctl = self.py.system, self.ctl
        self._rows(rec)
        rows = int(self.lib.rpr_adapt_run(
            self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, len(sysm.v),
            self.v_saved.ctypes.data, self.lo.ctypes.data, self.hi.ctypes.data, ctypes.byref(ctl),
            self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx), rec.ctypes.data,
            self.h_rec.ctypes.data, len(rec), CALL_BUDGET_NS))
        self.py.stats.steps.extend((self.h_rec[:rows] / 1e9).tolist())
        if ctl.status:
            self._ended(ctl.status, ctl.bad_slave, ctl.bad_status, ctl.last_err)
        return rows

    def _ended(self, code: int, bad: int, st: int, err: float) -> None:
        from ..slaves.slave import Status

        sysm, opt, t = self.py.system, self.py.opt, self.t
        if code == 1:
            self.status = "stopped"
            self.message = f"{sysm.slaves[bad].name} asked to terminate the simulation at t = {t:.9g} s"
        elif code == 2:
            s = sysm.slaves[bad] if bad >= 0 else None
            who = s.name if s is not None else "the coupling error"
            detail = (f"{s.name} returned {Status(st).name}" + (f": {s.last_message}" if s.last_message else "")
                      if s is not None else f"scaled coupling error {err:.3g} > 1")
            self.status = "unstable"
            self.message = (f"the step floor h_min = {opt['h_min']:g} s was reached at t = {t:.9g} s "
                            f"({detail}; limited by {who})")
        else:
            s = sysm.slaves[bad]
            what = "getting" if code == 3 else "setting"
            raise UserError(f"{s.name}: {what} the FMU state failed ({Status(st).name})"
                            + (f": {s.last_message}" if s.last_message else ""))


class CompiledEcco(_CompiledVariable):
    """Drop-in for :class:`cosim.master.algorithms.ecco.EccoStepper` whose stepping runs in C: the
    same steps (never retried), the same bond statistics and endings, bit for bit
    (``tests/test_native.py``); the same interface as :class:`CompiledAdaptive`."""

    def __init__(self, stepper, timing: bool = True):
        super().__init__(stepper, states=False)
        opt, bonds = stepper.opt, stepper.bonds
        nb = len(bonds)
        self.ctl = ctl = CEccoControl()
        ctl.t_ns, ctl.stop_ns, ctl.h, ctl.h_prev, ctl.err_prev = (stepper.t_ns, stepper.stop_ns, stepper.h,
                                                                   stepper.h_prev, stepper.err_prev)
        for name in ("rtol", "atol", "h_min", "h_max", "safety", "fac_min", "fac_max", "k_i", "k_p"):
            setattr(ctl, name, opt[name])
        ctl.timing, ctl.n_bonds, ctl.floor_patience = int(timing), nb, stepper.patience
        ctl.h_min_taken, ctl.h_max_taken = math.inf, 0.0
        buf = self.arr.buffer
        ctl.out_idx = buf(np.array([b.out_idx for b in bonds]).ravel(), np.int64)
        ctl.in_idx = buf(np.array([b.in_idx for b in bonds]).ravel(), np.int64)
        ctl.side = buf(np.array([b.side for b in bonds]).ravel(), np.int32)
        ctl.slot = buf(np.array([b.slot for b in bonds]).ravel(), np.int32)
        ctl.y0, ctl.scaled = buf(np.zeros(2 * nb)), buf(np.zeros(nb))
        self.bond_stats = {k: np.zeros(nb) for k in ("max_scaled", "max_residual", "residual_sum",
                                                     "abs_residual_sum", "energy")}
        self.bond_stats["over"] = np.zeros(nb, dtype=np.int64)
        for k, a in self.bond_stats.items():
            setattr(ctl, k, buf(a, a.dtype))

    @property
    def stats(self):
        st, c = self.py.stats, self.ctl
        st.accepted, st.h_min_taken, st.h_max_taken = c.accepted, c.h_min_taken, c.h_max_taken
        for k, b in enumerate(self.py.bonds):
            rec = st.bonds[b.name]
            for name, a in self.bond_stats.items():
                setattr(rec, name, int(a[k]) if name == "over" else float(a[k]))
        return st

    def run(self, rec: np.ndarray) -> int:
        """Steps into ``rec`` as :meth:`CompiledAdaptive.run`."""
        sysm, ctl = self.py.system, self.ctl
        self._rows(rec)
        rows = int(self.lib.rpr_ecco_run(
            self.arr.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, ctypes.byref(ctl),
            self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx), rec.ctypes.data,
            self.h_rec.ctypes.data, len(rec), CALL_BUDGET_NS))
        self.py.stats.steps.extend((self.h_rec[:rows] / 1e9).tolist())
        if ctl.status:
            self._ended(ctl.status, ctl.bad_slave, ctl.bad_status)
        return rows

    def _ended(self, code: int, bad: int, st: int) -> None:
        """The endings of :meth:`cosim.master.algorithms.ecco.EccoStepper.step`, worded alike."""
        from ..slaves.slave import Status

        py, sysm, t = self.py, self.py.system, self.t
        if code == 1:
            self.status = "stopped"
            self.message = f"{sysm.slaves[bad].name} asked to terminate the simulation at t = {t:.9g} s"
        elif code == 6:
            sl = sysm.slaves[bad]
            name = Status(st).name if st in Status._value2member_map_ else str(st)
            self.status = "failed"
            self.message = (f"{sl.name} returned {name} in the step from t = {t:.9g} s (ecco does not roll back)"
                            + (f": {sl.last_message}" if sl.last_message else ""))
        elif code == 7:
            u0 = sysm.v[py._in_idx]
            self.status = "unstable"
            self.message = (f"the energy residual of bond {py.bonds[bad].name} is not finite in the step from "
                            f"t = {t:.9g} s (y = {sysm.v[py._out_idx[bad]]}, u = {u0[bad]})")
        else:
            self.status = "unstable"
            self.message = (f"the energy residual of bond {py.bonds[self.ctl.end_bond].name} stayed over its "
                            f"tolerance for {self.ctl.at_floor} steps at the step floor h_min = "
                            f"{py.opt['h_min']:g} s (scaled {self.ctl.end_scaled:.3g} at t = {t:.9g} s)")


#: The compiled loop of each stepper class, by the ``native_loop`` its class itself declares (a
#: subclass that changes the stepping declares none and runs in Python).
LOOPS = {"adaptive": CompiledAdaptive, "ecco": CompiledEcco}


def has_compiled(stepper_cls: type) -> bool:
    """Whether ``stepper_cls`` has a compiled loop here."""
    return stepper_cls.__dict__.get("native_loop") in LOOPS


def compiled_stepper(stepper, timing: bool = True) -> _CompiledVariable:
    """The compiled drop-in of ``stepper`` (:class:`CompiledAdaptive` or :class:`CompiledEcco`)."""
    loop = LOOPS.get(type(stepper).__dict__.get("native_loop"))
    if loop is None:
        raise ValueError(f"no compiled loop runs {type(stepper).__name__}")
    return loop(stepper, timing)
