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

:class:`Server` is the same watch around a child that stays: it serves one request after
another (the runs of a Dask worker, keeping its FMU instances between them) until it dies or
is closed.
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
from ..slaves import fmu_slave

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
    "interrupted") and ``reason``; for "crashed", :attr:`from_outside` tells whether it may have
    been killed by someone else (SIGKILL or SIGTERM: the OOM killer, a user) or died outside any
    FMI call, rather than by an FMU."""

    def __init__(self, status: str, reason: str, signal_exc: Interrupted | None = None, from_outside: bool = False):
        super().__init__(reason)
        self.status, self.reason, self.signal_exc = status, reason, signal_exc
        self.from_outside = from_outside


def _crashed(status: int, state: dict, signal_exc: Interrupted | None = None) -> Failed:
    """The :class:`Failed` of a child that ended with wait status ``status``, its crumb ``state``."""
    external = os.WIFSIGNALED(status) and os.WTERMSIG(status) in (signal.SIGKILL, signal.SIGTERM)
    return Failed("crashed", _describe_exit(status, crumb.describe(state)), signal_exc,
                  external or not state["inside"])


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


def _become_child(buf) -> None:
    """In a freshly forked child: die with the parent, write the breadcrumb into ``buf``, and
    supervise nothing itself (what it runs is supervised already)."""
    global _IN_CHILD
    _IN_CHILD = True
    _die_with_parent()
    crumb.attach(buf)


def _dumps(payload: tuple) -> bytes:
    """``payload`` pickled; an exception that does not pickle goes as its text."""
    try:
        return pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # noqa: BLE001
        return pickle.dumps(("raise", UserError(f"{type(payload[1]).__name__}: {payload[1]} ({exc})"),
                             *payload[2:]))


def _write_all(fd: int, data: bytes) -> None:
    view, done = memoryview(data), 0
    while done < len(data):
        done += os.write(fd, view[done:])


def _end_child(code: int, inherited: set) -> None:
    """Remove the FMU folders this child unpacked (``os._exit`` skips the atexit hook that would),
    flush, and exit with ``code``."""

    try:
        for key in set(fmu_slave._UNZIPPED) - inherited:
            shutil.rmtree(fmu_slave._UNZIPPED[key], ignore_errors=True)
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


def _child(work: Callable[[Callable[[str], None]], Any], wfd: int, buf) -> None:

    code = 0
    notes: list[str] = []
    inherited = set(fmu_slave._UNZIPPED)  # the parent's unpacked FMUs: the parent removes those
    try:
        _become_child(buf)
        try:
            payload = ("result", work(notes.append))
        except Interrupted as exc:
            payload = ("interrupted", exc.signum)
        except KeyboardInterrupt:
            payload = ("interrupted", int(signal.SIGINT))
        except BaseException as exc:  # noqa: BLE001 - everything goes to the parent
            payload = ("raise", exc)
        _write_all(wfd, _dumps((*payload, notes)))
    except BaseException:  # noqa: BLE001 - the parent sees no result and reports the exit
        code = 70
    finally:
        _end_child(code, inherited)


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
    say = log or (lambda m: None)
    try:
        data, status, signalled = _watch(pid, rfd, buf, timeout)
        if status is None:
            status = os.waitpid(pid, 0)[1]
        try:
            kind, value, notes = pickle.loads(data) if data else (None, None, [])
        except Exception:  # noqa: BLE001 - a result cut short: the child died writing it
            kind, value, notes = None, None, []
        for n in notes:
            say(n)
        if kind == "result":
            return value
        if kind == "raise":
            raise value
        if kind == "interrupted":
            raise signalled or Interrupted(value)
        raise _crashed(status, crumb.read(buf), signalled)
    except Failed:
        _remove_leftovers(pid)
        raise
    finally:
        os.close(rfd)
        buf.close()


def _drain(rfd: int) -> bytes:
    """What is in the pipe ``rfd`` now, without waiting for more (its writer may have exited)."""
    out = bytearray()
    while select.select([rfd], [], [], 0)[0]:
        data = os.read(rfd, 1 << 20)
        if not data:
            break
        out += data
    return bytes(out)


def _watch(pid: int, rfd: int, buf, timeout: float, complete: Callable[[bytearray], bool] | None = None
           ) -> tuple[bytes, int | None, Interrupted | None]:
    """What child ``pid`` writes on ``rfd``, read until EOF (or until ``complete(data)``), while
    its breadcrumb in ``buf`` is watched: returns (data, its wait status if it has exited, the
    signal that interrupted this process); raises :class:`Failed` ("hung", or "interrupted"
    when it did not end within :data:`GRACE_S` of a signal) after killing it."""
    chunks = bytearray()
    seen, since, status, signalled = None, time.monotonic(), None, None
    deadline = None  # after a signal: when the child is killed
    while True:
        try:
            ready, _, _ = select.select([rfd], [], [], POLL_S)
            if ready:
                data = os.read(rfd, 1 << 20)
                if data:
                    chunks += data
                    if complete is not None and complete(chunks):
                        break
                    continue
                break  # EOF: the child closed its end (exited, normally or not)
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:  # exited (what it wrote after the select above is still in the pipe), or a
                status = st  # process it started keeps the pipe open
                chunks += _drain(rfd)
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
    return bytes(chunks), status, signalled


class Server:
    """A supervised child that serves requests one after another, for a process that keeps what
    its runs share (loaded FMU instances) between them and is not supervised itself (a Dask
    worker).  ``handle(request)`` runs in the child, forked here once (after ``on_start()``
    there); :meth:`call` sends it a request and watches the child as :func:`supervised` watches
    a run.  A child that crashes or hangs raises :class:`Failed` from :meth:`call` and is gone
    (:attr:`alive` False): start another.  ``on_exit()`` runs in the child when :meth:`close`
    ends it."""

    _HEADER = 8  # each message: its length (8 bytes, little-endian), then its pickle

    def __init__(self, handle: Callable[[Any], Any], *, on_start: Callable[[], None] | None = None,
                 on_exit: Callable[[], None] | None = None):

        self.buf = crumb.shared()
        self._handle, self._on_start, self._on_exit = handle, on_start, on_exit
        down_r, self._down = os.pipe()
        self._up, up_w = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        self.pid = os.fork()
        if self.pid == 0:  # pragma: no cover - the child never returns
            os.close(self._down)
            os.close(self._up)
            self._serve(down_r, up_w, set(fmu_slave._UNZIPPED))
        os.close(down_r)
        os.close(up_w)
        self._open = True

    @classmethod
    def _frame(cls, data: bytes) -> bytes:
        return len(data).to_bytes(cls._HEADER, "little") + data

    @classmethod
    def _whole(cls, data: bytearray) -> bool:
        return len(data) >= cls._HEADER and len(data) >= cls._HEADER + int.from_bytes(data[:cls._HEADER], "little")

    def _serve(self, down: int, up: int, inherited: set) -> None:
        """The child's loop: requests read from ``down``, answers written to ``up``."""
        handle, on_start, on_exit = self._handle, self._on_start, self._on_exit
        code = 0
        try:
            _become_child(self.buf)
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides
            if on_start is not None:
                on_start()
            pending = bytearray()
            while True:
                while not self._whole(pending):
                    data = os.read(down, 1 << 20)
                    if not data:  # the parent closed its end: done
                        if on_exit is not None:
                            on_exit()
                        return
                    pending += data
                n = self._HEADER + int.from_bytes(pending[:self._HEADER], "little")
                request = pickle.loads(bytes(pending[self._HEADER:n]))
                del pending[:n]
                try:
                    payload: tuple = ("result", handle(request))
                except Exception as exc:  # noqa: BLE001 - to the parent
                    payload = ("raise", exc)
                _write_all(up, self._frame(_dumps(payload)))
        except BaseException:  # noqa: BLE001 - the parent sees no result and reports the exit
            code = 70
        finally:
            _end_child(code, inherited)

    @property
    def is_open(self) -> bool:
        """Whether this child has not been seen to end (no check of the child: safe from any
        thread while another one calls it)."""
        return self._open

    @property
    def alive(self) -> bool:
        """Whether the child is there to serve (it may have been killed while idle)."""
        if self._open and os.waitpid(self.pid, os.WNOHANG)[0]:
            self._closed()
        return self._open

    def call(self, request: Any, timeout_s: float | None = None) -> Any:
        """``handle(request)``'s result (or its exception) from the child; :class:`Failed` when the
        child crashed ("crashed") or one of its FMI calls ran longer than ``timeout_s``
        ("hung"); it is gone then."""
        timeout = call_timeout(timeout_s)
        try:
            _write_all(self._down, self._frame(pickle.dumps(request, protocol=pickle.HIGHEST_PROTOCOL)))
        except OSError:  # it died while idle or reading the request
            pass
        try:
            data, status, _ = _watch(self.pid, self._up, self.buf, timeout, self._whole)
        except Failed:
            self._closed()
            raise
        if self._whole(bytearray(data)):
            kind, value = pickle.loads(data[self._HEADER:])
            if kind == "raise":
                raise value
            return value
        status = status if status is not None else os.waitpid(self.pid, 0)[1]
        failed = _crashed(status, crumb.read(self.buf))
        self._closed(reaped=True)
        raise failed

    def _closed(self, reaped: bool = True) -> None:
        """Forget the child (killed and reaped here unless ``reaped`` already) and its leftovers."""
        if not self._open:
            return
        self._open = False
        for fd in (self._down, self._up):
            if fd >= 0:
                os.close(fd)
        if not reaped:
            _kill(self.pid)
            os.waitpid(self.pid, 0)
        _remove_leftovers(self.pid)
        self.buf.close()

    def close(self, wait_s: float = 2.0) -> None:
        """End the child: at the end of its requests it runs ``on_exit`` and exits (killed if it
        has not within ``wait_s`` [s])."""
        if not self._open:
            return
        os.close(self._down)
        self._down = -1
        deadline, reaped = time.monotonic() + wait_s, False
        while not reaped and time.monotonic() < deadline:
            reaped = bool(os.waitpid(self.pid, os.WNOHANG)[0])
            if not reaped:
                time.sleep(0.005)
        self._closed(reaped)


def _kill(pid: int) -> None:
    for target in (lambda: os.killpg(pid, signal.SIGKILL), lambda: os.kill(pid, signal.SIGKILL)):
        try:
            target()
            return
        except (ProcessLookupError, PermissionError):
            continue


__all__ = ["DEFAULT_TIMEOUT_S", "Failed", "Server", "call_timeout", "enabled", "supervised"]
