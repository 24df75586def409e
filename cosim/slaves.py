"""Slaves: what the master steps.  An FMU (FMI 2.0 or 3.0) is one kind; an analytic linear
system is another (for algorithm tests and as a known plant); a hardware rig will be a third.

A slave is described *before* it runs by a :class:`SlaveDescription` (variable names, causality,
direct feedthrough, flanges, sample period): that is what scene validation checks connections
against.  At run time the master talks to it through :class:`Slave`, always in this order::

    instantiate()                      load and create the instance
    set_start(values)                  parameters and start values (by name), before initialisation
    enter_initialization(t0, t_stop)
    bind(in_vrs, in_buf, out_vrs, out_buf)
    [push(); pull()] ...               initial exchange (inputs from in_buf, outputs into out_buf)
    exit_initialization()
    loop: push(); do_step(t, h) -> status; pull()
    terminate(); free()

``in_buf`` and ``out_buf`` are numpy float64 arrays owned by the master (views of its value
vector); ``push``/``pull`` move values between them and the slave with no allocation, so the
master's inner loop allocates nothing.  A slave that can expose C entry points
(:meth:`Slave.native`) can also be stepped by the compiled loop of :mod:`cosim.fastloop`.

Status codes follow FMI (:class:`Status`); ``do_step`` returns one of them, and
:attr:`Status.STOP_REQUESTED` when an FMI 3.0 slave sets ``terminateSimulation`` or an FMI 2.0
slave returns Discard with ``fmi2Terminated`` true.  Variables of other types than scalar Float64
(and FMI 3.0 arrays) are set and read by name through ``set_values``/``get_values``
(see :mod:`cosim.typedio`); FMI 3.0 structural parameters are set in configuration mode.
"""
from __future__ import annotations

import atexit
import ctypes
import dataclasses
import enum
import os
import shutil
import tempfile
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Sequence
from ctypes import POINTER, c_bool, c_double, c_int, c_size_t, c_uint32, c_void_p
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from models.interface import Flange

from .errors import UserError

if TYPE_CHECKING:
    from models.block import Block


class Status(enum.IntEnum):
    """FMI status codes (identical in FMI 2.0 and 3.0), plus the master's own stop request."""

    OK = 0
    WARNING = 1
    DISCARD = 2
    ERROR = 3
    FATAL = 4
    PENDING = 5
    STOP_REQUESTED = 100  # FMI 3.0 terminateSimulation


#: Status codes at which a fixed-step run stops (Discard included: a fixed-step master cannot retry).
FAILING = frozenset({Status.DISCARD, Status.ERROR, Status.FATAL, Status.PENDING})


@dataclass(frozen=True)
class Variable:
    """One variable (a scalar, or an FMI 3.0 array of ``shape``): FMI ``causality`` (parameter,
    structuralParameter, calculatedParameter, input, output, local, independent),
    ``variability``, canonical ``type`` (:mod:`cosim.fmitypes`: ``Real`` for FMI 2.0 Real and FMI 3.0
    Float64, ``Integer`` for Integer/Int32, else the FMI 3.0 name), ``start`` (a float for numeric
    scalars, None when it has none or is not a number; ``raw_start`` as written), unit and value
    reference (None until an FMU exists)."""

    name: str
    causality: str
    variability: str = "continuous"
    type: str = "Real"
    start: float | None = None
    unit: str = ""
    description: str = ""
    vr: int | None = None
    fmi_type: str = ""  # the type as the modelDescription writes it (Float64, Int32, Integer, ...)
    shape: tuple[int, ...] = ()  # array dimensions (FMI 3.0); () for a scalar
    initial: str | None = None  # exact, approx or calculated (FMI), None when not given
    dims: tuple = ()  # per dimension: a fixed size (int) or the name of the structural parameter
    raw_start: object = None  # the start value as written (text, or a list for an array)

    @property
    def size(self) -> int:
        """Number of values (1 for a scalar)."""
        n = 1
        for d in self.shape:
            n *= d
        return n

    @property
    def fast(self) -> bool:
        """A scalar Float64: carried by the master's value vector and the compiled loop."""
        return self.type == "Real" and not self.shape


@dataclass
class SlaveDescription:
    """What a scene needs to know about a component before anything runs.

    ``feedthrough`` maps each output to the inputs it depends on *directly* (within one
    communication point); ``flanges`` are its power ports; ``sample_period`` [s] is set for a
    sampled (discrete) slave, whose communication step must be a whole multiple of it.
    """

    kind: str  # "block", "fmu" or "python"
    source: str  # "model/fidelity", the FMU path, or the class name
    variables: dict[str, Variable]
    feedthrough: dict[str, list[str]]
    flanges: list[Flange] = field(default_factory=list)
    sample_period: float | None = None
    fmi_version: str | None = None
    can_get_set_state: bool = False
    can_interpolate_inputs: bool = False  # follows first-order input slopes (FMI 2.0 canInterpolateInputs)
    default_experiment: dict = field(default_factory=dict)  # start, stop, tolerance, step [s] as the FMU gives them
    interfaces: tuple[str, ...] = ()  # FMI interface kinds the FMU has (co-simulation, model exchange, ...)
    guid: str = ""  # the FMU's GUID / instantiation token and model identifier ("" until read from an FMU)
    model_identifier: str = ""
    provides_directional_derivative: bool = False  # FMI get directional derivative (partials at the current instant)

    def of(self, *causalities: str) -> list[str]:
        """Names of the variables with one of the given causalities, in declaration order."""
        return [v.name for v in self.variables.values() if v.causality in causalities]

    def flange(self, name: str) -> Flange | None:
        for f in self.flanges:
            if f.name == name:
                return f
        return None


def describe_block(block: Block, source: str = "") -> SlaveDescription:
    """The description of ``block`` as its exported FMU will present it (value references are
    unknown until the FMU exists)."""
    vs: dict[str, Variable] = {}
    for p in block.params:
        vs[p.name] = Variable(p.name, "parameter", "fixed" if p.structural else "tunable", "Real",
                              float(p.default), p.unit, p.description)
    for s in block.states:
        vs[s.name] = Variable(s.name, "local", "discrete" if block.integrator == "discrete" else "continuous",
                              "Real", None, s.unit, s.description)
    for u in block.inputs:
        vs[u.name] = Variable(u.name, "input", "continuous", "Real", 0.0, u.unit, u.description)
    for y in block.outputs:
        vs[y.name] = Variable(y.name, "output", "continuous", "Real", None, y.unit, y.description)
    period = float(block.sample_period) if block.integrator == "discrete" and block.sample_period else None
    return SlaveDescription("block", source or block.name, vs, block.feedthrough(), list(block.flanges),
                            period, None, True)


def _interfaces(md) -> tuple[str, ...]:
    kinds = [("co-simulation", md.coSimulation), ("model exchange", md.modelExchange),
             ("scheduled execution", getattr(md, "scheduledExecution", None))]
    return tuple(k for k, present in kinds if present is not None)


def _fmu_variable(v, fmi_version: str) -> Variable:
    from .fmitypes import canonical

    start = None
    if v.start is not None and not v.dimensions:
        try:
            start = float(v.start)
        except (TypeError, ValueError):
            start = None
    dims = tuple(d.variable.name if d.variable is not None else int(d.start) for d in v.dimensions)
    causality = v.causality or "local"
    return Variable(v.name, causality, v.variability or "continuous", canonical(v.type), start, v.unit or "",
                    v.description or "", v.valueReference, v.type, tuple(int(n) for n in (v.shape or ())),
                    getattr(v, "initial", None), dims, v.start)


def resolve_shapes(desc: SlaveDescription, structural: dict[str, int]) -> SlaveDescription:
    """``desc`` with array shapes recomputed for the structural parameter values ``structural``
    (the others keep their start values)."""
    if not any(v.dims for v in desc.variables.values()):
        return desc
    size = {n: int(v.raw_start) for n, v in desc.variables.items() if v.causality == "structuralParameter"
            and v.raw_start is not None}
    size.update({k: int(x) for k, x in structural.items()})
    vs = {}
    for n, v in desc.variables.items():
        if v.dims:
            shape = tuple(d if isinstance(d, int) else size.get(d, 0) for d in v.dims)
            v = dataclasses.replace(v, shape=shape)
        vs[n] = v
    return dataclasses.replace(desc, variables=vs)


def describe_fmu(path: Path) -> SlaveDescription:
    """Read an FMU's ``modelDescription.xml``.  Raises :class:`UserError` naming the file when it
    is not a readable co-simulation FMU."""
    import fmpy

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such FMU file")
    try:
        md = fmpy.read_model_description(str(path), validate=False)
    except Exception as exc:  # fmpy raises bare Exceptions for any malformed archive or XML
        raise UserError(f"{path}: not a readable FMU ({exc})") from None
    if not str(md.fmiVersion or "").startswith(("2", "3")):
        raise UserError(f"{path}: FMI {md.fmiVersion} FMUs are not supported; export it as FMI 2.0 or 3.0 "
                        f"co-simulation")
    kinds = _interfaces(md)
    if md.coSimulation is None:
        raise UserError(f"{path}: the FMU has no co-simulation interface (it has "
                        f"{' and '.join(kinds) or 'no interface'} only); rpr-cosim steps co-simulation FMUs")
    vs: dict[str, Variable] = {v.name: _fmu_variable(v, md.fmiVersion) for v in md.modelVariables}
    de = md.defaultExperiment
    default = {} if de is None else {k: float(x) for k, x in (("start", de.startTime), ("stop", de.stopTime),
                                                               ("tolerance", de.tolerance), ("step", de.stepSize))
                                     if x is not None}
    inputs = [v.name for v in md.modelVariables if v.causality == "input"]
    ft: dict[str, list[str]] = {}
    listed = {u.variable.name: u for u in md.outputs}
    for v in md.modelVariables:
        if v.causality != "output":
            continue
        unknown = listed.get(v.name)
        if unknown is None or unknown.dependencies is None:
            ft[v.name] = list(inputs)  # FMI: no dependency list means "depends on every known"
        else:
            ft[v.name] = [d.name for d in unknown.dependencies if d.causality == "input"]
    period = None
    cs = md.coSimulation
    can_state = bool(getattr(cs, "canGetAndSetFMUstate", False) or getattr(cs, "canGetAndSetFMUState", False))
    interp = md.fmiVersion.startswith("2") and bool(getattr(cs, "canInterpolateInputs", False))
    ddx = bool(getattr(cs, "providesDirectionalDerivative", False) or getattr(cs, "providesDirectionalDerivatives", False))
    return SlaveDescription("fmu", str(path), vs, ft, [], period, md.fmiVersion, can_state, interp, default, kinds,
                            md.guid or "", cs.modelIdentifier or "", ddx)


def _boolean_status(dll) -> int:
    """Address of the FMU's fmi2GetBooleanStatus, 0 when it does not export one."""
    try:
        return _addr(dll.fmi2GetBooleanStatus)
    except AttributeError:
        return 0


# --- the interface ----------------------------------------------------------------------------
@dataclass(frozen=True)
class NativeEntry:
    """C entry points of a slave for the compiled loop: the instance pointer and the addresses of
    its doStep, GetReal/GetFloat64 and SetReal/SetFloat64 functions, and of
    fmi2SetRealInputDerivatives (0 when the slave does not interpolate inputs); for the compiled
    adaptive engine also get/set/free FMU state (0 when it cannot roll back) and
    fmi2GetBooleanStatus (0 for FMI 3.0)."""

    fmi3: bool
    instance: int
    do_step: int
    get_real: int
    set_real: int
    set_input_derivatives: int = 0
    get_state: int = 0
    set_state: int = 0
    free_state: int = 0
    get_boolean_status: int = 0


class Slave(ABC):
    """A steppable component (see the module docstring for the call order)."""

    name: str
    description: SlaveDescription

    def __init__(self, name: str, description: SlaveDescription):
        self.name = name
        self.description = description
        self.messages: deque[str] = deque(maxlen=20)

    @property
    def last_message(self) -> str:
        """The slave's most recent log message ('' if none)."""
        return self.messages[-1] if self.messages else ""

    def vr(self, name: str) -> int:
        var = self.description.variables.get(name)
        if var is None or var.vr is None:
            raise UserError(f"{self.name}: no variable {name!r}")
        return var.vr

    @abstractmethod
    def instantiate(self) -> None: ...

    @abstractmethod
    def set_start(self, values: dict[str, float]) -> None:
        """Parameter and start values by variable name, before initialisation."""

    @abstractmethod
    def enter_initialization(self, start_time: float, stop_time: float) -> None: ...

    @abstractmethod
    def bind(self, in_vrs: np.ndarray, in_buf: np.ndarray, out_vrs: np.ndarray, out_buf: np.ndarray) -> None:
        """Fix the inputs written by :meth:`push` (from ``in_buf``) and the variables read by
        :meth:`pull` (into ``out_buf``); the arrays are owned by the master and must stay alive."""

    @abstractmethod
    def push(self) -> int:
        """Set the bound inputs from ``in_buf``; returns a :class:`Status`."""

    @abstractmethod
    def pull(self) -> int:
        """Read the bound variables into ``out_buf``; returns a :class:`Status`."""

    def bind_slopes(self, slope_buf: np.ndarray) -> bool:
        """Offer a buffer of first-order slopes [unit/s] of the bound inputs for
        :meth:`push_slopes`; False (the default) when the slave holds its inputs over a step."""
        return False

    def push_slopes(self) -> int:
        """Set the bound inputs' slopes from the buffer of :meth:`bind_slopes`, valid for the next
        step only; returns a :class:`Status`."""
        raise RuntimeError(f"{self.name}: this slave does not interpolate its inputs")

    @abstractmethod
    def exit_initialization(self) -> None: ...

    @abstractmethod
    def do_step(self, t: float, h: float) -> int:
        """Advance from communication point ``t`` [s] by ``h`` [s]; returns a :class:`Status`."""

    def asked_to_stop(self) -> bool:
        """After a Discard from :meth:`do_step`: was it a request to end the simulation (FMI 2.0
        fmi2Terminated)?  False by default."""
        return False

    def terminate(self) -> None:
        """End the simulation (the instance may still be read)."""

    def free(self) -> None:
        """Release the instance and its resources."""

    def native(self) -> NativeEntry | None:
        """C entry points for the compiled loop, or None (the Python loop is used)."""
        return None

    # rollback (variable-step and iterative algorithms) --------------------------------------------
    @property
    def can_rollback(self) -> bool:
        """Whether :meth:`save_state` and :meth:`restore_state` work (FMI get/set FMU state)."""
        return False

    def save_state(self) -> None:
        """Remember the complete state, inputs and input slopes included (one slot: the next save
        overwrites it).  Only for slaves that :attr:`can_rollback`."""
        raise RuntimeError(f"{self.name}: this slave cannot save its state (no rollback)")

    def restore_state(self) -> None:
        """Return to the state of the last :meth:`save_state`."""
        raise RuntimeError(f"{self.name}: this slave cannot restore a state (no rollback)")

    def output_jacobian(self, outputs: Sequence[str], inputs: Sequence[str]) -> np.ndarray | None:
        """Partial derivatives ``d outputs / d inputs`` at the current instant (FMI get directional
        derivative: the direct feedthrough, not the sensitivity of a step), shape
        ``(len(outputs), len(inputs))``; None when the slave does not provide them."""
        return None


# --- FMUs -------------------------------------------------------------------------------------
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
    from .outputs import pid_alive

    for d in Path(tempfile.gettempdir()).glob("rpr-fmu-*-*"):
        pid = d.name.split("-")[2]
        if pid.isdigit() and int(pid) != os.getpid() and not pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


def _unzip(path: Path) -> str:
    import fmpy

    key = (str(path.resolve()), path.stat().st_mtime)
    if key not in _UNZIPPED:
        if not _UNZIPPED:  # once per process
            _sweep_dead_unzips()
        # sources/ is not needed to load the binary (and is most of a generated FMU's bytes)
        _UNZIPPED[key] = fmpy.extract(str(path), unzipdir=tempfile.mkdtemp(prefix=f"rpr-fmu-{os.getpid()}-"),
                                      include=lambda name: not name.startswith("sources/"))
    return _UNZIPPED[key]


_DoStep2 = ctypes.CFUNCTYPE(c_int, c_void_p, c_double, c_double, c_int)
_GetState = ctypes.CFUNCTYPE(c_int, c_void_p, POINTER(c_void_p))  # also the free function's signature
_SetState = ctypes.CFUNCTYPE(c_int, c_void_p, c_void_p)
_IO2 = ctypes.CFUNCTYPE(c_int, c_void_p, POINTER(c_uint32), c_size_t, POINTER(c_double))
_DoStep3 = ctypes.CFUNCTYPE(c_int, c_void_p, c_double, c_double, c_bool, POINTER(c_bool), POINTER(c_bool),
                            POINTER(c_bool), POINTER(c_double))
_IO3 = ctypes.CFUNCTYPE(c_int, c_void_p, POINTER(c_uint32), c_size_t, POINTER(c_double), c_size_t)
_RAW2 = ctypes.CFUNCTYPE(c_int, c_void_p, c_void_p, c_size_t, c_void_p)
_RAW3 = ctypes.CFUNCTYPE(c_int, c_void_p, c_void_p, c_size_t, c_void_p, c_size_t)
_SetDer2 = ctypes.CFUNCTYPE(c_int, c_void_p, POINTER(c_uint32), c_size_t, POINTER(c_int), POINTER(c_double))


def _addr(fn) -> int:
    return ctypes.cast(fn, c_void_p).value


class FmuSlave(Slave):
    """A co-simulation FMU (FMI 2.0 or 3.0).  FMPy loads the library and handles instantiation,
    initialisation and termination; the per-step calls go straight to the FMI functions through
    ctypes with preallocated buffers (or through the compiled loop via :meth:`native`)."""

    def __init__(self, name: str, path: Path, description: SlaveDescription | None = None):
        self.path = Path(path)
        super().__init__(name, description or describe_fmu(self.path))
        self.fmi3 = str(self.description.fmi_version).startswith("3")
        self.fmu = None
        self._terminated = False
        self._empty_vr = (c_uint32 * 1)()
        self._empty_val = (c_double * 1)()

    #: Keep the instance when a run ends (:meth:`free` leaves it alive) so that the next run's
    #: :meth:`instantiate` resets it (fmi2Reset / fmi3Reset) instead of loading the FMU again;
    #: :meth:`release` frees it for good.  Used by batches (:mod:`cosim.batch`).
    reuse: bool = False

    # lifecycle ---------------------------------------------------------------------------------
    def instantiate(self) -> None:
        if self.fmu is not None:  # kept from a previous run (reuse): back to the instantiated state
            self.reset()
            return
        import fmpy
        from fmpy.fmi2 import FMU2Slave, defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE
        from fmpy.fmi3 import FMU3Slave, fmi3LogMessageCallback

        guid, ident = self.description.guid, self.description.model_identifier
        if not (guid and ident):
            md = fmpy.read_model_description(str(self.path), validate=False)
            guid, ident = md.guid, md.coSimulation.modelIdentifier
        unzip = _unzip(self.path)
        try:
            if self.fmi3:
                self._log = fmi3LogMessageCallback(self._on_log3)
                self.fmu = FMU3Slave(guid=guid, unzipDirectory=unzip, modelIdentifier=ident,
                                     instanceName=self.name)
                self.fmu.instantiate(logMessage=self._log)
            else:
                cb = fmi2CallbackFunctions()
                cb.logger = fmi2CallbackLoggerTYPE(self._on_log2)
                cb.allocateMemory = defaultCallbacks.allocateMemory
                cb.freeMemory = defaultCallbacks.freeMemory
                self._callbacks = cb
                self.fmu = FMU2Slave(guid=guid, unzipDirectory=unzip, modelIdentifier=ident,
                                     instanceName=self.name)
                self.fmu.instantiate(callbacks=cb)
        except Exception as exc:  # fmpy raises bare Exceptions for a missing binary or failed call
            raise UserError(f"{self.name}: cannot instantiate {self.path} ({exc}"
                            f"{'; ' + self.last_message if self.last_message else ''})") from None
        dll = self.fmu.dll
        if self.fmi3:
            self._step3 = _DoStep3(_addr(dll.fmi3DoStep))
            self._get = _IO3(_addr(dll.fmi3GetFloat64))
            self._set = _IO3(_addr(dll.fmi3SetFloat64))
            self._flags = [c_bool(), c_bool(), c_bool()]  # eventHandlingNeeded, terminateSimulation, earlyReturn
            self._last_t = c_double()
            self._p_flags = [ctypes.byref(f) for f in self._flags]
            self._p_last = ctypes.byref(self._last_t)
        else:
            self._step2 = _DoStep2(_addr(dll.fmi2DoStep))
            self._get = _IO2(_addr(dll.fmi2GetReal))
            self._set = _IO2(_addr(dll.fmi2SetReal))
        self._inst = c_void_p(self.fmu.component)

    def _on_log2(self, env, instance, status, category, message) -> None:
        self.messages.append(f"[{Status(status).name if status in Status._value2member_map_ else status}] "
                             f"{(message or b'').decode(errors='replace')}")

    def _on_log3(self, env, status, category, message) -> None:
        self.messages.append(f"[{Status(status).name if status in Status._value2member_map_ else status}] "
                             f"{(message or b'').decode(errors='replace')}")

    def _call(self, what: str, fn, *args) -> None:
        try:
            fn(*args)
        except Exception as exc:  # fmpy's FMICallException and friends
            detail = f": {self.last_message}" if self.last_message else ""
            raise UserError(f"{self.name}: {what} failed ({exc}){detail}") from None

    def set_start(self, values: dict[str, object]) -> None:
        """Parameters and start values of any FMI type by name (arrays as lists); FMI 3.0
        structural parameters are set first, in configuration mode."""
        if not values:
            return
        vs = self.description.variables
        structural = [k for k in values if vs[k].causality == "structuralParameter"]
        if structural and self.fmi3:
            self._call("fmi3EnterConfigurationMode", self.fmu.enterConfigurationMode)
            for k in structural:
                self._call(f"setting structural parameter {k}", self.set_values, k, values[k])
            self._call("fmi3ExitConfigurationMode", self.fmu.exitConfigurationMode)
        for k, val in values.items():
            if k not in structural:
                self._call(f"setting start value {k}", self.set_values, k, val)

    def _accessor(self, verb: str, type_name: str):
        from .fmitypes import TYPES

        ft = TYPES[type_name]
        return getattr(self.fmu, verb + (ft.fmi3 if self.fmi3 else ft.fmi2))

    def set_values(self, name: str, value) -> None:
        """Set variable ``name`` (any type; an array as its values in row-major order); raises
        fmpy's exception on a failing status."""
        from .fmitypes import TYPES, parse_start

        var = self.description.variables[name]
        ft = TYPES[var.type]
        vals = parse_start(value, ft, var.size, name)
        self._accessor("set", var.type)([var.vr], [v.item() if hasattr(v, "item") else v for v in vals])

    def raw_io(self, verb: str, type_name: str, vrs: list[int], n_values: int) -> tuple[Callable[[], int], np.ndarray]:
        """A no-argument call of fmi2/3 ``Get``/``Set`` (``verb``) of numeric type ``type_name`` on
        ``vrs`` (``n_values`` values in all) and the numpy buffer it reads into or writes from (the
        FMI storage type: FMI 2.0 Boolean and Enumeration are int32); returns the FMI status."""
        from .fmitypes import TYPES

        ft = TYPES[type_name]
        if self.fmi3:
            dtype = np.bool_ if type_name == "Boolean" else ft.dtype
            proto = _RAW3
        else:
            dtype = np.float64 if type_name == "Real" else np.int32
            proto = _RAW2
        fname = f"fmi{'3' if self.fmi3 else '2'}{verb.capitalize()}{ft.fmi3 if self.fmi3 else ft.fmi2}"
        fn = proto(_addr(getattr(self.fmu.dll, fname)))
        vr = np.ascontiguousarray(vrs, dtype=np.uint32)
        buf = np.zeros(n_values, dtype=dtype)
        inst, p_vr, n_vr, p_buf = self._inst, vr.ctypes.data, len(vr), buf.ctypes.data
        keep = (vr, buf)
        if self.fmi3:
            return (lambda: fn(inst, p_vr, n_vr, p_buf, n_values) if keep else 0), buf
        return (lambda: fn(inst, p_vr, n_vr, p_buf) if keep else 0), buf

    def get_values(self, type_name: str, vrs: list[int], n_values: int) -> list:
        """Values of the variables ``vrs`` of one type (``n_values`` in all, arrays flattened)."""
        get = self._accessor("get", type_name)
        vals = get(vrs, n_values) if self.fmi3 else get(vrs)
        if type_name == "String":
            vals = [v.decode("utf-8", errors="replace") if isinstance(v, bytes) else v for v in vals]
        return vals

    def enter_initialization(self, start_time: float, stop_time: float, tolerance: float | None = None) -> None:
        if self.fmi3:
            self._call("fmi3EnterInitializationMode", self.fmu.enterInitializationMode,
                       tolerance, start_time, stop_time)
        else:
            self._call("fmi2SetupExperiment", self.fmu.setupExperiment, tolerance, start_time, stop_time)
            self._call("fmi2EnterInitializationMode", self.fmu.enterInitializationMode)

    def exit_initialization(self) -> None:
        self._call("exitInitializationMode", self.fmu.exitInitializationMode)

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
        if self.fmi3:
            n_in, n_out, inst, setf, getf = self._n_in, self._n_out, self._inst, self._set, self._get
            a_in, v_in, a_out, v_out = self._p_in_vr, self._p_in, self._p_out_vr, self._p_out
            self.push = (lambda: setf(inst, a_in, n_in, v_in, n_in)) if n_in else (lambda: 0)
            self.pull = (lambda: getf(inst, a_out, n_out, v_out, n_out)) if n_out else (lambda: 0)
        else:
            n_in, n_out, inst, setf, getf = self._n_in, self._n_out, self._inst, self._set, self._get
            a_in, v_in, a_out, v_out = self._p_in_vr, self._p_in, self._p_out_vr, self._p_out
            self.push = (lambda: setf(inst, a_in, n_in, v_in)) if n_in else (lambda: 0)
            self.pull = (lambda: getf(inst, a_out, n_out, v_out)) if n_out else (lambda: 0)

    def bind_slopes(self, slope_buf: np.ndarray) -> bool:
        if self.fmi3 or not self.description.can_interpolate_inputs or not self._n_in:
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

    def push(self) -> int:  # replaced per instance by bind()
        raise RuntimeError(f"{self.name}: push() before bind()")

    def pull(self) -> int:  # replaced per instance by bind()
        raise RuntimeError(f"{self.name}: pull() before bind()")

    def do_step(self, t: float, h: float) -> int:
        if self.fmi3:
            # noSetFMUStatePriorToCurrentPoint: only promised when this slave cannot be rolled back
            st = self._step3(self._inst, t, h, not self.can_rollback, *self._p_flags, self._p_last)
            if st < 2 and self._flags[1].value:
                return Status.STOP_REQUESTED
            return st
        st = self._step2(self._inst, t, h, 0)
        if st == Status.DISCARD and self.asked_to_stop():
            return Status.STOP_REQUESTED
        return st

    def asked_to_stop(self) -> bool:
        """After an FMI 2.0 Discard: did the FMU ask to end the simulation (fmi2Terminated)?"""
        if self.fmi3 or self.fmu is None:
            return False
        from fmpy.fmi2 import fmi2Terminated

        try:
            return bool(self.fmu.getBooleanStatus(fmi2Terminated))
        except Exception:  # an FMU that does not implement the status inquiry: a plain Discard
            return False

    def stop_detail(self) -> str:
        """Why and when the FMU asked to stop: its last successful time [s] (FMI 2.0 status, FMI 3.0
        doStep output), '' when unknown."""
        try:
            if self.fmi3:
                return f"its last successful time {self._last_t.value:.9g} s"
            from fmpy.fmi2 import fmi2LastSuccessfulTime

            return f"its last successful time {self.fmu.getRealStatus(fmi2LastSuccessfulTime):.9g} s"
        except Exception:  # optional inquiry
            return ""

    def terminate(self) -> None:
        if self.fmu is not None and not self._terminated:
            self._terminated = True
            try:
                self.fmu.terminate()
            except Exception:  # terminating after an Error/Fatal status may itself fail
                pass

    def reset(self) -> None:
        """Return the instance to its state right after instantiation (FMI reset): every
        variable back to its default, ready for :meth:`set_start` and another run."""
        self.messages.clear()
        self._call("reset", self.fmu.reset)
        self._terminated = False

    def free(self) -> None:
        if not self.reuse:
            self.release()

    def release(self) -> None:
        """Free the instance and its resources (also one kept for reuse)."""
        if self.fmu is not None:
            try:
                self._free_state()
            except Exception:  # a state of a failed instance: nothing more to do
                pass
            try:
                self.fmu.freeInstance()
            except Exception:  # after Fatal, freeInstance is undefined: nothing more to do
                pass
            self.fmu = None

    def native(self) -> NativeEntry | None:
        if self.fmu is None:
            return None
        dll = self.fmu.dll
        st = (0, 0, 0)
        if self.can_rollback:
            v = "3" if self.fmi3 else "2"
            try:
                st = tuple(_addr(getattr(dll, f"fmi{v}{x}")) for x in
                           (("GetFMUState", "SetFMUState", "FreeFMUState") if self.fmi3 else
                            ("GetFMUstate", "SetFMUstate", "FreeFMUstate")))
            except AttributeError:  # declared but not exported: no compiled rollback
                st = (0, 0, 0)
        if self.fmi3:
            return NativeEntry(True, self.fmu.component, _addr(dll.fmi3DoStep), _addr(dll.fmi3GetFloat64),
                               _addr(dll.fmi3SetFloat64), 0, *st)
        return NativeEntry(False, self.fmu.component, _addr(dll.fmi2DoStep), _addr(dll.fmi2GetReal),
                           _addr(dll.fmi2SetReal),
                           _addr(dll.fmi2SetRealInputDerivatives) if self.description.can_interpolate_inputs else 0,
                           *st, _boolean_status(dll))

    @property
    def can_rollback(self) -> bool:
        return bool(self.description.can_get_set_state)

    def _state_calls(self) -> tuple:
        """(get, set) FMU-state functions of the loaded library, made once per loaded FMU."""
        calls = getattr(self, "_state_fns", None)
        if calls is None or calls[0] is not self.fmu:
            dll = self.fmu.dll
            calls = self._state_fns = (
                self.fmu, _GetState(_addr(dll.fmi3GetFMUState if self.fmi3 else dll.fmi2GetFMUstate)),
                _SetState(_addr(dll.fmi3SetFMUState if self.fmi3 else dll.fmi2SetFMUstate)))
        return calls[1:]

    def save_state(self) -> None:
        if not self.can_rollback:
            return Slave.save_state(self)
        dll, state = self.fmu.dll, getattr(self, "_state", None)
        if state is None:
            state = self._state = c_void_p()
        st = self._state_calls()[0](self._inst, ctypes.byref(state))
        if st in FAILING:
            raise UserError(f"{self.name}: getting the FMU state failed ({Status(st).name})"
                            + (f": {self.last_message}" if self.last_message else ""))

    def restore_state(self) -> None:
        state = getattr(self, "_state", None)
        if state is None:
            raise RuntimeError(f"{self.name}: restore_state() before save_state()")
        st = self._state_calls()[1](self._inst, state)
        if st in FAILING:
            raise UserError(f"{self.name}: setting the FMU state failed ({Status(st).name})"
                            + (f": {self.last_message}" if self.last_message else ""))

    def _free_state(self) -> None:
        state = getattr(self, "_state", None)
        if state is not None and state.value and self.fmu is not None:
            fn = _GetState(_addr(self.fmu.dll.fmi3FreeFMUState if self.fmi3 else self.fmu.dll.fmi2FreeFMUstate))
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
            raise UserError(f"{self.name}: get directional derivative failed ({exc})"
                            + (f": {self.last_message}" if self.last_message else "")) from None
        return jac


# --- analytic slaves --------------------------------------------------------------------------
class LinearSlave(Slave):
    """A continuous linear system ``x' = A x + B u``, ``y = C x + D u`` stepped *exactly* under a
    zero-order hold on ``u``: ``x+ = Ad x + Bd u`` with ``[Ad Bd] = expm([[A, B], [0, 0]] h)[:n]``.

    Inputs are named ``u[1]..u[m]``, outputs ``y[1]..y[p]``, states ``x[1]..x[n]`` unless names are
    given; outputs with a nonzero column in ``D`` have direct feedthrough from that input.  The
    start state is settable by name (``set_start``) before initialisation.  This is the analytic
    slave of the master's tests (a coupled pair has a known discrete solution) and a known plant.
    """

    def __init__(self, name: str, A, B, C, D=None, *, x0=None, inputs: list[str] | None = None,
                 outputs: list[str] | None = None, states: list[str] | None = None):
        A = np.atleast_2d(np.asarray(A, float))
        B = np.asarray(B, float).reshape(A.shape[0], -1)
        C = np.asarray(C, float).reshape(-1, A.shape[0])
        D = np.zeros((C.shape[0], B.shape[1])) if D is None else np.asarray(D, float).reshape(C.shape[0], B.shape[1])
        self.A, self.B, self.C, self.D = A, B, C, D
        n, m, p = A.shape[0], B.shape[1], C.shape[0]
        inputs = inputs or [f"u[{i + 1}]" for i in range(m)]
        outputs = outputs or [f"y[{i + 1}]" for i in range(p)]
        states = states or [f"x[{i + 1}]" for i in range(n)]
        self.x = np.zeros(n) if x0 is None else np.asarray(x0, float).copy()
        vs: dict[str, Variable] = {}
        for i, s in enumerate(states):
            vs[s] = Variable(s, "local", "continuous", "Real", float(self.x[i]), vr=i)
        for i, u in enumerate(inputs):
            vs[u] = Variable(u, "input", "continuous", "Real", 0.0, vr=n + i)
        for i, y in enumerate(outputs):
            vs[y] = Variable(y, "output", "continuous", "Real", None, vr=n + m + i)
        ft = {y: [inputs[j] for j in range(m) if D[i, j] != 0.0] for i, y in enumerate(outputs)}
        super().__init__(name, SlaveDescription("python", type(self).__name__, vs, ft, can_get_set_state=True))
        self.u = np.zeros(m)
        self._n, self._m = n, m
        self._h = None

    def instantiate(self) -> None:
        pass

    def set_start(self, values: dict[str, float]) -> None:
        for k, v in values.items():
            vr = self.vr(k)
            if vr < self._n:
                self.x[vr] = v
            elif vr < self._n + self._m:
                self.u[vr - self._n] = v
            else:
                raise UserError(f"{self.name}: {k!r} is an output; it has no start value")

    def enter_initialization(self, start_time: float, stop_time: float) -> None:
        pass

    def exit_initialization(self) -> None:
        pass

    def bind(self, in_vrs, in_buf, out_vrs, out_buf) -> None:
        self._in_idx = np.asarray(in_vrs, dtype=np.int64) - self._n
        self._out_vrs = np.asarray(out_vrs, dtype=np.int64)
        self._in_buf, self._out_buf = in_buf, out_buf

    def push(self) -> int:
        self.u[self._in_idx] = self._in_buf
        return Status.OK

    def pull(self) -> int:
        allv = np.concatenate([self.x, self.u, self.C @ self.x + self.D @ self.u])
        self._out_buf[:] = allv[self._out_vrs]
        return Status.OK

    def discretize(self, h: float) -> tuple[np.ndarray, np.ndarray]:
        """``(Ad, Bd)`` of the exact zero-order-hold step of length ``h`` [s]."""
        import scipy.linalg  # here: scipy costs ~0.3 s of start-up that only this slave needs

        n, m = self._n, self._m
        M = np.zeros((n + m, n + m))
        M[:n, :n], M[:n, n:] = self.A, self.B
        E = scipy.linalg.expm(M * h)
        return E[:n, :n], E[:n, n:]

    def do_step(self, t: float, h: float) -> int:
        if self._h != h:
            self._Ad, self._Bd = self.discretize(h)
            self._h = h
        self.x = self._Ad @ self.x + self._Bd @ self.u
        return Status.OK if np.all(np.isfinite(self.x)) else Status.DISCARD

    def get_state(self) -> tuple[np.ndarray, np.ndarray]:
        return self.x.copy(), self.u.copy()

    def set_state(self, state: tuple[np.ndarray, np.ndarray]) -> None:
        self.x, self.u = state[0].copy(), state[1].copy()

    @property
    def can_rollback(self) -> bool:
        return True

    def save_state(self) -> None:
        self._saved = self.get_state()

    def output_jacobian(self, outputs: Sequence[str], inputs: Sequence[str]) -> np.ndarray | None:
        rows, cols = [self.vr(y) - self._n - self._m for y in outputs], [self.vr(u) - self._n for u in inputs]
        if min(rows, default=0) < 0:
            raise UserError(f"{self.name}: output_jacobian takes outputs only, got {list(outputs)}")
        return self.D[np.ix_(rows, cols)].copy()

    def restore_state(self) -> None:
        self.set_state(self._saved)

