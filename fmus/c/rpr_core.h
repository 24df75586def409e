/* Model-independent co-simulation core shared by the FMI 2.0 and FMI 3.0 wrappers.
 *
 * One instance owns every value it needs (no globals), so any number of instances of any number
 * of FMUs may live in one process.  Variables are addressed by value reference (vr):
 *   vr 0                 time [s] (read-only)
 *   1 .. np              parameters
 *   then nm modes (discrete states of a block with events), nx states, nu inputs, ny outputs
 *   (in the block's declaration order).
 * The model data (sizes, defaults, names, the CasADi functions) comes from the generated
 * "rpr_model.h", which only rpr_core.c includes.
 *
 * Call order (either FMI version): instantiate -> [setup] -> enter_init -> set/get ->
 * exit_init -> { set inputs, do_step, get outputs }* -> terminate -> free.
 */
#ifndef RPR_CORE_H
#define RPR_CORE_H

#include <stddef.h>

enum { RPR_OK = 0, RPR_WARNING = 1, RPR_DISCARD = 2, RPR_ERROR = 3, RPR_FATAL = 4 };
enum { RPR_MODE_INSTANTIATED = 0, RPR_MODE_INIT = 1, RPR_MODE_STEP = 2, RPR_MODE_TERMINATED = 3,
       RPR_MODE_ERROR = 4, RPR_MODE_EVENT = 5 };
/* log categories (bit positions) */
enum { RPR_LOG_ERROR = 0, RPR_LOG_DISCARD = 1, RPR_LOG_WARNING = 2, RPR_LOG_NONLINEAR = 3,
       RPR_LOG_CALLS = 4, RPR_LOG_EVENTS = 5, RPR_N_LOG = 6 };

typedef struct RprInstance RprInstance;

/* The wrapper's logger: receives an already formatted message (never a format string). */
typedef void (*RprLogger)(void *env, const char *instance_name, int status, const char *category,
                          const char *message);

const char *rpr_guid(void);
const char *rpr_model_identifier(void);
const char *rpr_log_category_name(int category);
int rpr_log_category_index(const char *name);

RprInstance *rpr_instantiate(const char *name, const char *token, RprLogger logger, void *env,
                             int logging_on);
void rpr_free(RprInstance *c);
int rpr_set_debug_logging(RprInstance *c, int on, size_t n, const char *const categories[]);
void rpr_log(RprInstance *c, int status, int category, const char *fmt, ...);
int rpr_mode(const RprInstance *c);
const char *rpr_name(const RprInstance *c);

/* start time, and the stop time when defined (a doStep that would end past it is an error) */
int rpr_setup(RprInstance *c, double start_time, int stop_defined, double stop_time);
/* tolerance [s] of "this communication point is the previous one's end" and of the stop time */
#define RPR_TIME_TOL 1e-9
int rpr_enter_init(RprInstance *c);
int rpr_exit_init(RprInstance *c);
int rpr_terminate(RprInstance *c);
int rpr_reset(RprInstance *c);

int rpr_get_real(RprInstance *c, const unsigned int vr[], size_t n, double value[]);
int rpr_set_real(RprInstance *c, const unsigned int vr[], size_t n, const double value[]);
/* first-order input slopes for the next doStep only (FMI 2.0 canInterpolateInputs) */
int rpr_set_input_derivatives(RprInstance *c, const unsigned int vr[], size_t n, const int order[],
                              const double value[]);
/* other FMI types: the model has none, so only an empty request succeeds */
int rpr_no_such_variables(RprInstance *c, const char *function, const unsigned int vr[], size_t n);

int rpr_do_step(RprInstance *c, double t, double h);

/* FMI 3 event mode (blocks with events only; docs/explanation/events.md).  With early return the
   step stops at the first event, state at its left limit, and rpr_event_pending says so; the
   importer enters event mode and rpr_update_discrete_states applies the update. */
int rpr_has_event_mode(void);
void rpr_use_event_mode(RprInstance *c, int early_return);
int rpr_event_pending(const RprInstance *c);
int rpr_enter_event_mode(RprInstance *c);
int rpr_update_discrete_states(RprInstance *c, int *next_time_defined, double *next_time);
int rpr_enter_step_mode(RprInstance *c);
double rpr_time(const RprInstance *c);
int rpr_last_step_discarded(const RprInstance *c);

size_t rpr_state_size(void);
int rpr_get_state(RprInstance *c, void **state);
int rpr_set_state(RprInstance *c, const void *state);
int rpr_free_state(RprInstance *c, void **state);
int rpr_serialize(RprInstance *c, const void *state, char *buffer, size_t size);
int rpr_deserialize(RprInstance *c, const char *buffer, size_t size, void **state);

int rpr_directional_derivative(RprInstance *c, const unsigned int unknown[], size_t n_unknown,
                               const unsigned int known[], size_t n_known, const double seed[],
                               double sensitivity[]);

int rpr_unsupported(RprInstance *c, const char *function);

#endif
