"""Supervised runs: the stepping happens in a child process and this one watches it, so that
whatever an FMU does (a NULL write, ``abort()``, ``exit(0)``, a call that never returns, SIGTERM
ignored) the run ends with a final status, its whole rows and a non-zero exit code.

:func:`supervised` forks after the FMUs were built (before any FMU library is loaded).  The
child keeps the breadcrumb (:mod:`cosim.slaves.crumb`) in shared memory: which component and FMI
call it is in.  The parent waits for the child's result on a pipe and reads the crumb every
0.1 s:

* the child died by a signal, or exited without a result: status ``"crashed"``, reason naming
  the signal (or exit code) and the component and FMI call that was running;
* one FMI call ran longer than the per-call timeout (``$RPR_COSIM_CALL_TIMEOUT`` or
  ``master.call_timeout``, default :data:`DEFAULT_TIMEOUT_S`): the child is killed, status
  ``"hung"``;
* SIGTERM, SIGINT or SIGHUP to the parent: forwarded to the child, which ends its run as usual
  ("interrupted"); a child that has not ended within :data:`GRACE_S` (stuck in an FMU, or
  ignoring the signal) is killed and the parent writes the status itself.

In every case the ``settle`` callback writes the final trace and sidecar (:func:`cosim.outputs.
settle_run`).  ``$RPR_COSIM_SUPERVISE=0`` runs in-process (for debugging an FMU under gdb).
"""
from __future__ import annotations

import ctypes
import os
import pickle
import select
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from typing import Any, TypeVar

from ..errors import UserError
from ..interrupts import Interrupted
from ..slaves import crumb

#: Default longest wall time of one FMI call before the run is declared hung [s].
DEFAULT_TIMEOUT_S = 60.0
TIMEOUT_ENV = "RPR_COSIM_CALL_TIMEOUT"
SUPERVISE_ENV = "RPR_COSIM_SUPERVISE"
#: How long a signalled child may take to end its run before it is killed [s].
GRACE_S = 0.4
POLL_S = 0.1

T = TypeVar("T")


class Failed(Exception):
    """How a supervised child ended when it did not return: ``status`` ("crashed", "hung" or
    "interrupted") and ``reason``."""

    def __init__(self, status: str, reason: str, signal_exc: Interrupted | None = None):
        super().__init__(reason)
        self.status, self.reason, self.signal_exc = status, reason, signal_exc


_IN_CHILD = False  # True in a supervised child: what it runs is supervised already


def enabled() -> bool:
    """Whether runs are supervised here (``fork`` exists, ``$RPR_COSIM_SUPERVISE`` is not 0, and
    this is not a supervised child already)."""
    return (hasattr(os, "fork") and not _IN_CHILD
            and os.environ.get(SUPERVISE_ENV, "1").strip().lower() not in ("0", "no", "false", "off"))


def call_timeout(value: object = None) -> float:
    """The per-call timeout [s]: ``value``, else ``$RPR_COSIM_CALL_TIMEOUT``, else 60 s;
    :class:`UserError` for anything but a positive number."""
    raw = value if value is not None else os.environ.get(TIMEOUT_ENV)
    if raw is None or raw == "":
        return DEFAULT_TIMEOUT_S
    try:
        t = float(raw)
    except (TypeError, ValueError):
        t = float("nan")
    if not t > 0 or isinstance(raw, bool):
        where = "master.call_timeout" if value is not None else f"${TIMEOUT_ENV}"
        raise UserError(f"{where}: expected a positive number of seconds (the longest an FMI call may take), "
                        f"got {raw!r}")
    return t


def _die_with_parent() -> None:
    """In the child: be killed when the supervisor dies (Linux), and take no terminal signals
    (the supervisor forwards them once)."""
    try:
        os.setpgid(0, 0)
    except OSError:
        pass
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _child(work: Callable[[Callable[[str], None]], Any], wfd: int, buf) -> None:
    from ..slaves import fmu

    global _IN_CHILD
    _IN_CHILD = True
    code = 0
    notes: list[str] = []
    inherited = set(fmu._UNZIPPED)  # the parent's unpacked FMUs: the parent removes those
    try:
        _die_with_parent()
        crumb.attach(buf)
        try:
            payload = ("result", work(notes.append))
        except Interrupted as exc:
            payload = ("interrupted", exc.signum)
        except KeyboardInterrupt:
            payload = ("interrupted", int(signal.SIGINT))
        except BaseException as exc:  # noqa: BLE001 - everything goes to the parent
            payload = ("raise", exc)
        try:
            data = pickle.dumps((*payload, notes), protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # an exception that does not pickle: its text
            data = pickle.dumps(("raise", UserError(f"{type(payload[1]).__name__}: {payload[1]} ({exc})"), notes))
        view, done = memoryview(data), 0
        while done < len(data):
            done += os.write(wfd, view[done:])
    except BaseException:  # noqa: BLE001 - the parent sees no result and reports the exit
        code = 70
    finally:
        try:
            for key in set(fmu._UNZIPPED) - inherited:  # os._exit skips the atexit hook that would
                shutil.rmtree(fmu._UNZIPPED[key], ignore_errors=True)
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _describe_exit(status: int, where: str) -> str:
    in_call = f" in {where}" if where else " before the first FMI call"
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else f"signal {sig}"
        return f"the run's process died of {name} (signal {sig}){in_call}"
    code = os.WEXITSTATUS(status) if os.WIFEXITED(status) else status
    return f"the run's process exited (code {code}) without finishing the run{in_call}; did an FMU call exit()?"


def _remove_leftovers(pid: int) -> None:
    """The temporary FMU folders of a child that died before it could remove them."""
    prefix = f"rpr-fmu-{pid}-"
    with os.scandir(tempfile.gettempdir()) as entries:  # a busy /tmp: scandir, not glob's fnmatch per entry
        found = [e.path for e in entries if e.name.startswith(prefix)]
    for d in found:
        shutil.rmtree(d, ignore_errors=True)


def supervised(work: Callable[[Callable[[str], None]], T], *, timeout_s: float | None = None,
               log: Callable[[str], None] | None = None) -> T:
    """``work(say)`` run in a forked child; its result (pickled) or exception comes back, and
    what it passed to ``say`` goes to ``log`` here.  A child
    that crashes, hangs in an FMI call or is interrupted raises :class:`Failed` here (the
    caller settles the run's files); the signal that interrupted the parent is in
    :attr:`Failed.signal_exc` and must be raised again once the files are settled."""
    timeout = call_timeout(timeout_s)
    buf = crumb.shared()
    rfd, wfd = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child never returns
        os.close(rfd)
        _child(work, wfd, buf)
    os.close(wfd)
    try:
        return _watch(pid, rfd, buf, timeout, log or (lambda m: None))
    except Failed:
        _remove_leftovers(pid)
        raise
    finally:
        os.close(rfd)
        buf.close()


def _watch(pid: int, rfd: int, buf, timeout: float, log: Callable[[str], None]) -> Any:
    chunks: list[bytes] = []
    seen, since, status, signalled = None, time.monotonic(), None, None
    deadline = None  # after a signal: when the child is killed
    while True:
        try:
            ready, _, _ = select.select([rfd], [], [], POLL_S)
            if ready:
                data = os.read(rfd, 1 << 20)
                if data:
                    chunks.append(data)
                    continue
                break  # EOF: the child closed its end (exited, normally or not)
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:  # exited while something else (a process it started) keeps the pipe open
                status = st
                break
            now = time.monotonic()
            if deadline is not None:
                if now > deadline:
                    _kill(pid)
                    status = os.waitpid(pid, 0)[1]
                    where = crumb.describe(crumb.read(buf))
                    raise Failed("interrupted", f"interrupted by {signalled}; the run did not end within {GRACE_S:g} s "
                                 f"of the signal{' (in ' + where + ')' if where else ''} and was killed", signalled)
                continue
            state = crumb.read(buf)
            if state["inside"] and state["seq"] == seen:
                if now - since > timeout:
                    _kill(pid)
                    status = os.waitpid(pid, 0)[1]
                    raise Failed("hung", f"{crumb.describe(state)} did not return within {timeout:g} s "
                                 f"(the FMI call timeout, ${TIMEOUT_ENV}); the run was stopped")
            else:
                seen, since = state["seq"], now
        except KeyboardInterrupt as exc:
            if signalled is not None:
                continue
            signalled = exc if isinstance(exc, Interrupted) else Interrupted(signal.SIGINT)
            try:
                os.kill(pid, signalled.signum)
            except ProcessLookupError:
                pass
            deadline = time.monotonic() + GRACE_S
    if status is None:
        status = os.waitpid(pid, 0)[1]
    try:
        kind, value, notes = pickle.loads(b"".join(chunks)) if chunks else (None, None, [])
    except Exception:  # noqa: BLE001 - a result cut short: the child died writing it
        kind, value, notes = None, None, []
    for n in notes:
        log(n)
    if kind == "result":
        return value
    if kind == "raise":
        raise value
    if kind == "interrupted":
        raise signalled or Interrupted(value)
    raise Failed("crashed", _describe_exit(status, crumb.describe(crumb.read(buf))), signalled)


def _kill(pid: int) -> None:
    for target in (lambda: os.killpg(pid, signal.SIGKILL), lambda: os.kill(pid, signal.SIGKILL)):
        try:
            target()
            return
        except (ProcessLookupError, PermissionError):
            continue


__all__ = ["DEFAULT_TIMEOUT_S", "Failed", "call_timeout", "enabled", "supervised"]
