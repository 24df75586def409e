/* Lag: a first-order lag with an input, der(x) = -k x + g u, y = x (no direct feedthrough), for
 * the model-exchange tests (two in a loop against the monolithic solution) and, with FMI3cs.xml,
 * the FMI 3.0 co-simulation event-mode tests (the framework's forward Euler at FIXED_SOLVER_STEP,
 * event mode and early return).  Parameter ``fault`` makes it misbehave from t = 0.5 s: 1 NaN
 * derivative, 2 a time event every 1e-7 s (chattering), 3 an event iteration that never settles,
 * 4 a NaN event indicator, 5/6 a crash/hang in getDerivatives, 7/8 a crash/hang in the update of
 * its event at 0.5 s; 0 (default): none.  Built on the Reference FMUs' framework (its include/ and
 * src/, read from ../shared at test time). */
#ifndef config_h
#define config_h

#define MODEL_IDENTIFIER Lag
#define INSTANTIATION_TOKEN "{6f1d0c5e-6b2a-4d53-9a51-1a7e0c3b5d21}"

#define MODEL_EXCHANGE

#define MAX_CONTINUOUS_STATES 1
#define MAX_EVENT_INDICATORS 1
#define EVENT_UPDATE

#define SET_FLOAT64

#define FIXED_SOLVER_STEP 1e-5
#define DEFAULT_STOP_TIME 5

typedef enum {
    vr_time, vr_x, vr_der_x, vr_k, vr_g, vr_u, vr_fault
} ValueReference;

typedef struct {
    double x, der_x, k, g, u, fault;
} ModelData;

#endif /* config_h */
