"""The compiled inner loop of the fixed-step master (Jacobi and Gauss-Seidel).

A small C function, compiled on demand with the system C compiler into the cache directory
(keyed by a hash of its source and the compiler; never committed), steps FMUs through their
``fmi2DoStep``/``fmi2GetReal``/``fmi2SetReal`` (or FMI 3.0 ``Float64``) entry points, which it
receives as function pointers.  It implements exactly the algorithms of :mod:`cosim.master`
(see there for the conventions); the Python loop is the reference it is tested against.

All values live in one float64 vector ``v`` owned by the master: each slave reads its bound
variables into ``v[out_off : out_off + n_out]`` and takes its connected inputs from
``v[in_src[j]]``, copied into ``v[in_off : in_off + n_in]`` before being set.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import sys
import tempfile
from ctypes import POINTER, c_int32, c_int64, c_void_p
from functools import lru_cache
from pathlib import Path

from ..errors import UserError
from ..slaves.crumb import C_SOURCE as CRUMB_SOURCE

#: Longest wall time of one call of the compiled loop [ns]; it returns to Python (where signals
#: are handled) at least this often.
CALL_BUDGET_NS = 250_000_000

#: The FMI entry points the compiled loops call (C function-pointer types), shared with
#: :mod:`cosim.master.adaptive_engine`.
FMI_CALL_TYPES = r"""
#include <stdint.h>
#include <stddef.h>
#include <stdbool.h>
#include <time.h>

typedef int (*step2_t)(void *, double, double, int);
typedef int (*io2_t)(void *, const uint32_t *, size_t, double *);
typedef int (*step3_t)(void *, double, double, bool, bool *, bool *, bool *, double *);
typedef int (*io3_t)(void *, const uint32_t *, size_t, double *, size_t);
typedef int (*der2_t)(void *, const uint32_t *, size_t, const int32_t *, const double *);
""" + CRUMB_SOURCE

SOURCE = FMI_CALL_TYPES + r"""

typedef struct {
    int32_t fmi3, n_in, n_out, in_off, out_off, interp;
    void *inst, *do_step, *get, *set;
    const uint32_t *in_vr;
    const int64_t *in_src;
    const uint32_t *out_vr;
    int64_t calls, ns;
    /* linear inputs (interp = 1): fmi2SetRealInputDerivatives, orders (all 1), per input whether
       it is interpolated (its source already stepped) or extrapolated, the source's previous
       value and the slope buffer */
    void *set_der;
    const int32_t *orders;
    const int8_t *fresh;
    double *hist, *slope;
    /* multirate (cosim.master.multirate): rate doSteps of sub_ns per macro step; base holds the input
       values pushed for the first sub-step (linear inputs) */
    int32_t rate;
    int64_t sub_ns;
    double *base;
} rpr_slave;

enum { ST_OK = 0, ST_WARNING = 1, ST_STOP = 100 };

static inline int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static inline int push(rpr_slave *s, double *v, double inv_h) {
    int j, st;
    double *in = v + s->in_off;
    if (!s->n_in) return 0;
    for (j = 0; j < s->n_in; ++j) in[j] = v[s->in_src[j]];
    if (s->fmi3) return FMI(s->inst, C_SET, ((io3_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in, (size_t)s->n_in));
    if (!s->interp) return FMI(s->inst, C_SET, ((io2_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in));
    for (j = 0; j < s->n_in; ++j) {
        double now = in[j];
        s->slope[j] = (now - s->hist[j]) * inv_h;
        if (s->fresh[j]) in[j] = s->hist[j];
        s->hist[j] = now;
    }
    st = FMI(s->inst, C_SET, ((io2_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in));
    if (st > ST_WARNING) return st;
    return FMI(s->inst, C_SET_DER, ((der2_t)s->set_der)(s->inst, s->in_vr, (size_t)s->n_in, s->orders, s->slope));
}

static inline int pull(rpr_slave *s, double *v) {
    if (!s->n_out) return 0;
    if (s->fmi3) return FMI(s->inst, C_GET, ((io3_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out, v + s->out_off, (size_t)s->n_out));
    return FMI(s->inst, C_GET, ((io2_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out, v + s->out_off));
}

static inline int step(rpr_slave *s, double t, double h) {
    s->calls++;
    if (s->fmi3) {
        bool ev = 0, term = 0, early = 0;
        double last = t;
        int st = FMI_T(s->inst, C_DO_STEP, t, ((step3_t)s->do_step)(s->inst, t, h, 1, &ev, &term, &early, &last));
        if (st <= ST_WARNING && term) return ST_STOP;
        return st;
    }
    return FMI_T(s->inst, C_DO_STEP, t, ((step2_t)s->do_step)(s->inst, t, h, 0));
}

/* one macro step from t_ns of a slave at rate > 1: sub-steps at the exact sub-instants, its
   inputs held or set on the macro step's line before every later sub-step (cosim.master.multirate) */
static inline int advance(rpr_slave *s, double *v, int64_t t_ns, double t, double h) {
    int32_t j, m;
    int st;
    double hs, *in;
    if (s->rate <= 1) return step(s, t, h);
    hs = (double)s->sub_ns / 1e9;
    in = v + s->in_off;
    if (s->interp) for (m = 0; m < s->n_in; ++m) s->base[m] = in[m];
    st = step(s, (double)t_ns / 1e9, hs);
    for (j = 1; j < s->rate; ++j) {
        if (st > ST_WARNING) return st;
        if (s->interp) {
            double tau = (double)(j * s->sub_ns) / 1e9;
            for (m = 0; m < s->n_in; ++m) in[m] = s->slope[m] * tau + s->base[m];
            st = FMI(s->inst, C_SET, ((io2_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in));
            if (st > ST_WARNING) return st;
            st = FMI(s->inst, C_SET_DER, ((der2_t)s->set_der)(s->inst, s->in_vr, (size_t)s->n_in, s->orders, s->slope));
            if (st > ST_WARNING) return st;
        }
        st = step(s, (double)(t_ns + j * s->sub_ns) / 1e9, hs);
    }
    return st;
}

#define CHECK(expr, who) do { int st_ = (expr); if (st_ > ST_WARNING) { *fail_slave = (who); \
    *fail_status = st_; goto out; } } while (0)
#define TICK(i) do { if (timing) { int64_t t_ = now_ns(); S[i].ns += t_ - tprev; tprev = t_; } } while (0)

/* Run up to nsteps macro steps from step index k0.  algorithm 0 = Jacobi, 1 = Gauss-Seidel
   (slaves in `order`).  After every `rec_every`-th step a row (t, v[rec_idx]...) is appended to
   rec.  Returns the number of steps completed; on a failure *fail_slave >= 0.  With
   budget_ns > 0 it also returns (early, no failure) once that much wall time has passed, so
   that Python can handle signals between calls. */
int64_t rpr_run(rpr_slave *S, int32_t n, const int32_t *order, int32_t algorithm, double *v,
                int64_t k0, int64_t nsteps, int64_t step_ns, int32_t timing,
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
        double t = (double)(k * step_ns) / 1e9;
        if (timing) tprev = now_ns();  /* time since the last slave call is the master's own */
        if (algorithm == 0) {
            for (i = 0; i < n; ++i) { CHECK(push(&S[i], v, inv_h), i); TICK(i); }
            for (i = 0; i < n; ++i) { CHECK(advance(&S[i], v, k * step_ns, t, h), i); TICK(i); }
            for (i = 0; i < n; ++i) { CHECK(pull(&S[i], v), i); TICK(i); }
        } else {
            for (c = 0; c < n; ++c) {
                i = order[c];
                CHECK(push(&S[i], v, inv_h), i);
                CHECK(advance(&S[i], v, k * step_ns, t, h), i);
                CHECK(pull(&S[i], v), i);
                TICK(i);
            }
        }
        ++done;
        if ((k + 1) % rec_every == 0) {
            double *row = rec + rows * (n_rec + 1);
            row[0] = (double)((k + 1) * step_ns) / 1e9;
            for (c = 0; c < n_rec; ++c) row[c + 1] = v[rec_idx[c]];
            ++rows;
        }
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
"""


class CSlave(ctypes.Structure):
    """Mirror of ``rpr_slave`` in :data:`SOURCE`."""

    _fields_ = [("fmi3", c_int32), ("n_in", c_int32), ("n_out", c_int32), ("in_off", c_int32),
                ("out_off", c_int32), ("interp", c_int32), ("inst", c_void_p), ("do_step", c_void_p),
                ("get", c_void_p), ("set", c_void_p), ("in_vr", c_void_p), ("in_src", c_void_p),
                ("out_vr", c_void_p), ("calls", c_int64), ("ns", c_int64), ("set_der", c_void_p),
                ("orders", c_void_p), ("fresh", c_void_p), ("hist", c_void_p), ("slope", c_void_p),
                ("rate", c_int32), ("sub_ns", c_int64), ("base", c_void_p)]


def _cache_dir() -> Path:
    from fmus.cache import cache_root

    return cache_root().parent / "master"


@lru_cache(maxsize=4)
def _compiler_version(cc: str) -> str:
    """``cc --version`` (asked once per process and compiler)."""
    try:
        return subprocess.run([cc, "--version"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise UserError(f"the compiled master loop needs a C compiler ({cc}: {exc}); "
                        f"set master.engine: python to use the Python loop") from None


def compile_library(source: str, stem: str) -> ctypes.CDLL:
    """Compile ``source`` (once per source and compiler, cached on disk as ``<stem>_<hash>.so``)
    and load it.  Raises :class:`UserError` when no C compiler works."""
    cc = os.environ.get("CC", "gcc")
    version = _compiler_version(cc)
    key = hashlib.sha256((source + version + sys.platform).encode()).hexdigest()[:20]
    from fmus.cache import writable_root

    root = _cache_dir()
    if not (root / f"{stem}_{key}.so").exists():
        fallback = writable_root(root)
        root = fallback if fallback == root else fallback / "master"
        root.mkdir(parents=True, exist_ok=True)
    lib = root / f"{stem}_{key}.so"
    if not lib.exists():
        with tempfile.TemporaryDirectory(dir=root) as tmp:
            src = Path(tmp) / "loop.c"
            src.write_text(source)
            out = Path(tmp) / lib.name
            res = subprocess.run([cc, "-O2", "-shared", "-fPIC", "-std=c99", "-D_POSIX_C_SOURCE=199309L",
                                  "-o", str(out), str(src), "-lm"], capture_output=True, text=True)
            if res.returncode != 0:
                raise UserError(f"compiling the master loop failed: {res.stderr.strip()[:500]}")
            os.replace(out, lib)
    return ctypes.CDLL(str(lib))


@lru_cache(maxsize=1)
def library() -> ctypes.CDLL:
    """Compile (once per source and compiler, cached on disk) and load the loop library.
    Raises :class:`UserError` when no C compiler works."""
    dll = compile_library(SOURCE, "rpr_loop")
    dll.rpr_set_crumb.argtypes = [c_void_p]
    fn = dll.rpr_run
    fn.restype = c_int64
    fn.argtypes = [POINTER(CSlave), c_int32, c_void_p, c_int32, c_void_p, c_int64, c_int64, c_int64, c_int32,
                   c_void_p, c_int32, c_int64, c_void_p, POINTER(c_int64), POINTER(c_int32), POINTER(c_int32),
                   POINTER(c_int64), c_int64]
    return dll


def available() -> bool:
    """True when the loop library can be built and loaded here."""
    try:
        library()
    except UserError:
        return False
    return True
