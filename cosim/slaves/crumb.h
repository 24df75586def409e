/* The breadcrumb's C side (cosim/slaves/crumb.py): FMI(key, call, expr) and
   FMI_T(key, call, t, expr) wrap an FMI call of a compiled loop; rpr_set_crumb points the
   library at the shared record.  rpr_crumb_t and the call numbers C_<CALL> come from the
   generated header (rpr_decls.h, declared once in crumb.py).  With -DRPR_NO_CRUMB the macros
   are the bare call (benchmarks/bench_supervise.py measures the difference). */
#ifndef RPR_CRUMB_H
#define RPR_CRUMB_H

#include <stdint.h>
#include "rpr_decls.h"

static rpr_crumb_t rpr_crumb_own;
static rpr_crumb_t *rpr_crumb = &rpr_crumb_own;

void rpr_set_crumb(void *p) { rpr_crumb = p ? (rpr_crumb_t *)p : &rpr_crumb_own; }

static inline int rpr_out(int st) { rpr_crumb->seq++; return st; }

#ifdef RPR_NO_CRUMB
#define FMI(key, c, expr) (expr)
#define FMI_T(key, c, tt, expr) (expr)
#else
#define FMI(key, c, expr) \
    (rpr_crumb->who = (int64_t)(intptr_t)(key), rpr_crumb->call = (c), rpr_crumb->seq++, rpr_out(expr))
#define FMI_T(key, c, tt, expr) (rpr_crumb->t = (tt), FMI(key, c, expr))
#endif

#endif
