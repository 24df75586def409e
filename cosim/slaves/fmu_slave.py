"""FMU slaves: an FMI 2.0 or 3.0 co-simulation FMU stepped through its C entry points."""
from __future__ import annotations

import atexit
import contextlib
import ctypes
import os
import shutil
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from ctypes import POINTER, c_bool, c_double, c_int, c_uint32, c_void_p
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fmus.fmi_functions import prototype

from ..errors import UserError
from . import crumb
from .crumb import CALL, enter, leave
from .description import SlaveDescription, describe_fmu
from .slave import FAILING, NativeEntry, Slave, Status
from ..outputs import pid_alive
from .archive import check_archive
from .types import TYPES, parse_start

if TYPE_CHECKING:
    pass


def _boolean_status(dll) -> int:
    """Address of the FMU's fmi2GetBooleanStatus, 0 when it does not export one."""
    try:
        return _addr(dll.fmi2GetBooleanStatus)
    except AttributeError:
        return 0


# --- the interface ----------------------------------------------------------------------------
_UNZIPPED: dict[tuple[str, float], str] = {}


def _cleanup() -> None:
    for d in _UNZIPPED.values():
        shutil.rmtree(d, ignore_errors=True)


atexit.register(_cleanup)


def unpack_fmu(path: Path) -> str:
    """The folder ``path`` is unpacked into (once per process and file; removed at exit)."""
    return _unzip(Path(path))


def forget_unpacked(path: Path) -> None:
    """Remove the folder(s) :func:`unpack_fmu` unpacked ``path`` into, and forget them."""
    name = str(Path(path).resolve())
    for key in [k for k in _UNZIPPED if k[0] == name]:
        shutil.rmtree(_UNZIPPED.pop(key), ignore_errors=True)


def _sweep_dead_unzips() -> None:
    """Remove the FMU folders of processes that died without their atexit (SIGKILL)."""

    for d in Path(tempfile.gettempdir()).glob("rpr-fmu-*-*"):
        pid = d.name.split("-")[2]
        if pid.isdigit() and int(pid) != os.getpid() and not pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


@contextlib.contextmanager
def _file_size_limit_as_error():
    """While unpacking: a write past the file-size limit (``RLIMIT_FSIZE``) fails with EFBIG
    instead of SIGXFSZ killing the process before its folder is removed (main thread only; a
    signal disposition cannot be changed from another)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "SIGXFSZ"):
        yield
        return
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGXFSZ, old)


def _unzip(path: Path) -> str:
    import fmpy


    key = (str(path.resolve()), path.stat().st_mtime)
    if key not in _UNZIPPED:
        if not _UNZIPPED:  # once per process
            _sweep_dead_unzips()
        check_archive(path)  # member names and sizes before a byte is extracted
        folder = tempfile.mkdtemp(prefix=f"rpr-fmu-{os.getpid()}-")
        try:  # sources/ is not needed to load the binary (and is most of a generated FMU's bytes)
            with _file_size_limit_as_error():
                _UNZIPPED[key] = fmpy.extract(str(path), unzipdir=folder,
                                              include=lambda name: not name.startswith("sources/"))
        except BaseException as exc:
            shutil.rmtree(folder, ignore_errors=True)  # a failed extraction leaves nothing behind
            if isinstance(exc, OSError):
                raise UserError(f"{path}: cannot unpack the FMU into {tempfile.gettempdir()} "
                                f"({exc.strerror or exc})") from None
            raise
    return _UNZIPPED[key]


_DoStep2 = prototype("fmi2DoStep")
_GetState = prototype("fmi2GetFMUstate")  # FMI 3.0's and the free functions have the same signature
_SetState = prototype("fmi2SetFMUstate")
_Get2, _Set2 = prototype("fmi2GetReal"), prototype("fmi2SetReal")
_DoStep3 = prototype("fmi3DoStep")
_Get3, _Set3 = prototype("fmi3GetFloat64"), prototype("fmi3SetFloat64")
_SetDer2 = prototype("fmi2SetRealInputDerivatives")


def _addr(fn) -> int:
    return ctypes.cast(fn, c_void_p).value


class FmiVersion(ABC):
    """What differs between FMI 2.0 and 3.0 for a co-simulation slave: the C names and call shapes
    of the per-step functions, how an instance is made and initialised, and what the FMU can say
    about a stop.  One instance per version (:data:`FMI2`, :data:`FMI3`); an :class:`FmuSlave`
    holds the one its FMU declares and asks it wherever the versions differ."""

    major: str
    state_names: tuple[str, str, str]  # get, set, free FMU state
    configuration_mode = False  # structural parameters set in configuration mode
    input_derivatives = False  # fmi2SetRealInputDerivatives (linear inputs inside the FMU)

    @abstractmethod
    def make(self, slave: "FmuSlave", guid: str, unzip: str, ident: str, model_exchange: bool = False):
        """The loaded and instantiated FMPy object: its co-simulation interface, or with
        ``model_exchange`` its model-exchange one (:mod:`cosim.slaves.model_exchange`)."""
        ...

    @abstractmethod
    def bind_step(self, slave: "FmuSlave", dll) -> None:
        """``slave._step(t, h) -> status`` and ``slave._get``/``_set`` (Float64 by value reference)."""
        ...

    @abstractmethod
    def io(self, fn, inst, p_vr, n: int, p_val) -> Callable[[], int]:
        """A no-argument call of a Float64 getter or setter on ``n`` values."""
        ...

    @abstractmethod
    def accessor(self, ft) -> str:
        """The FMPy method suffix of FMI type ``ft`` (``Real``, ``Float64``, ...)."""
        ...

    @abstractmethod
    def raw(self, type_name: str, ft) -> tuple[str, object]:
        """(the type's name in the C function, numpy storage type) of a typed getter or setter."""
        ...

    @abstractmethod
    def raw_call(self, fn, inst, p_vr, n_vr: int, p_buf, n_values: int, keep) -> Callable[[], int]:
        ...

    @abstractmethod
    def get(self, accessor, vrs: list[int], n_values: int) -> list:
        ...

    @abstractmethod
    def enter_initialization(self, slave: "FmuSlave", start: float, stop: float, tolerance: float | None) -> None:
        ...

    def asked_to_stop(self, slave: "FmuSlave") -> bool:
        """After a Discard: did the FMU ask to end the simulation?"""
        return False

    @abstractmethod
    def last_time(self, slave: "FmuSlave") -> float:
        """The FMU's last successful time [s] after it asked to stop."""
        ...

    @abstractmethod
    def native(self, slave: "FmuSlave", dll, state: tuple[int, int, int], directional: int) -> NativeEntry:
        """The C entry points (``state``: get/set/free FMU state, ``directional``:
        GetDirectionalDerivative; 0 where absent)."""
        ...


class _Fmi2(FmiVersion):
    major = "2"
    state_names = ("fmi2GetFMUstate", "fmi2SetFMUstate", "fmi2FreeFMUstate")
    input_derivatives = True

    def make(self, slave, guid, unzip, ident, model_exchange=False):
        from fmpy.fmi2 import FMU2Model, FMU2Slave, defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE

        cb = fmi2CallbackFunctions()
        cb.logger = fmi2CallbackLoggerTYPE(slave._on_log2)
        cb.allocateMemory = defaultCallbacks.allocateMemory
        cb.freeMemory = defaultCallbacks.freeMemory
        slave._callbacks = cb
        kind = FMU2Model if model_exchange else FMU2Slave
        fmu = kind(guid=guid, unzipDirectory=unzip, modelIdentifier=ident, instanceName=slave.name)
        fmu.instantiate(callbacks=cb)
        return fmu

    def bind_step(self, slave, dll):
        step = _DoStep2(_addr(dll.fmi2DoStep))
        slave._get = _Get2(_addr(dll.fmi2GetReal))
        slave._set = _Set2(_addr(dll.fmi2SetReal))
        inst = slave._inst

        def do_step(t: float, h: float) -> int:
            st = step(inst, t, h, 1 if slave.no_prior else 0)  # noSetFMUStatePriorToCurrentPoint
            if st == Status.DISCARD and slave.asked_to_stop():
                return Status.STOP_REQUESTED
            return st

        slave._step = do_step

    def io(self, fn, inst, p_vr, n, p_val):
        return (lambda: fn(inst, p_vr, n, p_val)) if n else (lambda: 0)

    def accessor(self, ft):
        return ft.fmi2

    def raw(self, type_name, ft):
        return ft.fmi2, (np.float64 if type_name == "Real" else np.int32)

    def raw_call(self, fn, inst, p_vr, n_vr, p_buf, n_values, keep):
        return lambda: fn(inst, p_vr, n_vr, p_buf) if keep else 0

    def get(self, accessor, vrs, n_values):
        return accessor(vrs)

    def enter_initialization(self, slave, start, stop, tolerance):
        slave._call("fmi2SetupExperiment", slave.fmu.setupExperiment, tolerance, start, stop, call=4)
        slave._call("fmi2EnterInitializationMode", slave.fmu.enterInitializationMode, call=5)

    def asked_to_stop(self, slave):
        from fmpy.fmi2 import fmi2Terminated

        try:
            return bool(slave.fmu.getBooleanStatus(fmi2Terminated))
        except Exception:  # an FMU that does not implement the status inquiry: a plain Discard
            return False

    def last_time(self, slave):
        from fmpy.fmi2 import fmi2LastSuccessfulTime

        return slave.fmu.getRealStatus(fmi2LastSuccessfulTime)

    def native(self, slave, dll, state, directional):
        der = _addr(dll.fmi2SetRealInputDerivatives) if slave.description.can_interpolate_inputs else 0
        return NativeEntry(False, slave.fmu.component, _addr(dll.fmi2DoStep), _addr(dll.fmi2GetReal),
                           _addr(dll.fmi2SetReal), der, *state, _boolean_status(dll), directional)


class _Fmi3(FmiVersion):
    major = "3"
    state_names = ("fmi3GetFMUState", "fmi3SetFMUState", "fmi3FreeFMUState")
    configuration_mode = True

    def make(self, slave, guid, unzip, ident, model_exchange=False):
        from fmpy.fmi3 import FMU3Model, FMU3Slave, fmi3LogMessageCallback

        slave._log = fmi3LogMessageCallback(slave._on_log3)
        if model_exchange:
            fmu = FMU3Model(guid=guid, unzipDirectory=unzip, modelIdentifier=ident, instanceName=slave.name)
            fmu.instantiate(logMessage=slave._log)
            return fmu
        fmu = FMU3Slave(guid=guid, unzipDirectory=unzip, modelIdentifier=ident, instanceName=slave.name)
        # event mode and early return only for a run whose algorithm ends its steps at events
        fmu.instantiate(logMessage=slave._log, eventModeUsed=slave.event_mode, earlyReturnAllowed=slave.event_mode)
        return fmu

    def bind_step(self, slave, dll):
        step = _DoStep3(_addr(dll.fmi3DoStep))
        slave._get = _Get3(_addr(dll.fmi3GetFloat64))
        slave._set = _Set3(_addr(dll.fmi3SetFloat64))
        # eventHandlingNeeded, terminateSimulation, earlyReturn: one array, which a compiled loop writes too
        flags = (c_bool * 3)()
        slave._last_t = c_double()
        p_flags = [ctypes.byref(c_bool.from_buffer(flags, k * ctypes.sizeof(c_bool))) for k in range(3)]
        p_last, inst = ctypes.byref(slave._last_t), slave._inst
        slave._step_flags, slave._planned_end = flags, c_double()
        planned = slave._planned_end

        def do_step(t: float, h: float) -> int:
            # noSetFMUStatePriorToCurrentPoint: promised unless the algorithm may restore a state
            planned.value = t + h
            st = step(inst, t, h, slave.no_prior, *p_flags, p_last)
            if st < 2 and flags[1]:
                return Status.STOP_REQUESTED
            return st

        slave._step = do_step

    def io(self, fn, inst, p_vr, n, p_val):
        return (lambda: fn(inst, p_vr, n, p_val, n)) if n else (lambda: 0)

    def accessor(self, ft):
        return ft.fmi3

    def raw(self, type_name, ft):
        return ft.fmi3, (np.bool_ if type_name == "Boolean" else ft.dtype)

    def raw_call(self, fn, inst, p_vr, n_vr, p_buf, n_values, keep):
        return lambda: fn(inst, p_vr, n_vr, p_buf, n_values) if keep else 0

    def get(self, accessor, vrs, n_values):
        return accessor(vrs, n_values)

    def enter_initialization(self, slave, start, stop, tolerance):
        slave._call("fmi3EnterInitializationMode", slave.fmu.enterInitializationMode, tolerance, start, stop, call=5)

    def last_time(self, slave):
        return slave._last_t.value

    def native(self, slave, dll, state, directional):
        return NativeEntry(True, slave.fmu.component, _addr(dll.fmi3DoStep), _addr(dll.fmi3GetFloat64),
                           _addr(dll.fmi3SetFloat64), 0, *state, directional_derivative=directional,
                           last_time=ctypes.addressof(slave._last_t))


FMI2, FMI3 = _Fmi2(), _Fmi3()


class FmuSlave(Slave):
    """A co-simulation FMU (FMI 2.0 or 3.0).  FMPy loads the library and handles instantiation,
    initialisation and termination; the per-step calls go straight to the FMI functions through
    ctypes with preallocated buffers (or through the compiled loop via :meth:`native`)."""

    #: The slave class of each interface other than co-simulation (its name in a description ->
    #: class), registered by its module (model exchange: :mod:`cosim.slaves.model_exchange`).
    kinds: dict[str, type] = {}

    def __new__(cls, name: str | None = None, path: Path | None = None, description: SlaveDescription | None = None):
        """An FMU's slave of the class its interface needs (``FmuSlave(...)`` of a model-exchange
        description makes a model-exchange slave); without arguments (copy, pickle) the class asked."""
        if cls is not FmuSlave or path is None:
            return super().__new__(cls)
        desc = description or describe_fmu(Path(path))
        obj = super().__new__(FmuSlave.kinds.get(desc.interface, cls))
        obj._described = desc
        return obj

    def __init__(self, name: str, path: Path, description: SlaveDescription | None = None):
        self.path = Path(path)
        super().__init__(name, description or getattr(self, "_described", None) or describe_fmu(self.path))
        self.fmi: FmiVersion = FMI3 if str(self.description.fmi_version).startswith("3") else FMI2
        self.fmu = None
        self.always_no_prior = "always_no_prior" in self.description.workarounds
        self._terminated = False
        self._empty_vr = (c_uint32 * 1)()
        self._empty_val = (c_double * 1)()
        self._ck = crumb.key(name, self.fmi3)  # this component in the breadcrumb (cosim.slaves.crumb)

    #: Keep the instance when a run ends (:meth:`free` leaves it alive) so that the next run's
    #: :meth:`instantiate` resets it (fmi2Reset / fmi3Reset) instead of loading the FMU again;
    #: :meth:`release` frees it for good.  Used by batches (:mod:`cosim.batch`).
    reuse: bool = False

    #: Workaround from the behavioural check (:mod:`cosim.slaves.behaviour`) for an FMU that does
    #: not advance when that flag is false: pass true always, rollbacks included.
    always_no_prior: bool = False

    @property
    def no_prior(self) -> bool:
        """The ``noSetFMUStatePriorToCurrentPoint`` this slave's doSteps pass (the workaround too)."""
        return self.forward_only or self.always_no_prior or not self.can_rollback

    # lifecycle ---------------------------------------------------------------------------------
    def instantiate(self) -> None:
        if self.fmu is not None:  # kept from a previous run (reuse): back to the instantiated state
            self.reset()
            return
        import fmpy

        guid, ident = self.description.guid, self.description.model_identifier
        if not (guid and ident):
            md = fmpy.read_model_description(str(self.path), validate=False)
            guid, ident = md.guid, md.coSimulation.modelIdentifier
        unzip = _unzip(self.path)
        enter(self._ck, CALL["fmi2Instantiate"])  # loading the binary and instantiating
        try:
            self.fmu = self._make(guid, unzip, ident)
        except Exception as exc:  # fmpy raises bare Exceptions for a missing binary or failed call
            raise UserError(f"{self.name}: cannot instantiate {self.path} ({exc}"
                            f"{'; ' + self.last_message if self.last_message else ''})") from None
        finally:
            leave()
        crumb.name_instance(self.name, self.fmi3, self.fmu.component)
        self._inst = c_void_p(self.fmu.component)
        self._bind_step(self.fmu.dll)

    def _make(self, guid: str, unzip: str, ident: str):
        """The loaded and instantiated FMPy object of the FMU."""
        return self.fmi.make(self, guid, unzip, ident)

    def _bind_step(self, dll) -> None:
        """``self._step(t, h) -> status`` and ``self._get``/``_set`` (Float64 by value reference)."""
        self.fmi.bind_step(self, dll)

    def _on_log2(self, env, instance, status, category, message) -> None:
        self.messages.append(f"[{Status(status).name if status in Status._value2member_map_ else status}] "
                             f"{(message or b'').decode(errors='replace')}")

    def _on_log3(self, env, status, category, message) -> None:
        self.messages.append(f"[{Status(status).name if status in Status._value2member_map_ else status}] "
                             f"{(message or b'').decode(errors='replace')}")

    def _call(self, what: str, fn, *args, call: int = 0) -> None:
        enter(self._ck, call)
        try:
            fn(*args)
        except Exception as exc:  # fmpy's FMICallException and friends
            raise self._failed(what, exc) from None
        finally:
            leave()

    def _failed(self, what: str, why: object) -> UserError:
        """The one-line error of a failed FMI call: ``NAME: WHAT failed (WHY): the FMU's last message``."""
        return UserError(f"{self.name}: {what} failed ({why})" + (f": {self.last_message}" if self.last_message else ""))

    def set_start(self, values: dict[str, object]) -> None:
        """Parameters and start values of any FMI type by name (arrays as lists); FMI 3.0
        structural parameters are set first, in configuration mode."""
        if not values:
            return
        vs = self.description.variables
        structural = [k for k in values if vs[k].causality == "structuralParameter"]
        if structural and self.fmi.configuration_mode:
            self._call("fmi3EnterConfigurationMode", self.fmu.enterConfigurationMode, call=3)
            for k in structural:
                self._call(f"setting structural parameter {k}", self.set_values, k, values[k], call=3)
            self._call("fmi3ExitConfigurationMode", self.fmu.exitConfigurationMode, call=3)
        for k, val in values.items():
            if k not in structural:
                self._call(f"setting start value {k}", self.set_values, k, val, call=3)
        self._start = {k: v for k, v in values.items() if k not in structural}

    def _accessor(self, verb: str, type_name: str):

        ft = TYPES[type_name]
        return getattr(self.fmu, verb + self.fmi.accessor(ft))

    def set_values(self, name: str, value) -> None:
        """Set variable ``name`` (any type; an array as its values in row-major order); raises
        fmpy's exception on a failing status."""

        var = self.description.variables[name]
        ft = TYPES[var.type]
        vals = parse_start(value, ft, var.size, name)
        self._accessor("set", var.type)([var.vr], [v.item() if hasattr(v, "item") else v for v in vals])

    def raw_io(self, verb: str, type_name: str, vrs: list[int], n_values: int) -> tuple[Callable[[], int], np.ndarray]:
        """A no-argument call of fmi2/3 ``Get``/``Set`` (``verb``) of numeric type ``type_name`` on
        ``vrs`` (``n_values`` values in all) and the numpy buffer it reads into or writes from (the
        FMI storage type: FMI 2.0 Boolean and Enumeration are int32); returns the FMI status."""

        ctype, dtype = self.fmi.raw(type_name, TYPES[type_name])
        fname = f"fmi{self.fmi.major}{verb.capitalize()}{ctype}"
        fn = prototype(fname, raw=True)(_addr(getattr(self.fmu.dll, fname)))
        vr = np.ascontiguousarray(vrs, dtype=np.uint32)
        buf = np.zeros(n_values, dtype=dtype)
        inst, p_vr, n_vr, p_buf = self._inst, vr.ctypes.data, len(vr), buf.ctypes.data
        return self.fmi.raw_call(fn, inst, p_vr, n_vr, p_buf, n_values, (vr, buf)), buf

    def get_values(self, type_name: str, vrs: list[int], n_values: int) -> list:
        """Values of the variables ``vrs`` of one type (``n_values`` in all, arrays flattened)."""
        vals = self.fmi.get(self._accessor("get", type_name), vrs, n_values)
        if type_name == "String":
            vals = [v.decode("utf-8", errors="replace") if isinstance(v, bytes) else v for v in vals]
        return vals

    def enter_initialization(self, start_time: float, stop_time: float, tolerance: float | None = None) -> None:
        self.fmi.enter_initialization(self, start_time, stop_time, tolerance)
        if "set_in_init" in self.description.workarounds:  # an FMU that forgets values set before initialisation
            for k, val in getattr(self, "_start", {}).items():
                if self.description.variables[k].variability != "constant":
                    self._call(f"setting start value {k} in initialisation mode", self.set_values, k, val, call=3)

    def exit_initialization(self) -> None:
        self._call("exitInitializationMode", self.fmu.exitInitializationMode, call=6)
        if self.event_mode and self.fmi3:  # FMI 3.0: in event mode now; the initial event iteration, then step mode
            for _ in range(100):
                st, more, terminate = self.update_discrete_states()
                if st in FAILING:
                    raise self._failed("the initial event iteration", Status(st).name)
                if terminate:
                    raise UserError(f"{self.name}: the FMU asked to terminate the simulation in its initial event "
                                    f"iteration")
                if not more:
                    break
            else:
                raise UserError(f"{self.name}: the initial event iteration did not settle in 100 rounds")
            st = self.enter_step_mode()
            if st in FAILING:
                raise self._failed("fmi3EnterStepMode", Status(st).name)

    def bind(self, in_vrs, in_buf, out_vrs, out_buf) -> None:
        self._in_vr = np.ascontiguousarray(in_vrs, dtype=np.uint32)
        self._out_vr = np.ascontiguousarray(out_vrs, dtype=np.uint32)
        for buf in (in_buf, out_buf):
            if buf.dtype != np.float64 or not buf.flags.c_contiguous:
                raise ValueError(f"{self.name}: buffers must be contiguous float64 arrays")
        self._in_buf, self._out_buf = in_buf, out_buf
        self._n_in, self._n_out = len(self._in_vr), len(self._out_vr)
        pu, pd = POINTER(c_uint32), POINTER(c_double)
        self._p_in_vr = self._in_vr.ctypes.data_as(pu) if self._n_in else self._empty_vr
        self._p_in = in_buf.ctypes.data_as(pd) if self._n_in else self._empty_val
        self._p_out_vr = self._out_vr.ctypes.data_as(pu) if self._n_out else self._empty_vr
        self._p_out = out_buf.ctypes.data_as(pd) if self._n_out else self._empty_val
        self.push = self.fmi.io(self._set, self._inst, self._p_in_vr, self._n_in, self._p_in)
        self.pull = self.fmi.io(self._get, self._inst, self._p_out_vr, self._n_out, self._p_out)

    def bind_slopes(self, slope_buf: np.ndarray) -> bool:
        if not (self.fmi.input_derivatives and self.description.can_interpolate_inputs and self._n_in):
            return False
        if slope_buf.dtype != np.float64 or not slope_buf.flags.c_contiguous or len(slope_buf) != self._n_in:
            raise ValueError(f"{self.name}: the slope buffer must be {self._n_in} contiguous float64 values")
        self._slope_buf = slope_buf
        self._orders = np.ones(self._n_in, dtype=np.int32)
        self._set_der = _SetDer2(_addr(self.fmu.dll.fmi2SetRealInputDerivatives))
        setder, inst, n_in, a_in = self._set_der, self._inst, self._n_in, self._p_in_vr
        p_ord, p_slope = self._orders.ctypes.data_as(POINTER(c_int)), slope_buf.ctypes.data_as(POINTER(c_double))
        self.push_slopes = lambda: setder(inst, a_in, n_in, p_ord, p_slope)
        return True

    @property
    def fmi3(self) -> bool:
        """True for an FMI 3.0 FMU."""
        return self.fmi is FMI3

    def push(self) -> int:  # replaced per instance by bind()
        raise RuntimeError(f"{self.name}: push() before bind()")

    def pull(self) -> int:  # replaced per instance by bind()
        raise RuntimeError(f"{self.name}: pull() before bind()")

    def do_step(self, t: float, h: float) -> int:
        enter(self._ck, 7, t)
        st = self._step(t, h)  # made by the FMI version at instantiation
        leave()
        return st

    def step_end(self) -> tuple[float, bool]:
        if not (self.event_mode and self.fmi3):
            return Slave.step_end(self)
        event, _, early = self._step_flags
        return (self._last_t.value if early else self._planned_end.value), bool(event)

    def event_slots(self) -> tuple[int, int, int] | None:
        if not (self.event_mode and self.fmi3):
            return None
        return (ctypes.addressof(self._step_flags), ctypes.addressof(self._last_t),
                ctypes.addressof(self._planned_end))

    def enter_event_mode(self) -> int:
        return self._status_of("fmi3EnterEventMode", self.fmu.enterEventMode)

    def update_discrete_states(self) -> tuple[int, bool, bool]:
        out: list = []
        st = self._status_of("fmi3UpdateDiscreteStates", lambda: out.extend(self.fmu.updateDiscreteStates()))
        return (st, bool(out[0]), bool(out[1])) if out else (st, False, False)

    def enter_step_mode(self) -> int:
        return self._status_of("fmi3EnterStepMode", self.fmu.enterStepMode)

    def _status_of(self, what: str, fn) -> int:
        """Call ``fn`` (an FMI call named ``what``, in the breadcrumb for the supervisor with the
        event's time); its status."""
        enter(self._ck, CALL[what], self.step_end()[0])
        try:
            fn()
        except Exception as exc:  # fmpy's FMICallException
            self.messages.append(f"[ERROR] {what} failed ({exc})")
            return int(getattr(exc, "status", Status.ERROR))
        finally:
            leave()
        return Status.OK

    def asked_to_stop(self) -> bool:
        """After an FMI 2.0 Discard: did the FMU ask to end the simulation (fmi2Terminated)?"""
        return self.fmu is not None and self.fmi.asked_to_stop(self)

    def stop_detail(self) -> str:
        """Why and when the FMU asked to stop: its last successful time [s] (FMI 2.0 status, FMI 3.0
        doStep output), '' when unknown."""
        try:
            return f"its last successful time {self.fmi.last_time(self):.9g} s"
        except Exception:  # optional inquiry
            return ""

    def terminate(self) -> None:
        if self.fmu is not None and not self._terminated:
            self._terminated = True
            enter(self._ck, CALL["fmi2Terminate"])
            try:
                self.fmu.terminate()
            except Exception:  # terminating after an Error/Fatal status may itself fail
                pass
            finally:
                leave()

    def reset(self) -> None:
        """Return the instance to its state right after instantiation (FMI reset): every
        variable back to its default, ready for :meth:`set_start` and another run."""
        self.messages.clear()
        self._call("reset", self.fmu.reset, call=CALL["fmi2Reset"])
        self._terminated = False

    def free(self) -> None:
        if not self.reuse or "no_reset" in self.description.workarounds:  # a reset that does not reset: load anew
            self.release()

    def release(self) -> None:
        """Free the instance and its resources (also one kept for reuse)."""
        if self.fmu is not None:
            try:
                self._free_state()
            except Exception:  # a state of a failed instance: nothing more to do
                pass
            enter(self._ck, CALL["fmi2FreeInstance"])
            try:
                self.fmu.freeInstance()
            except Exception:  # after Fatal, freeInstance is undefined: nothing more to do
                pass
            finally:
                leave()
            self.fmu = None

    def native(self) -> NativeEntry | None:
        if self.fmu is None:
            return None
        dll = self.fmu.dll
        st = (0, 0, 0)
        if self.can_rollback:
            try:
                st = tuple(_addr(getattr(dll, x)) for x in self.fmi.state_names)
            except AttributeError:  # declared but not exported: no compiled rollback
                st = (0, 0, 0)
        dd = 0
        if self.description.provides_directional_derivative:
            try:
                dd = _addr(getattr(dll, f"fmi{self.fmi.major}GetDirectionalDerivative"))
            except AttributeError:  # declared but not exported: finite differences
                dd = 0
        return self.fmi.native(self, dll, st, dd)

    def state_slot(self) -> int:
        """The address of this slave's FMU-state pointer (the one :meth:`save_state` fills): a
        compiled loop that saves states there leaves them to be freed with the instance."""
        if getattr(self, "_state", None) is None:
            self._state = c_void_p()
        return ctypes.addressof(self._state)

    @property
    def can_rollback(self) -> bool:
        return bool(self.description.can_get_set_state)

    def _state_calls(self) -> tuple:
        """(get, set) FMU-state functions of the loaded library, made once per loaded FMU."""
        calls = getattr(self, "_state_fns", None)
        if calls is None or calls[0] is not self.fmu:
            dll = self.fmu.dll
            get, set_, _ = self.fmi.state_names
            calls = self._state_fns = (self.fmu, _GetState(_addr(getattr(dll, get))), _SetState(_addr(getattr(dll, set_))))
        return calls[1:]

    def save_state(self) -> None:
        if not self.can_rollback:
            return Slave.save_state(self)
        state = getattr(self, "_state", None)
        if state is None:
            state = self._state = c_void_p()
        enter(self._ck, CALL["fmi2GetFMUstate"])
        st = self._state_calls()[0](self._inst, ctypes.byref(state))
        leave()
        if st in FAILING:
            raise self._failed("getting the FMU state", Status(st).name)

    def restore_state(self) -> None:
        state = getattr(self, "_state", None)
        if state is None:
            raise RuntimeError(f"{self.name}: restore_state() before save_state()")
        enter(self._ck, CALL["fmi2SetFMUstate"])
        st = self._state_calls()[1](self._inst, state)
        leave()
        if st in FAILING:
            raise self._failed("setting the FMU state", Status(st).name)

    def _free_state(self) -> None:
        state = getattr(self, "_state", None)
        if state is not None and state.value and self.fmu is not None:
            fn = _GetState(_addr(getattr(self.fmu.dll, self.fmi.state_names[2])))
            fn(self._inst, ctypes.byref(state))
        self._state = None

    def output_jacobian(self, outputs: Sequence[str], inputs: Sequence[str]) -> np.ndarray | None:
        if not self.description.provides_directional_derivative or self.fmu is None:
            return None
        unknown, known = [self.vr(y) for y in outputs], [self.vr(u) for u in inputs]
        jac = np.zeros((len(unknown), len(known)))
        try:
            for j in range(len(known)):
                seed = [1.0 if k == j else 0.0 for k in range(len(known))]
                jac[:, j] = self.fmu.getDirectionalDerivative(unknown, known, seed)
        except Exception as exc:  # fmpy raises its FMICallException on a failing status
            raise self._failed("get directional derivative", exc) from None
        return jac


# --- analytic slaves --------------------------------------------------------------------------

