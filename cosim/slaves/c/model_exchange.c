/* A model-exchange FMU (FMI 2.0 or 3.0) stepped as a co-simulation slave: SUNDIALS CVODES (BDF,
 * Newton, dense direct linear solver, difference-quotient Jacobian) integrates the FMU's
 * continuous states between communication points, with root finding on the FMU's event
 * indicators (state events), the FMU's next event time as a stop time (time events), and
 * fmi*CompletedIntegratorStep after every internal step (step events).  At each event the FMU
 * goes through event mode and its event iteration (at most ME_MAX_ROUNDS rounds); the solver
 * then restarts from the FMU's states.  A right-hand-side evaluation is two FMI calls from C.
 *
 * The FMU is instantiated and initialised by the caller (FMPy); this file resolves the ME
 * functions in the same shared library (dlopen of a path already loaded returns its handle),
 * and takes over at the end of initialisation (me_start).  Rollback: me_save / me_restore keep
 * the FMU state (fmi*GetFMUstate) or, for an FMU that cannot save it, the time and continuous
 * states (set back through the ME interface); either way the solver restarts at the saved
 * point, and so does the step after a save (CVODES cannot save its history), so a repeated step
 * is the first one to the bit.  Compiled and cached by fmus.c_loader (linked with -lsundials_cvodes and friends).
 */
#include <dlfcn.h>
#include <math.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <cvodes/cvodes.h>
#include <nvector/nvector_serial.h>
#include <sunlinsol/sunlinsol_dense.h>
#include <sunmatrix/sunmatrix_dense.h>

/* --- the FMI C API (binary-stable; declared here so no FMI headers are needed) -------------- */
typedef void *Inst;
typedef struct {
    int newDiscreteStatesNeeded, terminateSimulation, nominalsOfContinuousStatesChanged,
        valuesOfContinuousStatesChanged, nextEventTimeDefined;
    double nextEventTime;
} Fmi2EventInfo;

typedef int (*F_inst)(Inst);
typedef int (*F_time)(Inst, double);
typedef int (*F_vec2)(Inst, double *, size_t);            /* FMI 2.0 and 3.0 alike */
typedef int (*F_setvec)(Inst, const double *, size_t);
typedef int (*F_completed2)(Inst, int, int *, int *);
typedef int (*F_completed3)(Inst, bool, bool *, bool *);
typedef int (*F_new2)(Inst, Fmi2EventInfo *);
typedef int (*F_update3)(Inst, bool *, bool *, bool *, bool *, bool *, double *);
typedef int (*F_state)(Inst, void **);
typedef int (*F_setstate)(Inst, void *);
typedef int (*F_real2)(Inst, const unsigned *, size_t, double *);
typedef int (*F_real3)(Inst, const unsigned *, size_t, double *, size_t);

enum { ST_OK = 0, ST_WARNING = 1, ST_DISCARD = 2, ST_ERROR = 3, ST_FATAL = 4 };
/* me_do_step's extra result: the FMU asked to end the simulation (terminateSimulation) */
enum { ME_STOP = 100 };
enum { EV_STATE = 1, EV_TIME = 2, EV_STEP = 3, EV_INPUT = 4 };
#define ME_MAX_ROUNDS 100
#define ME_EVENT_LOG 10000

typedef struct {
    int fmi3;
    Inst inst;
    void *lib;
    F_inst enter_event_mode, enter_ct_mode;
    F_time set_time;
    F_vec2 get_x, get_dx, get_z, get_nominals;
    F_setvec set_x;
    F_completed2 completed2;
    F_completed3 completed3;
    F_new2 new_discrete2;
    F_update3 update3;
    F_state get_state, free_state;
    F_setstate set_state;
    void *get_real, *set_real;   /* fmi2GetReal/SetReal or fmi3GetFloat64/SetFloat64 */

    size_t nx, nz, ny;           /* ny = max(nx, 1): CVODES needs a state; a dummy one stays 1 */
    int needs_completed;
    double rtol;
    long max_events_per_step, max_steps_per_step;

    SUNContext ctx;
    void *cv;
    N_Vector y, abstol;
    SUNMatrix A;
    SUNLinearSolver LS;
    int restart;                 /* reinitialise CVODES before the next integration */

    double t;                    /* the slave's time [s] */
    int next_defined;
    double next_time;
    double *z_prev, *zbuf;
    int *roots;
    int terminated;

    /* rollback */
    int use_fmu_state;
    void *fmu_state;
    int saved;
    double s_t, s_next_time;
    int s_next_defined, s_terminated;
    double *s_x, *s_z, *s_dx;

    /* statistics and the event log */
    long n_rhs, n_steps, n_state, n_time, n_step, n_input, n_restarts;
    long n_log;
    double *log_t;
    int *log_kind;

    char message[1024];
} MeSlave;

static void say(MeSlave *s, const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(s->message, sizeof s->message, fmt, ap);
    va_end(ap);
}

const char *me_message(MeSlave *s) { return s->message; }

static void *sym(MeSlave *s, const char *name, int required) {
    void *f = dlsym(s->lib, name);
    if (!f && required && !s->message[0]) say(s, "the FMU's library does not export %s", name);
    return f;
}

/* A new slave over the instance ``inst`` (made by the caller) of the FMU library at ``lib_path``.
 * Check me_message(s) for "" before use. */
MeSlave *me_new(const char *lib_path, int fmi3, void *inst, long nx, long nz, int needs_completed,
                int use_fmu_state, double rtol, long max_events_per_step, long max_steps_per_step) {
    MeSlave *s = calloc(1, sizeof *s);
    if (!s) return NULL;
    s->fmi3 = fmi3;
    s->inst = inst;
    s->nx = (size_t)nx;
    s->nz = (size_t)nz;
    s->ny = nx > 0 ? (size_t)nx : 1;
    s->needs_completed = needs_completed;
    s->use_fmu_state = use_fmu_state;
    s->rtol = rtol;
    s->max_events_per_step = max_events_per_step;
    s->max_steps_per_step = max_steps_per_step;
    s->lib = dlopen(lib_path, RTLD_NOW | RTLD_LOCAL);
    if (!s->lib) {
        say(s, "cannot open %s: %s", lib_path, dlerror());
        return s;
    }
    if (fmi3) {
        s->enter_event_mode = (F_inst)sym(s, "fmi3EnterEventMode", 1);
        s->enter_ct_mode = (F_inst)sym(s, "fmi3EnterContinuousTimeMode", 1);
        s->set_time = (F_time)sym(s, "fmi3SetTime", 1);
        s->get_x = (F_vec2)sym(s, "fmi3GetContinuousStates", 1);
        s->set_x = (F_setvec)sym(s, "fmi3SetContinuousStates", 1);
        s->get_dx = (F_vec2)sym(s, "fmi3GetContinuousStateDerivatives", 1);
        s->get_z = (F_vec2)sym(s, "fmi3GetEventIndicators", 1);
        s->get_nominals = (F_vec2)sym(s, "fmi3GetNominalsOfContinuousStates", 1);
        s->completed3 = (F_completed3)sym(s, "fmi3CompletedIntegratorStep", 1);
        s->update3 = (F_update3)sym(s, "fmi3UpdateDiscreteStates", 1);
        s->get_real = sym(s, "fmi3GetFloat64", 1);
        s->set_real = sym(s, "fmi3SetFloat64", 1);
        s->get_state = (F_state)sym(s, "fmi3GetFMUState", use_fmu_state);
        s->set_state = (F_setstate)sym(s, "fmi3SetFMUState", use_fmu_state);
        s->free_state = (F_state)sym(s, "fmi3FreeFMUState", use_fmu_state);
    } else {
        s->enter_event_mode = (F_inst)sym(s, "fmi2EnterEventMode", 1);
        s->enter_ct_mode = (F_inst)sym(s, "fmi2EnterContinuousTimeMode", 1);
        s->set_time = (F_time)sym(s, "fmi2SetTime", 1);
        s->get_x = (F_vec2)sym(s, "fmi2GetContinuousStates", 1);
        s->set_x = (F_setvec)sym(s, "fmi2SetContinuousStates", 1);
        s->get_dx = (F_vec2)sym(s, "fmi2GetDerivatives", 1);
        s->get_z = (F_vec2)sym(s, "fmi2GetEventIndicators", 1);
        s->get_nominals = (F_vec2)sym(s, "fmi2GetNominalsOfContinuousStates", 1);
        s->completed2 = (F_completed2)sym(s, "fmi2CompletedIntegratorStep", 1);
        s->new_discrete2 = (F_new2)sym(s, "fmi2NewDiscreteStates", 1);
        s->get_real = sym(s, "fmi2GetReal", 1);
        s->set_real = sym(s, "fmi2SetReal", 1);
        s->get_state = (F_state)sym(s, "fmi2GetFMUstate", use_fmu_state);
        s->set_state = (F_setstate)sym(s, "fmi2SetFMUstate", use_fmu_state);
        s->free_state = (F_state)sym(s, "fmi2FreeFMUstate", use_fmu_state);
    }
    size_t nzz = s->nz ? s->nz : 1;
    s->z_prev = calloc(nzz, sizeof(double));
    s->zbuf = calloc(nzz, sizeof(double));
    s->roots = calloc(nzz, sizeof(int));
    s->s_z = calloc(nzz, sizeof(double));
    s->s_x = calloc(s->ny, sizeof(double));
    s->s_dx = calloc(s->ny, sizeof(double));
    s->log_t = malloc(ME_EVENT_LOG * sizeof(double));
    s->log_kind = malloc(ME_EVENT_LOG * sizeof(int));
    if (!(s->z_prev && s->zbuf && s->roots && s->s_z && s->s_x && s->s_dx && s->log_t && s->log_kind))
        say(s, "out of memory");
    return s;
}

static int failed(int st) { return st >= ST_DISCARD; }

/* Times closer than this to ``t`` [s] are ``t`` (a time event announced a rounding error away). */
static double close_to(double t) { return 1e-13 * (1.0 + fabs(t)); }

/* --- CVODES callbacks ---------------------------------------------------------------------- */
static int rhs(double t, N_Vector y, N_Vector ydot, void *data) {
    MeSlave *s = data;
    double *dx = N_VGetArrayPointer(ydot);
    s->n_rhs++;
    if (s->nx == 0) {
        dx[0] = 0.0;
        return 0;
    }
    int st = s->set_time(s->inst, t);
    if (!failed(st)) st = s->set_x(s->inst, N_VGetArrayPointer(y), s->nx);
    if (!failed(st)) st = s->get_dx(s->inst, dx, s->nx);
    if (failed(st)) {
        say(s, "the derivatives at t = %.12g s returned status %d", t, st);
        return st == ST_DISCARD ? 1 : -1; /* Discard: CVODES tries a smaller step */
    }
    for (size_t i = 0; i < s->nx; i++)
        if (!isfinite(dx[i])) {
            say(s, "the derivative of continuous state %zu is %g at t = %.12g s", i, dx[i], t);
            return 1;
        }
    return 0;
}

static int roots_fn(double t, N_Vector y, double *g, void *data) {
    MeSlave *s = data;
    int st = s->set_time(s->inst, t);
    if (!failed(st) && s->nx) st = s->set_x(s->inst, N_VGetArrayPointer(y), s->nx);
    if (!failed(st)) st = s->get_z(s->inst, g, s->nz);
    if (failed(st)) {
        say(s, "the event indicators at t = %.12g s returned status %d", t, st);
        return -1;
    }
    for (size_t i = 0; i < s->nz; i++)
        if (!isfinite(g[i])) {
            say(s, "event indicator %zu is %g at t = %.12g s", i, g[i], t);
            return -1;
        }
    return 0;
}

#if SUNDIALS_VERSION_MAJOR >= 7
static void on_error(int line, const char *func, const char *file, const char *msg, SUNErrCode code,
                     void *data, SUNContext ctx) {
    (void)line; (void)file; (void)ctx;
    MeSlave *s = data;
    if (!s->message[0]) say(s, "CVODES %s (%d): %s", func, (int)code, msg);
}
#else
static void on_error(int code, const char *module, const char *func, char *msg, void *data) {
    (void)module;
    MeSlave *s = data;
    if (!s->message[0]) say(s, "CVODES %s (%d): %s", func, code, msg);
}
#endif

/* --- events -------------------------------------------------------------------------------- */
static void log_event(MeSlave *s, double t, int kind) {
    if (s->n_log < ME_EVENT_LOG) {
        s->log_t[s->n_log] = t;
        s->log_kind[s->n_log] = kind;
    }
    s->n_log++;
    if (kind == EV_STATE) s->n_state++;
    else if (kind == EV_TIME) s->n_time++;
    else if (kind == EV_STEP) s->n_step++;
    else s->n_input++;
}

/* Absolute tolerances: rtol times each state's nominal (as FMPy and OMSimulator do). */
static int read_states(MeSlave *s, int nominals) {
    double *y = N_VGetArrayPointer(s->y), *a = N_VGetArrayPointer(s->abstol);
    if (s->nx == 0) {
        y[0] = 1.0;
        a[0] = s->rtol;
        return ST_OK;
    }
    int st = s->get_x(s->inst, y, s->nx);
    if (!failed(st) && nominals) {
        st = s->get_nominals(s->inst, a, s->nx);
        for (size_t i = 0; i < s->nx; i++) a[i] = s->rtol * fabs(a[i] > 0 || a[i] < 0 ? a[i] : 1.0);
    }
    return st;
}

/* The discrete-state update of FMI 2.0 or 3.0: one round of the event iteration. */
static int update_round(MeSlave *s, int *again, int *terminate, int *nominals, int *values) {
    if (s->fmi3) {
        bool a = false, term = false, nom = false, val = false, def = false;
        double next = 0.0;
        int st = s->update3(s->inst, &a, &term, &nom, &val, &def, &next);
        *again = a, *terminate = term, *nominals = nom, *values = val;
        s->next_defined = def, s->next_time = next;
        return st;
    }
    Fmi2EventInfo e = {0};
    int st = s->new_discrete2(s->inst, &e);
    *again = e.newDiscreteStatesNeeded, *terminate = e.terminateSimulation;
    *nominals = e.nominalsOfContinuousStatesChanged, *values = e.valuesOfContinuousStatesChanged;
    s->next_defined = e.nextEventTimeDefined, s->next_time = e.nextEventTime;
    return st;
}

/* Event iteration (event mode entered by the caller); leaves the FMU in continuous-time mode
 * with the solver to restart.  Returns a status, or ME_STOP. */
static int iterate(MeSlave *s, double t) {
    int again = 1, term = 0, nominals = 0, values = 0, any_nominal = 0, rounds = 0;
    while (again) {
        if (++rounds > ME_MAX_ROUNDS) {
            say(s, "the event iteration at t = %.12g s did not settle in %d rounds "
                   "(the FMU kept asking for new discrete states)", t, ME_MAX_ROUNDS);
            return ST_ERROR;
        }
        int st = update_round(s, &again, &term, &nominals, &values);
        if (failed(st)) {
            say(s, "%s at t = %.12g s returned status %d", s->fmi3 ? "fmi3UpdateDiscreteStates" :
                "fmi2NewDiscreteStates", t, st);
            return st;
        }
        any_nominal |= nominals;
        if (term) {
            s->terminated = 1;
            return ME_STOP;
        }
    }
    int st = s->enter_ct_mode(s->inst);
    if (!failed(st)) st = read_states(s, any_nominal || !s->cv);
    if (!failed(st) && s->nz) st = s->get_z(s->inst, s->z_prev, s->nz);
    if (failed(st)) {
        say(s, "leaving event mode at t = %.12g s returned status %d", t, st);
        return st;
    }
    s->restart = 1;
    return ST_OK;
}

static int handle_event(MeSlave *s, double t, int kind) {
    log_event(s, t, kind);
    int st = s->set_time(s->inst, t);
    if (!failed(st)) st = s->enter_event_mode(s->inst);
    if (failed(st)) {
        say(s, "entering event mode at t = %.12g s returned status %d", t, st);
        return st;
    }
    return iterate(s, t);
}

/* --- lifecycle ----------------------------------------------------------------------------- */
/* After fmi*ExitInitializationMode at ``t0`` (the FMU in event mode): the initial event iteration,
 * continuous-time mode and the solver.  Returns a status or ME_STOP. */
int me_start(MeSlave *s, double t0) {
    if (s->message[0]) return ST_ERROR;
    s->t = t0;
    s->ctx = NULL;
#if SUNDIALS_VERSION_MAJOR >= 7
    if (SUNContext_Create(SUN_COMM_NULL, &s->ctx)) { say(s, "SUNContext_Create failed"); return ST_ERROR; }
#else
    if (SUNContext_Create(NULL, &s->ctx)) { say(s, "SUNContext_Create failed"); return ST_ERROR; }
#endif
    s->y = N_VNew_Serial((sunindextype)s->ny, s->ctx);
    s->abstol = N_VNew_Serial((sunindextype)s->ny, s->ctx);
    int st = iterate(s, t0);
    if (st != ST_OK) return st;
    s->cv = CVodeCreate(CV_BDF, s->ctx);
    if (!s->cv) { say(s, "CVodeCreate failed"); return ST_ERROR; }
    int f = CVodeInit(s->cv, rhs, t0, s->y);
    if (!f) f = CVodeSetUserData(s->cv, s);
    if (!f) f = CVodeSVtolerances(s->cv, s->rtol, s->abstol);
    if (!f && s->nz) f = CVodeRootInit(s->cv, (int)s->nz, roots_fn);
    if (!f) f = CVodeSetNoInactiveRootWarn(s->cv);
#if SUNDIALS_VERSION_MAJOR >= 7
    if (!f) f = SUNContext_PushErrHandler(s->ctx, on_error, s);
#else
    if (!f) f = CVodeSetErrHandlerFn(s->cv, on_error, s);
#endif
    s->A = SUNDenseMatrix((sunindextype)s->ny, (sunindextype)s->ny, s->ctx);
    s->LS = SUNLinSol_Dense(s->y, s->A, s->ctx);
    if (!f) f = CVodeSetLinearSolver(s->cv, s->LS, s->A);
    if (f) { say(s, "setting up CVODES failed (%d)", f); return ST_ERROR; }
    s->restart = 0;
    return ST_OK;
}

/* Input events: a sign change of an indicator between the end of the last step and now (the
 * inputs set in between moved it). */
static int input_event(MeSlave *s) {
    if (!s->nz) return ST_OK;
    int st = s->get_z(s->inst, s->zbuf, s->nz);
    if (failed(st)) { say(s, "the event indicators at t = %.12g s returned status %d", s->t, st); return st; }
    for (size_t i = 0; i < s->nz; i++) {
        if (!isfinite(s->zbuf[i])) { say(s, "event indicator %zu is %g at t = %.12g s", i, s->zbuf[i], s->t); return ST_ERROR; }
        if ((s->zbuf[i] > 0) != (s->z_prev[i] > 0)) return handle_event(s, s->t, EV_INPUT);
    }
    return ST_OK;
}

/* Advance from ``t`` to ``t + h`` (FMI 2.0 doStep's shape; the FMU is at ``t``). */
int me_do_step(MeSlave *s, double t, double h, int no_prior) {
    if (s->terminated) { say(s, "doStep after the FMU asked to end the simulation"); return ST_ERROR; }
    if (!s->cv) { if (!s->message[0]) say(s, "doStep before initialisation"); return ST_ERROR; }
    if (fabs(t - s->t) > 1e-9 * (1.0 + fabs(t))) {
        say(s, "doStep from t = %.12g s, but the FMU is at %.12g s", t, s->t);
        return ST_ERROR;
    }
    s->message[0] = 0;
    s->t = t;
    int st = input_event(s);
    if (st != ST_OK) return st;
    const double tend = t + h;
    long events = 0, steps = 0;
    /* a time event at the start (announced by the last event, e.g. nextEventTime == t) */
    while (s->next_defined && s->next_time <= s->t + close_to(s->t)) {
        if (++events > s->max_events_per_step) goto chattering;
        st = handle_event(s, s->t, EV_TIME);
        if (st != ST_OK) return st;
    }
    while (s->t < tend - close_to(tend)) {
        double tstop = tend;
        if (s->next_defined && s->next_time < tend) tstop = s->next_time;
        if (s->restart) {
            if (CVodeReInit(s->cv, s->t, s->y)) { say(s, "restarting CVODES at t = %.12g s failed", s->t); return ST_ERROR; }
            s->restart = 0;
            s->n_restarts++;
        }
        CVodeSetStopTime(s->cv, tstop);
        double tret = s->t;
        int flag = CVode(s->cv, tstop, s->y, &tret, CV_ONE_STEP);
        if (flag < 0) {
            char why[1024];
            snprintf(why, sizeof why, "%s", s->message);
            say(s, "CVODES failed at t = %.12g s (flag %d, %s)%s%s", tret, flag, CVodeGetReturnFlagName(flag),
                why[0] ? ": " : "", why);
            return ST_DISCARD; /* an adaptive master retries a shorter step; a fixed-step one stops */
        }
        if (++steps > s->max_steps_per_step) {
            say(s, "more than %ld CVODES steps in one communication step at t = %.12g s", s->max_steps_per_step, tret);
            return ST_ERROR;
        }
        s->n_steps++;
        if (flag == CV_TSTOP_RETURN) tret = tstop;
        st = s->set_time(s->inst, tret);
        if (!failed(st) && s->nx) st = s->set_x(s->inst, N_VGetArrayPointer(s->y), s->nx);
        if (failed(st)) { say(s, "setting the states at t = %.12g s returned status %d", tret, st); return st; }
        s->t = tret;
        int step_event = 0, term = 0;
        if (s->needs_completed) {
            if (s->fmi3) {
                bool ev = false, tm = false;
                st = s->completed3(s->inst, no_prior != 0, &ev, &tm);
                step_event = ev, term = tm;
            } else {
                st = s->completed2(s->inst, no_prior != 0, &step_event, &term);
            }
            if (failed(st)) { say(s, "CompletedIntegratorStep at t = %.12g s returned status %d", tret, st); return st; }
            if (term) { s->terminated = 1; return ME_STOP; }
        }
        int kind = flag == CV_ROOT_RETURN ? EV_STATE
                 : (flag == CV_TSTOP_RETURN && s->next_defined && tstop == s->next_time) ? EV_TIME
                 : step_event ? EV_STEP : 0;
        if (kind) {
            if (++events > s->max_events_per_step) goto chattering;
            st = handle_event(s, tret, kind);
            if (st != ST_OK) return st;
        } else if (s->nz && flag != CV_ROOT_RETURN) {
            /* remember the indicators' signs for the input-event test of the next step */
            if (tret >= tend) {
                st = s->get_z(s->inst, s->z_prev, s->nz);
                if (failed(st)) { say(s, "the event indicators at t = %.12g s returned status %d", tret, st); return st; }
            }
        }
    }
    s->t = tend;
    return ST_OK;
chattering:
    say(s, "more than %ld events in one communication step [%.12g, %.12g] s (chattering); the last at t = %.12g s",
        s->max_events_per_step, t, tend, s->t);
    return ST_ERROR;
}

/* --- rollback ------------------------------------------------------------------------------ */
int me_save(MeSlave *s) {
    if (s->use_fmu_state) {
        int st = s->get_state(s->inst, &s->fmu_state);
        if (failed(st)) { say(s, "getting the FMU state returned status %d", st); return st; }
    } else if (s->nx) {
        int st = s->get_x(s->inst, s->s_x, s->nx);
        if (!failed(st)) st = s->get_dx(s->inst, s->s_dx, s->nx);
        if (failed(st)) { say(s, "reading the continuous states returned status %d", st); return st; }
    }
    memcpy(s->s_z, s->z_prev, (s->nz ? s->nz : 1) * sizeof(double));
    s->s_t = s->t, s->s_next_time = s->next_time, s->s_next_defined = s->next_defined;
    s->s_terminated = s->terminated;
    s->saved = 1;
    s->restart = 1; /* a saved point is a restart point: a repeated step is the first one to the bit */
    return ST_OK;
}

/* Back to the last me_save.  Through continuous states, the derivatives there must come out as
 * they were saved: a difference is a discrete state the FMU does not show (rollback impossible). */
int me_restore(MeSlave *s) {
    if (!s->saved) { say(s, "restore before save"); return ST_ERROR; }
    int st;
    if (s->use_fmu_state) {
        st = s->set_state(s->inst, s->fmu_state);
        if (failed(st)) { say(s, "setting the FMU state returned status %d", st); return st; }
    } else if (s->nx) {
        st = s->set_time(s->inst, s->s_t);
        if (!failed(st)) st = s->set_x(s->inst, s->s_x, s->nx);
        double *dx = N_VGetArrayPointer(s->abstol); /* scratch, refilled by read_states below */
        if (!failed(st)) st = s->get_dx(s->inst, dx, s->nx);
        if (failed(st)) { say(s, "setting the continuous states returned status %d", st); return st; }
        for (size_t i = 0; i < s->nx; i++)
            if (dx[i] != s->s_dx[i] && !(isnan(dx[i]) && isnan(s->s_dx[i]))) {
                say(s, "rollback through the continuous states: at t = %.12g s the derivative of state %zu is %.12g, "
                       "%.12g when saved (the FMU has a discrete state it does not declare; it cannot roll back "
                       "without an FMU state)", s->s_t, i, dx[i], s->s_dx[i]);
                return ST_ERROR;
            }
    }
    st = s->set_time(s->inst, s->s_t);
    if (!failed(st)) st = read_states(s, 1);
    if (failed(st)) { say(s, "reading the restored states returned status %d", st); return st; }
    memcpy(s->z_prev, s->s_z, (s->nz ? s->nz : 1) * sizeof(double));
    s->t = s->s_t, s->next_time = s->s_next_time, s->next_defined = s->s_next_defined;
    s->terminated = s->s_terminated;
    s->restart = 1;
    return ST_OK;
}

/* --- entry points for the compiled master loops (FMI 2.0 shapes; the instance is the slave) --- */
int me_native_do_step(MeSlave *s, double t, double h, int no_prior) {
    int st = me_do_step(s, t, h, no_prior);
    return st == ME_STOP ? ST_DISCARD : st; /* with me_native_boolean_status: a stop request */
}

int me_native_boolean_status(MeSlave *s, int kind, int *value) {
    *value = kind == 3 && s->terminated; /* fmi2Terminated */
    return ST_OK;
}

int me_native_get_real(MeSlave *s, const unsigned *vr, size_t n, double *values) {
    return s->fmi3 ? ((F_real3)s->get_real)(s->inst, vr, n, values, n) : ((F_real2)s->get_real)(s->inst, vr, n, values);
}

int me_native_set_real(MeSlave *s, const unsigned *vr, size_t n, const double *values) {
    return s->fmi3 ? ((F_real3)s->set_real)(s->inst, vr, n, (double *)values, n)
                   : ((F_real2)s->set_real)(s->inst, vr, n, (double *)values);
}

/* the slave holds its one saved state itself: the pointer handed out is the slave */
int me_native_get_state(MeSlave *s, void **state) {
    *state = s;
    return me_save(s);
}

int me_native_set_state(MeSlave *s, void *state) {
    (void)state;
    return me_restore(s);
}

int me_native_free_state(MeSlave *s, void **state) {
    (void)s;
    *state = NULL;
    return ST_OK;
}

/* --- inquiries and the end ----------------------------------------------------------------- */
double me_time(MeSlave *s) { return s->t; }
int me_terminated(MeSlave *s) { return s->terminated; }

/* Statistics: rhs evaluations, CVODES steps, state, time, step and input events, restarts. */
void me_stats(MeSlave *s, long out[7]) {
    long v[7] = {s->n_rhs, s->n_steps, s->n_state, s->n_time, s->n_step, s->n_input, s->n_restarts};
    memcpy(out, v, sizeof v);
}

/* The event log: up to ``cap`` (time, kind) pairs from ``first``; returns the number of events. */
long me_events(MeSlave *s, long first, long cap, double *t, int *kind) {
    for (long i = 0; i < cap && first + i < s->n_log && first + i < ME_EVENT_LOG; i++) {
        t[i] = s->log_t[first + i];
        kind[i] = s->log_kind[first + i];
    }
    return s->n_log;
}

void me_free(MeSlave *s) {
    if (!s) return;
    if (s->fmu_state && s->free_state) s->free_state(s->inst, &s->fmu_state);
    if (s->cv) CVodeFree(&s->cv);
    if (s->LS) SUNLinSolFree(s->LS);
    if (s->A) SUNMatDestroy(s->A);
    if (s->y) N_VDestroy(s->y);
    if (s->abstol) N_VDestroy(s->abstol);
    if (s->ctx) SUNContext_Free(&s->ctx);
    if (s->lib) dlclose(s->lib);
    free(s->z_prev); free(s->zbuf); free(s->roots); free(s->s_z); free(s->s_x); free(s->s_dx);
    free(s->log_t); free(s->log_kind);
    free(s);
}
