/* A recording played back as an FMI 2.0 co-simulation FMU (fmus/replay.py generates replay_table.h).
 *
 * The table is compiled in: RP_N instants RP_TIME[] (strictly increasing, seconds) and RP_M
 * columns, row-major in RP_DATA[RP_N * RP_M].  Output j (value reference j) at time t is column j
 *   - hold (RP_LINEAR 0): at the last instant <= t (a sample holds until the next one);
 *   - linear (RP_LINEAR 1): interpolated between the two instants around t.
 * Before the first instant or after the last one the end value is held (the scene check refuses a
 * scene that runs outside the recording).  An instant within RP_EPS seconds of t counts as reached,
 * so a master's time that is the recorded time but for rounding reads that sample.
 *
 * The only state is the time (and a cached row index): the FMU state functions save and restore it,
 * so variable-step and iterative masters can roll back.  No inputs, no parameters.
 */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "replay_table.h"

#define RP_EPS 1e-9

typedef struct {
    double time;
    size_t row; /* last row with RP_TIME[row] <= time + RP_EPS (0 before the first) */
} State;

typedef struct {
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    char name[128];
    State s;
} Replay;

#define R ((Replay *)c)
#define NEED(c) do { if (!(c)) return fmi2Error; } while (0)

static void say(Replay *r, fmi2Status status, const char *msg) {
    if (r->logger) r->logger(r->env, r->name, status, "logStatusError", msg);
}

/* the row of time t: binary search from scratch (rows change by one per step: try that first) */
static size_t find_row(size_t hint, double t) {
    size_t lo = 0, hi = RP_N - 1, mid;
    double tt = t + RP_EPS;
    if (hint < RP_N && RP_TIME[hint] <= tt && (hint + 1 == RP_N || RP_TIME[hint + 1] > tt)) return hint;
    if (hint + 1 < RP_N && RP_TIME[hint + 1] <= tt && (hint + 2 == RP_N || RP_TIME[hint + 2] > tt)) return hint + 1;
    if (RP_TIME[0] > tt) return 0;
    while (lo < hi) { /* invariant: RP_TIME[lo] <= tt, and RP_TIME[hi + 1] > tt or hi is the last row */
        mid = lo + (hi - lo + 1) / 2;
        if (RP_TIME[mid] <= tt) lo = mid; else hi = mid - 1;
    }
    return lo;
}

static double value(const State *s, size_t j) {
    size_t i = s->row;
    double t0, t1, w;
    if (!RP_LINEAR || i + 1 >= RP_N || s->time <= RP_TIME[0]) return RP_DATA[i * RP_M + j];
    t0 = RP_TIME[i];
    t1 = RP_TIME[i + 1];
    w = (s->time - t0) / (t1 - t0);
    if (w <= 0.0) return RP_DATA[i * RP_M + j];
    if (w >= 1.0) return RP_DATA[(i + 1) * RP_M + j];
    return RP_DATA[i * RP_M + j] + w * (RP_DATA[(i + 1) * RP_M + j] - RP_DATA[i * RP_M + j]);
}

static void set_time(Replay *r, double t) {
    r->s.time = t;
    r->s.row = find_row(r->s.row, t);
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *f, fmi2Boolean visible, fmi2Boolean logging) {
    Replay *r;
    (void)resources; (void)visible; (void)logging;
    if (!f || !f->logger) return NULL;
    if (type != fmi2CoSimulation) {
        f->logger(f->componentEnvironment, name, fmi2Error, "logStatusError", "a replay FMU is co-simulation only");
        return NULL;
    }
    if (!guid || strcmp(guid, RP_GUID) != 0) {
        f->logger(f->componentEnvironment, name, fmi2Error, "logStatusError", "wrong GUID for this replay FMU");
        return NULL;
    }
    r = (Replay *)calloc(1, sizeof(Replay));
    if (!r) return NULL;
    r->logger = f->logger;
    r->env = f->componentEnvironment;
    strncpy(r->name, name ? name : "replay", sizeof r->name - 1);
    set_time(r, RP_TIME[0]);
    return r;
}

void fmi2FreeInstance(fmi2Component c) { free(c); }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[]) {
    (void)on; (void)n; (void)cats;
    NEED(c);
    return fmi2OK;
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDefined, fmi2Real tol, fmi2Real start,
                               fmi2Boolean stopDefined, fmi2Real stop) {
    (void)tolDefined; (void)tol; (void)stopDefined; (void)stop;
    NEED(c);
    set_time(R, start);
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { NEED(c); return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component c) { NEED(c); return fmi2OK; }
fmi2Status fmi2Terminate(fmi2Component c) { NEED(c); return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component c) {
    NEED(c);
    R->s.row = 0;
    set_time(R, RP_TIME[0]);
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    size_t i;
    NEED(c);
    for (i = 0; i < n; i++) {
        if (vr[i] >= RP_M) return fmi2Error;
        v[i] = value(&R->s, vr[i]);
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Real v[]) {
    (void)vr; (void)v;
    NEED(c);
    if (n) {
        say(R, fmi2Error, "a replay has outputs only: nothing can be set");
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[]) {
    (void)vr; (void)v; NEED(c); return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[]) {
    (void)vr; (void)v; NEED(c); return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[]) {
    (void)vr; (void)v; NEED(c); return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[]) {
    (void)vr; (void)v; NEED(c); return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[]) {
    (void)vr; (void)v; NEED(c); return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[]) {
    (void)vr; (void)v; NEED(c); return n ? fmi2Error : fmi2OK;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    (void)noSetPrior;
    NEED(c);
    if (!(h >= 0.0)) {
        say(R, fmi2Error, "doStep with a negative step size");
        return fmi2Error;
    }
    set_time(R, t + h);
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { NEED(c); return fmi2Error; }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) {
    (void)s; (void)v; NEED(c); return fmi2Discard;
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    NEED(c);
    if (s == fmi2LastSuccessfulTime) { *v = R->s.time; return fmi2OK; }
    return fmi2Discard;
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v) {
    (void)s; (void)v; NEED(c); return fmi2Discard;
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v) {
    NEED(c);
    if (s == fmi2Terminated) { *v = fmi2False; return fmi2OK; }
    return fmi2Discard;
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v) {
    (void)s; (void)v; NEED(c); return fmi2Discard;
}

/* FMU state: the time and row */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) {
    State *st;
    NEED(c);
    if (!s) return fmi2Error;
    st = *s ? (State *)*s : (State *)malloc(sizeof(State));
    if (!st) return fmi2Error;
    *st = R->s;
    *s = st;
    return fmi2OK;
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) {
    NEED(c);
    if (!s) return fmi2Error;
    R->s = *(const State *)s;
    return fmi2OK;
}
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) {
    NEED(c);
    if (s && *s) {
        free(*s);
        *s = NULL;
    }
    return fmi2OK;
}
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) {
    (void)s; (void)n; NEED(c); return fmi2Error;
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) {
    (void)s; (void)b; (void)n; NEED(c); return fmi2Error;
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s) {
    (void)b; (void)n; (void)s; NEED(c); return fmi2Error;
}
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real dv[], fmi2Real dz[]) {
    (void)u; (void)nu; (void)z; (void)nz; (void)dv; (void)dz; NEED(c); return fmi2Error;
}
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer order[], const fmi2Real v[]) {
    (void)vr; (void)order; (void)v; NEED(c); return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer order[], fmi2Real v[]) {
    (void)vr; (void)n; (void)order; (void)v; NEED(c); return fmi2Error;
}
