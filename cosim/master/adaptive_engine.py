"""The compiled engine of ``master.algorithm: adaptive``: the accepted-step loop in C.

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

Timing (per-slave wall time in the run statistics) reads the clock once per slave, as the
fixed-step loop does: a slave's time includes preparing its inputs; the master's own time is the
rest (saving and restoring states, the estimate, the controller, recording).
"""
from __future__ import annotations

import ctypes
import math
from ctypes import POINTER, c_double, c_int32, c_int64, c_void_p
from functools import lru_cache

import numpy as np

from ..errors import UserError
from .fastloop import FMI_CALL_TYPES

SOURCE = FMI_CALL_TYPES + r"""
#include <string.h>
#include <math.h>

typedef int (*state_get_t)(void *, void **);
typedef int (*state_set_t)(void *, void *);
typedef int (*bstatus_t)(void *, int, int *);

typedef struct {
    int32_t fmi3, n_in, n_out, in_off, out_off, interp;
    void *inst, *do_step, *get, *set, *set_der, *get_state, *set_state, *bool_status;
    void **state;                 /* the slave's FMU state, allocated by its first get */
    const uint32_t *in_vr;
    const int64_t *in_src;
    const uint32_t *out_vr;
    const int32_t *orders;        /* all 1 */
    const int8_t *fresh;          /* input interpolated (its source stepped before) */
    double *cur, *prev, *slope, *guess;
    int64_t calls, ns;
} ad_slave;

typedef struct {
    int64_t t_ns, stop_ns;
    double h, h_prev, err_prev;
    double rtol, atol, h_ref, h_min, h_max, safety, fac_min, fac_max, k_i, k_p, p_lin, p_hold;
    int32_t any_interp, timing;
    int64_t accepted, rejected, rollbacks, discards;
    double h_min_taken, h_max_taken;
    /* why a call returned early: 0 running, 1 a slave asked to stop, 2 the step floor,
       3 getting an FMU state failed, 4 setting it failed */
    int32_t status, bad_slave, bad_status;
    double last_err;
    int64_t master_ns;  /* wall time in this loop outside the slaves' calls (with timing) */
} ad_ctl;

enum { ST_OK = 0, ST_WARNING = 1, ST_DISCARD = 2, ST_STOP = 100 };

static inline int failing(int st) { return st >= 2 && st <= 5; }

static inline int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* numpy's maximum/minimum: NaN if either is NaN; Python's max/min: the first unless the second
   is larger/smaller */
static inline double np_max(double a, double b) { return (isnan(a) || isnan(b)) ? NAN : (b > a ? b : a); }
static inline double np_min(double a, double b) { return (isnan(a) || isnan(b)) ? NAN : (b < a ? b : a); }
static inline double py_max(double a, double b) { return b > a ? b : a; }
static inline double py_min(double a, double b) { return b < a ? b : a; }

static int stop_asked(ad_slave *s) {   /* FMI 2.0 Discard with fmi2Terminated (status kind 3) */
    int b = 0;
    if (s->fmi3 || !s->bool_status) return 0;
    if (((bstatus_t)s->bool_status)(s->inst, 3, &b) > ST_WARNING) return 0;
    return b != 0;
}

static int slave_step(ad_slave *s, double *v, double t, double h) {
    int st = 0;
    double *in = v + s->in_off;
    if (s->n_in) {
        st = s->fmi3 ? ((io3_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in, (size_t)s->n_in)
                     : ((io2_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in);
        if (!failing(st) && s->interp)
            st = ((der2_t)s->set_der)(s->inst, s->in_vr, (size_t)s->n_in, s->orders, s->slope);
    }
    if (failing(st)) return st;
    s->calls++;
    if (s->fmi3) {
        bool ev = 0, term = 0, early = 0;
        double last = t;
        st = ((step3_t)s->do_step)(s->inst, t, h, 0 /* may roll back */, &ev, &term, &early, &last);
        if (st < 2 && term) return ST_STOP;
    } else {
        st = ((step2_t)s->do_step)(s->inst, t, h, 0);
        if (st == ST_DISCARD && stop_asked(s)) return ST_STOP;
    }
    if (failing(st) || st == ST_STOP) return st;
    if (!s->n_out) return 0;
    return s->fmi3 ? ((io3_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out, v + s->out_off, (size_t)s->n_out)
                   : ((io2_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out, v + s->out_off);
}

/* One Gauss-Seidel step of h from t (AdaptiveStepper._attempt); returns the scaled error, or
   INFINITY with *bad set to the failing slave. */
static double attempt(ad_slave *S, int32_t n, const int32_t *order, double *v, const double *lo,
                      const double *hi, ad_ctl *c, double t, double h, int32_t *bad, int32_t *bad_st) {
    int32_t k, i, j;
    double err = 0.0, weight = h / c->h_ref;
    int64_t tprev = c->timing ? now_ns() : 0;  /* one clock read per slave, as the fixed-step loop */
    for (k = 0; k < n; ++k) {
        ad_slave *s = &S[order[k]];
        double *in = v + s->in_off;
        int st;
        i = order[k];
        for (j = 0; j < s->n_in; ++j) {
            double now = v[s->in_src[j]];
            if (s->interp) {
                double ext = c->h_prev > 0 ? (s->cur[j] - s->prev[j]) / c->h_prev : 0.0;
                s->slope[j] = s->fresh[j] ? (now - s->cur[j]) / h : ext;
                in[j] = s->fresh[j] ? s->cur[j] : now;
                s->guess[j] = now + ext * h;
            } else {
                in[j] = now;
                s->guess[j] = now;
            }
        }
        st = slave_step(s, v, t, h);
        if (c->timing) { int64_t t1 = now_ns(); s->ns += t1 - tprev; tprev = t1; }
        if (failing(st) || st == ST_STOP) { *bad = i; *bad_st = st; return INFINITY; }
    }
    for (k = 0; k < n; ++k) {
        ad_slave *s = &S[order[k]];
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
    *bad = -1;
    *bad_st = 0;
    return err;
}

static inline int64_t round_ns(double x) {   /* Python's round(x): half to even */
    if (!(x < 9.0e18)) return INT64_MAX;
    return (int64_t)nearbyint(x);
}

static int64_t rpr_adapt_loop(ad_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv,
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
            int st = ((state_get_t)S[i].get_state)(S[i].inst, S[i].state);
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
                int st = ((state_set_t)S[i].set_state)(S[i].inst, *S[i].state);
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
        for (i = 0; i < n; ++i) {
            ad_slave *s = &S[i];
            for (j = 0; j < s->n_in; ++j) {
                s->prev[j] = s->cur[j];
                s->cur[j] = v[s->in_src[j]];
            }
        }
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
        {
            double *row = rec + rows * (n_rec + 1);
            row[0] = (double)c->t_ns / 1e9;
            for (j = 0; j < n_rec; ++j) row[j + 1] = v[rec_idx[j]];
            h_rec[rows] = h_ns;
            ++rows;
        }
        if (budget_ns > 0 && (rows & 15) == 0 && now_ns() - t_start > budget_ns) break;
    }
    return rows;
}

/* Accepted steps until max_rows rows are recorded, the stop time, the wall-time budget, or an
   event for Python (c->status != 0).  Each accepted step appends (t, v[rec_idx]...) to rec and
   its step [ns] to h_rec.  Returns the number of rows; with timing, adds the loop's own time
   outside the slaves' calls to c->master_ns. */
int64_t rpr_adapt_run(ad_slave *S, int32_t n, const int32_t *order, double *v, int64_t nv, double *v_saved,
                      double *lo, double *hi, ad_ctl *c, const int64_t *rec_idx, int32_t n_rec, double *rec,
                      int64_t *h_rec, int64_t max_rows, int64_t budget_ns) {
    int64_t t_start = (budget_ns > 0 || c->timing) ? now_ns() : 0, slave_ns0 = 0, slave_ns1 = 0, rows;
    int32_t i;
    for (i = 0; i < n; ++i) slave_ns0 += S[i].ns;
    rows = rpr_adapt_loop(S, n, order, v, nv, v_saved, lo, hi, c, rec_idx, n_rec, rec, h_rec, max_rows, budget_ns,
                          t_start);
    if (c->timing) {
        for (i = 0; i < n; ++i) slave_ns1 += S[i].ns;
        c->master_ns += (now_ns() - t_start) - (slave_ns1 - slave_ns0);
    }
    return rows;
}
"""


class CAdaptSlave(ctypes.Structure):
    """Mirror of ``ad_slave`` in :data:`SOURCE`."""

    _fields_ = [("fmi3", c_int32), ("n_in", c_int32), ("n_out", c_int32), ("in_off", c_int32),
                ("out_off", c_int32), ("interp", c_int32), ("inst", c_void_p), ("do_step", c_void_p),
                ("get", c_void_p), ("set", c_void_p), ("set_der", c_void_p), ("get_state", c_void_p),
                ("set_state", c_void_p), ("bool_status", c_void_p), ("state", c_void_p), ("in_vr", c_void_p),
                ("in_src", c_void_p), ("out_vr", c_void_p), ("orders", c_void_p), ("fresh", c_void_p),
                ("cur", c_void_p), ("prev", c_void_p), ("slope", c_void_p), ("guess", c_void_p),
                ("calls", c_int64), ("ns", c_int64)]


class CAdaptControl(ctypes.Structure):
    """Mirror of ``ad_ctl`` in :data:`SOURCE`."""

    _fields_ = [("t_ns", c_int64), ("stop_ns", c_int64), ("h", c_double), ("h_prev", c_double),
                ("err_prev", c_double), ("rtol", c_double), ("atol", c_double), ("h_ref", c_double),
                ("h_min", c_double), ("h_max", c_double), ("safety", c_double), ("fac_min", c_double),
                ("fac_max", c_double), ("k_i", c_double), ("k_p", c_double), ("p_lin", c_double),
                ("p_hold", c_double), ("any_interp", c_int32), ("timing", c_int32), ("accepted", c_int64),
                ("rejected", c_int64), ("rollbacks", c_int64), ("discards", c_int64),
                ("h_min_taken", c_double), ("h_max_taken", c_double), ("status", c_int32),
                ("bad_slave", c_int32), ("bad_status", c_int32), ("last_err", c_double), ("master_ns", c_int64)]


#: Longest wall time of one call [ns]: it returns to Python (signals, progress) at least this often.
CALL_BUDGET_NS = 100_000_000


@lru_cache(maxsize=1)
def library() -> ctypes.CDLL:
    """Compile (cached on disk, see :func:`cosim.master.fastloop.compile_library`) and load the engine."""
    from .fastloop import compile_library

    dll = compile_library(SOURCE, "rpr_adapt")
    fn = dll.rpr_adapt_run
    fn.restype = c_int64
    fn.argtypes = [POINTER(CAdaptSlave), c_int32, c_void_p, c_void_p, c_int64, c_void_p, c_void_p, c_void_p,
                   POINTER(CAdaptControl), c_void_p, c_int32, c_void_p, c_void_p, c_int64, c_int64]
    return dll


def usable(system) -> bool:
    """Whether the compiled engine can run ``system``: FMU slaves with C entry points and FMU
    state get/set, scalar Float64 connections copied as they are, and a working C compiler."""
    if system.typed.active or system.transformed:
        return False
    for s in system.slaves:
        ne = s.native()
        if ne is None or not (ne.get_state and ne.set_state):
            return False
    try:
        library()
    except UserError:
        return False
    return True


class CompiledAdaptive:
    """Drop-in for :class:`cosim.master.algorithms.adaptive.AdaptiveStepper` whose accepted-step loop runs in C.
    It shares the stepper's setup (order, fresh inputs, options) and exposes the same ``t_ns``,
    ``stats``, ``calls``, ``slave_ns``, ``status`` and ``message``; :meth:`run` replaces the
    Python loop of :class:`cosim.master.algorithms.adaptive.VariableStepper` one block at a time."""

    def __init__(self, stepper, timing: bool = True):
        self.py = stepper  # the Python stepper: its setup, statistics and messages
        sysm, opt = stepper.system, stepper.opt
        self.lib = library()
        n = len(sysm.slaves)
        self.arr = (CAdaptSlave * n)()
        self.states = (c_void_p * n)()  # the FMU states, freed by close()
        self.entries = []
        self.keep: list = []
        for i, s in enumerate(sysm.slaves):
            ne = s.native()
            self.entries.append(ne)
            c = self.arr[i]
            n_in = len(sysm.in_vrs[i])
            c.fmi3, c.n_in, c.n_out = int(ne.fmi3), n_in, len(sysm.out_vrs[i])
            c.in_off, c.out_off = sysm.in_off[i], sysm.out_off[i]
            c.inst, c.do_step, c.get, c.set = ne.instance, ne.do_step, ne.get_real, ne.set_real
            c.get_state, c.set_state, c.bool_status = ne.get_state, ne.set_state, ne.get_boolean_status
            c.state = ctypes.addressof(self.states) + i * ctypes.sizeof(c_void_p)
            interp = bool(stepper.interp[i]) and n_in > 0
            c.interp, c.set_der = int(interp), ne.set_input_derivatives if interp else 0
            orders, fresh = np.ones(n_in, dtype=np.int32), stepper.fresh[i].astype(np.int8)
            cur = np.ascontiguousarray(sysm.v[sysm.in_src[i]], dtype=np.float64)
            prev, guess = cur.copy(), np.zeros(n_in)
            slope = stepper.slopes[i]
            self.keep += [orders, fresh, cur, prev, guess, slope, sysm.in_vrs[i], sysm.in_src[i], sysm.out_vrs[i]]
            if n_in:
                c.in_vr, c.in_src = sysm.in_vrs[i].ctypes.data, sysm.in_src[i].ctypes.data
                c.orders, c.fresh = orders.ctypes.data, fresh.ctypes.data
                c.cur, c.prev, c.slope, c.guess = (cur.ctypes.data, prev.ctypes.data, slope.ctypes.data,
                                                   guess.ctypes.data)
            if c.n_out:
                c.out_vr = sysm.out_vrs[i].ctypes.data
        self.order = np.array(stepper.order, dtype=np.int32)
        self.v_saved = np.empty_like(sysm.v)
        self.lo, self.hi = stepper.lo, stepper.hi
        self.ctl = ctl = CAdaptControl()
        ctl.t_ns, ctl.stop_ns, ctl.h, ctl.h_prev, ctl.err_prev = (stepper.t_ns, stepper.stop_ns, stepper.h,
                                                                   stepper.h_prev, stepper.err_prev)
        for name in ("rtol", "atol", "h_ref", "h_min", "h_max", "safety", "fac_min", "fac_max"):
            setattr(ctl, name, opt[name])
        ctl.k_i, ctl.k_p = stepper.k_i, stepper.k_p
        ctl.p_lin, ctl.p_hold = stepper.order_p_linear, stepper.order_p_hold
        ctl.any_interp, ctl.timing = int(any(stepper.interp)), int(timing)
        ctl.h_min_taken, ctl.h_max_taken = math.inf, 0.0
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
    def stats(self):
        st, c = self.py.stats, self.ctl
        st.accepted, st.rejected, st.rollbacks, st.discards = c.accepted, c.rejected, c.rollbacks, c.discards
        st.h_min_taken, st.h_max_taken = c.h_min_taken, c.h_max_taken
        return st

    @property
    def master_ns(self) -> int:
        """The master's own time in the compiled loop [ns] (outside the slaves' calls)."""
        return int(self.ctl.master_ns)

    @property
    def calls(self) -> list[int]:
        return [int(c.calls) for c in self.arr]

    @property
    def slave_ns(self) -> list[int]:
        return [int(c.ns) for c in self.arr]

    def run(self, rec: np.ndarray) -> int:
        """Accepted steps into ``rec`` (rows of time and the recorded values) until it is full,
        the stop time, the call's time budget or the end of the run; returns the rows written."""
        sysm, ctl = self.py.system, self.ctl
        if len(self.h_rec) < len(rec):
            self.h_rec = np.empty(len(rec), dtype=np.int64)
        rows = int(self.lib.rpr_adapt_run(
            self.arr, len(self.arr), self.order.ctypes.data, sysm.v.ctypes.data, len(sysm.v),
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

    def close(self) -> None:
        """Free the FMU states (before the instances are freed)."""
        for i, ne in enumerate(self.entries):
            if self.states[i] and ne.free_state:
                fn = ctypes.CFUNCTYPE(c_int32, c_void_p, POINTER(c_void_p))(ne.free_state)
                fn(ne.instance, ctypes.byref(c_void_p.from_address(ctypes.addressof(self.states) +
                                                                    i * ctypes.sizeof(c_void_p))))
                self.states[i] = None
