"""Engines, who runs an algorithm's steps: its compiled loop (FMUs directly, Python slaves and
typed ports through callbacks; :class:`CompiledLoop` says what each runs), or, for an algorithm
registered without a kernel (the Python extension point), its own Python loop.  The choice is made here, once for every algorithm
(:func:`choose_engine`).  A run needs a working C compiler (:func:`cosim.master.kernels.compile_loop`
says which is missing); the Python twins of the kernels are test oracles (``tests/oracles``),
plugged in through the one seam of :class:`Engine` (:func:`register_engine`)."""
from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import UserError
from . import adaptive_engine, fastloop, iterative_engine
from .algorithm import MAX_EVENTS_PER_STEP, Algorithm, MasterAlgorithm
from .algorithms.jacobi_extrapolated import WEIGHTS
from .entries import FIXED_CONTROL, FixedEnd, struct
from .kernels import SlaveArray, called_back
from .stepper import FixedStepper, Runner, StepResult, python_runner
from .system import CoupledSystem

#: :attr:`Algorithm.native_code` of the fixed-step loop's algorithms (0 Jacobi, 1 Gauss-Seidel, 3 Jacobi with
#: extrapolated inputs) and of iterative
ITERATIVE, EXTRAPOLATED = 2, 3
#: jacobi_extrapolated's weights as the kernel reads them: row m for m past values (zeros after)
WEIGHTS_3x3 = [list(w) + [0.0] * (3 - len(w)) for w in WEIGHTS]

#: what ``master.engine`` may be: auto (the compiled loop; an algorithm's own Python loop where that
#: is product code and the compiled one cannot run the scene) or compiled
ENGINES = ("auto", "compiled")
#: the answer to ``master.engine: python``
PYTHON_GONE = ("master.engine: python is gone: the Python loops are test oracles now (tests/oracles) and a run "
               "needs a C compiler; use auto or compiled")


@dataclass(frozen=True)
class Engine:
    """An engine besides the compiled one, registered under its name (:func:`register_engine`;
    the test oracles, ``tests/oracles``): the class it instantiates for a fixed-step algorithm
    (``algorithm(cls)``) and for a variable-step stepping (``stepping(kind)``), the runner of a
    fixed-step algorithm (``runner(alg)``: ``(n, record_every, rec) -> rows``, as
    :class:`FixedStepper` takes the compiled one) and the loop of a variable-step stepping
    (``loop(stepping)``: the interface of :class:`cosim.master.adaptive_engine.CompiledAdaptive`)."""

    name: str
    runner: Callable[[Algorithm], Runner]
    loop: Callable[[Any], Any]
    algorithm: Callable[[type], type] = lambda cls: cls
    stepping: Callable[[type], type] = lambda kind: kind


#: engines registered besides the compiled one, by name
REGISTERED: dict[str, Engine] = {}


def register_engine(engine: Engine) -> None:
    """Make ``engine`` selectable by its name (``master.engine``, ``simulate(engine=...)``)."""
    REGISTERED[engine.name] = engine


def engine_names() -> tuple[str, ...]:
    """The values ``master.engine`` takes here: :data:`ENGINES` and the registered engines."""
    return ENGINES + tuple(REGISTERED)


def check_engine(name: str) -> str:
    """``name`` when it is an engine here; else :class:`UserError` (``python``: :data:`PYTHON_GONE`)."""
    if name == "python":
        raise UserError(PYTHON_GONE)
    if name not in engine_names():
        raise UserError(f"master.engine must be one of {', '.join(engine_names())}, got {name!r}")
    return name


@dataclass(frozen=True)
class CompiledLoop:
    """What an algorithm's compiled loop is and needs: its library's loader (None: the algorithm
    has none), FMU state get/set (``rollback``); ``callbacks``: it runs slaves without C entry
    points (callback slaves, :mod:`cosim.master.callbacks`); ``typed``: typed ports too (their
    slaves called back, their text changes noted); ``transforms``: it applies the connections'
    linear transformations; ``events``: it ends its steps at FMI 3.0 events."""

    algorithm: str
    library: Callable[[], ctypes.CDLL] | None
    rollback: bool = False
    callbacks: bool = False
    typed: bool = False
    transforms: bool = False
    #: it ends steps at FMI 3.0 event-mode components' events (the event iteration runs in Python between calls)
    events: bool = False
    #: its slave structs carry FMU states: a slave that rolls back only in Python is called back
    states: bool = False
    #: the algorithm's own Python loop is product code and runs the scene (an algorithm registered
    #: without a kernel, :attr:`Algorithm.native_code` None: the Python extension point)
    python: bool = False


def fixed_loop(cls: type[Algorithm]) -> CompiledLoop:
    """The compiled loop of the fixed-step algorithm ``cls`` (by its :attr:`native_code`)."""
    if cls.native_code is None:
        return CompiledLoop(cls.name, None, python=True)
    if cls.native_code == ITERATIVE:
        return CompiledLoop(cls.name, iterative_engine.library, cls.needs_rollback, callbacks=True, typed=True,
                            transforms=True, events=True, states=True)
    return CompiledLoop(cls.name, fastloop.library, callbacks=True, typed=True, transforms=True, events=True)


def _why_not(system: CoupledSystem, loop: CompiledLoop) -> str:
    """Why ``loop`` cannot run ``system`` ('' when it can)."""
    if loop.library is None:
        return "has no compiled loop (no kernel)"
    if any(s.event_mode for s in system.slaves) and not loop.events:
        return "does not end its steps at events (this scene has FMI 3.0 event-mode components)"
    if system.transformed and not loop.transforms:
        return "copies connections as they are (this scene has connections with a linear transformation)"
    if system.typed.active and not loop.typed:
        return "carries scalar Float64 variables only; this scene connects or records other types or arrays"
    entries = [(s, None if called_back(system, i, loop.states) else s.native()) for i, s in enumerate(system.slaves)]
    missing = [s.name for s, ne in entries if ne is None and not loop.callbacks]
    if missing:
        return f"needs FMU slaves with C entry points ({', '.join(missing)} has none)"
    # a callback slave rolls back through its own save_state/restore_state
    stateless = [s.name for s, ne in entries
                 if loop.rollback and not (s.can_rollback if ne is None else ne.get_state and ne.set_state)]
    if stateless:
        return f"needs FMU state get/set ({', '.join(stateless)} has none)"
    return ""


def ends_steps_at_events(cls: type[MasterAlgorithm], engine: str) -> bool:
    """Whether a run of ``cls`` on ``engine`` (:func:`engine_names`) ends its steps at FMI 3.0
    events, so that its event-mode FMUs are instantiated in event mode: the algorithm does, and
    its compiled loop too when that loop is asked for."""
    if not cls.ends_steps_at_events:
        return False
    if engine != "compiled":
        return True
    if cls.variable_step:
        return cls.stepper is not None and adaptive_engine.ends_steps_at_events(cls.stepper)
    return issubclass(cls, Algorithm) and fixed_loop(cls).events


def needs_compiler(cls: type[MasterAlgorithm], engine: str) -> None:
    """At a run's start: ``engine`` checked (:func:`check_engine`) and the compiled loop of ``cls``
    built (on disk once), so that a machine without a working C compiler hears it before anything
    runs (:class:`UserError` naming the compiler, :func:`cosim.master.kernels.compile_loop`)."""
    check_engine(engine)
    if engine in REGISTERED:
        return
    if cls.variable_step:
        library = adaptive_engine.library if cls.stepper is None or adaptive_engine.has_compiled(cls.stepper) else None
    else:
        library = fixed_loop(cls).library if issubclass(cls, Algorithm) else None
    if library is not None:
        library()


def choose_engine(system: CoupledSystem, engine: str, loop: CompiledLoop) -> str:
    """Who runs ``loop``'s algorithm for ``engine`` (:func:`engine_names`): ``"compiled"``, a
    registered engine by its name, or ``"python"``, the algorithm's own Python loop where that is
    product code (:attr:`CompiledLoop.python`) and auto finds the compiled loop unable to run the
    scene; compiled refuses such a scene with the reason.  A missing C compiler is a
    :class:`UserError` here, never a fallback."""
    check_engine(engine)
    if engine in REGISTERED:
        return engine
    why = _why_not(system, loop)
    if why and engine == "auto" and loop.python:
        return "python"
    if why:
        hint = "; master.engine: auto runs it in the algorithm's Python loop" if loop.python else ""
        raise UserError(f"master.engine: {engine} for {loop.algorithm} {why}{hint}")
    loop.library()
    return "compiled"


class _Compiled:
    """Runs Jacobi's or Gauss-Seidel's steps in the compiled loop (:mod:`cosim.master.fastloop`):
    ``run(nsteps, rec_every, rec) -> rows``, updating the algorithm's step count, status,
    counters and event state (a call that ends at an event leaves it pending, its row the left
    limit) as its own loop would."""

    def __init__(self, alg: Algorithm):
        self.lib = fastloop.library()
        sysm = alg.system
        self.arr = arr = SlaveArray(sysm, callbacks=True)
        self.weights = np.array(WEIGHTS_3x3 if alg.native_code == EXTRAPOLATED else [], dtype=np.float64)
        for i in range(len(arr)):
            c = arr[i]
            if alg.interpolating[i]:
                c.interp, c.set_der = 1, arr.entries[i].set_input_derivatives
                c.orders, c.fresh = arr.buffer(np.ones(c.n_in, dtype=np.int32), np.int32), arr.buffer(
                    alg.fresh[i].astype(np.int8), np.int8)
                c.hist, c.slope = arr.buffer(alg.hist[i]), arr.buffer(alg.slopes[i])
            c.rate, c.sub_ns = alg.rates[i], alg.step_ns // alg.rates[i]
            if alg.rates[i] > 1 and alg.interpolating[i]:
                c.base = arr.buffer(np.empty(c.n_in))
            if alg.native_code == EXTRAPOLATED and c.n_in and i not in alg.exchange:
                c.past = arr.buffer(np.zeros(2 * c.n_in))
        self.ctl = self._events(alg) if alg.event_slaves else None
        self.order = np.array(alg.order, dtype=np.int32)
        self.rec_idx = sysm.record_idx
        self.alg = alg
        self.n_rows = ctypes.c_int64()
        self.fail_slave = ctypes.c_int32()
        self.fail_status = ctypes.c_int32()
        self.master_ns = ctypes.c_int64()
        #: wall time after which one call returns early [ns]: signals are handled between calls
        self.budget_ns = fastloop.CALL_BUDGET_NS

    def _events(self, alg: Algorithm):
        """The event state (``fx_ctl``) and the slaves' event fields: the event-mode slaves' step
        reports (:meth:`cosim.slaves.slave.Slave.event_slots`), the FMU state calls of those that
        roll back (an FMU's own state slot, as its ``save_state`` uses)."""
        arr, slaves = self.arr, alg.system.slaves
        for i in alg.event_slaves:
            c = arr[i]
            c.event_mode = 1
            c.step_flags, c.last_time, c.planned_end = slaves[i].event_slots()
        for i, s in enumerate(slaves):
            ne, c = arr.entries[i], arr[i]
            if s.can_rollback and ne.get_state and ne.set_state:
                c.get_state, c.set_state = ne.get_state, ne.set_state
                # a callback slave's trampolines keep their own state: the slot is only a non-null pointer
                c.state = (ctypes.addressof(arr.states) + i * ctypes.sizeof(ctypes.c_void_p)
                           if arr.callbacks[i] is not None else s.state_slot())
        ctl = struct(FIXED_CONTROL)()
        ctl.n_event, ctl.max_events = len(alg.event_slaves), MAX_EVENTS_PER_STEP
        return ctl

    def run(self, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
        alg, sysm, ctl = self.alg, self.alg.system, self.ctl
        self.master_ns.value = 0
        t_call = alg.t  # the first step's start (the later ones start on the grid)
        if ctl is not None:
            ctl.has_t_event, ctl.t_event = alg.t_event is not None, alg.t_event or 0.0
            ctl.events_in_step = alg._events_in_step
        done = self.lib.rpr_run(self.arr.arr, len(self.arr), self.order.ctypes.data, alg.native_code,
                                self.weights.ctypes.data if self.weights.size else None,
                                sysm.v.ctypes.data, alg.k, nsteps, alg.start_ns, alg.step_ns, int(alg.timing),
                                self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx),
                                rec_every, rec.ctypes.data, ctypes.byref(self.n_rows),
                                ctypes.byref(self.fail_slave), ctypes.byref(self.fail_status),
                                ctypes.byref(self.master_ns), self.budget_ns,
                                None if ctl is None else ctypes.byref(ctl))
        for i, c in enumerate(self.arr.arr):
            alg.calls[i], alg.slave_ns[i] = c.calls, c.ns
        alg.master_ns += self.master_ns.value
        alg.k += int(done)
        self.arr.reraise()  # a callback slave's exception (a model's error, Ctrl-C), raised here
        rows = int(self.n_rows.value)
        i, st = self.fail_slave.value, self.fail_status.value
        if ctl is not None and self._after_events(ctl, t_call if done == 0 else alg.time_at(alg.k)):
            if alg.pending_event is not None or alg.status == "stopped":  # its row (at an event the left limit)
                rec[rows, 0] = alg.t
                np.take(sysm.v, sysm.record_idx, out=rec[rows, 1:])
                rows += 1
            return rows
        t_fail = alg.t
        if i >= 0 and alg.stop_requested(i, st):
            alg.complete_after_stop(i, t_fail)
            if alg.status == "stopped":  # the last point, on the output grid or not
                rec[rows, 0] = alg.t
                np.take(sysm.v, sysm.record_idx, out=rec[rows, 1:])
                rows += 1
        elif i >= 0:
            alg._fail(i, st, t_fail)
        return rows

    def _after_events(self, ctl, start: float) -> bool:
        """The algorithm's event state after a call (as its Python event step leaves it; ``start``:
        the last step's start [s]); True when the call ended at an event or ended the run (else the
        common ending follows)."""
        alg, arr = self.alg, self.arr
        alg.t_event = ctl.t_event if ctl.has_t_event else None
        alg._events_in_step = ctl.events_in_step
        ahead = {j for j in range(len(arr)) if arr[j].ahead}
        end = FixedEnd(ctl.status)
        if end in (FixedEnd.EVENT, FixedEnd.STOPPED):  # (at the grid point none is ahead)
            for j in sorted(ahead - alg._ahead):
                alg.late(j, ctl.who, ctl.t_e, arr[j].reached)
        alg._ahead = ahead
        if end in (FixedEnd.EVENT, FixedEnd.GRID_EVENT):
            alg.pending_event = StepResult(alg.t_ns, True, ctl.who, "event")
        elif end == FixedEnd.CHATTERING:
            alg.chattering(ctl.who, ctl.t_e)
        elif end == FixedEnd.FAILED:
            alg._fail(self.fail_slave.value, self.fail_status.value, alg.t)
        elif end == FixedEnd.STOPPED:  # the step ended at the grid point or its event (t_event)
            alg.stopped_by(next(j for j in range(len(arr)) if arr[j].stop), start, alg.t_event)
        return end != FixedEnd.RUNNING


def fixed_stepper(system: CoupledSystem, *, cls: type[Algorithm], step_ns: int, n_steps: int, record_every: int,
                  engine: str = "auto", options: dict | None = None, record: str = "grid", **kw) -> FixedStepper:
    """A fixed-step algorithm ``cls`` over the initialised ``system`` on its engine (``engine``:
    see :func:`choose_engine`); ``kw`` go to the algorithm (``record``: a fixed-step run's steps
    are its grid)."""
    name = choose_engine(system, engine, fixed_loop(cls))
    other = REGISTERED.get(name)
    make = other.algorithm(cls) if other is not None else cls
    alg = make(system, step_ns, **kw, **({"options": options} if cls.options else {}))
    if other is not None:
        runner = other.runner(alg)
    elif name == "python":
        runner = python_runner(alg)
    else:  # (iterative's kernel takes its start-time iteration at once)
        runner = (iterative_engine.CompiledIterative(alg) if cls.native_code == ITERATIVE else _Compiled(alg)).run
    return FixedStepper(alg, runner, n_steps, record_every, name)


def variable_loop(name: str, stepper_cls: type) -> CompiledLoop:
    """The compiled loop of a variable-step stepper class (:mod:`cosim.master.adaptive_engine`)."""
    library = adaptive_engine.library if adaptive_engine.has_compiled(stepper_cls) else None
    return CompiledLoop(name, library, stepper_cls.needs_rollback, callbacks=True, typed=True, transforms=True,
                        states=stepper_cls.needs_rollback,
                        events=adaptive_engine.ends_steps_at_events(stepper_cls))


__all__ = ["CompiledLoop", "ENGINES", "Engine", "ITERATIVE", "PYTHON_GONE", "REGISTERED", "check_engine",
           "choose_engine", "engine_names", "ends_steps_at_events", "fixed_loop", "fixed_stepper", "needs_compiler",
           "register_engine", "variable_loop"]
