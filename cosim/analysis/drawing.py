"""Figures drawn beside the run: :class:`Drawer` forks, when a command starts, a process that
imports matplotlib (about 1 s of CPU) while the scene loads and the run steps; each figure then
asked of it is drawn in a child forked from that warm process (matplotlib imported once, its pages
shared), so the run chart, the animation and the comparison plot are drawn at the same time as
each other and as the reference (the machine's second core).

* A figure that fails comes back as :class:`DrawError`, one line naming the exception; the other
  figures and the run's files are not touched.
* Ctrl-C belongs to the command: the drawing processes ignore SIGINT, and :meth:`Drawer.stop`
  ends them with SIGTERM, which unwinds a figure being written (its temporary file is removed,
  :func:`cosim.outputs.staged`), then waits for them: no process is left behind, none a zombie.
* A drawing process whose parent dies ends too (``PR_SET_PDEATHSIG``, and the closed pipe).
* Without ``os.fork`` (Windows) each figure is drawn in this process when it is asked for.

:class:`Forked` runs one function in a child forked from the command's own process (what it has
loaded shared, e.g. the scene): the run's monolithic reference integrates there while the run
steps (``run --reference``), its progress in a :class:`SharedProgress`.
"""
from __future__ import annotations

import ctypes
import gc
import mmap
import os
import pickle
import select
import signal
import struct
import sys
import time
from collections.abc import Callable
from multiprocessing.connection import Pipe, wait
from typing import Any

import numpy  # noqa: F401 - imported before the drawing process is forked: once for both processes

#: How long the drawing processes may take to end after SIGTERM before they are killed [s].
GRACE_S = 5.0


class DrawError(Exception):
    """A figure (or a :class:`Forked` job) that could not be made; ``str()`` is one line (the
    exception's type and message)."""


def warm_up() -> None:
    """What every figure needs, done once in the drawing process: matplotlib on Agg and pyplot
    imported, the default font loaded and a text laid out, the figures' own modules imported
    (else imported when the first figure's arguments are unpickled, after the run: :mod:`.compare`
    and what it imports are 0.15 s of CPU).  A richer warm-up, a chart and a frame drawn, saved
    no measurable time in the figures."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import GifImagePlugin, ImageDraw, PngImagePlugin  # noqa: F401 - the files' encoders

    from . import animate, charts, trace_diff  # noqa: F401 - the figures' code, shared by every child

    fig = plt.figure(figsize=(1, 1), dpi=10)
    fig.text(0.5, 0.5, "0.5 [m]")
    fig.canvas.draw()
    plt.close(fig)


class Drawer:
    """A warm matplotlib process that draws figures in parallel: :meth:`submit` a module-level
    function and its (picklable) arguments, :meth:`result` its return value or :class:`DrawError`;
    :meth:`close` when done (also as a context manager), :meth:`stop` on an interrupt."""

    def __init__(self, *, parallel: bool = True, warm: Callable[[], None] | None = warm_up):
        self._results: dict[int, tuple[str, Any]] = {}
        self._next = 0
        self._pid: int | None = None
        if not (parallel and hasattr(os, "fork")):
            return
        ours, theirs = Pipe()
        parent = os.getpid()
        sys.stdout.flush()
        sys.stderr.flush()
        try:
            pid = os.fork()
        except OSError:  # no process to spare: each figure drawn here, when asked for
            ours.close()
            theirs.close()
            return
        if pid == 0:  # pragma: no cover - runs in the drawing process, which never returns
            code = 1
            try:
                ours.close()
                _serve(theirs, parent, warm)
                code = 0
            except SystemExit:  # SIGTERM, SIGHUP: stopped on purpose
                code = 0
            finally:
                os._exit(code)
        theirs.close()
        self._pid, self._conn = pid, ours

    @property
    def parallel(self) -> bool:
        """Whether figures are drawn in other processes (else in this one, when submitted)."""
        return self._pid is not None

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> int:
        """Ask for ``fn(*args, **kwargs)``; returns the job's number for :meth:`result`."""
        job, self._next = self._next, self._next + 1
        if self._pid is None:
            self._results[job] = _call(fn, args, kwargs)
        else:
            self._conn.send((job, fn, args, kwargs))
        return job

    def finished(self, job: int) -> bool:
        """Whether job ``job`` has ended (drawn or failed), without waiting."""
        while job not in self._results and self._pid is not None and self._conn.poll():
            self._receive()
        return job in self._results

    def result(self, job: int) -> Any:
        """The value of job ``job`` once drawn; :class:`DrawError` when it failed."""
        while job not in self._results:
            self._receive()
        kind, value = self._results.pop(job)
        if kind == "error":
            raise DrawError(value)
        return value

    def _receive(self) -> None:
        if self._pid is None:
            raise DrawError("the drawing process was stopped before the figure was written")
        try:
            done, outcome = self._conn.recv()
        except (EOFError, OSError):
            raise DrawError("the drawing process ended before the figure was written") from None
        self._results[done] = outcome

    def stop(self) -> None:
        """End the drawing processes now (a figure being written leaves no temporary file) and
        wait for them."""
        if self._pid is None:
            return
        try:
            os.kill(self._pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        self._reap()

    def close(self) -> None:
        """End the drawing process (figures not yet collected are abandoned) and wait for it."""
        self.stop()

    def _reap(self) -> None:
        pid, self._pid = self._pid, None
        self._conn.close()
        deadline = time.monotonic() + GRACE_S
        while True:
            try:
                done, _ = os.waitpid(pid, os.WNOHANG)
            except ChildProcessError:
                return
            if done:
                return
            if time.monotonic() > deadline:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return
            time.sleep(0.005)

    def __enter__(self) -> Drawer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Forked:
    """``fn(*args, **kwargs)`` started now in a child forked from this process, which shares
    what this process has loaded: :meth:`result` waits for its value (or raises
    :class:`DrawError`), :meth:`stop` ends it (also after it ended: then it only reaps it).  The
    child ignores Ctrl-C (the command's) and ends on SIGTERM or with this process.  Without
    ``os.fork`` (or a process to spare) the call runs in this process at :meth:`result`."""

    def __init__(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any):
        self._job: tuple | None = (fn, args, kwargs)
        self._pid: int | None = None
        self._outcome: tuple[str, Any] | None = None
        if not hasattr(os, "fork"):
            return
        sys.stdout.flush()
        sys.stderr.flush()
        try:
            self._rfd, self._pid = _fork_call(fn, args, kwargs, _beside_the_command)
        except OSError:
            return
        self._job = None

    def result(self, waiting: Callable[[], None] | None = None, every_s: float = 0.1) -> Any:
        """The call's value once it ended (``waiting()`` every ``every_s`` seconds until then);
        :class:`DrawError` when it failed."""
        if self._outcome is None:
            if self._pid is None:
                fn, args, kwargs = self._job
                self._outcome = _call(fn, args, kwargs)
            else:
                self._outcome = self._collect(waiting, every_s)
        kind, value = self._outcome
        if kind == "error":
            raise DrawError(value)
        return value

    def _collect(self, waiting: Callable[[], None] | None, every_s: float) -> tuple[str, Any]:
        data = bytearray()
        while True:
            if not data and waiting is not None and not select.select([self._rfd], [], [], every_s)[0]:
                waiting()
                continue
            chunk = os.read(self._rfd, 1 << 20)
            if not chunk:
                break
            data += chunk
        os.close(self._rfd)
        pid, self._pid = self._pid, None
        return _outcome(bytes(data), os.waitpid(pid, 0)[1])

    def stop(self) -> None:
        """End the child now if it still runs, and wait for it."""
        if self._pid is None:
            return
        pid, self._pid = self._pid, None
        os.close(self._rfd)  # a child still writing its result gets EPIPE, or SIGTERM first
        _end(pid)


def _beside_the_command() -> None:
    """In a :class:`Forked` child: Ctrl-C is the command's; SIGTERM ends the child."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for s in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, _stopped)


class SharedProgress:
    """A ``progress(done, total)`` callback whose last values a forked child shares with its
    parent (anonymous shared memory): the child calls it, the parent :meth:`read` s it."""

    def __init__(self) -> None:
        self._cell = mmap.mmap(-1, 16)

    def __call__(self, done: int, total: int) -> None:
        struct.pack_into("qq", self._cell, 0, int(done), int(total))

    def read(self) -> tuple[int, int]:
        """(done, total) as last reported; (0, 0) before the first report."""
        done, total = struct.unpack_from("qq", self._cell, 0)
        return done, total


def _call(fn: Callable[..., Any], args: tuple, kwargs: dict) -> tuple[str, Any]:
    """("ok", value) or ("error", one line) of ``fn(*args, **kwargs)``."""
    try:
        return "ok", fn(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 - any failure of a figure is reported, as one line
        text = " ".join(str(exc).split())
        return "error", f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _stopped(signum: int, frame: object) -> None:
    raise SystemExit(0)


def _die_with_parent(parent: int) -> None:
    """SIGTERM to this process when ``parent`` ends (Linux; elsewhere the closed pipe tells)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # it ended before the request
        raise SystemExit(0)


def _serve(conn, parent: int, warm: Callable[[], None] | None) -> None:
    """The drawing process: warm up, then fork a child per job received on ``conn`` and send
    back (job, outcome) as each ends; ends on None or a closed pipe, ending its children."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for s in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, _stopped)
    _die_with_parent(parent)
    if warm is not None:
        warm()
    gc.freeze()  # what is here stays out of the figures' collections: their pages stay shared
    children: dict[int, tuple[int, int, bytearray]] = {}  # read end -> (job, pid, bytes so far)
    try:
        while True:
            for ready in wait([conn, *children]):
                if ready is conn:
                    try:
                        msg = conn.recv()
                    except (EOFError, OSError):
                        return
                    if msg is None:
                        return
                    rfd, pid = _start(msg, conn, children)
                    children[rfd] = (msg[0], pid, bytearray())
                else:
                    job, pid, data = children[ready]
                    chunk = os.read(ready, 1 << 16)
                    if chunk:
                        data += chunk
                        continue
                    del children[ready]
                    os.close(ready)
                    conn.send((job, _outcome(data, os.waitpid(pid, 0)[1])))
    finally:
        for rfd, (_, pid, _) in children.items():
            _end(pid)
            os.close(rfd)


def _start(msg: tuple, conn, children: dict) -> tuple[int, int]:
    """Fork the child that draws job ``msg`` = (job, fn, args, kwargs); returns (read end, pid)."""
    _, fn, args, kwargs = msg

    def in_child() -> None:
        conn.close()
        for other in children:
            os.close(other)
        gc.disable()  # a short life: its memory goes with it, uncollected

    return _fork_call(fn, args, kwargs, in_child)


def _fork_call(fn: Callable[..., Any], args: tuple, kwargs: dict, in_child: Callable[[], None]) -> tuple[int, int]:
    """Fork a child that runs ``in_child()`` then ``fn(*args, **kwargs)`` and writes its pickled
    outcome (:func:`_call`) to a pipe, and ends with its parent; returns (read end, pid)."""
    rfd, wfd = os.pipe()
    me = os.getpid()
    held = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}  # held over the fork: the child's handlers first
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child never returns
        try:
            os.close(rfd)
            _die_with_parent(me)
            in_child()
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            data = pickle.dumps(_call(fn, args, kwargs))
            with os.fdopen(wfd, "wb") as fh:
                fh.write(data)
        finally:
            os._exit(0)
    signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    os.close(wfd)
    return rfd, pid


def _outcome(data: bytes, status: int) -> tuple[str, Any]:
    """A child's outcome from what it wrote, or why it wrote nothing."""
    try:
        return pickle.loads(data)
    except Exception:  # noqa: BLE001 - nothing or a cut result: the child died
        if os.WIFSIGNALED(status):
            return "error", f"the drawing process was killed by {signal.Signals(os.WTERMSIG(status)).name}"
        return "error", f"the drawing process exited with code {os.waitstatus_to_exitcode(status)}"


def _end(pid: int) -> None:
    """SIGTERM child ``pid`` and wait for it (killed after :data:`GRACE_S`)."""
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        pass
    deadline = time.monotonic() + GRACE_S
    while not os.waitpid(pid, os.WNOHANG)[0]:
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return
        time.sleep(0.005)
