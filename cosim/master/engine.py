"""Engines, who runs an algorithm's steps: a compiled loop (for the algorithms that have one: FMUs
directly, Python slaves and typed ports through callbacks; :class:`CompiledLoop` says what each
runs) or the Python loop; the choice between them is made here, once for every algorithm
(:func:`choose_engine`)."""
from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import UserError
from . import adaptive_engine, fastloop, iterative_engine
from .algorithm import Algorithm
from .algorithms.jacobi_extrapolated import WEIGHTS
from .native import SlaveArray, builds, called_back
from .stepper import FixedStepper
from .system import CoupledSystem

#: :attr:`Algorithm.native_code` of the fixed-step loop's algorithms (0 Jacobi, 1 Gauss-Seidel, 3 Jacobi with
#: extrapolated inputs) and of iterative
ITERATIVE, EXTRAPOLATED = 2, 3
#: jacobi_extrapolated's weights as the kernel reads them: row m for m past values (zeros after)
WEIGHTS_3x3 = [list(w) + [0.0] * (3 - len(w)) for w in WEIGHTS]

ENGINES = ("auto", "compiled", "python")


@dataclass(frozen=True)
class CompiledLoop:
    """What an algorithm's compiled loop is and needs: its library's loader (None: the algorithm
    has none), FMU state get/set (``rollback``); ``callbacks``: it runs slaves without C entry
    points (callback slaves, :mod:`cosim.master.callbacks`); ``typed``: typed ports too (their
    slaves called back, their text changes noted); ``transforms``: it applies the connections'
    linear transformations."""

    algorithm: str
    library: Callable[[], ctypes.CDLL] | None
    rollback: bool = False
    callbacks: bool = False
    typed: bool = False
    transforms: bool = False


def fixed_loop(cls: type[Algorithm]) -> CompiledLoop:
    """The compiled loop of the fixed-step algorithm ``cls`` (by its :attr:`native_code`)."""
    if cls.native_code is None:
        return CompiledLoop(cls.name, None)
    if cls.native_code == ITERATIVE:
        return CompiledLoop(cls.name, iterative_engine.library, cls.needs_rollback, callbacks=True, typed=True,
                            transforms=True)
    return CompiledLoop(cls.name, fastloop.library, callbacks=True, typed=True, transforms=True)


def _why_not(system: CoupledSystem, loop: CompiledLoop) -> str:
    """Why ``loop`` cannot run ``system`` ('' when it can)."""
    if loop.library is None:
        return "has no loop"
    if any(s.event_mode for s in system.slaves):
        return "does not end its steps at events; FMI 3.0 event-mode components run in the Python loop"
    if system.transformed and not loop.transforms:
        return ("copies connections as they are; connections with a linear transformation (factor, offset) run "
                "in the Python loop")
    if system.typed.active and not loop.typed:
        return "carries scalar Float64 variables only; this scene connects or records other types or arrays"
    entries = [(s, None if called_back(system, i) else s.native()) for i, s in enumerate(system.slaves)]
    missing = [s.name for s, ne in entries if ne is None and not loop.callbacks]
    if missing:
        return f"needs FMU slaves with C entry points ({', '.join(missing)} has none)"
    # a callback slave rolls back through its own save_state/restore_state
    stateless = [s.name for s, ne in entries
                 if loop.rollback and not (s.can_rollback if ne is None else ne.get_state and ne.set_state)]
    if stateless:
        return f"needs FMU state get/set ({', '.join(stateless)} has none)"
    return ""


def choose_engine(system: CoupledSystem, engine: str, loop: CompiledLoop) -> str:
    """``"compiled"`` or ``"python"`` for ``engine`` in auto | compiled | python: auto takes the
    compiled loop where it can run the scene and builds here, compiled refuses with the reason a
    scene it cannot run."""
    if engine not in ENGINES:
        raise UserError(f"master.engine must be auto, compiled or python, got {engine!r}")
    if engine == "python":
        return "python"
    why = _why_not(system, loop)
    if engine == "compiled":
        if why:
            raise UserError(f"master.engine: compiled for {loop.algorithm} {why}; use master.engine auto or python")
        return "compiled"  # a missing C compiler is said when the library is built
    return "python" if why or not builds(loop.library) else "compiled"


class _Compiled:
    """Runs Jacobi's or Gauss-Seidel's steps in the compiled loop (:mod:`cosim.master.fastloop`):
    ``run(nsteps, rec_every, rec) -> rows``, updating the algorithm's step count, status and
    counters as its own loop would."""

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
        self.order = np.array(alg.order, dtype=np.int32)
        self.rec_idx = sysm.record_idx
        self.alg = alg
        self.n_rows = ctypes.c_int64()
        self.fail_slave = ctypes.c_int32()
        self.fail_status = ctypes.c_int32()
        self.master_ns = ctypes.c_int64()
        #: wall time after which one call returns early [ns]: signals are handled between calls
        self.budget_ns = fastloop.CALL_BUDGET_NS

    def run(self, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
        alg, sysm = self.alg, self.alg.system
        self.master_ns.value = 0
        done = self.lib.rpr_run(self.arr.arr, len(self.arr), self.order.ctypes.data, alg.native_code,
                                self.weights.ctypes.data if self.weights.size else None,
                                sysm.v.ctypes.data, alg.k, nsteps, alg.start_ns, alg.step_ns, int(alg.timing),
                                self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx),
                                rec_every, rec.ctypes.data, ctypes.byref(self.n_rows),
                                ctypes.byref(self.fail_slave), ctypes.byref(self.fail_status),
                                ctypes.byref(self.master_ns), self.budget_ns)
        for i, c in enumerate(self.arr.arr):
            alg.calls[i], alg.slave_ns[i] = c.calls, c.ns
        alg.master_ns += self.master_ns.value
        alg.k += int(done)
        self.arr.reraise()  # a callback slave's exception (a model's error, Ctrl-C), raised here
        t_fail = alg.t
        rows = int(self.n_rows.value)
        i, st = self.fail_slave.value, self.fail_status.value
        if i >= 0 and alg.stop_requested(i, st):
            alg.complete_after_stop(i, t_fail)
            if alg.status == "stopped":  # the last point, on the output grid or not
                rec[rows, 0] = alg.t
                np.take(sysm.v, sysm.record_idx, out=rec[rows, 1:])
                rows += 1
        elif i >= 0:
            alg._fail(i, st, t_fail)
        return rows


def fixed_stepper(system: CoupledSystem, *, cls: type[Algorithm], step_ns: int, n_steps: int, record_every: int,
                  engine: str = "auto", options: dict | None = None, record: str = "grid", **kw) -> FixedStepper:
    """A fixed-step algorithm ``cls`` over the initialised ``system`` on its engine (``engine``:
    auto | compiled | python, see :func:`choose_engine`); ``kw`` go to the algorithm (``record``:
    a fixed-step run's steps are its grid)."""
    alg = cls(system, step_ns, **kw, **({"options": options} if cls.options else {}))
    name = choose_engine(system, engine, fixed_loop(cls))
    runner = None
    if name == "compiled":
        runner = (iterative_engine.CompiledIterative(alg) if cls.native_code == ITERATIVE else _Compiled(alg)).run
    return FixedStepper(alg, runner, n_steps, record_every)


def variable_loop(name: str, stepper_cls: type) -> CompiledLoop:
    """The compiled loop of a variable-step stepper class (:mod:`cosim.master.adaptive_engine`)."""
    library = adaptive_engine.library if adaptive_engine.has_compiled(stepper_cls) else None
    return CompiledLoop(name, library, stepper_cls.needs_rollback, callbacks=True, typed=True, transforms=True)


__all__ = ["CompiledLoop", "ENGINES", "ITERATIVE", "choose_engine", "fixed_loop", "fixed_stepper", "variable_loop"]
