/* The native engine's common part (cosim/master/kernels.py): what every compiled master loop
   starts with.  The types (FMI function pointers, rpr_slave, the control structs, the end
   codes) and the entry points' prototypes are generated into rpr_decls.h from their one
   declaration in cosim/master/entries.py; here are the calls every loop makes on a slave: set
   its inputs (and their slopes), step it, read its outputs, save and restore its state. */
#ifndef RPR_NATIVE_H
#define RPR_NATIVE_H

#include <stdint.h>
#include <stddef.h>
#include <stdbool.h>
#include <string.h>
#include <math.h>
#include <time.h>

#include "rpr_decls.h"
#include "crumb.h"

/* Discard, Error, Fatal, Pending: the statuses that end a step */
static inline int failing(int st) { return st >= ST_DISCARD && st <= ST_PENDING; }

static inline int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* numpy's maximum/minimum: NaN if either is NaN; Python's max/min: the first unless the second
   is larger/smaller */
static inline double np_max(double a, double b) { return (isnan(a) || isnan(b)) ? NAN : (b > a ? b : a); }
static inline double np_min(double a, double b) { return (isnan(a) || isnan(b)) ? NAN : (b < a ? b : a); }
static inline double py_max(double a, double b) { return b > a ? b : a; }
static inline double py_min(double a, double b) { return b < a ? b : a; }

/* Python's round(x) to whole nanoseconds: half to even (nearbyint in the default rounding mode) */
static inline int64_t round_ns(double x) {
    if (!(x < 9.0e18)) return INT64_MAX;
    return (int64_t)nearbyint(x);
}

/* FMI 2.0 Discard with fmi2Terminated (status kind 3): the slave asks to end the simulation */
static inline int stop_asked(rpr_slave *s) {
    int b = 0;
    if (s->fmi3 || !s->bool_status) return 0;
    if (((fmi2GetBooleanStatus_t)s->bool_status)(s->inst, 3, &b) > ST_WARNING) return 0;
    return b != 0;
}

/* input j of slave s from its source's value x, through its connection's linear transformation
   where the slave has one (CoupledSystem.gather: x * factor + offset) */
static inline double through(const rpr_slave *s, int32_t j, double x) {
    return s->in_factor ? x * s->in_factor[j] + s->in_offset[j] : x;
}

/* set the slave's inputs from in[] (its place in v) */
static inline int set_inputs(rpr_slave *s, const double *in) {
    if (!s->n_in && !s->callback) return 0;
    if (s->fmi3) return FMI(s->inst, C_SET, ((fmi3SetFloat64_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in,
                                                                        (size_t)s->n_in));
    return FMI(s->inst, C_SET, ((fmi2SetReal_t)s->set)(s->inst, s->in_vr, (size_t)s->n_in, in));
}

/* set the slopes of linear inputs (fmi2SetRealInputDerivatives, order 1) */
static inline int set_slopes(rpr_slave *s) {
    return FMI(s->inst, C_SET_DER, ((fmi2SetRealInputDerivatives_t)s->set_der)(s->inst, s->in_vr, (size_t)s->n_in,
                                                                                s->orders, s->slope));
}

/* read the slave's outputs into v */
static inline int get_outputs(rpr_slave *s, double *v) {
    if (!s->n_out && !s->callback) return 0;
    if (s->fmi3) return FMI(s->inst, C_GET, ((fmi3GetFloat64_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out,
                                                                        v + s->out_off, (size_t)s->n_out));
    return FMI(s->inst, C_GET, ((fmi2GetReal_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out, v + s->out_off));
}

/* one doStep from t of h; ST_STOP_REQUESTED when the slave asks to end the simulation (FMI 3.0
   terminateSimulation, FMI 2.0 Discard with fmi2Terminated) */
static inline int do_step(rpr_slave *s, double t, double h) {
    int st;
    s->calls++;
    if (s->fmi3) {
        bool own[3] = {0, 0, 0}, *f = s->step_flags ? s->step_flags : own;  /* event, terminate, early return */
        double last = t;
        if (s->planned_end) *s->planned_end = t + h;
        st = FMI_T(s->inst, C_DO_STEP, t, ((fmi3DoStep_t)s->do_step)(s->inst, t, h, s->no_prior != 0, &f[0], &f[1],
                                                                      &f[2], &last));
        if (s->last_time) *s->last_time = last;
        if (st <= ST_WARNING && f[1]) return ST_STOP_REQUESTED;
        return st;
    }
    st = FMI_T(s->inst, C_DO_STEP, t, ((fmi2DoStep_t)s->do_step)(s->inst, t, h, s->no_prior != 0));
    if (st == ST_DISCARD && stop_asked(s)) return ST_STOP_REQUESTED;
    return st;
}

/* After a doStep in event mode: the time the slave reached [s] (its last successful time after an
   early return, else the step's end; Slave.step_end) and whether it asks for event handling */
static inline double step_end(const rpr_slave *s) { return s->step_flags[2] ? *s->last_time : *s->planned_end; }
static inline int event_asked(const rpr_slave *s) { return s->step_flags[0] != 0; }

/* The recorded row of communication point t_ns [ns]: t [s], then v[rec_idx[0..n_rec)]. */
static inline void record_row(double *row, int64_t t_ns, const double *v, const int64_t *rec_idx, int32_t n_rec) {
    int32_t c;
    row[0] = (double)t_ns / 1e9;
    for (c = 0; c < n_rec; ++c) row[c + 1] = v[rec_idx[c]];
}

/* wall time in the slaves' calls so far [ns] */
static inline int64_t slaves_ns(const rpr_slave *S, int32_t n) {
    int64_t ns = 0;
    int32_t i;
    for (i = 0; i < n; ++i) ns += S[i].ns;
    return ns;
}

static inline int save_state(rpr_slave *s) {
    return FMI(s->inst, C_GET_STATE, ((fmi2GetFMUstate_t)s->get_state)(s->inst, s->state));
}

static inline int restore_state(rpr_slave *s) {
    return FMI(s->inst, C_SET_STATE, ((fmi2SetFMUstate_t)s->set_state)(s->inst, *s->state));
}

#endif
