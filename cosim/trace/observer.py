"""The observer contract of a run: every method the run loop (:func:`cosim.master.stepper.drive`,
:func:`cosim.master.simulate`) calls on an observer, declared once, with defaults that do nothing
where an observer may not care.

Call order: ``start(columns, meta)``; ``initial(info)`` once with the values at the start time;
then per block of steps ``step(info)`` after every step (only observers that override it: the
loop then goes one step per block), ``record(rows)`` (a 2-D array, column 0 time [s]; at an event
two rows with the same time, the left limit then the right limit), ``record_text`` and
``record_event``; at the end ``statistics()`` and ``finish(status, reason, stats)`` exactly once,
also after a failure or an interrupt.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np


class Observer(ABC):
    """Receives the rows of a run (see the module docstring for the call order)."""

    #: a one-line remark for the run's log once it has finished (e.g. where a trace was placed)
    note: ClassVar[str] = ""

    @abstractmethod
    def start(self, columns: list[str], meta: dict) -> None: ...

    @abstractmethod
    def record(self, rows: np.ndarray) -> None: ...

    @abstractmethod
    def finish(self, status: str, reason: str, stats: dict) -> None: ...

    def initial(self, info: Any) -> None:
        """The initialised values at the start time (a :class:`cosim.master.stepper.StepInfo`
        with ``h`` = 0 and ``k`` = 0).  Ignored by default."""

    def step(self, info: Any) -> str | None:
        """After every step (a :class:`cosim.master.stepper.StepInfo`); a non-empty string ends the
        run as "failed" with that reason.  Not called unless a subclass overrides it."""
        return None

    @classmethod
    def watches_steps(cls) -> bool:
        """Whether :meth:`step` is overridden (the loop then steps one step per block)."""
        return cls.step is not Observer.step

    def record_text(self, t: float, column: str, value: str) -> None:
        """A String or Binary variable (``column``) took ``value`` (Binary as hexadecimal) at ``t``
        [s]; called when it changes, between ``record`` calls.  Ignored by default."""

    def record_event(self, t: float, component: str, kind: str) -> None:
        """An event at ``t`` [s] in ``component`` (``kind``: its indicator, or "time event"); its two
        rows (left, then right limit) come through :meth:`record`.  Ignored by default."""

    def statistics(self) -> dict | None:
        """The observer's own figures for the run statistics (under :attr:`name`), or None."""
        return None

    @property
    def name(self) -> str:
        """The key of :meth:`statistics` in the run statistics."""
        return type(self).__name__


__all__ = ["Observer"]
