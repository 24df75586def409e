"""Engines, who runs an algorithm's steps: the compiled loop (:mod:`cosim.master.fastloop`, for FMU
slaves and algorithms with a ``native_code``) or the Python loop, its bit-identical reference."""
from __future__ import annotations

import numpy as np

from ..errors import UserError
from .algorithm import Algorithm
from .stepper import FixedStepper
from .system import CoupledSystem

#: :attr:`Algorithm.native_code` of the fixed-step loop's algorithms (0 Jacobi, 1 Gauss-Seidel) and of iterative
ITERATIVE = 2


class _Compiled:
    """Runs an algorithm's steps in the compiled loop (:mod:`cosim.master.fastloop`; for
    ``iterative``, :class:`cosim.master.iterative_engine.CompiledIterative`, which it returns)."""

    def __new__(cls, alg: Algorithm):
        if alg.native_code == ITERATIVE:
            from .iterative_engine import CompiledIterative

            return CompiledIterative(alg)
        return super().__new__(cls)

    def __init__(self, alg: Algorithm):
        import ctypes

        from . import fastloop
        from .native import SlaveArray

        self.lib = fastloop.library()
        sysm = alg.system
        self.arr = arr = SlaveArray(sysm)
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
        self.order = np.array(alg.order, dtype=np.int32)
        self.rec_idx = sysm.record_idx
        self.alg = alg
        self.c = ctypes
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
                                sysm.v.ctypes.data, alg.k, nsteps, alg.step_ns, int(alg.timing),
                                self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx),
                                rec_every, rec.ctypes.data, self.c.byref(self.n_rows),
                                self.c.byref(self.fail_slave), self.c.byref(self.fail_status),
                                self.c.byref(self.master_ns), self.budget_ns)
        for i, c in enumerate(self.arr.arr):
            alg.calls[i], alg.slave_ns[i] = c.calls, c.ns
        alg.master_ns += self.master_ns.value
        alg.k += int(done)
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


def _python_run(alg: Algorithm, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
    v, idx = alg.system.v, alg.system.record_idx
    rows, typed = 0, alg.system.typed
    for _ in range(nsteps):
        ok = alg.step()
        if (ok and alg.k % rec_every == 0) or alg.status == "stopped":
            rec[rows, 0] = alg.t
            np.take(v, idx, out=rec[rows, 1:])
            rows += 1
            if typed.texts:
                alg.text_events += [(alg.t, c, x) for c, x in typed.text_changes()]
        if not ok:
            break
    return rows



def fixed_stepper(system: CoupledSystem, *, cls: type[Algorithm], step_ns: int, n_steps: int, record_every: int,
                  engine: str = "auto", options: dict | None = None, **kw) -> FixedStepper:
    """A fixed-step algorithm ``cls`` over the initialised ``system`` on its engine (``engine``:
    auto | compiled | python, see :func:`choose_engine`); ``kw`` go to the algorithm."""
    alg = cls(system, step_ns, **kw, **({"options": options} if getattr(cls, "options", ()) else {}))
    name = choose_engine(system, cls, engine, alg.start_ns)
    runner = _Compiled(alg).run if name == "compiled" else (lambda n, e, r: _python_run(alg, n, e, r))
    return FixedStepper(alg, runner, name, n_steps, record_every)


def choose_engine(system: CoupledSystem, alg_cls: type[Algorithm], engine: str, start_ns: int = 0) -> str:
    """``"compiled"`` or ``"python"`` for ``engine`` in auto | compiled | python."""
    if engine not in ("auto", "compiled", "python"):
        raise UserError(f"master.engine must be auto, compiled or python, got {engine!r}")
    if engine == "python":
        return "python"
    entries = [s.native() for s in system.slaves]
    native = alg_cls.native_code is not None and all(ne is not None for ne in entries)
    if native and getattr(alg_cls, "needs_rollback", False):  # iterative: the loop saves and restores states
        native = all(ne.get_state and ne.set_state for ne in entries)
    if engine == "compiled" and system.transformed:
        raise UserError("master.engine: compiled copies connections as they are; connections with a linear "
                        "transformation (factor, offset) run in the Python loop: use master.engine: python or auto")
    if engine == "compiled" and system.typed.active:
        raise UserError("master.engine: compiled carries scalar Float64 variables only; this scene connects or "
                        "records other types or arrays: use engine auto or python")
    if engine == "compiled" and start_ns:
        raise UserError("master.engine: compiled runs from start_time 0; use engine auto or python")
    native = native and not system.typed.active and not start_ns and not system.transformed
    if engine == "compiled":
        if not native:
            raise UserError(f"master.engine: compiled needs FMU slaves and an algorithm with a compiled loop "
                            f"({alg_cls.name} / {', '.join(s.name for s in system.slaves if s.native() is None) or 'all FMUs'})")
        return "compiled"
    if alg_cls.native_code == ITERATIVE:
        from . import iterative_engine as loop
    else:
        from . import fastloop as loop

    return "compiled" if native and loop.available() else "python"
