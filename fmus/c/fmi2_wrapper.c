/* FMI 2.0 co-simulation entry points over the model-independent core (rpr_core.h).
 *
 * Compiled with -fvisibility=hidden: only the fmi2* functions below are exported (the FMI
 * header marks them visible).  Model-exchange functions exist, as the standard's header
 * declares them, and return fmi2Error.
 */
#include <stdarg.h>
#include <string.h>

#include "fmi2Functions.h"
#include "rpr_core.h"

typedef struct {
    RprInstance *core;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
} Fmi2Component;

static void fmi2_log(void *env, const char *name, int status, const char *category, const char *message) {
    Fmi2Component *self = (Fmi2Component *)env;
    if (self && self->logger) self->logger(self->env, name, (fmi2Status)status, category, message);
}

#define CORE(c) (((Fmi2Component *)(c))->core)
#define CHECK(c)                                                                  \
    do {                                                                              \
        if (!(c)) return fmi2Error;                                                   \
    } while (0)

static fmi2Status st(int s) { return (fmi2Status)s; }

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    CHECK(c);
    return st(rpr_set_debug_logging(CORE(c), loggingOn, nCategories, categories));
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    Fmi2Component *self;
    (void)fmuResourceLocation;
    (void)visible;
    self = (Fmi2Component *)calloc(1, sizeof(Fmi2Component));
    if (!self) return NULL;
    self->logger = functions ? functions->logger : NULL;
    self->env = functions ? functions->componentEnvironment : NULL;
    if (fmuType != fmi2CoSimulation) {
        if (self->logger)
            self->logger(self->env, instanceName, fmi2Error, "logStatusError",
                         "this FMU supports co-simulation only, not model exchange");
        free(self);
        return NULL;
    }
    self->core = rpr_instantiate(instanceName, fmuGUID, fmi2_log, self, loggingOn);
    if (!self->core) {
        free(self);
        return NULL;
    }
    return self;
}

void fmi2FreeInstance(fmi2Component c) {
    if (!c) return;
    rpr_free(CORE(c));
    free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance;
    CHECK(c);
    return st(rpr_setup(CORE(c), startTime, stopTimeDefined != fmi2False, stopTime));
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    CHECK(c);
    return st(rpr_enter_init(CORE(c)));
}
fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    CHECK(c);
    return st(rpr_exit_init(CORE(c)));
}
fmi2Status fmi2Terminate(fmi2Component c) {
    CHECK(c);
    return st(rpr_terminate(CORE(c)));
}
fmi2Status fmi2Reset(fmi2Component c) {
    CHECK(c);
    return st(rpr_reset(CORE(c)));
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    CHECK(c);
    /* FMI 2.0 (Table 4.2 / the state machine): no getters before initialization mode */
    if (rpr_mode(CORE(c)) == RPR_MODE_INSTANTIATED) {
        rpr_log(CORE(c), RPR_ERROR, RPR_LOG_ERROR,
                "fmi2GetReal is not allowed in instantiated (call fmi2EnterInitializationMode first)");
        return fmi2Error;
    }
    return st(rpr_get_real(CORE(c), vr, nvr, value));
}
fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    CHECK(c);
    return st(rpr_set_real(CORE(c), vr, nvr, value));
}
fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    (void)value;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi2GetInteger", vr, nvr));
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    (void)value;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi2GetBoolean", vr, nvr));
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    (void)value;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi2GetString", vr, nvr));
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    (void)value;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi2SetInteger", vr, nvr));
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    (void)value;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi2SetBoolean", vr, nvr));
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    (void)value;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi2SetString", vr, nvr));
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    CHECK(c);
    return st(rpr_get_state(CORE(c), FMUstate));
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    CHECK(c);
    return st(rpr_set_state(CORE(c), FMUstate));
}
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    CHECK(c);
    return st(rpr_free_state(CORE(c), FMUstate));
}
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)FMUstate;
    CHECK(c);
    *size = rpr_state_size();
    return fmi2OK;
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size) {
    CHECK(c);
    return st(rpr_serialize(CORE(c), FMUstate, serializedState, size));
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    CHECK(c);
    return st(rpr_deserialize(CORE(c), serializedState, size, FMUstate));
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    CHECK(c);
    return st(rpr_directional_derivative(CORE(c), vUnknown_ref, nUnknown, vKnown_ref, nKnown, dvKnown, dvUnknown));
}

/* --- co-simulation ----------------------------------------------------------------------- */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    CHECK(c);
    return st(rpr_set_input_derivatives(CORE(c), vr, nvr, order, value));
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2GetRealOutputDerivatives (maxOutputDerivativeOrder is 0)"));
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(c);
    return st(rpr_do_step(CORE(c), currentCommunicationPoint, communicationStepSize));
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2CancelStep (doStep is synchronous)"));
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    CHECK(c);
    if (s == fmi2DoStepStatus) {
        *value = rpr_last_step_discarded(CORE(c)) ? fmi2Discard : fmi2OK;
        return fmi2OK;
    }
    return st(rpr_unsupported(CORE(c), "fmi2GetStatus for this status kind"));
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    CHECK(c);
    if (s == fmi2LastSuccessfulTime) {
        *value = rpr_time(CORE(c));
        return fmi2OK;
    }
    return st(rpr_unsupported(CORE(c), "fmi2GetRealStatus for this status kind"));
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s; (void)value;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2GetIntegerStatus"));
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    CHECK(c);
    if (s == fmi2Terminated) {
        *value = fmi2False;
        return fmi2OK;
    }
    return st(rpr_unsupported(CORE(c), "fmi2GetBooleanStatus for this status kind"));
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s; (void)value;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2GetStringStatus"));
}

/* --- model exchange: not provided ---------------------------------------------------------- */
fmi2Status fmi2EnterEventMode(fmi2Component c) {
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2EnterEventMode (model exchange)"));
}
fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info) {
    (void)info;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2NewDiscreteStates (model exchange)"));
}
fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) {
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2EnterContinuousTimeMode (model exchange)"));
}
fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation) {
    (void)noSetFMUStatePriorToCurrentPoint; (void)enterEventMode; (void)terminateSimulation;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2CompletedIntegratorStep (model exchange)"));
}
fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    (void)time;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2SetTime (model exchange)"));
}
fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    (void)x; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2SetContinuousStates (model exchange)"));
}
fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real derivatives[], size_t nx) {
    (void)derivatives; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2GetDerivatives (model exchange)"));
}
fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real eventIndicators[], size_t ni) {
    (void)eventIndicators; (void)ni;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2GetEventIndicators (model exchange)"));
}
fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    (void)x; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2GetContinuousStates (model exchange)"));
}
fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[], size_t nx) {
    (void)x_nominal; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi2GetNominalsOfContinuousStates (model exchange)"));
}
