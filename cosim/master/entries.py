"""The native kernels' interface, declared once: the records they share with Python (C structs),
their end codes and their entry points.  From these tables come both the C header every kernel
includes (:func:`header`, ``rpr_decls.h``, generated at build time) and the ctypes side
(:func:`ctypes_struct`, :func:`bind`), so the two cannot drift; ``tests/test_native.py`` checks
every generated layout against the C compiler's ``offsetof``/``sizeof``.

The kernels themselves are C files beside their modules: ``fastloop.c`` (Jacobi, Gauss-Seidel),
``adaptive_engine.c`` (adaptive, ecco), ``iterative_engine.c``, on the common ``native.h``
(:mod:`cosim.master.kernels` compiles them).
"""
from __future__ import annotations

import ctypes
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

from fmus.fmi_functions import c_typedefs

from ..slaves import crumb
from ..slaves.slave import Status

Field = tuple[str, str, str]  # (C type, name, what it is)


@dataclass(frozen=True)
class Record:
    """A C struct shared with Python: its typedef name and fields (C type, name, comment)."""

    name: str
    fields: tuple[Field, ...]

    def c(self) -> str:
        """The C ``typedef struct {...} name;``."""
        lines = [f"    {t}{'' if t.endswith('*') else ' '}{n};  /* {doc} */" for t, n, doc in self.fields]
        return "typedef struct {\n" + "\n".join(lines) + f"\n}} {self.name};\n"


_CTYPES = {"int8_t": ctypes.c_int8, "int32_t": ctypes.c_int32, "int64_t": ctypes.c_int64,
           "uint32_t": ctypes.c_uint32, "double": ctypes.c_double}


def _scalar(ctype: str):
    return _CTYPES[ctype.replace("volatile ", "").replace("const ", "").strip()]


def ctypes_struct(record: Record) -> type[ctypes.Structure]:
    """The ctypes mirror of ``record`` (pointers as ``c_void_p``: assigned addresses)."""
    return type(record.name, (ctypes.Structure,), {
        "_fields_": [(n, ctypes.c_void_p if t.endswith("*") else _scalar(t)) for t, n, _ in record.fields],
        "__doc__": f"Mirror of the C struct ``{record.name}`` (generated from the same declaration)."})


#: The slave struct ``rpr_slave``.  Pointers are addresses of the FMU's entry points or of numpy
#: arrays the Python side keeps alive.
SLAVE = Record("rpr_slave", (
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
    ("int32_t", "n_past", "jacobi_extrapolated: gathered inputs remembered so far (0 to 2)"),
    ("int32_t", "callback", "1: a callback slave (cosim.master.callbacks), its set and get called even with no "
                            "Float64 value (they convert its typed ports)"),
    ("const double *", "in_factor", "per input, the factor of its connection's linear transformation (0: none)"),
    ("const double *", "in_offset", "per input, the offset of its connection's linear transformation"),
    ("double *", "past", "jacobi_extrapolated: the gathered inputs at t_k-1, then at t_k-2 (0: not extrapolated)"),
    ("int32_t", "event_mode", "FMI 3.0 event mode: its doStep may return early at an event (fixed step: rpr_run)"),
    ("int32_t", "ahead", "event step: at the grid point already while the others finish a step an event cut"),
    ("int32_t", "stop", "event step: it asked to stop the simulation in this step (a request whose doStep is rolled "
                        "back goes with it)"),
    ("bool *", "step_flags", "event mode: eventHandlingNeeded, terminateSimulation, earlyReturn of its last doStep "
                             "(the slave's own)"),
    ("double *", "planned_end", "event mode: t + h of its last doStep [s] (the slave's own)"),
    ("double", "reached", "event step: the time it reached [s]"),
    ("int64_t", "calls", "doStep calls"),
    ("int64_t", "ns", "wall time in this slave's calls [ns] (with timing)"),
))

_STATS = ("int64_t", "master_ns", "wall time in this loop outside the slaves' calls (with timing)")

#: The variable-step loops' FMI 3.0 event state (docs/explanation/events.md): a step cut at the earliest early
#: return, every slave rolled back and the step retaken to it; an accepted step at whose end a slave asks for
#: event handling returns to Python (the event iteration).
_VARIABLE_EVENTS = (
    ("int32_t", "n_event", "slaves in FMI 3.0 event mode (0: none; then no step is cut)"),
    ("int32_t", "events_here", "in/out: events in a row within one output interval (AdaptiveStepper._events_here)"),
    ("int64_t", "event_cuts", "statistics: steps retaken to end at an event"),
    ("int64_t", "t_e_ns", "NO_PROGRESS: the early return's time [ns], the step's start"),
)

#: The adaptive controller's state and the run's counters (``ad_ctl``).
ADAPTIVE_CONTROL = Record("ad_ctl", (
    ("int64_t", "t_ns", "current point [ns]"), ("int64_t", "stop_ns", "stop time [ns]"),
    ("int64_t", "start_ns", "start time [ns]: the output grid's origin"),
    ("int64_t", "grid_ns", "output interval [ns] the steps land on (0: none)"),
    ("double", "h", "the next step tried [s]"), ("double", "h_prev", "the last accepted step [s] (0: none)"),
    ("double", "err_prev", "the last accepted step's error"),
    *[("double", k, "option") for k in ("rtol", "atol", "h_ref", "h_min", "h_max", "safety", "fac_min", "fac_max")],
    ("double", "k_i", "controller gain"), ("double", "k_p", "controller gain"),
    ("double", "p_lin", "order with linear inputs"), ("double", "p_hold", "order with held inputs"),
    ("int32_t", "any_interp", "some slave follows input slopes"), ("int32_t", "timing", "time the slaves' calls"),
    ("int64_t", "accepted", "statistics"), ("int64_t", "rejected", "statistics"),
    ("int64_t", "rollbacks", "statistics"), ("int64_t", "discards", "statistics"),
    ("double", "h_min_taken", "statistics"), ("double", "h_max_taken", "statistics"),
    ("int32_t", "status", "why a call returned early (AdaptiveEnd)"),
    ("int32_t", "bad_slave", "the slave of that status"), ("int32_t", "bad_status", "its FMI status"),
    ("double", "last_err", "the error at the step floor"),
    *_VARIABLE_EVENTS,
    _STATS,
))

#: ecco's controller state, its bonds (by index into v and the slaves) and their statistics (``ec_ctl``).
ECCO_CONTROL = Record("ec_ctl", (
    ("int64_t", "t_ns", "current point [ns]"), ("int64_t", "stop_ns", "stop time [ns]"),
    ("int64_t", "start_ns", "start time [ns]: the output grid's origin"),
    ("int64_t", "grid_ns", "output interval [ns] the steps land on (0: none)"),
    ("double", "h", "the next step [s]"), ("double", "h_prev", "the last step [s] (0: none)"),
    ("double", "err_prev", "the last step's error"),
    *[("double", k, "option") for k in ("rtol", "atol", "h_min", "h_max", "safety", "fac_min", "fac_max", "k_i",
                                        "k_p")],
    ("int32_t", "timing", "time the slaves' calls"), ("int32_t", "n_bonds", "power bonds"),
    ("const int64_t *", "out_idx", "per bond, v indices of y_a, y_b"),
    ("const int64_t *", "in_idx", "per bond, v indices of u_a, u_b"),
    ("const int32_t *", "side", "per bond, the slaves a, b"),
    ("const int32_t *", "slot", "per bond, u_a, u_b among their slaves' inputs"),
    ("double *", "y0", "work: the bonds' outputs at the step's start"), ("double *", "scaled", "work: eps per bond"),
    ("double *", "max_scaled", "per bond statistics"), ("double *", "max_residual", "[J]"),
    ("double *", "residual_sum", "[J]"), ("double *", "abs_residual_sum", "[J]"), ("double *", "energy", "[J]"),
    ("int64_t *", "over", "steps over tolerance"),
    ("int64_t", "accepted", "statistics"), ("double", "h_min_taken", "statistics"),
    ("double", "h_max_taken", "statistics"),
    ("int32_t", "floor_patience", "steps over tolerance at h_min before the run ends (0: never)"),
    ("int32_t", "at_floor", "such steps in a row"), ("int32_t", "ending", "the run ends before the next step"),
    ("int32_t", "end_bond", "the bond it ends on"), ("double", "end_scaled", "its eps"),
    ("int32_t", "status", "why a call returned early (EccoEnd)"),
    ("int32_t", "bad_slave", "the slave of that status (the bond for EC_NOT_FINITE, EC_FLOOR_PATIENCE)"),
    ("int32_t", "bad_status", "its FMI status"),
    *_VARIABLE_EVENTS,
    _STATS,
))

#: The iteration's options, state, scratch buffers and counters (``it_ctl``).
ITERATIVE_CONTROL = Record("it_ctl", (
    ("int32_t", "m", "cut connections (unknowns)"), ("int32_t", "max_iter", "passes per step"),
    ("int32_t", "newton", "1: Newton, 0: fixed point"), ("int32_t", "jac_auto", "directional derivatives allowed"),
    ("int32_t", "linear", "master.inputs linear: the first guess extrapolates"), ("int32_t", "timing", "time calls"),
    ("int32_t", "has_J", "a Jacobian is kept"), ("int32_t", "has_z_prev", "z at the previous point is known"),
    ("double", "omega", "fixed-point relaxation"), ("double", "rtol", "convergence"), ("double", "atol", "convergence"),
    ("double", "growth", "divergence: residual over this times the first"), ("double", "fd_rel", "FD perturbation"),
    ("double *", "z", "the cut inputs at the current point"), ("double *", "z_prev", "at the previous point"),
    ("double *", "zi", "the iterate"), ("double *", "g", "G(z)"), ("double *", "r", "G(z) - z"),
    ("double *", "e", "the scaled residual"), ("double *", "z_old", "the previous iterate"),
    ("double *", "r_old", "its residual"), ("double *", "dz", "the update"), ("double *", "J", "dG/dz (m x m)"),
    ("double *", "A", "I - J, factorised (m x m)"), ("double *", "w", "work (m)"),
    ("double *", "dv", "chain rule: d v / d z per value (nv x m)"), ("int8_t *", "dv_has", "per value: dv known"),
    ("double *", "du", "chain rule: d inputs / d z of one slave (max_in x m)"),
    ("double *", "L", "a slave's local Jacobian (max_feed x max_in)"), ("int32_t *", "cols", "its columns"),
    ("double *", "ends", "a slave's inputs at t+h"), ("double *", "base_in", "finite differences: its inputs"),
    ("double *", "base_out", "finite differences: its feeding outputs"),
    ("double *", "saved_out", "finite differences: its outputs"), ("uint32_t *", "known", "directional: inputs"),
    ("uint32_t *", "unknown", "directional: outputs"), ("double *", "seed", "directional: seed"),
    ("double *", "sens", "directional: result"),
    ("const int64_t *", "cut_src", "per unknown, its source in v"), ("const double *", "cut_factor", "transformation"),
    ("const double *", "cut_offset", "transformation"), ("int32_t *", "passes", "passes of each step of the call"),
    ("int64_t", "rollbacks", "statistics"), ("int64_t", "jacobians", "statistics"),
    ("int64_t", "directional", "statistics"), ("int64_t", "broyden", "statistics"),
    ("int64_t", "fd_steps", "statistics"),
    ("int32_t", "status", "why a call returned early (IterativeEnd)"),
    ("int32_t", "bad_slave", "the slave of that status"), ("int32_t", "bad_status", "its FMI status"),
    ("int32_t", "fail_it", "passes of the step that did not converge"), ("double", "fail_err", "its residual"),
    ("int32_t", "step", "1: steps are taken; 0: the start point (inputs set, outputs read, nothing stepped)"),
    ("int32_t", "n_passes", "out: the passes recorded in c->passes by this call"),
    # FMI 3.0 event mode (the oracle's Iterative._event_step): the iteration's state at a step's start, for a retake to an event
    ("double *", "v_kept", "event step: v at the step's start (nv)"), ("double *", "z_kept", "z there (m)"),
    ("double *", "z_prev_kept", "z_prev there (m)"), ("double *", "J_kept", "J there (m x m)"),
    ("double *", "start_kept", "every slave's inputs there, one after the other"),
    ("int32_t", "has_z_prev_kept", "has_z_prev there"), ("int32_t", "has_J_kept", "has_J there"),
    _STATS,
))

#: The fixed-step loops' event state across calls (``fx_ctl``, FMI 3.0 event mode; docs/explanation/events.md):
#: ``rpr_run``'s (Jacobi, Gauss-Seidel) and ``rpr_iter_run``'s (iterative).
FIXED_CONTROL = Record("fx_ctl", (
    ("int32_t", "n_event", "slaves in FMI 3.0 event mode (0: no event step)"),
    ("int32_t", "has_t_event", "1: the current point is an event that cut the step (t_event), not the grid point"),
    ("double", "t_event", "that event's time [s]"),
    ("int32_t", "events_in_step", "events in the current macro step so far"),
    ("int32_t", "max_events", "events in one macro step beyond which the run ends (chattering)"),
    ("int32_t", "status", "why the call returned (FixedEnd)"),
    ("int32_t", "who", "the event's slave (FX_EVENT, FX_GRID_EVENT, FX_CHATTERING)"),
    ("double", "t_e", "the event's time [s] (FX_EVENT, FX_CHATTERING)"),
))

CRUMB = Record("rpr_crumb_t", crumb.RECORD_FIELDS)

#: Every record of the generated header, in dependency order.
RECORDS = (CRUMB, SLAVE, FIXED_CONTROL, ADAPTIVE_CONTROL, ECCO_CONTROL, ITERATIVE_CONTROL)


class FixedEnd(IntEnum):
    """Why a fixed-step loop returned (``fx_ctl.status``) besides its step count: Jacobi's and
    Gauss-Seidel's (``rpr_run``: a failing call is ``fail_slave`` >= 0 with RUNNING or FAILED) and
    iterative's (``rpr_iter_run``: EVENT, GRID_EVENT, CHATTERING; a failure is ``it_ctl.status``)."""

    RUNNING = 0  # the steps asked for, the wall-time budget, or a failing call (its stop request handled after)
    EVENT = 1  # a step cut at the earliest early return of an event-mode slave, at t_e (the left limit)
    GRID_EVENT = 2  # a step completed at the grid point, where slave `who` asks for event handling
    CHATTERING = 3  # more than max_events events in one macro step (iterative: or an event at the step's start)
    FAILED = 4  # a call failed after the step was cut (a rollback or reading the outputs): the run fails
    STOPPED = 5  # a slave asked to stop in a step (its `stop`): the step completed, to the grid point or cut at t_e


class AdaptiveEnd(IntEnum):
    """Why the adaptive loop (Python or compiled) ended a step or a call early (``ad_ctl.status``)."""

    RUNNING = 0
    STOP_REQUESTED = 1  # a slave asked to end the simulation
    STEP_FLOOR = 2  # a rejected step at h_min
    GET_STATE = 3  # saving an FMU state failed
    SET_STATE = 4  # restoring it failed
    EVENT = 8  # an accepted step ended where an event-mode slave asks for event handling (its row the left limit)
    NO_PROGRESS = 9  # an event-mode slave returned early at the step's start (t_e_ns): the run fails


class EccoEnd(IntEnum):
    """Why the ecco loop ended (``ec_ctl.status``)."""

    RUNNING = 0
    STOP_REQUESTED = 1
    GET_STATE = 3  # with event-mode slaves: saving an FMU state failed
    SET_STATE = 4  # restoring it (to retake a step to an event) failed
    FLOOR_PATIENCE = 5  # over tolerance at h_min for floor_steps steps in a row
    SLAVE_FAILED = 6  # a Discard or error (ecco does not roll back)
    NOT_FINITE = 7  # a bond's residual is not finite
    EVENT = 8  # as AdaptiveEnd.EVENT
    NO_PROGRESS = 9  # as AdaptiveEnd.NO_PROGRESS


class IterativeEnd(IntEnum):
    """How an iterative macro step ended (``it_ctl.status``)."""

    OK = 0
    FAILED = 1  # a slave's call failed
    STOPPED = 2  # a slave asked to stop; the step was completed
    DIVERGED = 3
    NOT_CONVERGED = 4
    SAVE = 5  # saving an FMU state failed
    RESTORE = 6  # restoring it failed
    DIRECTIONAL = 7  # a directional derivative failed


class CallbackStatus(IntEnum):
    """What a callback slave's trampoline returns besides an FMI status (cosim.master.callbacks)."""

    NO_DERIVATIVES = -1  # the directional derivative: the slave provides none (output_jacobian is None)


#: The C enums of the header: (prefix, enum).  FMI statuses come as ST_<name>.
ENUMS: tuple[tuple[str, type[IntEnum]], ...] = (("ST_", Status), ("FX_", FixedEnd), ("AD_", AdaptiveEnd),
                                                 ("EC_", EccoEnd), ("IT_", IterativeEnd), ("CB_", CallbackStatus))


@dataclass(frozen=True)
class Entry:
    """A native entry point: its C name, return type and arguments (C type, name, what it is)."""

    name: str
    args: tuple[Field, ...]
    returns: str = "int64_t"

    def c(self) -> str:
        """Its C prototype."""
        args = ", ".join(f"{t}{'' if t.endswith('*') else ' '}{n}" for t, n, _ in self.args) or "void"
        return f"{self.returns} {self.name}({args});"


_IO = (("const int64_t *", "rec_idx", "the recorded values' indices in v"), ("int32_t", "n_rec", "their count"))

RUN = Entry("rpr_run", (
    ("rpr_slave *", "S", "the slaves"), ("int32_t", "n", "their count"),
    ("const int32_t *", "order", "the stepping order"),
    ("int32_t", "algorithm", "0 Jacobi, 1 Gauss-Seidel, 3 Jacobi with extrapolated inputs"),
    ("const double *", "weights", "algorithm 3: the held input's weights of u_k, u_k-1, u_k-2 by past values "
                                  "(3 x 3; 0 otherwise)"),
    ("double *", "v", "the value vector"), ("int64_t", "k0", "the first step's index"),
    ("int64_t", "nsteps", "steps to take at most"), ("int64_t", "start_ns", "the start time [ns]"),
    ("int64_t", "step_ns", "the step [ns]"),
    ("int32_t", "timing", "time the slaves' calls"), *_IO,
    ("int64_t", "rec_every", "record every this many steps"), ("double *", "rec", "the rows recorded"),
    ("int64_t *", "n_rows", "out: rows recorded"), ("int32_t *", "fail_slave", "out: the failing slave or -1"),
    ("int32_t *", "fail_status", "out: its status"), ("int64_t *", "master_ns", "in/out: the loop's own time [ns]"),
    ("int64_t", "budget_ns", "return after this much wall time (0: no limit)"),
    ("fx_ctl *", "c", "FMI 3.0 event mode: the event state (NULL: no event-mode slave)")))

ADAPT_RUN = Entry("rpr_adapt_run", (
    ("rpr_slave *", "S", "the slaves"), ("int32_t", "n", "their count"),
    ("const int32_t *", "order", "the stepping order"), ("double *", "v", "the value vector"),
    ("int64_t", "nv", "its length"), ("double *", "v_saved", "work: v at the step's start"),
    ("double *", "lo", "running minimum of v"), ("double *", "hi", "running maximum of v"),
    ("ad_ctl *", "c", "the controller"), *_IO, ("double *", "rec", "the rows recorded (at most one per step)"),
    ("int64_t *", "h_rec", "out: each accepted step [ns]"), ("int64_t", "max_steps", "steps at most"),
    ("int64_t", "budget_ns", "return after this much wall time (0: no limit)")))

ECCO_RUN = Entry("rpr_ecco_run", (
    ("rpr_slave *", "S", "the slaves"), ("int32_t", "n", "their count"),
    ("const int32_t *", "order", "the stepping order"), ("double *", "v", "the value vector"),
    ("int64_t", "nv", "its length"), ("double *", "v_saved", "work: v at the step's start (event mode)"),
    ("ec_ctl *", "c", "the controller"), *_IO, ("double *", "rec", "the rows recorded (at most one per step)"),
    ("int64_t *", "h_rec", "out: each accepted step [ns]"), ("int64_t", "max_steps", "steps at most"),
    ("int64_t", "budget_ns", "return after this much wall time (0: no limit)")))

ITER_RUN = Entry("rpr_iter_run", (
    ("rpr_slave *", "S", "the slaves"), ("int32_t", "n", "their count"),
    ("const int32_t *", "order", "the stepping order"), ("double *", "v", "the value vector"),
    ("int64_t", "nv", "its length"), ("it_ctl *", "c", "the iteration"), ("int64_t", "k0", "the first step's index"),
    ("int64_t", "nsteps", "steps to take at most"), ("int64_t", "start_ns", "the start time [ns]"),
    ("int64_t", "step_ns", "the step [ns]"), *_IO,
    ("int64_t", "rec_every", "record every this many steps"), ("double *", "rec", "the rows recorded"),
    ("int64_t *", "n_rows", "out: rows recorded"),
    ("int64_t", "budget_ns", "return after this much wall time (0: no limit)"),
    ("fx_ctl *", "ev", "FMI 3.0 event mode: the event state (NULL: no event-mode slave)")))

ITER_START = Entry("rpr_iter_start", (
    ("rpr_slave *", "S", "the slaves"), ("int32_t", "n", "their count"),
    ("const int32_t *", "order", "the stepping order"), ("double *", "v", "the value vector"),
    ("int64_t", "nv", "its length"), ("it_ctl *", "c", "the iteration"), ("double", "t", "the start time [s]")),
    returns="int32_t")

SET_CRUMB = Entry("rpr_set_crumb", (("void *", "p", "the crumb record (NULL: a private one)"),), returns="void")

ENTRIES = (SET_CRUMB, RUN, ADAPT_RUN, ECCO_RUN, ITER_RUN, ITER_START)

#: The FMI calls the kernels make (their function-pointer typedefs go into the header).
FMI_CALLS = ("fmi2DoStep", "fmi2GetReal", "fmi2SetReal", "fmi2SetRealInputDerivatives", "fmi2GetFMUstate",
             "fmi2SetFMUstate", "fmi2GetBooleanStatus", "fmi2GetDirectionalDerivative", "fmi3DoStep",
             "fmi3GetFloat64", "fmi3SetFloat64", "fmi3GetFMUState", "fmi3SetFMUState",
             "fmi3GetDirectionalDerivative")


def c_enum(prefix: str, enum: type[IntEnum]) -> str:
    """``enum { PREFIX_NAME = value, ... };``"""
    return "enum { " + ", ".join(f"{prefix}{m.name} = {int(m)}" for m in enum) + " };\n"


def header() -> str:
    """The generated C header ``rpr_decls.h``: FMI typedefs, crumb call numbers, enums, records,
    entry-point prototypes."""
    calls = "".join(f"#define C_{name} {crumb.CALL[call]}\n" for name, call in crumb.C_CALLS.items())
    includes = "".join(f"#include <{h}>\n" for h in ("stdint.h", "stddef.h", "stdbool.h"))
    guard = "".join(f"#{d} RPR_DECLS_H\n" for d in ("ifndef", "define"))
    return ("/* Generated from cosim/master/entries.py: do not edit. */\n" + guard + includes + "\n"
            + c_typedefs(FMI_CALLS) + "\n" + calls + "".join(c_enum(p, e) for p, e in ENUMS) + "\n"
            + "\n".join(r.c() for r in RECORDS) + "\n" + "\n".join(e.c() for e in ENTRIES) + "\n\n#endif\n")


_STRUCTS: dict[str, type[ctypes.Structure]] = {}


def struct(record: Record) -> type[ctypes.Structure]:
    """The one ctypes mirror of ``record`` (made once)."""
    if record.name not in _STRUCTS:
        _STRUCTS[record.name] = ctypes_struct(record)
    return _STRUCTS[record.name]


def argtype(ctype: str):
    """The ctypes argument type of a C argument type: a record pointer as ``POINTER`` of its
    mirror, other pointers as ``c_void_p`` (addresses, arrays, ``byref``)."""
    base = ctype.replace("const ", "").rstrip("* ").strip()
    for rec in RECORDS:
        if rec.name == base and ctype.endswith("*"):
            return ctypes.POINTER(struct(rec))
    return ctypes.c_void_p if ctype.endswith("*") else _scalar(ctype)


def bind(lib: ctypes.CDLL, entries: Sequence[Entry]) -> None:
    """Declare ``entries``' argument and return types on ``lib``."""
    for e in entries:
        fn = getattr(lib, e.name)
        fn.argtypes = [argtype(t) for t, _, _ in e.args]
        fn.restype = None if e.returns == "void" else argtype(e.returns)


__all__ = ["ADAPTIVE_CONTROL", "ADAPT_RUN", "AdaptiveEnd", "CRUMB", "CallbackStatus", "ECCO_CONTROL", "ECCO_RUN",
           "ENTRIES", "ENUMS", "EccoEnd", "Entry", "FIXED_CONTROL", "FixedEnd", "ITERATIVE_CONTROL", "ITER_RUN",
           "ITER_START", "IterativeEnd", "RECORDS", "RUN", "Record", "SLAVE", "bind", "ctypes_struct", "header",
           "struct"]
