"""An analytic linear slave (x' = A x + B u, y = C x + D u): a known plant for algorithm tests."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np


from ..errors import UserError
from .description import SlaveDescription, Variable
from .slave import Slave, Status

if TYPE_CHECKING:
    pass


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


