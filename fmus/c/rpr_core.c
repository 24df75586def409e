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

#define RPR_NV (1 + RPR_NP + RPR_NX + RPR_NU + RPR_NY)
#define RPR_P0 1
#define RPR_X0 (RPR_P0 + RPR_NP)
#define RPR_U0 (RPR_X0 + RPR_NX)
#define RPR_Y0 (RPR_U0 + RPR_NU)
#define RPR_NJAC (RPR_NY * (RPR_NX + RPR_NU + RPR_NP))

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

static const char *const log_names[RPR_N_LOG] = {"logStatusError", "logStatusDiscard",
                                                 "logStatusWarning", "logNonlinearSystems",
                                                 "logCalls"};
static const char *const mode_names[] = {"instantiated", "initialization mode", "step mode",
                                         "terminated", "error"};

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
static int call_step_memory(RprInstance *c, const double *xa, double h, double *xb, double *ok, double *err) {
    int status;
    RprMemory *m = &c->memory;
    c->arg[0] = xa; c->arg[1] = c->v + RPR_U0; c->arg[2] = c->v + RPR_P0; c->arg[3] = &h;
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

/* Before the end of initialisation, states not set by the user follow start(p). */
static int refresh_start(RprInstance *c) {
    int i;
    if (RPR_NX == 0 || c->mode >= RPR_MODE_STEP) return RPR_OK;
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
    rpr_casadi_work works[4];
    int k;
    works[0] = RPR_CAT(RPR_F_STEP, _work);
    works[1] = RPR_CAT(RPR_F_OUT, _work);
    works[2] = RPR_CAT(RPR_F_START, _work);
    works[3] = RPR_CAT(RPR_F_JAC, _work);
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
    for (k = 0; k < 4; ++k) {
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
    c->mode = RPR_MODE_STEP;
    c->y_valid = 0;
    if (update_outputs(c) != RPR_OK) return fail(c, "the output function failed");
    return RPR_OK;
}

int rpr_terminate(RprInstance *c) {
    if (require_mode(c, "terminate", M_STEP | M_INIT)) return RPR_ERROR;
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
    if (require_mode(c, "getReal/getFloat64", M_INST | M_INIT | M_STEP | M_TERM | M_ERR))
        return RPR_ERROR;
    for (i = 0; i < n; ++i) {
        if (vr[i] >= RPR_NV) return fail(c, "getReal: value reference %u does not exist", vr[i]);
        if (vr[i] >= RPR_Y0) { if (update_outputs(c) != RPR_OK) return fail(c, "the output function failed"); }
        else if (vr[i] >= RPR_X0 && vr[i] < RPR_U0) refresh_start(c);
        value[i] = c->v[vr[i]];
    }
    return RPR_OK;
}

int rpr_set_real(RprInstance *c, const unsigned int vr[], size_t n, const double value[]) {
    size_t i;
    if (n == 0) return RPR_OK;
    if (require_mode(c, "setReal/setFloat64", M_INST | M_INIT | M_STEP)) return RPR_ERROR;
    for (i = 0; i < n; ++i) {
        unsigned int r = vr[i];
        double x = value[i];
        if (r >= RPR_NV) return fail(c, "setReal: value reference %u does not exist", r);
        if (r == 0) return fail(c, "'time' cannot be set");
        if (r >= RPR_Y0) return fail(c, "output '%s' cannot be set (value %g)", rpr_names[r], x);
        if (!isfinite(x)) return fail(c, "'%s' cannot be set to the non-finite value %g", rpr_names[r], x);
        if (r < RPR_X0) { /* parameter */
            if (c->mode == RPR_MODE_STEP && !rpr_tunable[r - RPR_P0])
                return fail(c, "parameter '%s' is fixed: set it before the end of initialization (value %g)",
                            rpr_names[r], x);
            if (x < rpr_min[r] || x > rpr_max[r])
                return fail(c, "parameter '%s' = %.17g is outside [%.17g, %.17g]", rpr_names[r], x,
                            rpr_min[r], rpr_max[r]);
        } else if (r < RPR_U0) { /* state */
            if (c->mode == RPR_MODE_STEP)
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
#if RPR_NX > 0
    memcpy(xa, X_(c), sizeof(double) * RPR_NX);
    for (k = 0; k < n; ++k) {
#if RPR_STEP_MEMORY
        if (call_step_memory(c, xa, h, xb, &ok, &err) || !(ok == 1.0)) {
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
}

static int check_snapshot(RprInstance *c, const RprSnapshot *s) {
    if (s->magic != RPR_MAGIC || s->guid_hash != guid_hash() || s->nv != RPR_NV || s->nx != RPR_NX ||
        s->mode < RPR_MODE_INSTANTIATED || s->mode > RPR_MODE_TERMINATED) {
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
    if (require_mode(c, "getDirectionalDerivative", M_INIT | M_STEP | M_TERM)) return RPR_ERROR;
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
