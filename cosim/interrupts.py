"""Signals that end a run honestly: SIGTERM, SIGHUP and SIGINT become :class:`Interrupted` (a
KeyboardInterrupt) in the main thread, so the run's ``finally`` blocks write the status and
reason, close whole rows and remove temporary FMU folders, as for Ctrl-C.

The default action of SIGTERM and SIGHUP kills the process without any of that (the sidecar
would keep saying "running").  The stepping loop returns to Python at least every 0.25 s
(:mod:`cosim.master.fastloop`), so a signal takes effect within a second at any point of a run.
"""
from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: Signals turned into :class:`Interrupted`.
SIGNALS = tuple(s for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT) if s is not None)


class Interrupted(KeyboardInterrupt):
    """A run ended by a signal; ``str()`` names it (e.g. ``SIGTERM (signal 15)``)."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        super().__init__(f"{signal.Signals(signum).name} (signal {self.signum})")


_ACTIVE: dict = {"depth": 0, "raised": False, "last": None, "defer": 0, "pending": None}


def _handler(signum, frame) -> None:
    if _ACTIVE["raised"]:  # already stopping: let the clean-up finish
        print(f"rpr-cosim: {signal.Signals(signum).name} again; still writing the status, please wait "
              f"(SIGKILL would leave the run to be marked 'killed' later)", file=sys.stderr)
        return
    _ACTIVE["raised"] = True
    exc = _ACTIVE["last"] = Interrupted(signum)
    if _ACTIVE["defer"]:
        _ACTIVE["pending"] = exc
        return
    raise exc


def pending() -> bool:
    """True when a signal arrived inside a :func:`deferred` block and waits to be raised."""
    return _ACTIVE["pending"] is not None


@contextmanager
def deferred() -> Iterator[None]:
    """A block a signal must not cut in the middle (queue and lock operations): a signal that
    arrives inside it is raised when it ends.  Long waits inside should poll :func:`pending`."""
    _ACTIVE["defer"] += 1
    try:
        yield
    finally:
        _ACTIVE["defer"] -= 1
        exc = _ACTIVE["pending"]
        if exc is not None and not _ACTIVE["defer"]:
            _ACTIVE["pending"] = None
            raise exc


def last_signal() -> Interrupted | None:
    """The signal that interrupted the current :func:`signals_as_interrupts` block, if any (for
    code whose callee swallowed the exception, e.g. a solver that reports a failed callback)."""
    return _ACTIVE.get("last")


@contextmanager
def signals_as_interrupts() -> Iterator[None]:
    """Within the block, :data:`SIGNALS` raise :class:`Interrupted` (main thread only; nested
    uses are no-ops; the previous handlers come back afterwards)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if _ACTIVE["depth"]:
        _ACTIVE["depth"] += 1
        try:
            yield
        finally:
            _ACTIVE["depth"] -= 1
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}
    for s in SIGNALS:
        signal.signal(s, _handler)
    _ACTIVE.update(depth=1, raised=False, last=None, defer=0, pending=None)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _ACTIVE.update(depth=0, raised=False, last=None, defer=0, pending=None)


def exit_code(exc: BaseException) -> int:
    """Shell exit code for an interrupt: 128 + signal number (130 for a plain Ctrl-C)."""
    return 128 + getattr(exc, "signum", signal.SIGINT)
