"""The Slave contract: what the master steps, the FMI status codes, and a slave's C entry points."""
from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np


from ..errors import UserError
from .description import SlaveDescription

if TYPE_CHECKING:
    pass


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
class NativeEntry:
    """C entry points of a slave for the compiled loop: the instance pointer and the addresses of
    its doStep, GetReal/GetFloat64 and SetReal/SetFloat64 functions, and of
    fmi2SetRealInputDerivatives (0 when the slave does not interpolate inputs); for the compiled
    adaptive engine also get/set/free FMU state (0 when it cannot roll back) and
    fmi2GetBooleanStatus (0 for FMI 3.0); for the compiled iterative engine the FMU's
    GetDirectionalDerivative (0 when it does not provide directional derivatives)."""

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
    directional_derivative: int = 0
    #: FMI 3.0: the address of the double the slave reports its last successful time from (0: none)
    last_time: int = 0


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

    def stop_detail(self) -> str:
        """Why and when the slave asked to stop (e.g. its last successful time), '' when unknown."""
        return ""

    def terminate(self) -> None:
        """End the simulation (the instance may still be read)."""

    def free(self) -> None:
        """Release the instance and its resources."""

    def native(self) -> NativeEntry | None:
        """C entry points for the compiled loop, or None (the Python loop is used)."""
        return None

    # FMI 3.0 event mode (docs/explanation/events.md) -------------------------------------------------
    #: Set by the run before instantiation for an algorithm that ends its steps at events: the
    #: slave reports its events (and may end a step early at one) instead of handling them inside.
    event_mode: bool = False

    def step_end(self) -> tuple[float, bool]:
        """After :meth:`do_step` in event mode: (the time it reached [s], whether an event there
        needs handling)."""
        raise RuntimeError(f"{self.name}: this slave has no event mode")

    def event_slots(self) -> tuple[int, int, int] | None:
        """Where its doSteps in event mode leave what :meth:`step_end` reads, for a compiled loop:
        the addresses of its flags (three C bools: eventHandlingNeeded, terminateSimulation,
        earlyReturn), of its last successful time and of its step's planned end (C doubles [s]);
        None when it has no event mode."""
        return None

    def enter_event_mode(self) -> int:
        """Enter event mode at the current time; returns a :class:`Status`."""
        raise RuntimeError(f"{self.name}: this slave has no event mode")

    def update_discrete_states(self) -> tuple[int, bool, bool]:
        """One round of the event iteration: (status, more rounds needed, terminate requested)."""
        raise RuntimeError(f"{self.name}: this slave has no event mode")

    def enter_step_mode(self) -> int:
        """Leave event mode; returns a :class:`Status`."""
        raise RuntimeError(f"{self.name}: this slave has no event mode")

    # rollback (variable-step and iterative algorithms) --------------------------------------------
    #: Set by the run for an algorithm that never restores a state (fixed-step, ecco): every
    #: doStep then promises ``noSetFMUStatePriorToCurrentPoint = true``.
    forward_only: bool = False

    @property
    def can_rollback(self) -> bool:
        """Whether :meth:`save_state` and :meth:`restore_state` work (FMI get/set FMU state)."""
        return False

    @property
    def no_prior(self) -> bool:
        """The ``noSetFMUStatePriorToCurrentPoint`` this slave's doSteps pass: true unless the
        algorithm may restore its state."""
        return self.forward_only or not self.can_rollback

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





