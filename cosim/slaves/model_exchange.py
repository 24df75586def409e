"""Model-exchange FMUs (FMI 2.0 and 3.0) as slaves: the FMU's continuous states are integrated
between communication points by SUNDIALS CVODES inside a small compiled slave
(``c/model_exchange.c``, built and cached by :mod:`fmus.c_loader`), so a right-hand-side evaluation
costs two FMI calls from C and no Python.

Between communication points the slave handles the FMU's events itself: state events (CVODES's
root finding on the event indicators), time events (the FMU's next event time is a stop time of
the integration), step events (``CompletedIntegratorStep``) and input events (an indicator whose
sign the inputs set at a communication point changed); at each, event mode and the event
iteration (at most 100 rounds), then a solver restart.  ``terminateSimulation`` ends the run as
``stopped``.  Rollback: the FMU state plus a solver restart where the FMU declares
``canGetAndSetFMUstate``; otherwise, for an FMU with no discrete variable, its time and
continuous states set back through the ME interface (checked on every restore: the derivatives
there must be the saved ones, else the FMU has a hidden discrete state and the run says so).

Bounds (a run ends with the FMU, time and cause named): more than :data:`MAX_EVENTS_PER_STEP`
events in one communication step (chattering), :data:`MAX_SOLVER_STEPS` CVODES steps in one, an
event iteration that does not settle, NaN derivatives or event indicators.
"""
from __future__ import annotations

import ctypes
from ctypes import POINTER, c_char_p, c_double, c_int, c_long, c_void_p
from functools import lru_cache
from pathlib import Path

import numpy as np

from fmus.errors import BuildError
from fmus.c_loader import NoCompiler, library_path

from ..errors import UserError
from . import crumb
from .crumb import CALL, enter, leave
from .fmu_slave import FmuSlave, _addr, _Get2, _Get3, _Set2, _Set3
from .slave import FAILING, NativeEntry, Slave, Status

#: CVODES's relative tolerance when neither the scene (``rtol:``) nor the FMU's DefaultExperiment
#: asks for a tighter one; the absolute tolerance of each state is rtol times its nominal value.
DEFAULT_RTOL = 1e-6
#: Chattering: more events than this in one communication step end the run.
MAX_EVENTS_PER_STEP = 1000
#: CVODES steps in one communication step beyond which the run ends (a model CVODES cannot advance).
MAX_SOLVER_STEPS = 1_000_000
#: me_do_step's result when the FMU asked to end the simulation.
_ME_STOP = 100
#: Event kinds of the slave's event log.
EVENT_KINDS = {1: "state event", 2: "time event", 3: "step event", 4: "input event"}

_SOURCE = Path(__file__).with_name("c") / "model_exchange.c"
#: SUNDIALS libraries the slave links (Debian's libsundials-dev).
_LIBS = ("-lsundials_cvodes", "-lsundials_nvecserial", "-lsundials_sunlinsoldense", "-lsundials_sunmatrixdense",
         "-ldl")


@lru_cache(maxsize=1)
def _library() -> ctypes.CDLL:
    """The compiled slave (built once per source and compiler, cached on disk)."""
    try:
        path = library_path(_SOURCE.read_text(), "model_exchange", libs=_LIBS)
    except NoCompiler as exc:
        raise UserError(f"model-exchange FMUs need a C compiler ({exc})") from None
    except BuildError as exc:
        raise UserError("model-exchange FMUs need SUNDIALS CVODES (Debian: apt-get install libsundials-dev; "
                        f"bash .ci/setup installs it): compiling {_SOURCE.name} failed: "
                        f"{str(exc).splitlines()[0] if str(exc) else ''}") from None
    lib = ctypes.CDLL(str(path))
    lib.me_new.restype = c_void_p
    lib.me_new.argtypes = [c_char_p, c_int, c_void_p, c_long, c_long, c_int, c_int, c_double, c_long, c_long]
    lib.me_message.restype = c_char_p
    lib.me_message.argtypes = [c_void_p]
    for name in ("me_save", "me_restore", "me_terminated", "me_free"):
        getattr(lib, name).argtypes = [c_void_p]
    lib.me_start.argtypes = [c_void_p, c_double]
    lib.me_do_step.argtypes = [c_void_p, c_double, c_double, c_int]
    lib.me_time.restype = c_double
    lib.me_time.argtypes = [c_void_p]
    lib.me_free.restype = None
    lib.me_stats.restype = None
    lib.me_stats.argtypes = [c_void_p, POINTER(c_long)]
    lib.me_events.restype = c_long
    lib.me_events.argtypes = [c_void_p, c_long, c_long, POINTER(c_double), POINTER(c_int)]
    return lib


def available() -> str:
    """'' when model-exchange FMUs can run here, else why not (one line)."""
    try:
        _library()
    except UserError as exc:
        return str(exc)
    return ""


class ModelExchangeSlave(FmuSlave):
    """A model-exchange FMU stepped as a co-simulation slave (see the module docstring).  FMPy
    loads and instantiates it; everything from the end of initialisation on runs in C."""

    def __init__(self, name: str, path: Path, description=None):
        super().__init__(name, path, description)
        self._me = None  # the compiled slave (a pointer), made at the end of initialisation
        self._t0 = 0.0
        self._tolerance: float | None = None

    # lifecycle ---------------------------------------------------------------------------------
    def instantiate(self) -> None:
        self._me_free()
        super().instantiate()

    def _make(self, guid: str, unzip: str, ident: str):
        return self.fmi.make(self, guid, unzip, ident, model_exchange=True)

    def _bind_step(self, dll) -> None:
        if self.fmi3:
            self._get, self._set = _Get3(_addr(dll.fmi3GetFloat64)), _Set3(_addr(dll.fmi3SetFloat64))
        else:
            self._get, self._set = _Get2(_addr(dll.fmi2GetReal)), _Set2(_addr(dll.fmi2SetReal))
        self._step = self._me_step

    @property
    def rtol(self) -> float:
        """CVODES's relative tolerance: the scene's ``rtol:``, else the tighter of
        :data:`DEFAULT_RTOL` and the FMU's DefaultExperiment tolerance."""
        d = self.description
        if d.solver_rtol is not None:
            return float(d.solver_rtol)
        return min(DEFAULT_RTOL, d.default_experiment.get("tolerance", DEFAULT_RTOL))

    def enter_initialization(self, start_time: float, stop_time: float, tolerance: float | None = None) -> None:
        self._t0 = start_time
        super().enter_initialization(start_time, stop_time, self.rtol if tolerance is None else tolerance)

    def exit_initialization(self) -> None:
        super().exit_initialization()
        lib, d = _library(), self.description
        nx, nz = self._sizes()
        self._me = lib.me_new(str(self.fmu.dll._name).encode(), int(self.fmi3), self.fmu.component,
                              nx, nz, int(d.needs_completed_integrator_step),
                              int(d.rollback_through == "FMU state" and self.can_rollback), self.rtol,
                              MAX_EVENTS_PER_STEP, MAX_SOLVER_STEPS)
        if not self._me:
            raise UserError(f"{self.name}: out of memory for the model-exchange slave")
        crumb.name_instance(self.name, False, self._me)  # the compiled loops name it by this pointer
        enter(self._ck, CALL["fmi2ExitInitializationMode"], self._t0)
        try:
            st = lib.me_start(self._me, self._t0)
        finally:
            leave()
        if st == _ME_STOP:
            raise UserError(f"{self.name}: the FMU asked to terminate the simulation in its initial event iteration "
                            f"at t = {self._t0:g} s")
        if st in FAILING:
            raise self._failed("the initial event iteration", self._message())

    def _sizes(self) -> tuple[int, int]:
        """Numbers of continuous states and event indicators: FMI 3.0 asks the instance (array
        sizes follow structural parameters), FMI 2.0 has them in its XML."""
        d = self.description
        if not self.fmi3:
            return d.continuous_states, d.event_indicators
        sizes = []
        for what in ("ContinuousStates", "EventIndicators"):
            n = ctypes.c_size_t()
            fn = getattr(self.fmu.dll, f"fmi3GetNumberOf{what}")
            fn.argtypes, fn.restype = [c_void_p, POINTER(ctypes.c_size_t)], c_int
            if fn(self.fmu.component, ctypes.byref(n)) in FAILING:
                raise self._failed(f"fmi3GetNumberOf{what}", self.last_message or "failed")
            sizes.append(int(n.value))
        return sizes[0], sizes[1]

    @property
    def last_message(self) -> str:
        """The compiled slave's message about its last failure (also when a compiled master loop
        made the call), else the FMU's last log message."""
        msg = self._message() if getattr(self, "_me", None) else ""
        return msg or Slave.last_message.fget(self)

    def _message(self) -> str:
        return (_library().me_message(self._me) or b"").decode(errors="replace") if self._me else ""

    def _me_step(self, t: float, h: float) -> int:
        st = _library().me_do_step(self._me, t, h, 1 if self.no_prior else 0)
        if st == _ME_STOP:
            return Status.STOP_REQUESTED
        return st

    def bind(self, in_vrs, in_buf, out_vrs, out_buf) -> None:
        super().bind(in_vrs, in_buf, out_vrs, out_buf)
        n = self._n_in
        self._pushed, self._saved_in = np.zeros(max(1, n)), np.zeros(max(1, n))  # last set; set at the save
        set_inputs, pushed = self.push, self._pushed

        def push() -> int:
            pushed[:n] = in_buf
            return set_inputs()

        self.push = push
        self._set_saved = self.fmi.io(self._set, self._inst, self._p_in_vr, n,
                                      self._saved_in.ctypes.data_as(POINTER(c_double)))

    def asked_to_stop(self) -> bool:
        return bool(self._me) and bool(_library().me_terminated(self._me))

    def stop_detail(self) -> str:
        return f"its time {_library().me_time(self._me):.9g} s" if self._me else ""

    def reset(self) -> None:
        self._me_free()
        super().reset()

    def release(self) -> None:
        self._me_free()
        super().release()

    def _me_free(self) -> None:
        if getattr(self, "_me", None):
            self._last = (self.events(), self.solver_stats())  # still readable after the run freed it
            _library().me_free(self._me)
            self._me = None

    def native(self) -> NativeEntry | None:
        """The compiled slave's entry points in FMI 2.0 shapes (its pointer as the instance), for
        the compiled master loops; FMU state get/set where it rolls back through its FMU state
        (through continuous states its inputs are set back from Python: the Python loop)."""
        if not self._me:
            return None
        lib = _library()
        fn = {n: _addr(getattr(lib, f"me_native_{n}")) for n in ("do_step", "get_real", "set_real", "get_state",
                                                                  "set_state", "free_state", "boolean_status")}
        state = (fn["get_state"], fn["set_state"], fn["free_state"]) \
            if self.can_rollback and self.description.rollback_through == "FMU state" else (0, 0, 0)
        return NativeEntry(False, self._me, fn["do_step"], fn["get_real"], fn["set_real"], 0, *state,
                           fn["boolean_status"], 0)

    def _free_state(self) -> None:
        self._state = None  # a compiled loop's saved state is the slave itself (freed with it)

    # rollback ----------------------------------------------------------------------------------
    def save_state(self) -> None:
        if not self.can_rollback:
            return Slave.save_state(self)
        enter(self._ck, CALL["fmi2GetFMUstate"])
        try:
            st = _library().me_save(self._me)
        finally:
            leave()
        if st in FAILING:
            raise self._failed("saving the state", self._message())
        self._saved_in[:] = self._pushed

    def restore_state(self) -> None:
        if not self.can_rollback:
            return Slave.restore_state(self)
        if self._n_in:  # the inputs as they were at the save (part of an FMU state, not of the continuous states)
            st = self._set_saved()
            if st in FAILING:
                raise self._failed("setting the inputs back", Status(st).name)
        enter(self._ck, CALL["fmi2SetFMUstate"])
        try:
            st = _library().me_restore(self._me)
        finally:
            leave()
        if st in FAILING:
            raise self._failed("restoring the state", self._message())

    # what happened -----------------------------------------------------------------------------
    def solver_stats(self) -> dict[str, int]:
        """CVODES's and the events' counts so far: rhs evaluations, steps, state/time/step/input
        events, solver restarts."""
        if not self._me:
            return dict(getattr(self, "_last", ([], {}))[1])
        out = (c_long * 7)()
        _library().me_stats(self._me, out)
        keys = ("rhs_evaluations", "solver_steps", "state_events", "time_events", "step_events", "input_events",
                "solver_restarts")
        return dict(zip(keys, (int(x) for x in out)))

    def events(self) -> list[tuple[float, str]]:
        """The events handled so far (time [s], kind), the first 10,000 (after the run: its events)."""
        if not self._me:
            return list(getattr(self, "_last", ([], {}))[0])
        lib = _library()
        n = lib.me_events(self._me, 0, 0, None, None)
        cap = min(n, 10_000)
        ts, kinds = (c_double * max(1, cap))(), (c_int * max(1, cap))()
        lib.me_events(self._me, 0, cap, ts, kinds)
        return [(ts[i], EVENT_KINDS.get(kinds[i], "event")) for i in range(cap)]


FmuSlave.kinds["model exchange"] = ModelExchangeSlave

__all__ = ["DEFAULT_RTOL", "MAX_EVENTS_PER_STEP", "ModelExchangeSlave", "available"]
