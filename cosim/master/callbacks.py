"""Callback slaves: C entry points for a slave that has none of its own (a Python slave) or whose
values the master does not move itself (typed ports: non-Float64 or array variables, converted
in the slave's ``push``/``pull`` by :class:`cosim.slaves.typedio.TypedPorts`).

Each is a ctypes ``CFUNCTYPE`` trampoline in an FMI 2.0 shape (:func:`fmus.fmi_functions.prototype`)
around the slave's own method (``save_state``/``restore_state`` behind the FMU state calls, for
a slave that :attr:`~cosim.slaves.slave.Slave.can_rollback`), so a compiled loop calls it like
any FMU.  The buffers the loop
passes are the ones the slave is bound to (``system.in_buf``, ``out_buf`` and the slope buffers
are views of the value vector the loop writes into), so a trampoline does not read its value
references and arrays.  A ctypes callback cannot raise through C: an exception (a model's error,
Ctrl-C) is kept, the call returns Fatal, the loop ends its block, and :meth:`CallbackSlave.reraise`
raises it in Python after the loop has returned.
"""
from __future__ import annotations

import ctypes

import numpy as np

from fmus.fmi_functions import prototype

from ..slaves.slave import Slave, Status
from .entries import CallbackStatus

_DO_STEP = prototype("fmi2DoStep", raw=True)
_GET = prototype("fmi2GetReal", raw=True)
_SET = prototype("fmi2SetReal", raw=True)
_SET_DER = prototype("fmi2SetRealInputDerivatives", raw=True)
_BOOL_STATUS = prototype("fmi2GetBooleanStatus", raw=True)
_GET_STATE = prototype("fmi2GetFMUstate", raw=True)
_SET_STATE = prototype("fmi2SetFMUstate", raw=True)
_DIR_DER = prototype("fmi2GetDirectionalDerivative", raw=True)


class CallbackSlave:
    """The trampolines of one slave (kept alive as long as a loop may call them) and the exception
    one of them caught, if any."""

    def __init__(self, slave: Slave):
        self.slave = slave
        self.error: BaseException | None = None
        self.do_step = _DO_STEP(self._do_step)
        self.get = _GET(lambda _inst, _vr, _n, _values: self._call(slave.pull))
        self.set = _SET(lambda _inst, _vr, _n, _values: self._call(slave.push))
        self.set_der = _SET_DER(lambda _inst, _vr, _n, _orders, _values: self._call(slave.push_slopes))
        self.bool_status = _BOOL_STATUS(self._asked_to_stop)
        # its one saved state (Slave.save_state / restore_state): the FMU state pointer is not used
        self.get_state = _GET_STATE(lambda _inst, _state: self._call(slave.save_state))
        self.set_state = _SET_STATE(lambda _inst, _state: self._call(slave.restore_state))
        # the directional derivative (directional()): value references to names, the last Jacobian
        self._names: tuple[dict[int, str], dict[int, str]] = ({}, {})
        self._jac: tuple[tuple[list[str], list[str]], np.ndarray | None] | None = None

    def _keep(self, exc: BaseException) -> int:
        self.error = self.error or exc
        return int(Status.FATAL)

    @staticmethod
    def _status(st) -> int:
        """A method's status as C reads it (None, which the Python loop takes as not failing: OK)."""
        return 0 if st is None else int(st)

    def _call(self, method) -> int:
        try:
            return self._status(method())
        except BaseException as exc:  # noqa: BLE001 - raised again by reraise()
            return self._keep(exc)

    def _do_step(self, _inst, t: float, h: float, _no_prior) -> int:
        try:
            return self._status(self.slave.do_step(t, h))
        except BaseException as exc:  # noqa: BLE001 - raised again by reraise()
            return self._keep(exc)

    def _asked_to_stop(self, _inst, _kind, value) -> int:
        try:
            ctypes.c_int.from_address(value).value = int(self.slave.asked_to_stop())
        except BaseException as exc:  # noqa: BLE001 - raised again by reraise()
            return self._keep(exc)
        return int(Status.OK)

    def directional(self, outputs: dict[int, str], inputs: dict[int, str]) -> int:
        """The address of an ``fmi2GetDirectionalDerivative`` trampoline around the slave's
        :meth:`~cosim.slaves.slave.Slave.output_jacobian` (``outputs``, ``inputs``: the names of the
        value references the loop passes).  It returns ``CallbackStatus.NO_DERIVATIVES`` when the
        slave provides none (the loop then takes finite differences, as the Python loop does)."""
        self._names = (outputs, inputs)
        self.dir_der = _DIR_DER(self._directional)
        return self.address("dir_der")

    def _directional(self, _inst, unknown, n_unknown, known, n_known, seed, sens) -> int:
        """``sens = J seed`` of the outputs ``unknown`` by the inputs ``known`` (exactly ``J[:, k]``
        for the unit seed ``e_k``)."""
        try:
            s = np.ctypeslib.as_array((ctypes.c_double * n_known).from_address(seed))
            jac = self._jacobian([self._names[0][r] for r in (ctypes.c_uint32 * n_unknown).from_address(unknown)],
                                 [self._names[1][r] for r in (ctypes.c_uint32 * n_known).from_address(known)],
                                 s[0] == 1.0 and not s[1:].any())
            if jac is None:
                return int(CallbackStatus.NO_DERIVATIVES)
            out = np.ctypeslib.as_array((ctypes.c_double * n_unknown).from_address(sens))
            cols = np.flatnonzero(s)
            out[:] = jac[:, cols[0]] * s[cols[0]] if len(cols) else 0.0
            for c in cols[1:]:
                out += jac[:, c] * s[c]
        except BaseException as exc:  # noqa: BLE001 - raised again by reraise()
            return self._keep(exc)
        return int(Status.OK)

    def _jacobian(self, outputs: list[str], inputs: list[str], first: bool) -> np.ndarray | None:
        """The slave's output Jacobian, computed at the first column's seed (``first``: the loop asks
        column by column from the first) and kept for the others, so that the slave computes it
        once per local Jacobian, as in the Python loop; None when it provides none."""
        key = (outputs, inputs)
        if first or self._jac is None or self._jac[0] != key:
            jac = self.slave.output_jacobian(outputs, inputs)
            self._jac = (key, None if jac is None else np.asarray(jac, dtype=float).reshape(len(outputs), len(inputs)))
        return self._jac[1]

    def address(self, name: str) -> int:
        """The C address of trampoline ``name`` (do_step, get, set, set_der, bool_status, get_state,
        set_state, dir_der)."""
        return ctypes.cast(getattr(self, name), ctypes.c_void_p).value

    def reraise(self) -> None:
        """Raise the exception a trampoline caught (once)."""
        if self.error is not None:
            exc, self.error = self.error, None
            raise exc


__all__ = ["CallbackSlave"]
