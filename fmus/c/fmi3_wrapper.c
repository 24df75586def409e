/* FMI 3.0 co-simulation entry points over the model-independent core (rpr_core.h).
 *
 * Compiled with -fvisibility=hidden: only the fmi3* functions are exported.  Every function of
 * the FMI 3.0 header exists (importers such as FMPy look all of them up); those of model
 * exchange, scheduled execution and clocks return fmi3Error with a message.  All variables are
 * scalar Float64, so the other typed getters and setters accept only empty requests.
 */
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "rpr_core.h"

typedef struct {
    RprInstance *core;
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment env;
} Fmi3Component;

static void fmi3_log(void *env, const char *name, int status, const char *category, const char *message) {
    Fmi3Component *self = (Fmi3Component *)env;
    (void)name;
    if (self && self->logger) self->logger(self->env, (fmi3Status)status, category, message);
}

#define CORE(c) (((Fmi3Component *)(c))->core)
#define CHECK(c) \
    if (!(c)) return fmi3Error
static fmi3Status st(int s) { return (fmi3Status)s; }

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance c, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    CHECK(c);
    return st(rpr_set_debug_logging(CORE(c), loggingOn, nCategories, categories));
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible,
                                         fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
                                         fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate) {
    Fmi3Component *self;
    (void)resourcePath; (void)visible;
    (void)requiredIntermediateVariables; (void)intermediateUpdate;
    self = (Fmi3Component *)calloc(1, sizeof(Fmi3Component));
    if (!self) return NULL;
    self->logger = logMessage;
    self->env = instanceEnvironment;
    if ((eventModeUsed && !rpr_has_event_mode()) || nRequiredIntermediateVariables > 0) {
        if (logMessage)
            logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                       nRequiredIntermediateVariables > 0 ? "this FMU has no intermediate variables"
                                                          : "this FMU has no event mode (hasEventMode is false)");
        free(self);
        return NULL;
    }
    self->core = rpr_instantiate(instanceName, instantiationToken, fmi3_log, self, loggingOn);
    if (!self->core) {
        free(self);
        return NULL;
    }
    /* event mode with early return: doStep stops at each event, the importer applies it in event mode */
    if (eventModeUsed) rpr_use_event_mode(CORE(self), earlyReturnAllowed != fmi3False);
    return self;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   "this FMU supports co-simulation only, not model exchange");
    return NULL;
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible,
                                               fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   "this FMU supports co-simulation only, not scheduled execution");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance c) {
    if (!c) return;
    rpr_free(CORE(c));
    free(c);
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance c, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    (void)toleranceDefined; (void)tolerance;
    CHECK(c);
    if (rpr_setup(CORE(c), startTime, stopTimeDefined != fmi3False, stopTime) != RPR_OK) return fmi3Error;
    return st(rpr_enter_init(CORE(c)));
}
fmi3Status fmi3ExitInitializationMode(fmi3Instance c) {
    CHECK(c);
    return st(rpr_exit_init(CORE(c)));
}
fmi3Status fmi3EnterEventMode(fmi3Instance c) {
    CHECK(c);
    return st(rpr_enter_event_mode(CORE(c)));
}
fmi3Status fmi3Terminate(fmi3Instance c) {
    CHECK(c);
    return st(rpr_terminate(CORE(c)));
}
fmi3Status fmi3Reset(fmi3Instance c) {
    CHECK(c);
    return st(rpr_reset(CORE(c)));
}

fmi3Status fmi3GetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 values[],
                          size_t nValues) {
    CHECK(c);
    if (nValues != nvr) return st(rpr_unsupported(CORE(c), "fmi3GetFloat64 with nValues != nValueReferences (all variables are scalars)"));
    return st(rpr_get_real(CORE(c), vr, nvr, values));
}
fmi3Status fmi3SetFloat64(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Float64 values[],
                          size_t nValues) {
    CHECK(c);
    if (nValues != nvr) return st(rpr_unsupported(CORE(c), "fmi3SetFloat64 with nValues != nValueReferences (all variables are scalars)"));
    return st(rpr_set_real(CORE(c), vr, nvr, values));
}

#define NO_SUCH_GET(T, CT)                                                                            \
    fmi3Status fmi3Get##T(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, CT values[],     \
                          size_t nValues) {                                                           \
        (void)values; (void)nValues;                                                                  \
        CHECK(c);                                                                                     \
        return st(rpr_no_such_variables(CORE(c), "fmi3Get" #T, vr, nvr));                            \
    }
#define NO_SUCH_SET(T, CT)                                                                            \
    fmi3Status fmi3Set##T(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const CT values[], \
                          size_t nValues) {                                                           \
        (void)values; (void)nValues;                                                                  \
        CHECK(c);                                                                                     \
        return st(rpr_no_such_variables(CORE(c), "fmi3Set" #T, vr, nvr));                            \
    }
NO_SUCH_GET(Float32, fmi3Float32)
NO_SUCH_GET(Int8, fmi3Int8)
NO_SUCH_GET(UInt8, fmi3UInt8)
NO_SUCH_GET(Int16, fmi3Int16)
NO_SUCH_GET(UInt16, fmi3UInt16)
NO_SUCH_GET(Int32, fmi3Int32)
NO_SUCH_GET(UInt32, fmi3UInt32)
NO_SUCH_GET(Int64, fmi3Int64)
NO_SUCH_GET(UInt64, fmi3UInt64)
NO_SUCH_GET(Boolean, fmi3Boolean)
NO_SUCH_GET(String, fmi3String)
NO_SUCH_SET(Float32, fmi3Float32)
NO_SUCH_SET(Int8, fmi3Int8)
NO_SUCH_SET(UInt8, fmi3UInt8)
NO_SUCH_SET(Int16, fmi3Int16)
NO_SUCH_SET(UInt16, fmi3UInt16)
NO_SUCH_SET(Int32, fmi3Int32)
NO_SUCH_SET(UInt32, fmi3UInt32)
NO_SUCH_SET(Int64, fmi3Int64)
NO_SUCH_SET(UInt64, fmi3UInt64)
NO_SUCH_SET(Boolean, fmi3Boolean)
NO_SUCH_SET(String, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, size_t valueSizes[],
                         fmi3Binary values[], size_t nValues) {
    (void)valueSizes; (void)values; (void)nValues;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3GetBinary", vr, nvr));
}
fmi3Status fmi3SetBinary(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const size_t valueSizes[],
                         const fmi3Binary values[], size_t nValues) {
    (void)valueSizes; (void)values; (void)nValues;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3SetBinary", vr, nvr));
}
fmi3Status fmi3GetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Clock values[]) {
    (void)values;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3GetClock", vr, nvr));
}
fmi3Status fmi3SetClock(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Clock values[]) {
    (void)values;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3SetClock", vr, nvr));
}

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance c, fmi3ValueReference valueReference,
                                               size_t *nDependencies) {
    (void)valueReference; (void)nDependencies;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetNumberOfVariableDependencies (see ModelStructure)"));
}
fmi3Status fmi3GetVariableDependencies(fmi3Instance c, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[], fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[],
                                       fmi3DependencyKind dependencyKinds[], size_t nDependencies) {
    (void)dependent; (void)elementIndicesOfDependent; (void)independents; (void)elementIndicesOfIndependents;
    (void)dependencyKinds; (void)nDependencies;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetVariableDependencies (see ModelStructure)"));
}

fmi3Status fmi3GetFMUState(fmi3Instance c, fmi3FMUState *FMUState) {
    CHECK(c);
    return st(rpr_get_state(CORE(c), FMUState));
}
fmi3Status fmi3SetFMUState(fmi3Instance c, fmi3FMUState FMUState) {
    CHECK(c);
    return st(rpr_set_state(CORE(c), FMUState));
}
fmi3Status fmi3FreeFMUState(fmi3Instance c, fmi3FMUState *FMUState) {
    CHECK(c);
    return st(rpr_free_state(CORE(c), FMUState));
}
fmi3Status fmi3SerializedFMUStateSize(fmi3Instance c, fmi3FMUState FMUState, size_t *size) {
    (void)FMUState;
    CHECK(c);
    *size = rpr_state_size();
    return fmi3OK;
}
fmi3Status fmi3SerializeFMUState(fmi3Instance c, fmi3FMUState FMUState, fmi3Byte serializedState[], size_t size) {
    CHECK(c);
    return st(rpr_serialize(CORE(c), FMUState, (char *)serializedState, size));
}
fmi3Status fmi3DeserializeFMUState(fmi3Instance c, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState) {
    CHECK(c);
    return st(rpr_deserialize(CORE(c), (const char *)serializedState, size, FMUState));
}

fmi3Status fmi3GetDirectionalDerivative(fmi3Instance c, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                        const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                        size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    CHECK(c);
    if (nSeed != nKnowns || nSensitivity != nUnknowns)
        return st(rpr_unsupported(CORE(c), "fmi3GetDirectionalDerivative with nSeed != nKnowns or "
                                           "nSensitivity != nUnknowns (all variables are scalars)"));
    return st(rpr_directional_derivative(CORE(c), unknowns, nUnknowns, knowns, nKnowns, seed, sensitivity));
}
fmi3Status fmi3GetAdjointDerivative(fmi3Instance c, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                    size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed;
    (void)sensitivity; (void)nSensitivity;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetAdjointDerivative (providesAdjointDerivatives is false)"));
}

fmi3Status fmi3EnterConfigurationMode(fmi3Instance c) {
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3EnterConfigurationMode (no structural parameters)"));
}
fmi3Status fmi3ExitConfigurationMode(fmi3Instance c) {
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3ExitConfigurationMode (no structural parameters)"));
}

/* --- clocks: none ----------------------------------------------------------------------------- */
fmi3Status fmi3GetIntervalDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr,
                                  fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[]) {
    (void)intervals; (void)qualifiers;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3GetIntervalDecimal", vr, nvr));
}
fmi3Status fmi3GetIntervalFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr,
                                   fmi3UInt64 counters[], fmi3UInt64 resolutions[],
                                   fmi3IntervalQualifier qualifiers[]) {
    (void)counters; (void)resolutions; (void)qualifiers;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3GetIntervalFraction", vr, nvr));
}
fmi3Status fmi3GetShiftDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3Float64 shifts[]) {
    (void)shifts;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3GetShiftDecimal", vr, nvr));
}
fmi3Status fmi3GetShiftFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, fmi3UInt64 counters[],
                                fmi3UInt64 resolutions[]) {
    (void)counters; (void)resolutions;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3GetShiftFraction", vr, nvr));
}
fmi3Status fmi3SetIntervalDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr,
                                  const fmi3Float64 intervals[]) {
    (void)intervals;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3SetIntervalDecimal", vr, nvr));
}
fmi3Status fmi3SetIntervalFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr,
                                   const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    (void)counters; (void)resolutions;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3SetIntervalFraction", vr, nvr));
}
fmi3Status fmi3SetShiftDecimal(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr, const fmi3Float64 shifts[]) {
    (void)shifts;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3SetShiftDecimal", vr, nvr));
}
fmi3Status fmi3SetShiftFraction(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr,
                                const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    (void)counters; (void)resolutions;
    CHECK(c);
    return st(rpr_no_such_variables(CORE(c), "fmi3SetShiftFraction", vr, nvr));
}
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance c) {
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3EvaluateDiscreteStates (no clocks)"));
}
fmi3Status fmi3UpdateDiscreteStates(fmi3Instance c, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation,
                                    fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
                                    fmi3Float64 *nextEventTime) {
    int defined = 0, s;
    double next = 0.0;
    CHECK(c);
    s = rpr_update_discrete_states(CORE(c), &defined, &next);
    /* the core iterates the updates to the end itself: one call leaves nothing to update */
    if (discreteStatesNeedUpdate) *discreteStatesNeedUpdate = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (nominalsOfContinuousStatesChanged) *nominalsOfContinuousStatesChanged = fmi3False;
    if (valuesOfContinuousStatesChanged) *valuesOfContinuousStatesChanged = fmi3True;
    if (nextEventTimeDefined) *nextEventTimeDefined = defined ? fmi3True : fmi3False;
    if (nextEventTime) *nextEventTime = defined ? next : 0.0;
    return st(s);
}

/* --- model exchange: not provided --------------------------------------------------------- */
fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance c) {
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3EnterContinuousTimeMode (model exchange)"));
}
fmi3Status fmi3CompletedIntegratorStep(fmi3Instance c, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation) {
    (void)noSetFMUStatePriorToCurrentPoint; (void)enterEventMode; (void)terminateSimulation;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3CompletedIntegratorStep (model exchange)"));
}
fmi3Status fmi3SetTime(fmi3Instance c, fmi3Float64 time) {
    (void)time;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3SetTime (model exchange)"));
}
fmi3Status fmi3SetContinuousStates(fmi3Instance c, const fmi3Float64 x[], size_t nx) {
    (void)x; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3SetContinuousStates (model exchange)"));
}
fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance c, fmi3Float64 derivatives[], size_t nx) {
    (void)derivatives; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetContinuousStateDerivatives (model exchange)"));
}
fmi3Status fmi3GetEventIndicators(fmi3Instance c, fmi3Float64 eventIndicators[], size_t ni) {
    (void)eventIndicators; (void)ni;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetEventIndicators (model exchange)"));
}
fmi3Status fmi3GetContinuousStates(fmi3Instance c, fmi3Float64 x[], size_t nx) {
    (void)x; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetContinuousStates (model exchange)"));
}
fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance c, fmi3Float64 nominals[], size_t nx) {
    (void)nominals; (void)nx;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetNominalsOfContinuousStates (model exchange)"));
}
fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance c, size_t *n) {
    CHECK(c);
    *n = 0;
    return fmi3OK;
}
fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance c, size_t *n) {
    CHECK(c);
    *n = 0; /* a co-simulation FMU exposes no continuous states to the importer */
    return fmi3OK;
}

/* --- co-simulation ------------------------------------------------------------------------- */
fmi3Status fmi3EnterStepMode(fmi3Instance c) {
    CHECK(c);
    return st(rpr_enter_step_mode(CORE(c)));
}
fmi3Status fmi3GetOutputDerivatives(fmi3Instance c, const fmi3ValueReference vr[], size_t nvr,
                                    const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues) {
    (void)vr; (void)nvr; (void)orders; (void)values; (void)nValues;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3GetOutputDerivatives (maxOutputDerivativeOrder is 0)"));
}
fmi3Status fmi3DoStep(fmi3Instance c, fmi3Float64 currentCommunicationPoint, fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *eventHandlingNeeded,
                      fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    int s;
    double reached;
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(c);
    s = rpr_do_step(CORE(c), currentCommunicationPoint, communicationStepSize);
    reached = rpr_time(CORE(c));
    if (eventHandlingNeeded) *eventHandlingNeeded = rpr_event_pending(CORE(c)) ? fmi3True : fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn)
        *earlyReturn = (s <= RPR_WARNING && reached < currentCommunicationPoint + communicationStepSize) ? fmi3True
                                                                                                     : fmi3False;
    if (lastSuccessfulTime) *lastSuccessfulTime = reached;
    return st(s);
}

/* --- scheduled execution: not provided ------------------------------------------------------ */
fmi3Status fmi3ActivateModelPartition(fmi3Instance c, fmi3ValueReference clockReference, fmi3Float64 activationTime) {
    (void)clockReference; (void)activationTime;
    CHECK(c);
    return st(rpr_unsupported(CORE(c), "fmi3ActivateModelPartition (scheduled execution)"));
}
