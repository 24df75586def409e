/* Lag (see config.h): the model functions the Reference FMUs' framework calls. */
#include "config.h"
#include "model.h"
#include <math.h>
#include <stddef.h>

/* Faults 5 to 8 stand for an FMU that crashes or hangs inside an FMI call (the supervisor's case). */
static void misbehave(ModelInstance *comp, int crash, int hang) {
    const int fault = (int)M(fault);
    if (fault == crash) { volatile int *p = NULL; *p = 1; }
    if (fault == hang) for (;;) { }
}

Status setStartValues(ModelInstance *comp) {
    M(x) = 0.0;
    M(k) = 1.0;
    M(g) = 1.0;
    M(u) = 0.0;
    M(fault) = 0.0;
    comp->isDirtyValues = true;
    return OK;
}

Status calculateValues(ModelInstance *comp) {
    M(der_x) = M(fault) == 1 && comp->time > 0.5 ? NAN : -M(k) * M(x) + M(g) * M(u);
    comp->isDirtyValues = false;
    return OK;
}

static double *variable(ModelInstance *comp, ValueReference vr) {
    switch (vr) {
        case vr_x: return &M(x);
        case vr_der_x: return &M(der_x);
        case vr_k: return &M(k);
        case vr_g: return &M(g);
        case vr_u: return &M(u);
        case vr_fault: return &M(fault);
        default: return NULL;
    }
}

Status getFloat64(ModelInstance *comp, ValueReference vr, double values[], size_t nValues, size_t *index) {
    calculateValues(comp);
    if (vr == vr_time) {
        ASSERT_NVALUES(1);
        values[(*index)++] = comp->time;
        return OK;
    }
    double *p = variable(comp, vr);
    if (!p) {
        logError(comp, "Get Float64 is not allowed for value reference %u.", vr);
        return Error;
    }
    ASSERT_NVALUES(1);
    values[(*index)++] = *p;
    return OK;
}

Status setFloat64(ModelInstance *comp, ValueReference vr, const double values[], size_t nValues, size_t *index) {
    double *p = vr == vr_der_x ? NULL : variable(comp, vr);
    if (!p) {
        logError(comp, "Set Float64 is not allowed for value reference %u.", vr);
        return Error;
    }
    ASSERT_NVALUES(1);
    *p = values[(*index)++];
    comp->isDirtyValues = true;
    return OK;
}

size_t getNumberOfContinuousStates(ModelInstance *comp) {
    UNUSED(comp);
    return 1;
}

Status getContinuousStates(ModelInstance *comp, double x[], size_t nx) {
    ASSERT_SIZE_T(nx, 1);
    x[0] = M(x);
    return OK;
}

Status getNominalsOfContinuousStates(ModelInstance *comp, double nominals[], size_t nx) {
    UNUSED(comp);
    ASSERT_SIZE_T(nx, 1);
    nominals[0] = 1.0;
    return OK;
}

Status setContinuousStates(ModelInstance *comp, const double x[], size_t nx) {
    ASSERT_SIZE_T(nx, 1);
    M(x) = x[0];
    comp->isDirtyValues = true;
    return OK;
}

Status getDerivatives(ModelInstance *comp, double dx[], size_t nx) {
    ASSERT_SIZE_T(nx, 1);
    if (comp->time > 0.5) misbehave(comp, 5, 6);
    calculateValues(comp);
    dx[0] = M(der_x);
    return OK;
}

size_t getNumberOfEventIndicators(ModelInstance *comp) {
    UNUSED(comp);
    return 1;
}

Status getEventIndicators(ModelInstance *comp, double z[], size_t nz) {
    ASSERT_SIZE_T(nz, 1);
    z[0] = M(fault) == 4 && comp->time > 0.5 ? NAN : 1.0;
    return OK;
}

/* The faults' events: one at t = 0.5 s, then (fault 2) one every 1e-7 s, or (fault 3) an
 * iteration that always asks for more, or (faults 7, 8) a crash or a hang in that event's update. */
Status eventUpdate(ModelInstance *comp) {
    const int fault = (int)M(fault);
    if (comp->time >= 0.5) misbehave(comp, 7, 8);
    comp->newDiscreteStatesNeeded = fault == 3 && comp->time >= 0.5;
    comp->terminateSimulation = false;
    comp->nominalsOfContinuousStatesChanged = false;
    comp->valuesOfContinuousStatesChanged = false;
    comp->nextEventTimeDefined = fault == 2 || ((fault == 3 || fault >= 7) && comp->time < 0.5);
    comp->nextEventTime = comp->time < 0.5 ? 0.5 : comp->time + 1e-7;
    return OK;
}
