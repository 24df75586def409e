/* Model-independent co-simulation core: see rpr_core.h for the conventions.
 *
 * The generated "rpr_model.h" supplies the sizes, defaults, bounds, names and the CasADi
 * functions (generated C, see fmus/codegen.py):
 *   RPR_F_STEP  (x, u, p, h, du) -> (x_next, ok, err)   one kernel call (models/integrators.py)
 *               or, with RPR_STEP_MEMORY (Radau keeping its factors, radau_memory_kernel):
 *               (x, u, p, h, du, F, hF, Zp, hZ) -> (x_next, ok, err, F_new, Z, info)
 *   RPR_F_OUT   (x, u, p) -> y
 *   RPR_F_START (p) -> x0
 *   RPR_F_JAC   (x, u, p) -> dense [dy/dx dy/du dy/dp]   (ny x (nx + nu + np), column-major)
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "rpr_core.h"
#include "rpr_model.h"

#define RPR_CAT2(a, b) a##b
#define RPR_CAT(a, b) RPR_CAT2(a, b)
#define RPR_MAX1(n) ((n) > 0 ? (n) : 1)

#ifndef RPR_EVENTS
#define RPR_EVENTS 0
#define RPR_NM 0
#endif
#define RPR_NV (1 + RPR_NP + RPR_NM + RPR_NX + RPR_NU + RPR_NY)
#define RPR_P0 1
#define RPR_M0 (RPR_P0 + RPR_NP)
#define RPR_X0 (RPR_M0 + RPR_NM)
#define RPR_U0 (RPR_X0 + RPR_NX)
#define RPR_Y0 (RPR_U0 + RPR_NU)
#define RPR_NJAC (RPR_NY * (RPR_NX + RPR_NU + RPR_NP + RPR_NM))

#define RPR_INTEGRATOR_NONE 0
#define RPR_INTEGRATOR_RK4 1
#define RPR_INTEGRATOR_RADAU 2
#define RPR_INTEGRATOR_DISCRETE 3
#define RPR_INTEGRATOR_EXACT 4

#ifndef RPR_STEP_MEMORY
#define RPR_STEP_MEMORY 0
#define RPR_NF 0
#endif

/* What a step kernel with memory keeps between calls: the factorised Newton matrix F (valid for
   the step hF; 0: none) and the last step's stage increments Z (taken with the step hZ). */
typedef struct {
    double hF, hZ;
    double F[RPR_MAX1(RPR_NF)];
    double Z[RPR_MAX1(RPR_STEP_MEMORY ? 3 * RPR_NX : 0)];
} RprMemory;

typedef long long rpr_int; /* casadi_int of the generated code */
typedef int (*rpr_casadi_fn)(const double **arg, double **res, rpr_int *iw, double *w, int mem);
typedef int (*rpr_casadi_work)(rpr_int *sz_arg, rpr_int *sz_res, rpr_int *sz_iw, rpr_int *sz_w);

#define RPR_DECLARE(f)                                                                       \
    int f(const double **arg, double **res, rpr_int *iw, double *w, int mem);                \
    int RPR_CAT(f, _work)(rpr_int * sz_arg, rpr_int * sz_res, rpr_int * sz_iw, rpr_int * sz_w);
RPR_DECLARE(RPR_F_STEP)
RPR_DECLARE(RPR_F_OUT)
RPR_DECLARE(RPR_F_START)
RPR_DECLARE(RPR_F_JAC)
#if RPR_EVENTS
RPR_DECLARE(RPR_F_IND)
RPR_DECLARE(RPR_F_UPD)
RPR_DECLARE(RPR_F_MSTART)
RPR_DECLARE(RPR_F_ODE)
RPR_DECLARE(RPR_F_ZDOT)
#define RPR_NWORK 9
#else
#define RPR_NWORK 4
#endif

/* Event bookkeeping (part of the FMU state): for each indicator the sign it had at the last
   accepted point (zref: -1, 0, +1; after an event, the side it crossed to) and its value there
   (zprev); for each sample the index k of its next instant offset + k period; counters. */
#if RPR_EVENTS
typedef struct {
    double zref[RPR_MAX1(RPR_NZ)], zprev[RPR_MAX1(RPR_NZ)];
    double zlast[RPR_MAX1(RPR_NZ)]; /* the indicators' actual values where the last step ended */
    long long next_k[RPR_MAX1(RPR_NS)];
    unsigned long long events, step_events;
    double last_event_time;
    int pending[RPR_MAX1(RPR_NZ + RPR_NS)], npending; /* event mode: located, update not yet applied */
} RprEvents;
#endif

static const char *const log_names[RPR_N_LOG] = {"logStatusError", "logStatusDiscard",
                                                 "logStatusWarning", "logNonlinearSystems",
                                                 "logCalls", "logEvents"};
static const char *const mode_names[] = {"instantiated", "initialization mode", "step mode",
                                         "terminated", "error", "event mode"};

/* A snapshot (FMU state) is this fixed-size record; serialising it is a byte copy. */
#define RPR_MAGIC 0x3153544155464d52ULL /* "RMFUATS1" */
typedef struct {
    unsigned long long magic;
    unsigned long long guid_hash;
    long long nv, nx, mode, y_valid;
    double v[RPR_NV];
    double du[RPR_MAX1(RPR_NU)];
    unsigned char x_set[RPR_MAX1(RPR_NX)];
    RprMemory memory;
#if RPR_EVENTS
    RprEvents ev;
#endif
} RprSnapshot;

struct RprInstance {
    char *name;
    RprLogger logger;
    void *env;
    int logging_on;
    unsigned log_mask;
    int mode;
    int y_valid;
    int discarded;
    double stop_time; /* +INFINITY unless the importer defined one */
    double v[RPR_NV];
    /* input slopes [unit/s] for the next doStep: u(t + tau) = u + du tau (0: held) */
    double du[RPR_MAX1(RPR_NU)];
    unsigned char x_set[RPR_MAX1(RPR_NX)];
    double xa[RPR_MAX1(RPR_NX)], xb[RPR_MAX1(RPR_NX)], x0[RPR_MAX1(RPR_NX)];
    double jac[RPR_MAX1(RPR_NJAC)];
    RprMemory memory;
    double F_new[RPR_MAX1(RPR_NF)], Z_new[RPR_MAX1(RPR_STEP_MEMORY ? 3 * RPR_NX : 0)], info[4];
    unsigned long long factorisations, iterations; /* Radau with memory: totals since instantiation */
#if RPR_EVENTS
    RprEvents ev;
    /* scratch of the event loop */
    double z[RPR_MAX1(RPR_NZ)], zt[RPR_MAX1(RPR_NZ)], xe[RPR_MAX1(RPR_NX)], xd[RPR_MAX1(RPR_NX)];
    double fa[RPR_MAX1(RPR_NX)], fb[RPR_MAX1(RPR_NX)], Zs[RPR_MAX1(3 * RPR_NX)], ut[RPR_MAX1(RPR_NU)];
    double m_new[RPR_MAX1(RPR_NM)], x_new[RPR_MAX1(RPR_NX)];
#endif
    int event_mode, early_return; /* FMI 3: eventModeUsed, and earlyReturnAllowed with it */
    const double **arg;
    double **res;
    rpr_int *iw;
    double *w;
};

/* ------------------------------------------------------------------------------------------ */
const char *rpr_guid(void) { return RPR_GUID; }
const char *rpr_model_identifier(void) { return RPR_MODEL_IDENTIFIER; }
const char *rpr_log_category_name(int k) { return (k >= 0 && k < RPR_N_LOG) ? log_names[k] : ""; }
int rpr_log_category_index(const char *name) {
    int k;
    for (k = 0; k < RPR_N_LOG; ++k)
        if (name && strcmp(name, log_names[k]) == 0) return k;
    return -1;
}
int rpr_mode(const RprInstance *c) { return c->mode; }
const char *rpr_name(const RprInstance *c) { return c->name; }
double rpr_time(const RprInstance *c) { return c->v[0]; }
int rpr_last_step_discarded(const RprInstance *c) { return c->discarded; }
size_t rpr_state_size(void) { return sizeof(RprSnapshot); }

static unsigned long long guid_hash(void) {
    const unsigned char *s = (const unsigned char *)RPR_GUID;
    unsigned long long h = 1469598103934665603ULL; /* FNV-1a */
    while (*s) { h ^= *s++; h *= 1099511628211ULL; }
    return h;
}

void rpr_log(RprInstance *c, int status, int category, const char *fmt, ...) {
    char buf[1024];
    char *p;
    va_list ap;
    if (!c || !c->logger) return;
    /* errors and discards are always reported; the rest only when asked for */
    if (status < RPR_DISCARD && !(c->logging_on && (c->log_mask & (1u << category)))) return;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    for (p = buf; *p; ++p)
        if (*p == '%') *p = '?'; /* the FMI 2 logger treats the message as a format string */
    c->logger(c->env, c->name, status, rpr_log_category_name(category), buf);
}

/* Log an error "<block>: <message>" and return RPR_ERROR. */
static int fail(RprInstance *c, const char *fmt, ...) {
    char msg[900];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    rpr_log(c, RPR_ERROR, RPR_LOG_ERROR, "%s: %s", RPR_BLOCK_NAME, msg);
    return RPR_ERROR;
}

static int call(RprInstance *c, rpr_casadi_fn f, const double *a0, const double *a1,
                const double *a2, const double *a3, double *r0, double *r1, double *r2) {
    c->arg[0] = a0; c->arg[1] = a1; c->arg[2] = a2; c->arg[3] = a3; c->arg[4] = c->du;
    c->res[0] = r0; c->res[1] = r1; c->res[2] = r2;
    return f(c->arg, c->res, c->iw, c->w, 0);
}

#if RPR_STEP_MEMORY
/* One call of the kernel with memory from xa into xb; keeps what it returns for the next call. */
static int call_step_memory(RprInstance *c, const double *xa, const double *u, double h, double *xb, double *ok,
                            double *err) {
    int status;
    RprMemory *m = &c->memory;
    c->arg[0] = xa; c->arg[1] = u; c->arg[2] = c->v + RPR_P0; c->arg[3] = &h;
    c->arg[4] = c->du; c->arg[5] = m->F; c->arg[6] = &m->hF; c->arg[7] = m->Z; c->arg[8] = &m->hZ;
    c->res[0] = xb; c->res[1] = ok; c->res[2] = err; c->res[3] = c->F_new; c->res[4] = c->Z_new; c->res[5] = c->info;
    status = ((rpr_casadi_fn)RPR_F_STEP)(c->arg, c->res, c->iw, c->w, 0);
    if (status) return status;
    if (c->info[0] == 1.0) memcpy(m->F, c->F_new, sizeof m->F);
    m->hF = c->info[1];
    c->factorisations += (unsigned long long)c->info[2];
    c->iterations += (unsigned long long)c->info[3];
    if (*ok == 1.0) {
        memcpy(m->Z, c->Z_new, sizeof m->Z);
        m->hZ = h;
    } else {
        m->hZ = 0.0; /* no prediction from a discarded step */
    }
    return 0;
}
#endif

#define P_(c) ((c)->v + RPR_P0)
#define X_(c) ((c)->v + RPR_X0)
#define U_(c) ((c)->v + RPR_U0)
#define Y_(c) ((c)->v + RPR_Y0)

static void set_defaults(RprInstance *c) {
    int i;
    memset(c->v, 0, sizeof c->v);
    memset(c->du, 0, sizeof c->du);
    for (i = 0; i < RPR_NP; ++i) c->v[RPR_P0 + i] = rpr_p_default[i];
    for (i = 0; i < RPR_NU; ++i) c->v[RPR_U0 + i] = rpr_u_start[i];
    memset(c->x_set, 0, sizeof c->x_set);
    c->y_valid = 0;
    c->discarded = 0;
    c->stop_time = INFINITY;
    memset(&c->memory, 0, sizeof c->memory);
}

/* Before the end of initialisation, modes follow mode_start(p) and states not set by the user
   follow start(p). */
static int refresh_start(RprInstance *c) {
    int i;
    if (c->mode >= RPR_MODE_STEP) return RPR_OK;
#if RPR_EVENTS && RPR_NM > 0
    if (call(c, (rpr_casadi_fn)RPR_F_MSTART, P_(c), 0, 0, 0, c->v + RPR_M0, 0, 0)) return RPR_ERROR;
#endif
    if (RPR_NX == 0) return RPR_OK;
    if (call(c, (rpr_casadi_fn)RPR_F_START, P_(c), 0, 0, 0, c->x0, 0, 0)) return RPR_ERROR;
    for (i = 0; i < RPR_NX; ++i)
        if (!c->x_set[i]) X_(c)[i] = c->x0[i];
    return RPR_OK;
}

static int update_outputs(RprInstance *c) {
    if (c->y_valid) return RPR_OK;
    if (refresh_start(c) != RPR_OK) return RPR_ERROR;
    if (RPR_NY && call(c, (rpr_casadi_fn)RPR_F_OUT, X_(c), U_(c), P_(c), 0, Y_(c), 0, 0))
        return RPR_ERROR;
    c->y_valid = 1;
    return RPR_OK;
}

/* ------------------------------------------------------------------------------------------ */
RprInstance *rpr_instantiate(const char *name, const char *token, RprLogger logger, void *env,
                             int logging_on) {
    RprInstance *c;
    rpr_int sa = 0, sr = 0, si = 0, sw = 0, a, r, iw, w;
    rpr_casadi_work works[RPR_NWORK];
    int k;
    works[0] = RPR_CAT(RPR_F_STEP, _work);
    works[1] = RPR_CAT(RPR_F_OUT, _work);
    works[2] = RPR_CAT(RPR_F_START, _work);
    works[3] = RPR_CAT(RPR_F_JAC, _work);
#if RPR_EVENTS
    works[4] = RPR_CAT(RPR_F_IND, _work);
    works[5] = RPR_CAT(RPR_F_UPD, _work);
    works[6] = RPR_CAT(RPR_F_MSTART, _work);
    works[7] = RPR_CAT(RPR_F_ODE, _work);
    works[8] = RPR_CAT(RPR_F_ZDOT, _work);
#endif
    c = (RprInstance *)calloc(1, sizeof(RprInstance));
    if (!c) return NULL;
    c->logger = logger;
    c->env = env;
    c->logging_on = logging_on;
    c->log_mask = ~0u;
    name = name ? name : "";
    c->name = (char *)malloc(strlen(name) + 1);
    if (!c->name) { free(c); return NULL; }
    strcpy(c->name, name);
    if (!token || strcmp(token, RPR_GUID) != 0) {
        rpr_log(c, RPR_ERROR, RPR_LOG_ERROR,
                "%s: instantiation token/GUID '%s' does not match this FMU's '%s'",
                RPR_BLOCK_NAME, token ? token : "(null)", RPR_GUID);
        free(c->name); free(c);
        return NULL;
    }
    for (k = 0; k < RPR_NWORK; ++k) {
        works[k](&a, &r, &iw, &w);
        if (a > sa) sa = a;
        if (r > sr) sr = r;
        if (iw > si) si = iw;
        if (w > sw) sw = w;
    }
    if (sa < 5) sa = 5;
    if (sr < 3) sr = 3;
    c->arg = (const double **)calloc((size_t)sa, sizeof(double *));
    c->res = (double **)calloc((size_t)sr, sizeof(double *));
    c->iw = (rpr_int *)calloc((size_t)(si > 0 ? si : 1), sizeof(rpr_int));
    c->w = (double *)calloc((size_t)(sw > 0 ? sw : 1), sizeof(double));
    if (!c->arg || !c->res || !c->iw || !c->w) { rpr_free(c); return NULL; }
    c->mode = RPR_MODE_INSTANTIATED;
    set_defaults(c);
    rpr_log(c, RPR_OK, RPR_LOG_CALLS, "instantiated %s (%s)", RPR_MODEL_IDENTIFIER, RPR_GUID);
    return c;
}

void rpr_free(RprInstance *c) {
    if (!c) return;
    free(c->arg); free(c->res); free(c->iw); free(c->w); free(c->name);
    free(c);
}

int rpr_set_debug_logging(RprInstance *c, int on, size_t n, const char *const categories[]) {
    size_t i;
    unsigned mask = 0;
    if (n == 0) mask = ~0u;
    for (i = 0; i < n; ++i) {
        int k = rpr_log_category_index(categories[i]);
        if (categories[i] && strcmp(categories[i], "logAll") == 0) { mask = ~0u; continue; }
        if (k < 0) {
            rpr_log(c, RPR_ERROR, RPR_LOG_ERROR, "%s: unknown log category '%s'", RPR_BLOCK_NAME,
                    categories[i] ? categories[i] : "(null)");
            return RPR_ERROR;
        }
        mask |= 1u << k;
    }
    c->logging_on = on;
    c->log_mask = mask;
    return RPR_OK;
}

static int require_mode(RprInstance *c, const char *fn, int ok_mask) {
    if (ok_mask & (1 << c->mode)) return RPR_OK;
    rpr_log(c, RPR_ERROR, RPR_LOG_ERROR, "%s: %s is not allowed in %s", RPR_BLOCK_NAME, fn,
            mode_names[c->mode]);
    return RPR_ERROR;
}
#define M_INST (1 << RPR_MODE_INSTANTIATED)
#define M_INIT (1 << RPR_MODE_INIT)
#define M_STEP (1 << RPR_MODE_STEP)
#define M_TERM (1 << RPR_MODE_TERMINATED)
#define M_ERR (1 << RPR_MODE_ERROR)
#define M_EVENT (1 << RPR_MODE_EVENT)

int rpr_setup(RprInstance *c, double start_time, int stop_defined, double stop_time) {
    if (require_mode(c, "setup", M_INST)) return RPR_ERROR;
    if (!isfinite(start_time)) return fail(c, "the start time %g is not finite", start_time);
    if (stop_defined && !(stop_time >= start_time))
        return fail(c, "the stop time %.17g is before the start time %.17g", stop_time, start_time);
    c->v[0] = start_time;
    c->stop_time = stop_defined ? stop_time : INFINITY;
    return RPR_OK;
}

/* a and b are the same instant (RPR_TIME_TOL absolute, or relative for large times) */
static int same_time(double a, double b) {
    double m = fabs(a) > fabs(b) ? fabs(a) : fabs(b);
    return fabs(a - b) <= RPR_TIME_TOL * (m > 1.0 ? m : 1.0);
}

/* ------------------------------------------------------------------------------------------ */
#if RPR_EVENTS
/* Events (docs/explanation/events.md): after each internal step the indicators are evaluated; a
   sign change in an indicator's direction is located on the step's dense output by the Illinois
   method, the step is retaken to the event time, the update applied (an event iteration while
   updates fire further indicators), and integration restarts there.  Time events cut the
   internal steps at their instants. */

static double sgn(double z) { return z > 0 ? 1.0 : (z < 0 ? -1.0 : 0.0); }

/* whether an indicator of direction d fires going from sign s to value z */
static int fires(int d, double s, double z) {
    return (d >= 0 && s < 0 && z >= 0) || (d <= 0 && s > 0 && z <= 0);
}

static double event_tol(double t) { return RPR_EVENT_TOL_ABS + RPR_EVENT_TOL_REL * fabs(t); }
/* the look-ahead after an event: an indicator left at zero by it takes the side it moves to */
static double look_ahead(double t) { return 1000.0 * event_tol(t); }

/* inputs at tau into the communication step: u + du tau */
static void inputs_at(const RprInstance *c, double tau, double *u) {
    int k;
    for (k = 0; k < RPR_NU; ++k) u[k] = U_(c)[k] + c->du[k] * tau;
}

static int eval_z(RprInstance *c, double t, const double *x, const double *u, double *z) {
    if (RPR_NZ == 0) return 0;
    c->arg[0] = &t; c->arg[1] = x; c->arg[2] = u; c->arg[3] = P_(c);
    c->res[0] = z;
    return ((rpr_casadi_fn)RPR_F_IND)(c->arg, c->res, c->iw, c->w, 0);
}

static int eval_zdot(RprInstance *c, double t, const double *x, const double *u, double *zd) {
    if (RPR_NZ == 0) return 0;
    c->arg[0] = &t; c->arg[1] = x; c->arg[2] = u; c->arg[3] = c->du; c->arg[4] = P_(c);
    c->res[0] = zd;
    return ((rpr_casadi_fn)RPR_F_ZDOT)(c->arg, c->res, c->iw, c->w, 0);
}

static int eval_f(RprInstance *c, const double *x, const double *u, double *f) {
    if (RPR_NX == 0) return 0;
    c->arg[0] = x; c->arg[1] = u; c->arg[2] = P_(c);
    c->res[0] = f;
    return ((rpr_casadi_fn)RPR_F_ODE)(c->arg, c->res, c->iw, c->w, 0);
}

/* event k's update (k < nz: indicator k; nz + j: sample j) of x and of the modes in place */
static int apply_update(RprInstance *c, int k, double t, double *x, const double *u) {
    double kk = (double)k;
    c->arg[0] = &kk; c->arg[1] = &t; c->arg[2] = x; c->arg[3] = u; c->arg[4] = P_(c);
    c->res[0] = c->x_new; c->res[1] = c->m_new;
    if (((rpr_casadi_fn)RPR_F_UPD)(c->arg, c->res, c->iw, c->w, 0)) return 1;
    memcpy(x, c->x_new, sizeof(double) * RPR_NX);
    memcpy(c->v + RPR_M0, c->m_new, sizeof(double) * RPR_NM);
    return 0;
}

/* one internal step of length dt from x (inputs u at its start, slopes du) into xn; 0 when taken */
static int internal_step(RprInstance *c, const double *x, const double *u, double dt, double *xn, double *err) {
    double ok = 1.0;
    *err = 0.0;
    if (RPR_NX == 0) return 0;
#if RPR_STEP_MEMORY
    if (call_step_memory(c, x, u, dt, xn, &ok, err)) return 1;
#else
    if (call(c, (rpr_casadi_fn)RPR_F_STEP, x, u, P_(c), &dt, xn, &ok, err)) return 1;
#endif
    return ok == 1.0 ? 0 : 1;
}

/* the dense output of the internal step xa -> xb of length dt at s in [0, dt]: Radau IIA's
   collocation polynomial (stage increments Zs), else the cubic Hermite interpolant (slopes fa, fb) */
static void dense(const RprInstance *c, const double *xa, const double *xb, double dt, double s, double *x) {
    int i;
    double th = dt > 0 ? s / dt : 1.0;
#if RPR_INTEGRATOR == RPR_INTEGRATOR_RADAU
    static const double cn[3] = {0.15505102572168219, 0.64494897427831781, 1.0}; /* (4 -+ sqrt 6)/10, 1 */
    double l[3];
    int a, b;
    (void)xb;
    for (a = 0; a < 3; ++a) {
        double num = th, den = cn[a];
        for (b = 0; b < 3; ++b)
            if (b != a) { num *= th - cn[b]; den *= cn[a] - cn[b]; }
        l[a] = num / den;
    }
    for (i = 0; i < RPR_NX; ++i)
        x[i] = xa[i] + l[0] * c->Zs[i] + l[1] * c->Zs[RPR_NX + i] + l[2] * c->Zs[2 * RPR_NX + i];
#else
    double h00 = (1 + 2 * th) * (1 - th) * (1 - th), h10 = th * (1 - th) * (1 - th);
    double h01 = th * th * (3 - 2 * th), h11 = th * th * (th - 1);
    for (i = 0; i < RPR_NX; ++i)
        x[i] = h00 * xa[i] + h10 * dt * c->fa[i] + h01 * xb[i] + h11 * dt * c->fb[i];
#endif
}

/* indicator i at s into the internal step starting at tau (time t + tau) */
static int z_dense(RprInstance *c, int i, double t, double tau, const double *xa, const double *xb, double dt,
                   double s, double *zi) {
    dense(c, xa, xb, dt, s, c->xd);
    inputs_at(c, tau + s, c->ut);
    if (eval_z(c, t + tau + s, c->xd, c->ut, c->zt)) return 1;
    *zi = c->zt[i];
    return 0;
}

/* The crossing of indicator i inside the internal step [tau, tau + dt] (za strictly on the side it
   leaves, zb on the other): Illinois on the dense output until the bracket is below tol; returns
   the bracket's right end (the indicator has crossed there), in [0, dt]. */
static int locate(RprInstance *c, int i, double t, double tau, const double *xa, const double *xb, double dt,
                  double za, double zb, double tol, double *where) {
    double a = 0.0, b = dt, ga = za, gb = zb, before = sgn(za), s, gs, a0 = look_ahead(t + tau);
    int side = 0, it;
    /* za may be a look-ahead value (the step starts at an event): bracket from a0 if z is on the
       side it leaves there, so that the noise of an indicator left at zero is not taken for a root */
    if (a0 > 0.25 * dt) a0 = 0.25 * dt;
    if (z_dense(c, i, t, tau, xa, xb, dt, a0, &gs)) return 1;
    if (gs * before > 0) { a = a0; ga = gs; }
    else { b = a0; gb = gs; }
    for (it = 0; it < 200 && b - a > tol; ++it) {
        s = (gb != ga) ? (a * gb - b * ga) / (gb - ga) : 0.5 * (a + b);
        if (!(s > a && s < b)) s = 0.5 * (a + b);
        if (s - a < 0.25 * tol) s = a + 0.25 * tol; /* step across the root once the bracket is small */
        if (b - s < 0.25 * tol) s = b - 0.25 * tol;
        if (z_dense(c, i, t, tau, xa, xb, dt, s, &gs)) return 1;
        if (gs * before > 0) {
            a = s; ga = gs;
            if (side == -1) gb *= 0.5; /* Illinois: halve the stale end */
            side = -1;
        } else {
            b = s; gb = gs;
            if (side == 1) ga *= 0.5;
            side = 1;
            if (gs == 0.0) break;
        }
    }
    *where = b;
    return 0;
}

static double sample_time(int j, long long k) { return rpr_sample_offset[j] + (double)k * rpr_sample_period[j]; }

static double next_sample_time(const RprInstance *c) {
    double best = INFINITY;
    int j;
    for (j = 0; j < RPR_NS; ++j) {
        double ts = sample_time(j, c->ev.next_k[j]);
        if (ts < best) best = ts;
    }
    return best;
}

static void event_names_of(const int *fired, int nf, char *buf, size_t size) {
    int j;
    size_t used = 0;
    buf[0] = '\0';
    for (j = 0; j < nf && used + 2 < size; ++j)
        used += (size_t)snprintf(buf + used, size - used, "%s'%s'", j ? ", " : "", rpr_event_names[fired[j]]);
}

/* The event iteration at te: apply the updates of fired[0..nf) in order, re-evaluate the
   indicators, repeat with those the updates made fire (in their direction, against the values
   before the round), at most RPR_EVENT_MAX_ROUNDS rounds.  c->z holds the indicators at (te, x)
   on entry and on exit; the reference signs follow them. */
static int event_iteration(RprInstance *c, double te, double *x, const double *u, int *fired, int nf) {
    int rounds = 0, j, i;
    char names[300];
    unsigned char own[RPR_MAX1(RPR_NZ)]; /* the indicators that fired in this iteration */
    memset(own, 0, sizeof own);
    while (nf > 0) {
        if (++rounds > RPR_EVENT_MAX_ROUNDS) {
            event_names_of(fired, nf, names, sizeof names);
            return fail(c, "event iteration at t=%.17g s did not end after %d rounds: %s keep firing",
                        te, RPR_EVENT_MAX_ROUNDS, names);
        }
        for (j = 0; j < nf; ++j) {
            if (fired[j] < RPR_NZ) own[fired[j]] = 1;
            if (apply_update(c, fired[j], te, x, u)) return fail(c, "the update of event '%s' failed at t=%.17g s",
                                                                 rpr_event_names[fired[j]], te);
            c->ev.events++;
            c->ev.step_events++;
            rpr_log(c, RPR_OK, RPR_LOG_EVENTS, "event '%s' at t=%.17g s (round %d)", rpr_event_names[fired[j]],
                    te, rounds);
        }
        for (i = 0; i < RPR_NX; ++i)
            if (!isfinite(x[i])) return fail(c, "an event update at t=%.17g s made state '%s' non-finite", te,
                                             rpr_names[RPR_X0 + i]);
        if (c->ev.step_events > RPR_EVENT_MAX_PER_STEP) {
            event_names_of(fired, nf, names, sizeof names);
            return fail(c, "chattering: more than %d events in one communication step (the last at t=%.17g s, %s; "
                           "events at ever shorter intervals, a Zeno sequence, or an update that does not clear "
                           "its indicator)", RPR_EVENT_MAX_PER_STEP, te, names);
        }
        memcpy(c->zt, c->z, sizeof c->z);
        if (eval_z(c, te, x, u, c->z)) return fail(c, "the event indicators failed at t=%.17g s", te);
        nf = 0;
        for (i = 0; i < RPR_NZ; ++i)
            if (fires(rpr_direction[i], sgn(c->zt[i]), c->z[i])) fired[nf++] = i;
    }
    /* each indicator's side just after the event: one that fired, or one left exactly at zero,
       takes the side it moves to (its value a look-ahead later, to first order); any other keeps
       its own side, so one a rounding short of its threshold at the event (x = 1 - 2e-16 at a
       sample instant) is located when it crosses, not taken as crossed already (its crossing was
       lost) */
    if (eval_zdot(c, te, x, u, c->zt)) return fail(c, "the event indicators' rates failed at t=%.17g s", te);
    for (i = 0; i < RPR_NZ; ++i) {
        double zl = (own[i] || c->z[i] == 0.0) ? c->z[i] + c->zt[i] * look_ahead(te) : c->z[i];
        c->ev.zref[i] = sgn(zl);
        c->ev.zprev[i] = zl;
        c->ev.zlast[i] = c->z[i];
    }
    memset(&c->memory, 0, sizeof c->memory); /* Radau restarts afresh after the jump */
    c->ev.last_event_time = te;
    return RPR_OK;
}

/* samples due at tnow (within the communication-point tolerance) fire, in index order */
static int take_samples(RprInstance *c, double tnow, double *x, const double *u) {
    int fired[RPR_MAX1(RPR_NZ + RPR_NS)], nf = 0, j;
    for (j = 0; j < RPR_NS; ++j) {
        double ts = sample_time(j, c->ev.next_k[j]);
        if (ts <= tnow || same_time(ts, tnow)) {
            fired[nf++] = RPR_NZ + j;
            c->ev.next_k[j]++;
            while (sample_time(j, c->ev.next_k[j]) <= tnow) c->ev.next_k[j]++; /* a sample skipped is not replayed */
        }
    }
    if (nf == 0) return RPR_OK;
    if (eval_z(c, tnow, x, u, c->z)) return fail(c, "the event indicators failed at t=%.17g s", tnow);
    return event_iteration(c, tnow, x, u, fired, nf);
}

/* event mode with early return: the samples due at tnow become the pending event */
static void pend_samples(RprInstance *c, double tnow) {
    int j;
    c->ev.npending = 0;
    for (j = 0; j < RPR_NS; ++j) {
        double ts = sample_time(j, c->ev.next_k[j]);
        if (ts <= tnow || same_time(ts, tnow)) {
            c->ev.pending[c->ev.npending++] = RPR_NZ + j;
            c->ev.next_k[j]++;
        }
    }
}

/* at the end of initialisation: indicator signs, the first sample instants, the samples at t0 */
static int events_start(RprInstance *c) {
    int i, j, nf = 0, fired[RPR_MAX1(RPR_NZ)];
    double t0 = c->v[0];
    for (j = 0; j < RPR_NS; ++j) {
        double k = ceil((t0 - rpr_sample_offset[j]) / rpr_sample_period[j]);
        c->ev.next_k[j] = k > 0 ? (long long)k : 0;
        if (c->ev.next_k[j] > 0 && same_time(sample_time(j, c->ev.next_k[j] - 1), t0)) c->ev.next_k[j]--;
    }
    c->ev.events = c->ev.step_events = 0;
    c->ev.last_event_time = -INFINITY;
    if (eval_z(c, t0, X_(c), U_(c), c->z)) return fail(c, "the event indicators failed at the start time");
    /* a directed indicator strictly across its direction at the start fires there */
    for (i = 0; i < RPR_NZ; ++i) {
        int across = rpr_direction[i] * c->z[i] > 0;
        c->ev.zref[i] = across ? -sgn(c->z[i]) : sgn(c->z[i]);
        c->ev.zprev[i] = c->ev.zlast[i] = c->z[i];
        if (across) fired[nf++] = i;
    }
    memcpy(c->xa, X_(c), sizeof(double) * RPR_NX);
    if (nf && event_iteration(c, t0, c->xa, U_(c), fired, nf) != RPR_OK) return RPR_ERROR;
    if (take_samples(c, t0, c->xa, U_(c)) != RPR_OK) return RPR_ERROR;
    memcpy(X_(c), c->xa, sizeof(double) * RPR_NX);
    return RPR_OK;
}

/* doStep of a block with events: internal steps of h / substeps (cut at sample instants), each
   checked for crossings, located, updated, restarted (see the comment above sgn). */
static int events_do_step(RprInstance *c, double t, double h) {
    double tau = 0.0, hs = RPR_NX ? h / RPR_SUBSTEPS : h, err = 0.0, *xa = c->xa, *xb = c->xb, *tmp;
    double ua[RPR_MAX1(RPR_NU)], ub[RPR_MAX1(RPR_NU)];
    double m_entry[RPR_MAX1(RPR_NM)];
    RprEvents ev_entry = c->ev;
    int fired[RPR_MAX1(RPR_NZ + RPR_NS)], nf, i, k, status = RPR_OK;
    double s_at[RPR_MAX1(RPR_NZ)], z_at_e[RPR_MAX1(RPR_NZ)], before[RPR_MAX1(RPR_NZ)];
    memcpy(m_entry, c->v + RPR_M0, sizeof(double) * RPR_NM);
    memcpy(xa, X_(c), sizeof(double) * RPR_NX);
    c->ev.step_events = 0;
    inputs_at(c, 0.0, ua);
    if (c->ev.npending) { /* an early return the importer did not handle in event mode: handle it now */
        int n = c->ev.npending;
        memcpy(fired, c->ev.pending, sizeof(int) * (size_t)n);
        c->ev.npending = 0;
        status = eval_z(c, t, xa, ua, c->z) ? fail(c, "the event indicators failed at t=%.17g s", t)
                                            : event_iteration(c, t, xa, ua, fired, n);
    }
    if (status == RPR_OK) status = take_samples(c, t, xa, ua);
    if (status == RPR_OK && RPR_NZ > 0) { /* inputs set at the communication point may fire an indicator there */
        if (eval_z(c, t, xa, ua, c->z)) status = fail(c, "the event indicators failed at t=%.17g s", t);
        nf = 0;
        /* only an indicator the new inputs (or parameters) changed: the others keep their look-ahead side */
        for (i = 0; status == RPR_OK && i < RPR_NZ; ++i)
            if (c->z[i] != c->ev.zlast[i] && fires(rpr_direction[i], c->ev.zref[i], c->z[i]) &&
                fires(rpr_direction[i], sgn(c->ev.zprev[i]), c->z[i]))
                fired[nf++] = i;
        if (status == RPR_OK && nf) status = event_iteration(c, t, xa, ua, fired, nf);
        else if (status == RPR_OK)
            for (i = 0; i < RPR_NZ; ++i)
                if (c->z[i] != c->ev.zlast[i]) { c->ev.zref[i] = sgn(c->z[i]); c->ev.zprev[i] = c->ev.zlast[i] = c->z[i]; }
    }
    while (status == RPR_OK && tau < h) {
        double dt = h - tau, ts = next_sample_time(c), best;
        int cut = 0, slopes = 0;
        if (hs < dt && dt - hs > 1e-9 * hs) dt = hs; /* no sliver before the communication point */
        if (ts - t - tau < dt && !same_time(ts, t + h)) { dt = ts - t - tau; cut = 1; }
        if (!(dt > 0)) dt = 0.0;
        inputs_at(c, tau, ua);
        if (internal_step(c, xa, ua, dt, xb, &err)) { status = RPR_DISCARD; break; }
#if RPR_STEP_MEMORY
        memcpy(c->Zs, c->Z_new, sizeof(double) * 3 * RPR_NX);
#endif
        inputs_at(c, tau + dt, ub);
        if (eval_z(c, t + tau + dt, xb, ub, c->z)) { status = fail(c, "the event indicators failed at t=%.17g s", t + tau + dt); break; }
        nf = 0;
        for (i = 0; i < RPR_NZ; ++i)
            if (fires(rpr_direction[i], c->ev.zref[i], c->z[i]) && fires(rpr_direction[i], sgn(c->ev.zprev[i]), c->z[i]))
                fired[nf++] = i;
        if (nf == 0) { /* no crossing: accept the internal step */
            tmp = xa; xa = xb; xb = tmp;
            tau = cut ? ts - t : tau + dt;
            for (i = 0; i < RPR_NZ; ++i) { c->ev.zref[i] = sgn(c->z[i]); c->ev.zprev[i] = c->ev.zlast[i] = c->z[i]; }
            if (cut && c->early_return) { pend_samples(c, t + tau); break; }
            if (cut) status = take_samples(c, t + tau, xa, ub);
            continue;
        }
        /* locate each crossing; the earliest (and those within the tolerance of it) fire */
        if (!slopes) {
#if RPR_INTEGRATOR != RPR_INTEGRATOR_RADAU
            if (eval_f(c, xa, ua, c->fa) || eval_f(c, xb, ub, c->fb)) { status = fail(c, "the ode failed"); break; }
#endif
            slopes = 1;
        }
        memcpy(z_at_e, c->z, sizeof c->z); /* (values at the step's end, reused below as scratch) */
        best = dt;
        for (k = 0; k < nf; ++k) {
            i = fired[k];
            before[i] = sgn(c->ev.zprev[i]);
            if (locate(c, i, t, tau, xa, xb, dt, c->ev.zprev[i], z_at_e[i], event_tol(t + tau), &s_at[i])) {
                status = fail(c, "the event indicators failed while locating '%s'", rpr_event_names[i]);
                break;
            }
            if (s_at[i] < best) best = s_at[i];
        }
        if (status != RPR_OK) break;
        {   /* the state at the event from the integrator itself, on the far side of each firing indicator:
               at the located time where the integrator agrees with the dense output; else (the dense
               output's error, e.g. one long exact or Radau step) the bracket from there to dt (across:
               the step fired there) is found by doubling steps and narrowed by bisection on the
               integrator's own state, so the update never applies on the near side (it would fire again) */
            double s = best, lo = 0.0, hi = dt, tol = event_tol(t + tau), nudge = tol;
            int tries, far = 0, across = 0, n2 = 0;
            for (k = 0; k < nf; ++k)
                if (s_at[fired[k]] <= best + tol) fired[n2++] = fired[k];
            nf = n2;
            for (tries = 0; tries < 300; ++tries) {
                if (s >= dt) { memcpy(c->xe, xb, sizeof(double) * RPR_NX); s = dt; }
                else if (internal_step(c, xa, ua, s, c->xe, &err)) { status = RPR_DISCARD; break; }
                inputs_at(c, tau + s, ub);
                if (eval_z(c, t + tau + s, c->xe, ub, c->z)) { status = fail(c, "the event indicators failed"); break; }
                far = 1;
                for (k = 0; k < nf; ++k)
                    if (c->z[fired[k]] * before[fired[k]] > 0) far = 0;
                if (far) { hi = s; across = 1; } else lo = s;
                if (far && (tries == 0 || hi - lo <= tol)) break;
                if (across && hi - lo <= tol) s = hi; /* the bracket is closed: back to its far end's state */
                else if (!across) { s = lo + nudge; nudge *= 2.0; }
                else s = 0.5 * (lo + hi);
            }
            if (status != RPR_OK) break;
            tau += s;
            memcpy(xa, c->xe, sizeof(double) * RPR_NX);
        }
        if (c->early_return) { /* stop at the event's left limit: the importer applies it in event mode */
            memcpy(c->ev.pending, fired, sizeof(int) * (size_t)nf);
            c->ev.npending = nf;
            for (i = 0; i < RPR_NZ; ++i) { c->ev.zref[i] = sgn(c->z[i]); c->ev.zprev[i] = c->ev.zlast[i] = c->z[i]; }
            break;
        }
        status = event_iteration(c, t + tau, xa, ub, fired, nf);
        if (status == RPR_OK && next_sample_time(c) <= t + tau) status = take_samples(c, t + tau, xa, ub);
    }
    if (status != RPR_OK) { /* the step is not taken: back to its start */
        memcpy(c->v + RPR_M0, m_entry, sizeof(double) * RPR_NM);
        c->ev = ev_entry;
        memset(&c->memory, 0, sizeof c->memory);
        c->y_valid = 0;
        if (status == RPR_DISCARD) {
            c->discarded = 1;
            rpr_log(c, RPR_DISCARD, RPR_LOG_DISCARD,
                    "%s: doStep(t=%.17g, h=%.17g) discarded: an internal step failed (non-finite state or Radau "
                    "Newton residual/tolerance %.3g); state kept at t=%.17g, retry with a smaller step",
                    RPR_BLOCK_NAME, t, h, err, t);
        }
        return status;
    }
    if (tau > h || !c->ev.npending) tau = h;
    if (c->early_return && !c->ev.npending && same_time(next_sample_time(c), t + h)) pend_samples(c, t + h);
    memcpy(X_(c), xa, sizeof(double) * RPR_NX);
    for (k = 0; k < RPR_NU; ++k) { U_(c)[k] += c->du[k] * tau; c->du[k] = 0.0; }
    if (c->ev.step_events)
        rpr_log(c, RPR_OK, RPR_LOG_EVENTS, "doStep(t=%.17g, h=%.17g): %llu events (%llu since the start)", t, h,
                c->ev.step_events, c->ev.events);
    if (c->ev.npending)
        rpr_log(c, RPR_OK, RPR_LOG_EVENTS, "doStep(t=%.17g, h=%.17g): returns at the event at t=%.17g s (%s)", t, h,
                t + tau, rpr_event_names[c->ev.pending[0]]);
    c->v[0] = tau == h ? t + h : t + tau;
    c->y_valid = 0;
    return RPR_OK;
}
#endif

int rpr_enter_init(RprInstance *c) {
    if (require_mode(c, "enterInitializationMode", M_INST)) return RPR_ERROR;
    c->mode = RPR_MODE_INIT;
    return RPR_OK;
}

int rpr_exit_init(RprInstance *c) {
    int i;
    if (require_mode(c, "exitInitializationMode", M_INIT)) return RPR_ERROR;
    if (refresh_start(c) != RPR_OK) return fail(c, "the start-value function failed");
    for (i = 0; i < RPR_NX; ++i)
        if (!isfinite(X_(c)[i]))
            return fail(c, "start value of state '%s' is not finite (%g)", rpr_names[RPR_X0 + i],
                        X_(c)[i]);
    c->mode = c->event_mode ? RPR_MODE_EVENT : RPR_MODE_STEP;
    c->y_valid = 0;
#if RPR_EVENTS
    if (events_start(c) != RPR_OK) return RPR_ERROR;
#endif
    if (update_outputs(c) != RPR_OK) return fail(c, "the output function failed");
    return RPR_OK;
}

int rpr_terminate(RprInstance *c) {
    if (require_mode(c, "terminate", M_STEP | M_INIT | M_EVENT)) return RPR_ERROR;
    c->mode = RPR_MODE_TERMINATED;
    return RPR_OK;
}

int rpr_reset(RprInstance *c) {
    c->mode = RPR_MODE_INSTANTIATED;
    set_defaults(c);
    return RPR_OK;
}

/* ------------------------------------------------------------------------------------------ */
int rpr_get_real(RprInstance *c, const unsigned int vr[], size_t n, double value[]) {
    size_t i;
    if (n == 0) return RPR_OK;
    if (require_mode(c, "getReal/getFloat64", M_INST | M_INIT | M_STEP | M_TERM | M_ERR | M_EVENT))
        return RPR_ERROR;
    for (i = 0; i < n; ++i) {
        if (vr[i] >= RPR_NV) return fail(c, "getReal: value reference %u does not exist", vr[i]);
        if (vr[i] >= RPR_Y0) { if (update_outputs(c) != RPR_OK) return fail(c, "the output function failed"); }
        else if (vr[i] >= RPR_M0 && vr[i] < RPR_U0) refresh_start(c);
        value[i] = c->v[vr[i]];
    }
    return RPR_OK;
}

int rpr_set_real(RprInstance *c, const unsigned int vr[], size_t n, const double value[]) {
    size_t i;
    if (n == 0) return RPR_OK;
    if (require_mode(c, "setReal/setFloat64", M_INST | M_INIT | M_STEP | M_EVENT)) return RPR_ERROR;
    for (i = 0; i < n; ++i) {
        unsigned int r = vr[i];
        double x = value[i];
        if (r >= RPR_NV) return fail(c, "setReal: value reference %u does not exist", r);
        if (r == 0) return fail(c, "'time' cannot be set");
        if (r >= RPR_Y0) return fail(c, "output '%s' cannot be set (value %g)", rpr_names[r], x);
        if (!isfinite(x)) return fail(c, "'%s' cannot be set to the non-finite value %g", rpr_names[r], x);
        if (r >= RPR_M0 && r < RPR_X0)
            return fail(c, "mode '%s' is a discrete state the FMU computes (from its parameters, then at "
                           "events): it cannot be set (value %g)", rpr_names[r], x);
        if (r < RPR_X0) { /* parameter */
            if (c->mode >= RPR_MODE_STEP && !rpr_tunable[r - RPR_P0])
                return fail(c, "parameter '%s' is fixed: set it before the end of initialization (value %g)",
                            rpr_names[r], x);
            if (x < rpr_min[r] || x > rpr_max[r])
                return fail(c, "parameter '%s' = %.17g is outside [%.17g, %.17g]", rpr_names[r], x,
                            rpr_min[r], rpr_max[r]);
        } else if (r < RPR_U0) { /* state */
            if (c->mode >= RPR_MODE_STEP)
                return fail(c, "state '%s' can only be set before the end of initialization (value %g); "
                               "use an FMU state to restore a step", rpr_names[r], x);
            if (!rpr_x_exact[r - RPR_X0])
                return fail(c, "the start value of state '%s' is calculated from the parameters "
                               "(value %g refused); set those parameters instead", rpr_names[r], x);
            c->x_set[r - RPR_X0] = 1;
        }
        c->v[r] = x;
    }
    c->y_valid = 0;
    return RPR_OK;
}

int rpr_set_input_derivatives(RprInstance *c, const unsigned int vr[], size_t n, const int order[],
                              const double value[]) {
    size_t i;
    if (n == 0) return RPR_OK;
    if (require_mode(c, "setRealInputDerivatives", M_INIT | M_STEP)) return RPR_ERROR;
    if (!RPR_CAN_INTERPOLATE)
        return rpr_unsupported(c, "setRealInputDerivatives (a sampled block reads its inputs at its samples)");
    for (i = 0; i < n; ++i) {
        if (vr[i] < RPR_U0 || vr[i] >= RPR_Y0)
            return fail(c, "setRealInputDerivatives: '%s' (vr %u) is not an input",
                        vr[i] < RPR_NV ? rpr_names[vr[i]] : "?", vr[i]);
        if (order[i] != 1)
            return fail(c, "setRealInputDerivatives: derivative order %d of '%s' is not supported (only 1)",
                        order[i], rpr_names[vr[i]]);
        if (!isfinite(value[i]))
            return fail(c, "setRealInputDerivatives: the slope of '%s' is not finite (%g)", rpr_names[vr[i]],
                        value[i]);
    }
    for (i = 0; i < n; ++i) c->du[vr[i] - RPR_U0] = value[i];
    return RPR_OK;
}

int rpr_no_such_variables(RprInstance *c, const char *function, const unsigned int vr[], size_t n) {
    (void)vr;
    if (n == 0) return RPR_OK;
    rpr_log(c, RPR_ERROR, RPR_LOG_ERROR, "%s: %s: this FMU has only Real (Float64) variables",
            RPR_BLOCK_NAME, function);
    return RPR_ERROR;
}

/* ------------------------------------------------------------------------------------------ */
int rpr_do_step(RprInstance *c, double t, double h) {
    int k, n = 1;
    double *xa = c->xa, *xb = c->xb, *tmp;
    double ok = 1.0, err = 0.0;
    if (require_mode(c, "doStep", M_STEP)) return RPR_ERROR;
    if (!(h > 0) || !isfinite(h)) return fail(c, "doStep: communication step size %g must be positive and finite", h);
    if (!isfinite(t)) return fail(c, "doStep: communication point %g is not finite", t);
    if (!same_time(t, c->v[0])) {
        rpr_log(c, RPR_ERROR, RPR_LOG_ERROR,
                "%s: doStep: the communication point %.17g s does not follow the previous one: "
                "expected %.17g s (the end of the last step, or the start time)", RPR_BLOCK_NAME, t, c->v[0]);
        return RPR_ERROR;
    }
    if (t + h > c->stop_time && !same_time(t + h, c->stop_time)) {
        rpr_log(c, RPR_ERROR, RPR_LOG_ERROR,
                "%s: doStep(t=%.17g, h=%.17g) would end at %.17g s, past the stop time %.17g s "
                "given at initialization", RPR_BLOCK_NAME, t, h, t + h, c->stop_time);
        return RPR_ERROR;
    }
#if RPR_INTEGRATOR == RPR_INTEGRATOR_DISCRETE
    {
        double ts = RPR_SAMPLE_PERIOD;
        n = (int)floor(h / ts + 0.5);
        if (n < 1 || fabs(n * ts - h) > RPR_SAMPLE_TOL * (h > ts ? h : ts)) {
            rpr_log(c, RPR_ERROR, RPR_LOG_ERROR,
                    "%s: doStep: communication step %.17g s is not a whole multiple of the sample "
                    "period %.17g s", RPR_BLOCK_NAME, h, ts);
            return RPR_ERROR;
        }
    }
#endif
    c->discarded = 0;
#if RPR_EVENTS
    (void)k; (void)n; (void)xa; (void)xb; (void)tmp; (void)ok; (void)err;
    return events_do_step(c, t, h);
#endif
#if RPR_NX > 0
    memcpy(xa, X_(c), sizeof(double) * RPR_NX);
    for (k = 0; k < n; ++k) {
#if RPR_STEP_MEMORY
        if (call_step_memory(c, xa, U_(c), h, xb, &ok, &err) || !(ok == 1.0)) {
#else
        if (call(c, (rpr_casadi_fn)RPR_F_STEP, xa, U_(c), P_(c), &h, xb, &ok, &err) || !(ok == 1.0)) {
#endif
            c->discarded = 1;
#if RPR_INTEGRATOR == RPR_INTEGRATOR_RADAU
            if (!(err <= 1.0))
                rpr_log(c, RPR_DISCARD, RPR_LOG_DISCARD,
                        "%s: doStep(t=%.17g, h=%.17g) discarded: the Radau IIA Newton iteration did not "
                        "converge (residual/tolerance = %.3g); state kept at t=%.17g, retry with a smaller step",
                        RPR_BLOCK_NAME, t, h, err, c->v[0]);
            else
#endif
                rpr_log(c, RPR_DISCARD, RPR_LOG_DISCARD,
                        "%s: doStep(t=%.17g, h=%.17g) discarded: the state became non-finite (the step "
                        "diverged); state kept at t=%.17g, retry with a smaller step",
                        RPR_BLOCK_NAME, t, h, c->v[0]);
            return RPR_DISCARD;
        }
        tmp = xa; xa = xb; xb = tmp;
    }
    memcpy(X_(c), xa, sizeof(double) * RPR_NX);
#else
    (void)k; (void)xa; (void)xb; (void)tmp; (void)ok;
#endif
    /* the inputs were followed to the end of the step: they now hold u + du h; the slopes are
       consumed (a master that interpolates sets them again before the next step) */
    for (k = 0; k < RPR_NU; ++k) { U_(c)[k] += c->du[k] * h; c->du[k] = 0.0; }
#if RPR_INTEGRATOR == RPR_INTEGRATOR_RADAU
#if RPR_STEP_MEMORY
    rpr_log(c, RPR_OK, RPR_LOG_NONLINEAR, "doStep(t=%.17g, h=%.17g): Radau IIA residual/tolerance %.3g, "
            "%g Newton iterations, %s; %llu factorisations in %llu iterations so far", t, h, err, c->info[3],
            c->info[2] > 0 ? "iteration matrix factorised" : "factors of an earlier step reused",
            c->factorisations, c->iterations);
#else
    rpr_log(c, RPR_OK, RPR_LOG_NONLINEAR, "doStep(t=%.17g, h=%.17g): Radau IIA residual/tolerance %.3g",
            t, h, err);
#endif
#endif
    c->v[0] = t + h;
    c->y_valid = 0;
    return RPR_OK;
}

/* ------------------------------------------------------------------------------------------ */
static void snapshot(const RprInstance *c, RprSnapshot *s) {
    s->magic = RPR_MAGIC;
    s->guid_hash = guid_hash();
    s->nv = RPR_NV;
    s->nx = RPR_NX;
    s->mode = c->mode;
    s->y_valid = c->y_valid;
    memcpy(s->v, c->v, sizeof c->v);
    memcpy(s->du, c->du, sizeof c->du);
    memcpy(s->x_set, c->x_set, sizeof c->x_set);
    memcpy(&s->memory, &c->memory, sizeof c->memory);
#if RPR_EVENTS
    memcpy(&s->ev, &c->ev, sizeof c->ev);
#endif
}

static int check_snapshot(RprInstance *c, const RprSnapshot *s) {
    if (s->magic != RPR_MAGIC || s->guid_hash != guid_hash() || s->nv != RPR_NV || s->nx != RPR_NX ||
        s->mode < RPR_MODE_INSTANTIATED || s->mode > RPR_MODE_EVENT || s->mode == RPR_MODE_ERROR) {
        rpr_log(c, RPR_ERROR, RPR_LOG_ERROR, "%s: the FMU state was not made by this FMU (%s)",
                RPR_BLOCK_NAME, RPR_GUID);
        return RPR_ERROR;
    }
    return RPR_OK;
}

int rpr_get_state(RprInstance *c, void **state) {
    if (!state) return fail(c, "getFMUState: null FMU state pointer");
    if (!*state) {
        *state = malloc(sizeof(RprSnapshot));
        if (!*state) return fail(c, "getFMUState: out of memory");
    }
    snapshot(c, (RprSnapshot *)*state);
    return RPR_OK;
}

int rpr_set_state(RprInstance *c, const void *state) {
    const RprSnapshot *s = (const RprSnapshot *)state;
    if (!s) return fail(c, "setFMUState: null FMU state");
    if (check_snapshot(c, s)) return RPR_ERROR;
    c->mode = (int)s->mode;
    c->y_valid = (int)s->y_valid;
    memcpy(c->v, s->v, sizeof c->v);
    memcpy(c->du, s->du, sizeof c->du);
    memcpy(c->x_set, s->x_set, sizeof c->x_set);
    memcpy(&c->memory, &s->memory, sizeof c->memory);
#if RPR_EVENTS
    memcpy(&c->ev, &s->ev, sizeof c->ev);
#endif
    c->discarded = 0;
    return RPR_OK;
}

int rpr_free_state(RprInstance *c, void **state) {
    (void)c;
    if (state && *state) { free(*state); *state = NULL; }
    return RPR_OK;
}

int rpr_serialize(RprInstance *c, const void *state, char *buffer, size_t size) {
    if (!state || !buffer) return fail(c, "serializeFMUState: null argument");
    if (size < sizeof(RprSnapshot))
        return fail(c, "serializeFMUState: buffer too small (need %u bytes)", (unsigned)sizeof(RprSnapshot));
    memcpy(buffer, state, sizeof(RprSnapshot));
    return RPR_OK;
}

int rpr_deserialize(RprInstance *c, const char *buffer, size_t size, void **state) {
    RprSnapshot s;
    if (!buffer || !state) return fail(c, "deserializeFMUState: null argument");
    if (size != sizeof(RprSnapshot))
        return fail(c, "deserializeFMUState: the buffer has %u bytes, expected %u", (unsigned)size,
                    (unsigned)sizeof(RprSnapshot));
    memcpy(&s, buffer, sizeof s);
    if (check_snapshot(c, &s)) return RPR_ERROR;
    if (!*state) {
        *state = malloc(sizeof(RprSnapshot));
        if (!*state) return fail(c, "deserializeFMUState: out of memory");
    }
    memcpy(*state, &s, sizeof s);
    return RPR_OK;
}

/* ------------------------------------------------------------------------------------------ */
static int known_column(unsigned int r) {
    if (r >= RPR_X0 && r < RPR_U0) return (int)(r - RPR_X0);
    if (r >= RPR_U0 && r < RPR_Y0) return RPR_NX + (int)(r - RPR_U0);
    if (r >= RPR_P0 && r < RPR_X0) return RPR_NX + RPR_NU + (int)(r - RPR_P0);
    return -1;
}

int rpr_directional_derivative(RprInstance *c, const unsigned int unknown[], size_t n_unknown,
                               const unsigned int known[], size_t n_known, const double seed[],
                               double sensitivity[]) {
    size_t i, j;
    if (require_mode(c, "getDirectionalDerivative", M_INIT | M_STEP | M_TERM | M_EVENT)) return RPR_ERROR;
    /* modes sit among the known columns right after the parameters: the Jacobian's p' = [p; m] */
    for (j = 0; j < n_known; ++j)
        if (known[j] >= RPR_NV || (known[j] != 0 && known_column(known[j]) < 0))
            return fail(c, "getDirectionalDerivative: known '%s' (vr %u) must be a state, input or parameter",
                        known[j] < RPR_NV ? rpr_names[known[j]] : "?", known[j]);
    for (i = 0; i < n_unknown; ++i)
        if (unknown[i] >= RPR_NV || unknown[i] < RPR_X0 || (unknown[i] >= RPR_U0 && unknown[i] < RPR_Y0))
            return fail(c, "getDirectionalDerivative: unknown '%s' (vr %u) must be an output or a state",
                        unknown[i] < RPR_NV ? rpr_names[unknown[i]] : "?", unknown[i]);
    if (refresh_start(c) != RPR_OK) return RPR_ERROR;
    if (RPR_NJAC && call(c, (rpr_casadi_fn)RPR_F_JAC, X_(c), U_(c), P_(c), 0, c->jac, 0, 0))
        return fail(c, "getDirectionalDerivative: the Jacobian evaluation failed");
    for (i = 0; i < n_unknown; ++i) {
        double s = 0.0;
        unsigned int r = unknown[i];
        for (j = 0; j < n_known; ++j) {
            int col = known[j] == 0 ? -1 : known_column(known[j]);
            if (col < 0) continue; /* time: blocks are autonomous */
            if (r >= RPR_Y0)
                s += c->jac[(r - RPR_Y0) + (size_t)RPR_NY * (size_t)col] * seed[j];
            else if (known[j] == r)
                s += seed[j];
        }
        sensitivity[i] = s;
    }
    return RPR_OK;
}

int rpr_unsupported(RprInstance *c, const char *function) {
    rpr_log(c, RPR_ERROR, RPR_LOG_ERROR, "%s: %s is not supported by this co-simulation FMU",
            RPR_BLOCK_NAME, function);
    return RPR_ERROR;
}

/* ------------------------------------------------------------------------------------------ */
#if RPR_EVENTS
int rpr_has_event_mode(void) { return 1; }
void rpr_use_event_mode(RprInstance *c, int early_return) { c->event_mode = 1; c->early_return = early_return != 0; }
int rpr_event_pending(const RprInstance *c) { return c->ev.npending > 0; }
int rpr_enter_event_mode(RprInstance *c) {
    if (require_mode(c, "enterEventMode", M_STEP)) return RPR_ERROR;
    if (!c->event_mode) return fail(c, "enterEventMode: the FMU was instantiated with eventModeUsed = false");
    c->mode = RPR_MODE_EVENT;
    return RPR_OK;
}
int rpr_update_discrete_states(RprInstance *c, int *next_time_defined, double *next_time) {
    int status = RPR_OK, n = c->ev.npending, fired[RPR_MAX1(RPR_NZ + RPR_NS)];
    double t = c->v[0];
    if (require_mode(c, "updateDiscreteStates", M_EVENT)) return RPR_ERROR;
    c->ev.step_events = 0;
    memcpy(c->xa, X_(c), sizeof(double) * RPR_NX);
    if (n) {
        memcpy(fired, c->ev.pending, sizeof(int) * (size_t)n);
        c->ev.npending = 0;
        status = eval_z(c, t, c->xa, U_(c), c->z) ? fail(c, "the event indicators failed at t=%.17g s", t)
                                                  : event_iteration(c, t, c->xa, U_(c), fired, n);
    }
    if (status == RPR_OK) status = take_samples(c, t, c->xa, U_(c));
    if (status != RPR_OK) return status;
    memcpy(X_(c), c->xa, sizeof(double) * RPR_NX);
    c->y_valid = 0;
    *next_time = next_sample_time(c);
    *next_time_defined = isfinite(*next_time);
    return RPR_OK;
}
int rpr_enter_step_mode(RprInstance *c) {
    if (require_mode(c, "enterStepMode", M_EVENT)) return RPR_ERROR;
    c->mode = RPR_MODE_STEP;
    return RPR_OK;
}
#else
int rpr_has_event_mode(void) { return 0; }
void rpr_use_event_mode(RprInstance *c, int early_return) { (void)c; (void)early_return; }
int rpr_event_pending(const RprInstance *c) { (void)c; return 0; }
int rpr_enter_event_mode(RprInstance *c) { return rpr_unsupported(c, "enterEventMode (hasEventMode is false)"); }
int rpr_update_discrete_states(RprInstance *c, int *next_time_defined, double *next_time) {
    (void)next_time_defined; (void)next_time;
    return rpr_unsupported(c, "updateDiscreteStates (hasEventMode is false)");
}
int rpr_enter_step_mode(RprInstance *c) {
    return rpr_unsupported(c, "enterStepMode (hasEventMode is false: step mode follows exitInitializationMode directly)");
}
#endif
