"""The native engine's common part: one C prelude every compiled master loop starts with, and
the slave struct, declared once (:data:`SLAVE_FIELDS`) and turned into both its C text and its
ctypes mirror :class:`CSlave`, so the two cannot drift.

The prelude holds the FMI function-pointer typedefs (generated from :mod:`fmus.fmi_functions`,
the one declaration of the FMI C signatures), ``rpr_slave``, the status codes, the monotonic
clock, and the calls every loop makes on a slave: set its inputs (and their slopes), step it,
read its outputs.  The loops themselves: :mod:`cosim.master.fastloop` (Jacobi and Gauss-Seidel,
fixed step), :mod:`cosim.master.adaptive_engine` (adaptive and ecco),
:mod:`cosim.master.iterative_engine` (iterative).  Compiling goes through :func:`fmus.native.load`
(one compiler choice, cached on disk).
"""
from __future__ import annotations

import ctypes
from collections.abc import Sequence

import numpy as np

from fmus.errors import BuildError
from fmus.fmi_functions import c_typedefs
from fmus.native import NoCompiler, load

from ..errors import UserError
from ..slaves import crumb
from ..slaves.crumb import C_SOURCE as CRUMB_SOURCE

#: The slave struct ``rpr_slave``: (C type, name, what it is).  Pointers are addresses of the
#: FMU's entry points or of numpy arrays the Python side keeps alive.
SLAVE_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("int32_t", "fmi3", "1 for an FMI 3.0 FMU"),
    ("int32_t", "n_in", "connected Float64 inputs"),
    ("int32_t", "n_out", "outputs read into v"),
    ("int32_t", "in_off", "the inputs' place in v"),
    ("int32_t", "out_off", "the outputs' place in v"),
    ("int32_t", "interp", "1: linear inputs (fmi2SetRealInputDerivatives)"),
    ("int32_t", "no_prior", "noSetFMUStatePriorToCurrentPoint of doStep (no state will be restored)"),
    ("int32_t", "rate", "multirate: doSteps per macro step (1: none)"),
    ("int64_t", "sub_ns", "multirate: the sub-step [ns]"),
    ("void *", "inst", "the FMU instance"),
    ("void *", "do_step", "fmi2DoStep / fmi3DoStep"),
    ("void *", "get", "fmi2GetReal / fmi3GetFloat64"),
    ("void *", "set", "fmi2SetReal / fmi3SetFloat64"),
    ("void *", "set_der", "fmi2SetRealInputDerivatives (interp)"),
    ("void *", "get_state", "fmi2GetFMUstate / fmi3GetFMUState"),
    ("void *", "set_state", "fmi2SetFMUstate / fmi3SetFMUState"),
    ("void *", "bool_status", "fmi2GetBooleanStatus (0: none): a Discard that asks to stop"),
    ("void *", "dir_der", "fmi2GetDirectionalDerivative / fmi3GetDirectionalDerivative (0: none)"),
    ("void **", "state", "the slave's FMU state, allocated by its first get"),
    ("double *", "last_time", "FMI 3.0: where lastSuccessfulTime of fmi3DoStep goes (the slave's own report)"),
    ("const uint32_t *", "in_vr", "value references of the inputs"),
    ("const int64_t *", "in_src", "per input, the index in v of its source"),
    ("const uint32_t *", "out_vr", "value references of the outputs"),
    ("const int32_t *", "orders", "derivative orders of the inputs (all 1)"),
    ("const int8_t *", "fresh", "per input: its source stepped before (interpolated, not extrapolated)"),
    ("double *", "hist", "fixed step: the inputs' previous values (slopes of linear inputs)"),
    ("double *", "slope", "input slopes [unit/s]"),
    ("double *", "base", "multirate: the inputs pushed for the first sub-step"),
    ("double *", "cur", "variable step: the sources' values at the current point"),
    ("double *", "prev", "variable step: the sources' values at the previous point"),
    ("double *", "guess", "variable step: the extrapolated guess of each input's source"),
    ("const int64_t *", "cut", "iterative: per input, its unknown in z (-1: taken from its source)"),
    ("double *", "start_in", "iterative: the inputs at t"),
    ("double *", "last_in", "iterative: the inputs of its last run in this step"),
    ("int32_t", "has_last", "iterative: it ran in this step"),
    ("int32_t", "n_feed", "iterative: its outputs that feed some input"),
    ("const int32_t *", "feed", "iterative: their positions among its outputs"),
    ("int32_t", "memoryless", "Jacobi: evaluated within the exchange, after every output is read"),
    ("int64_t", "calls", "doStep calls"),
    ("int64_t", "ns", "wall time in this slave's calls [ns] (with timing)"),
)

_CTYPES = {"int32_t": ctypes.c_int32, "int64_t": ctypes.c_int64, "double": ctypes.c_double}


def c_struct(name: str, fields: Sequence[tuple[str, str, str]]) -> str:
    """The C ``typedef struct {...} name;`` of ``fields`` ((C type, name, comment))."""
    lines = [f"    {t}{'' if t.endswith('*') else ' '}{n};  /* {doc} */" for t, n, doc in fields]
    return "typedef struct {\n" + "\n".join(lines) + f"\n}} {name};\n"


def ctypes_struct(name: str, fields: Sequence[tuple[str, str, str]]) -> type[ctypes.Structure]:
    """The ctypes mirror of :func:`c_struct` (pointers as ``c_void_p``: assigned addresses)."""
    return type(name, (ctypes.Structure,), {
        "_fields_": [(n, ctypes.c_void_p if t.endswith("*") else _CTYPES[t]) for t, n, _ in fields],
        "__doc__": f"Mirror of the C struct ``{name}`` (generated from the same field list)."})


CSlave = ctypes_struct("rpr_slave", SLAVE_FIELDS)

_FMI_CALLS = ("fmi2DoStep", "fmi2GetReal", "fmi2SetReal", "fmi2SetRealInputDerivatives", "fmi2GetFMUstate",
              "fmi2SetFMUstate", "fmi2GetBooleanStatus", "fmi2GetDirectionalDerivative", "fmi3DoStep",
              "fmi3GetFloat64", "fmi3SetFloat64", "fmi3GetFMUState", "fmi3SetFMUState",
              "fmi3GetDirectionalDerivative")

#: The C every compiled loop starts with (module docstring).
PRELUDE = r"""
#include <stdint.h>
#include <stddef.h>
#include <stdbool.h>
#include <string.h>
#include <math.h>
#include <time.h>

""" + c_typedefs(_FMI_CALLS) + "\n" + CRUMB_SOURCE + "\n" + c_struct("rpr_slave", SLAVE_FIELDS) + r"""
enum { ST_OK = 0, ST_WARNING = 1, ST_DISCARD = 2, ST_STOP = 100 };

/* Discard, Error, Fatal, Pending: the statuses that end a step */
static inline int failing(int st) { return st >= 2 && st <= 5; }

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

/* FMI 2.0 Discard with fmi2Terminated (status kind 3): the slave asks to end the simulation */
static int stop_asked(rpr_slave *s) {
    int b = 0;
    if (s->fmi3 || !s->bool_status) return 0;
    if (((fmi2GetBooleanStatus_t)s->bool_status)(s->inst, 3, &b) > ST_WARNING) return 0;
    return b != 0;
}

/* set the slave's inputs from in[] (its place in v) */
static inline int set_inputs(rpr_slave *s, const double *in) {
    if (!s->n_in) return 0;
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
    if (!s->n_out) return 0;
    if (s->fmi3) return FMI(s->inst, C_GET, ((fmi3GetFloat64_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out,
                                                                        v + s->out_off, (size_t)s->n_out));
    return FMI(s->inst, C_GET, ((fmi2GetReal_t)s->get)(s->inst, s->out_vr, (size_t)s->n_out, v + s->out_off));
}

/* one doStep from t of h; ST_STOP when the slave asks to end the simulation (FMI 3.0
   terminateSimulation, FMI 2.0 Discard with fmi2Terminated) */
static inline int do_step(rpr_slave *s, double t, double h) {
    int st;
    s->calls++;
    if (s->fmi3) {
        bool ev = 0, term = 0, early = 0;
        double last = t;
        st = FMI_T(s->inst, C_DO_STEP, t, ((fmi3DoStep_t)s->do_step)(s->inst, t, h, s->no_prior != 0, &ev, &term,
                                                                      &early, &last));
        if (s->last_time) *s->last_time = last;
        if (st <= ST_WARNING && term) return ST_STOP;
        return st;
    }
    st = FMI_T(s->inst, C_DO_STEP, t, ((fmi2DoStep_t)s->do_step)(s->inst, t, h, s->no_prior != 0));
    if (st == ST_DISCARD && stop_asked(s)) return ST_STOP;
    return st;
}

/* wall time in the slaves' calls so far [ns] */
/* The recorded row of communication point t_ns [ns]: t [s], then v[rec_idx[0..n_rec)]. */
static inline void record_row(double *row, int64_t t_ns, const double *v, const int64_t *rec_idx, int32_t n_rec) {
    int32_t c;
    row[0] = (double)t_ns / 1e9;
    for (c = 0; c < n_rec; ++c) row[c + 1] = v[rec_idx[c]];
}

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
"""


def compile_loop(source: str, stem: str, entries: dict[str, list] | None = None) -> ctypes.CDLL:
    """:data:`PRELUDE` + ``source`` compiled (once; cached on disk by :func:`fmus.native.load`)
    and loaded; each of ``entries`` (function name -> ctypes argument types) is declared as
    returning ``int64_t``.  Raises :class:`UserError` when no C compiler works or the source does
    not compile."""
    try:
        lib = load(PRELUDE + source, stem)
    except NoCompiler as exc:
        raise UserError(f"the compiled master loop needs a C compiler ({exc}); "
                        f"set master.engine: python to use the Python loop") from None
    except BuildError as exc:
        raise UserError(f"compiling the master loop failed: {exc}") from None
    crumb.register_library(lib)  # its FMI calls write this process's breadcrumb (cosim.slaves.crumb)
    for name, argtypes in (entries or {}).items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = ctypes.c_int64, argtypes
    return lib



def builds(library) -> bool:
    """True when ``library()`` (a compiled loop's loader, e.g. :func:`cosim.master.fastloop.library`)
    builds and loads here."""
    try:
        library()
    except UserError:
        return False
    return True


class SlaveArray:
    """The :class:`CSlave` array of a system's slaves with their entry points and layout filled in
    (:meth:`cosim.slaves.slave.Slave.native`, the system's value-vector offsets and value
    references); the numpy arrays the structs point into are kept alive here (:meth:`keep`)."""

    def __init__(self, system, *, states: bool = False):
        n = len(system.slaves)
        self.arr = (CSlave * n)()
        self.entries = []
        self._keep: list = []
        self.states = (ctypes.c_void_p * n)()  # the FMU states (states=True), freed by free_states()
        for i, s in enumerate(system.slaves):
            ne = s.native()
            if ne is None:
                raise UserError(f"{s.name} has no C entry points; use master.engine: python")
            self.entries.append(ne)
            c = self.arr[i]
            c.fmi3, c.n_in, c.n_out = int(ne.fmi3), len(system.in_vrs[i]), len(system.out_vrs[i])
            c.in_off, c.out_off = system.in_off[i], system.out_off[i]
            # the slave's own promise (cosim.slaves.fmu: true unless the algorithm may restore a state)
            c.no_prior, c.rate, c.sub_ns = int(getattr(s, "no_prior", not s.can_rollback)), 1, 0
            c.inst, c.do_step, c.get, c.set = ne.instance, ne.do_step, ne.get_real, ne.set_real
            c.bool_status, c.last_time = ne.get_boolean_status, ne.last_time
            c.memoryless = int(getattr(s.description, "memoryless", False))
            if states:
                c.get_state, c.set_state = ne.get_state, ne.set_state
                c.state = ctypes.addressof(self.states) + i * ctypes.sizeof(ctypes.c_void_p)
            self.keep(system.in_vrs[i], system.in_src[i], system.out_vrs[i])
            c.in_vr = system.in_vrs[i].ctypes.data if c.n_in else None
            c.in_src = system.in_src[i].ctypes.data if c.n_in else None
            c.out_vr = system.out_vrs[i].ctypes.data if c.n_out else None

    def keep(self, *arrays: np.ndarray) -> None:
        """Keep ``arrays`` alive as long as the structs that point into them."""
        self._keep += arrays

    def buffer(self, values, dtype=np.float64) -> int:
        """The address of a kept contiguous copy of ``values`` (or of ``values`` itself when it is
        already a contiguous array of ``dtype``: the struct then writes into it)."""
        a = values if isinstance(values, np.ndarray) and values.dtype == dtype and values.flags.c_contiguous \
            else np.ascontiguousarray(values, dtype=dtype)
        self.keep(a)
        return a.ctypes.data if a.size else 0

    def __len__(self) -> int:
        return len(self.arr)

    def __getitem__(self, i: int):
        return self.arr[i]

    def free_states(self) -> None:
        """Free the FMU states (before the instances are freed)."""
        from fmus.fmi_functions import prototype

        for i, ne in enumerate(self.entries):
            if self.states[i] and ne.free_state:
                proto = prototype("fmi3FreeFMUState" if ne.fmi3 else "fmi2FreeFMUstate")
                slot = ctypes.c_void_p.from_address(ctypes.addressof(self.states) + i * ctypes.sizeof(ctypes.c_void_p))
                proto(ne.free_state)(ne.instance, ctypes.byref(slot))
                self.states[i] = None


__all__ = ["CSlave", "PRELUDE", "SLAVE_FIELDS", "SlaveArray", "c_struct", "compile_loop", "ctypes_struct"]
