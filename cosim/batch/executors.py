"""Where a batch's runs execute: local worker processes (the default, no set-up) or a Dask
distributed cluster.  Both take the same :class:`~cosim.batch.worker.Task` list and
:class:`~cosim.batch.worker.Shared` payload and report each run through ``on_done(task,
outcome)`` as it finishes, in completion order.

Local (:class:`LocalExecutor`)
    ``N`` processes forked from the batch process once it has warmed up (imports, the compiled
    loop, the stepping orders: :mod:`cosim.batch.preload`), or from a ``forkserver`` with the
    same warm-up preloaded when the batch process runs other threads; each fed over a pipe with
    its run and, while more remain for the others, the next one queued behind it (so it starts
    the moment the first ends); the parent knows which runs are where.  The FMUs' bytes go to
    each process once, when it starts (one first needed later travels with its run).
    A process that dies (killed, crashed in an FMU) is replaced and its run is given to a worker
    once more; a run that kills its worker twice is a failed row.  A worker is one core: it
    writes each run's trace in its stepping thread (``rpr-cosim run`` formats on a second
    thread, which would make each worker 1.3 cores).  Workers ignore Ctrl-C (the
    parent stops them) and die with the parent (``PR_SET_PDEATHSIG`` and a watchdog), so an
    interrupted batch leaves no run behind writing into its directory.
Dask (:class:`DaskExecutor`)
    On an existing scheduler (``--scheduler tcp://host:8786``; workers started with ``dask worker
    ADDRESS --nthreads 1``) or on a ``LocalCluster`` it starts (``--dask``).  The shared payload
    is scattered once to every worker (``broadcast=True``); each run writes into a temporary
    directory on its worker and sends its files back, so workers need no shared filesystem.  A
    worker that dies is restarted by its nanny and the scheduler reschedules its run; the
    ``LocalCluster`` allows one retry (``distributed.scheduler.allowed-failures = 1``), an
    external scheduler follows its own setting (default 3); after that the run is a failed row.
    Each run is supervised on its worker (:func:`~cosim.batch.worker.execute_supervised`): the
    worker forks a child that steps it and watches the child's breadcrumb, so an FMU that
    crashes, exits or hangs (past the batch process's call timeout) makes that run's row
    "crashed" or "hung" with the component and FMI call, and the worker lives on for the next
    runs.
"""
from __future__ import annotations

import ctypes
import gc
import multiprocessing as mp
import os
import signal
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from multiprocessing.connection import wait
from multiprocessing.reduction import ForkingPickler

from ..errors import UserError
from ..slaves import crumb
from .worker import STATE, Outcome, Shared, Task, execute, settle_files, worker_id
from ..trace import traces as trace
from . import preload
from ..run.supervise import POLL_S, call_timeout
from .worker import run_remote

OnStart = Callable[[Task, int], None]
OnDone = Callable[[Task, Outcome], None]


# --- local processes -----------------------------------------------------------------------------
def _die_with(parent_pid: int) -> None:
    """Make this process end when ``parent_pid`` (the batch) ends."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while True:
            try:
                os.kill(parent_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except PermissionError:
                pass
            try:
                with open(f"/proc/{parent_pid}/stat") as fh:
                    if fh.read().rsplit(")", 1)[1].split()[0] == "Z":  # a zombie: the batch is gone
                        os._exit(1)
            except OSError:
                pass
            time.sleep(0.2)

    threading.Thread(target=watch, name="batch-watchdog", daemon=True).start()


def _worker_main(conn, shared: Shared, parent_pid: int, writer_thread: bool = True,
                 crumb_path: str | None = None) -> None:
    """A local worker: runs tasks from ``conn`` until it receives None or the pipe closes;
    ``writer_thread`` False: each run writes its trace in its stepping thread; ``crumb_path``:
    the file its breadcrumb goes to (:mod:`cosim.slaves.crumb`), read by the batch process."""

    trace.WRITER_THREAD = writer_thread
    if crumb_path:
        crumb.attach(crumb.mapped(crumb_path))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with(parent_pid)
    STATE.detach()
    # what the worker inherited (the imports, the warm-up) stays out of its collections: a full
    # collection would scan it after every few runs and, by touching every object, copy the
    # pages it shares with the batch process
    gc.freeze()
    try:
        while True:
            try:
                task = conn.recv()
            except (EOFError, OSError):
                return
            if task is None:
                return
            conn.send(("started", (os.getpid(), time.perf_counter())))
            conn.send(("done", execute(task, shared)))
    finally:
        STATE.remove_files()  # a worker process ends with os._exit: its atexit hooks do not run


class _Slot:
    """A worker process and the tasks sent to it, in order: the first is running (or about to),
    the next one waits in its pipe so that it starts as soon as the first ends."""

    def __init__(self, proc, conn, crumb_path: str | None = None):
        self.proc, self.conn = proc, conn
        self.tasks: deque[Task] = deque()
        self.crumb_path = crumb_path
        self.crumb = crumb.mapped(crumb_path) if crumb_path else None
        self.seen, self.since = None, time.monotonic()  # the crumb's sequence number, and since when
        self.hung = ""  # why it was killed when one of its FMI calls hung

    def where(self) -> tuple[bool, str]:
        """Whether the worker is inside an FMI call, and where it is (or was) per its crumb."""
        if self.crumb is None:
            return False, ""
        state = crumb.read(self.crumb)
        return state["inside"], crumb.describe(state)

    def check_hung(self, timeout: float) -> bool:
        """Kill the worker when its current FMI call has run longer than ``timeout`` [s]."""
        if self.crumb is None or not self.tasks or self.hung:
            return False
        state = crumb.read(self.crumb)
        now = time.monotonic()
        if not (state["inside"] and state["seq"] == self.seen):
            self.seen, self.since = state["seq"], now
            return False
        if now - self.since <= timeout:
            return False
        self.hung = (f"{crumb.describe(state)} did not return within {timeout:g} s (the FMI call timeout, "
                     f"$RPR_COSIM_CALL_TIMEOUT); the run was stopped")
        self.proc.kill()
        return True

    def close(self) -> None:
        if self.crumb is not None:
            self.crumb.close()
            self.crumb = None
        if self.crumb_path:
            try:
                os.unlink(self.crumb_path)
            except OSError:
                pass

    @property
    def task(self) -> Task | None:
        return self.tasks[0] if self.tasks else None

    def send(self, task: Task, data: bytes | None = None) -> None:
        """Send ``task`` (``data``: its pickle, when made already)."""
        self.conn.send_bytes(data if data is not None else ForkingPickler.dumps(task))
        self.tasks.append(task)


def _context(scenes: Sequence = (), shared: Shared | None = None):
    """How workers start: forked from this process when it runs a single thread (after
    :func:`~cosim.batch.preload.warm`, so each worker inherits the imports, the compiled loop,
    the stepping orders and the unpacked FMUs), else from a ``forkserver`` that imported the
    warm-up (forking a process with other threads may copy a lock one of them holds)."""

    if "fork" in mp.get_all_start_methods() and threading.active_count() == 1:
        preload.warm(scenes)
        if shared is not None:
            STATE.prepare(shared.blobs)
        return mp.get_context("fork")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["cosim.batch.preload", "cosim.batch.worker", "cosim.run.execute", "cosim.batch.executors"])
    return ctx


class _Source:
    """Tasks read lazily from an iterable, with those handed back (a retry) first."""

    def __init__(self, tasks: Iterable[Task]):
        self.it: Iterator[Task] | None = iter(tasks)
        self.pending: deque[Task] = deque()

    def pull(self) -> bool:
        """Read one more task into :attr:`pending`; False when there are none left."""
        if self.it is None:
            return False
        t = next(self.it, None)
        if t is None:
            self.it = None
            return False
        self.pending.append(t)
        return True


class LocalExecutor:
    """``workers`` local processes (see the module docstring)."""

    def __init__(self, workers: int | None = None, *, writer_thread: bool = False):
        self.workers = max(1, workers or os.cpu_count() or 1)
        self.capacity = self.workers
        # a worker is one core: it writes each run's trace in its stepping thread unless asked
        # otherwise (cosim.trace.WRITER_THREAD)
        self.writer_thread = writer_thread
        self.replaced = 0  # workers that died and were replaced

    def _spawn(self, ctx, shared: Shared) -> _Slot:
        ours, theirs = ctx.Pipe()
        path = crumb.new_file()
        proc = ctx.Process(target=_worker_main, args=(theirs, shared, os.getpid(), self.writer_thread, path),
                           daemon=True, name="rpr-batch-worker")
        proc.start()
        theirs.close()
        return _Slot(proc, ours, path)

    def run(self, tasks: Iterable[Task], shared: Shared, on_done: OnDone, on_start: OnStart | None = None) -> None:
        """Run every task; returns when all are done (or raises KeyboardInterrupt after stopping
        the workers).  ``tasks`` is read lazily, a task or two ahead of the workers, so that
        making the next task (resolving its scene) overlaps the runs."""
        source = _Source(tasks)
        if not source.pull():
            return
        slots: list[_Slot] = []

        timeout = call_timeout()
        try:
            ctx = _context([source.pending[0].scene], shared)
            while source.pending or any(s.tasks for s in slots):
                self._dispatch(ctx, shared, slots, source)
                if not source.pending:
                    source.pull()  # the next run, resolved while the workers run
                busy = [s for s in slots if s.tasks]
                ready = set(wait([s.conn for s in busy] + [s.proc.sentinel for s in busy], timeout=POLL_S))
                if not ready:  # nothing finished: is a run stuck in an FMI call?
                    for s in busy:
                        s.check_hung(timeout)
                    continue
                finished: list[tuple[Task, Outcome]] = []
                for i, s in enumerate(slots):
                    if not s.tasks or not ({s.conn, s.proc.sentinel} & ready):
                        continue
                    alive = self._drain(s, on_start, finished)
                    if alive and s.proc.sentinel not in ready:
                        continue
                    if s.tasks:  # the worker died with this run
                        s.proc.join(timeout=1)
                        task, code = s.tasks.popleft(), s.proc.exitcode
                        source.pending.extendleft(reversed(s.tasks))  # sent, not started: as they were
                        s.tasks.clear()
                        inside, where = s.where()
                        # SIGKILL or SIGTERM came from outside (the OOM killer, a user): not the FMU's doing
                        external = code in (-signal.SIGKILL, -signal.SIGTERM)
                        if s.hung or (inside and not external):  # an FMU crashed or hung it: not retried
                            status = "hung" if s.hung else "crashed"
                            reason = s.hung or _death(code, where)
                            settle_files(task, status, reason)
                            finished.append((task, Outcome(task.run_id, status, reason, worker=str(s.proc.pid))))
                        elif task.attempt < 2:  # killed from outside (out of memory?): once more, on a new worker
                            task.attempt += 1
                            source.pending.appendleft(task)
                        else:
                            reason = f"the worker process died twice while running it ({_death(code, where)})"
                            settle_files(task, "crashed", reason)
                            finished.append((task, Outcome(task.run_id, "crashed", reason, worker=str(s.proc.pid))))
                    if source.pending or source.it is not None:
                        slots[i] = self._replace(ctx, shared, s)
                try:
                    self._dispatch(ctx, shared, slots, source)  # the next runs go out before the rows are written
                finally:
                    for task, outcome in finished:
                        on_done(task, outcome)
        finally:
            self._stop(slots)
            STATE.remove_files()  # what this process prepared for its forked workers

    def _dispatch(self, ctx, shared: Shared, slots: list[_Slot], source: _Source) -> None:
        """Give a task to every idle worker, starting workers (up to :attr:`workers`) while there
        are more tasks than idle ones; then queue a second task behind each busy worker's run
        while tasks remain for the others too (at the end of the batch a queued task could wait
        behind a long run while another worker is idle)."""
        idle = [i for i, s in enumerate(slots) if not s.tasks]
        while source.pending or source.pull():
            if not idle:
                if len(slots) >= self.workers:
                    break
                slots.append(self._spawn(ctx, shared))
                idle.append(len(slots) - 1)
            self._send(ctx, shared, slots, idle.pop(0), source.pending.popleft())
        for i, s in enumerate(slots):
            if len(s.tasks) == 1 and (source.pending or source.pull()) and (
                    self.workers == 1 or len(source.pending) > 1 or source.it is not None):
                data = ForkingPickler.dumps(source.pending[0])
                if len(data) > self.QUEUED_BYTES:  # it would not fit the pipe: sending would wait for the run
                    continue
                self._send(ctx, shared, slots, i, source.pending.popleft(), bytes(data))

    #: the largest task queued behind a running one (a pipe holds 64 kB; a larger one, e.g. with
    #: FMUs attached, waits in the batch process until its worker is free)
    QUEUED_BYTES = 48 * 1024

    def _send(self, ctx, shared: Shared, slots: list[_Slot], i: int, task: Task, data: bytes | None = None) -> None:
        try:
            slots[i].send(task, data)
        except (BrokenPipeError, OSError):  # died while idle: replace it, send its tasks again
            old = slots[i]
            slots[i] = self._replace(ctx, shared, old)
            for t in [*old.tasks, task]:
                slots[i].send(t)

    def _drain(self, s: _Slot, on_start: OnStart | None, finished: list) -> bool:
        """Read every message of ``s`` (finished runs go to ``finished``); False when its pipe is
        closed."""
        try:
            while s.conn.poll():
                kind, payload = s.conn.recv()
                if kind == "started":
                    pid, s.task.started_at = payload
                    if on_start:
                        on_start(s.task, pid)
                else:
                    finished.append((s.tasks.popleft(), payload))
        except (EOFError, OSError):
            return False
        return True

    def _replace(self, ctx, shared: Shared, s: _Slot) -> _Slot:
        self.replaced += 1
        s.proc.join(timeout=1)
        s.conn.close()
        s.close()
        return self._spawn(ctx, shared)

    @staticmethod
    def _stop(slots: list[_Slot]) -> None:
        for s in slots:
            try:
                s.conn.send(None)
            except (BrokenPipeError, OSError):
                pass
        deadline = time.monotonic() + 2.0
        for s in slots:
            if s.tasks:  # interrupted while running: do not wait for it
                s.proc.kill()
            s.proc.join(timeout=max(0.0, deadline - time.monotonic()))
            if s.proc.is_alive():
                s.proc.kill()
                s.proc.join(timeout=1)
            s.conn.close()
            s.close()


def _death(code: int | None, where: str) -> str:
    """How a worker ended (its exit code, negative for a signal) and where, per its crumb."""
    if code is not None and code < 0:
        how = f"died of {signal.Signals(-code).name} (signal {-code})"
    else:
        how = f"exited (code {code}) without finishing the run"
    return f"the worker process {how}" + (f" in {where}" if where else "")


# --- Dask ----------------------------------------------------------------------------------------
class DaskExecutor:
    """Runs on a Dask distributed cluster: an existing one at ``scheduler``, or a ``LocalCluster``
    of ``workers`` single-threaded processes (see the module docstring)."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None):
        try:
            import distributed  # noqa: F401
        except ModuleNotFoundError:
            raise UserError("Dask execution needs the 'distributed' package: pip install 'dask[distributed]'") from None
        self.scheduler, self.workers = scheduler, workers
        self.capacity = workers or 1

    def _client(self):
        import dask
        from distributed import Client, LocalCluster

        if self.scheduler:
            try:
                client = Client(self.scheduler, timeout=10)
            except OSError as exc:
                raise UserError(f"--scheduler {self.scheduler}: cannot reach the Dask scheduler ({exc})") from None
            return client, None
        with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
            # loopback only: a scheduler runs what it is sent, and the dashboard takes a free port
            cluster = LocalCluster(n_workers=self.workers or os.cpu_count() or 1, threads_per_worker=1,
                                   processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0")
        return Client(cluster), cluster

    def run(self, tasks: Iterable[Task], shared: Shared, on_done: OnDone, on_start: OnStart | None = None) -> None:
        from distributed import as_completed
        from distributed.scheduler import KilledWorker



        tasks = list(tasks)
        if not tasks:
            return
        timeout = call_timeout()  # this process's setting, for the workers' supervisors
        client, cluster = self._client()
        futures = {}
        try:
            self.capacity = max(1, sum(client.nthreads().values()))
            [shared_f] = client.scatter([shared], broadcast=True)
            tag = uuid.uuid4().hex[:8]
            for t in tasks:
                t.out_dir = None
                futures[client.submit(run_remote, t, shared_f, timeout, key=f"rpr-run-{t.run_id}-{tag}", pure=False)] = t
            for fut in as_completed(list(futures)):
                t = futures[fut]
                try:
                    out = fut.result()
                except KilledWorker as exc:
                    out = Outcome(t.run_id, "failed", f"the Dask workers running it died ({exc})", worker="dask")
                except Exception as exc:  # an error raised on the worker outside the run itself
                    out = Outcome(t.run_id, "failed", f"{type(exc).__name__}: {exc}", worker="dask")
                on_done(t, out)
        finally:
            if futures:
                client.cancel(list(futures))
            client.close()
            if cluster is not None:
                cluster.close()


def executor(workers: int | None = None, *, scheduler: str | None = None, dask: bool = False):
    """The executor for the CLI options: Dask with ``scheduler`` or ``dask``, else local."""
    if scheduler or dask:
        return DaskExecutor(scheduler, workers)
    return LocalExecutor(workers)


__all__ = ["DaskExecutor", "LocalExecutor", "executor", "worker_id"]
