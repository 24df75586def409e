"""Traces: outputs at communication points, recorded by observers apart from stepping.

An observer gets ``start(columns, meta)``, then ``record(rows)`` any number of times (a 2-D array,
column 0 is time [s], the others the recorded variables named ``component.variable``), then
``finish(status, reason, stats)`` exactly once, also after a failure or an interrupt.

:class:`CsvTrace` streams rows to a CSV file as the run goes: comment lines ``# key: <JSON>``
carry the metadata (scene hash, algorithm, step, package versions) before the data and the
outcome (status, reason, statistics) after it, String and Binary values are comment lines
``# text: [t, "component.variable", "value"]`` among the rows (written when the value changes), and a sidecar ``<name>.json`` holds the same
metadata and is rewritten at the end, so an interrupted or failed run leaves its partial trace
and the reason on disk.  :func:`read_trace` reads such a file back.
"""
from __future__ import annotations

import csv
import io
import json
import os
import platform
import queue
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from .text import json_text, rows_text
from ..errors import UserError

FORMAT = "rpr-cosim trace 1"


def package_versions() -> dict[str, str]:
    """Versions of Python and the packages a run depends on."""
    return dict(_package_versions())


@lru_cache(maxsize=1)
def _package_versions() -> dict[str, str]:
    """:func:`package_versions`, read once per process from the ``.dist-info`` folders
    (importlib.metadata takes 20-50 ms of a run's start-up)."""
    from fmus.index import installed_version

    out = {"python": platform.python_version()}
    for dist, module in (("rpr-cosim", "cosim"), ("numpy", "numpy"), ("scipy", "scipy"), ("casadi", "casadi"),
                         ("fmpy", "fmpy"), ("PyYAML", "yaml")):
        out[dist] = installed_version(dist, module) or "not installed"
    return out


class Observer(ABC):
    """Receives the rows of a run (see the module docstring for the call order)."""

    @abstractmethod
    def start(self, columns: list[str], meta: dict) -> None: ...

    @abstractmethod
    def record(self, rows: np.ndarray) -> None: ...

    @abstractmethod
    def finish(self, status: str, reason: str, stats: dict) -> None: ...

    def record_text(self, t: float, column: str, value: str) -> None:
        """A String or Binary variable (``column``) took ``value`` (Binary as hexadecimal) at ``t``
        [s]; called when it changes, between ``record`` calls.  Ignored by default."""


@dataclass
class Trace:
    """A recorded run: ``data[:, 0]`` is time [s], ``data[:, j]`` the variable ``columns[j]``."""

    columns: list[str]
    data: np.ndarray
    meta: dict = field(default_factory=dict)
    status: str = ""
    reason: str = ""
    stats: dict = field(default_factory=dict)
    text: dict[str, list[tuple[float, str]]] = field(default_factory=dict)  # String/Binary: (t, value) changes

    @property
    def time(self) -> np.ndarray:
        return self.data[:, 0]

    @property
    def names(self) -> list[str]:
        """The recorded variables (every column but time)."""
        return self.columns[1:]

    def __contains__(self, name: str) -> bool:
        return name in self.columns

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.data[:, self.columns.index(name)]
        except ValueError:
            import difflib

            close = difflib.get_close_matches(name, self.columns, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise KeyError(f"no column {name!r} in the trace{hint}") from None

    def at(self, name: str, t: float) -> float:
        """Value of ``name`` at the recorded time nearest to ``t`` [s]."""
        return float(self[name][int(np.argmin(np.abs(self.time - t)))])

    def final(self) -> dict[str, float]:
        """Last recorded value of every variable."""
        return {n: float(self.data[-1, j + 1]) for j, n in enumerate(self.names)} if len(self.data) else {}

    def to_pandas(self):
        """A pandas DataFrame indexed by time (pandas is imported on demand)."""
        import pandas as pd

        return pd.DataFrame(self.data[:, 1:], index=pd.Index(self.time, name="time"), columns=self.names)


class MemoryTrace(Observer):
    """Keeps the rows in memory; :attr:`trace` is the result."""

    def __init__(self) -> None:
        self._chunks: list[np.ndarray] = []
        self.trace: Trace | None = None

    def start(self, columns, meta) -> None:
        self.trace = Trace(list(columns), np.zeros((0, len(columns))), dict(meta))
        self._chunks = []

    def record(self, rows) -> None:
        if len(rows):
            self._chunks.append(np.array(rows, dtype=float, copy=True))

    def record_text(self, t, column, value) -> None:
        self.trace.text.setdefault(column, []).append((float(t), str(value)))

    def _collect(self) -> None:
        if self._chunks:
            self.trace.data = np.vstack([self.trace.data] + self._chunks)
            self._chunks = []

    def finish(self, status, reason, stats) -> None:
        self._collect()
        self.trace.status, self.trace.reason, self.trace.stats = status, reason, stats


def _comment(key: str, value) -> str:
    return f"# {key}: {json.dumps(value, default=_json_default)}\n"


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


class TraceWriteError(UserError):
    """Writing a trace failed (disk full, file too large, I/O error); the run stops with this
    reason and the rows written so far are kept whole."""


#: Whether trace rows are formatted and written by a thread of their own (the default: on a
#: machine with a core to spare, a run then lasts as long as its stepping).  Local batch workers
#: turn it off (:mod:`cosim.batch.executors`): a worker is one core.
WRITER_THREAD = True


class CsvTrace(Observer):
    """Streams the rows to ``path`` (CSV, shortest round-trip decimal text) with the metadata
    in comment lines and a sidecar ``path.with_suffix('.json')``.

    Formatting floats as text costs time (~0.06 µs per value by block, :mod:`cosim.trace.text`;
    1 µs one by one in Python); so rows are formatted and written by a background thread, which runs while the
    compiled loop (which releases the GIL) steps the next chunk.  :meth:`finish` drains it.

    Safety (:mod:`cosim.outputs`): while the run goes, the trace and its sidecar are written
    under temporary names (``.<name>.csv.part``, ``.<name>.json.part``, the sidecar saying
    "running" with the writer's pid) and moved into place by :meth:`finish`, whatever the
    status; a good earlier trace of the same name is kept as ``<name>.prev.csv`` (:attr:`note`
    says so).  Rows go out in whole lines: a failed write (disk full) is cut back to the last
    whole row, and :meth:`record` then raises :class:`TraceWriteError`, which stops the run.
    The writer holds at most ``max_queued_bytes`` of rows not yet written; :meth:`record` waits
    (back-pressure) rather than buffering without bound."""

    #: bytes reserved in the running sidecar so that the final status fits on a full disk
    SIDECAR_RESERVE = 64 * 1024

    def __init__(self, path: Path, *, flush_every_s: float = 0.5, extra: dict | None = None,
                 max_queued_bytes: int = 1 << 20) -> None:
        """``extra``: data for the sidecar only (e.g. the whole scene), kept out of the CSV header."""
        from ..outputs import part_path

        self.path = Path(path)
        self.extra = dict(extra or {})
        self.sidecar = self.path.with_suffix(".json")
        self.part = part_path(self.path)
        self.sidecar_part = part_path(self.sidecar)
        self.flush_every_s = flush_every_s
        self.max_queued_bytes = int(max_queued_bytes)
        self.note = ""
        self._fd: int | None = None
        self._end = 0  # bytes of whole lines written
        self.rows = 0
        self._queue: queue.Queue | None = None
        self._queued = 0
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._inline = False

    def start(self, columns, meta) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.meta = dict(meta, format=FORMAT, versions=package_versions(),
                         started=time.strftime("%Y-%m-%dT%H:%M:%S%z"), trace=self.path.name)
        from ..outputs import create_new

        self._fd = create_new(self.part)  # never through a link planted under the part's name
        buf = io.StringIO()
        buf.write(f"# {FORMAT}\n")
        for k, v in self.meta.items():
            if k != "format":
                buf.write(_comment(k, v))
        csv.writer(buf, lineterminator="\n").writerow(columns)
        try:
            self._write(buf.getvalue().encode())
            self._write_sidecar({"status": "running", "reason": "", "pid": os.getpid(), "columns": list(columns)},
                                reserve=True)
        except OSError as exc:  # nothing of this run is left behind: no stale part files
            os.close(self._fd)
            self._fd = None
            self.part.unlink(missing_ok=True)
            self.sidecar_part.unlink(missing_ok=True)
            raise TraceWriteError(f"cannot write the trace {self.path}: {exc.strerror or exc}") from None
        self._inline = not WRITER_THREAD
        if not self._inline:
            self._queue = queue.Queue()
            self._thread = threading.Thread(target=self._writer, name=f"trace-writer {self.path.name}", daemon=True)
            self._thread.start()

    def _write(self, data: bytes) -> None:
        """Append ``data`` (whole lines) at the end; on failure cut back to the last whole line."""
        view, done = memoryview(data), 0
        try:
            while done < len(data):
                done += os.write(self._fd, view[done:])
        except BaseException:
            os.ftruncate(self._fd, self._end)
            os.lseek(self._fd, self._end, os.SEEK_SET)
            raise
        self._end += len(data)

    def _writer(self) -> None:
        while True:
            rows = self._queue.get()
            if rows is None:
                return
            try:
                if self._error is None:
                    if isinstance(rows, str):  # a text event, in order with the rows
                        self._write(rows.encode())
                        continue
                    self._write(rows_text(rows))  # repr of each value, formatted by block
            except BaseException as exc:  # reported by record() and finish(); stops the run
                self._error = exc
            finally:
                with self._cond:
                    self._queued -= getattr(rows, "nbytes", 0)
                    self._cond.notify_all()

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            exc = self._error
            raise TraceWriteError(f"writing the trace {self.path} failed: "
                                  f"{getattr(exc, 'strerror', None) or exc} ({self._count_rows()} whole rows kept)")

    def record(self, rows) -> None:
        from ..interrupts import deferred, pending

        self._raise_if_failed()
        if not len(rows):
            return
        if self._inline:
            self._write_inline(np.asarray(rows, dtype=float))
            return
        arr = np.array(rows, dtype=float, copy=True)
        step = max(1, (self.max_queued_bytes // 4) // max(1, arr.itemsize * arr.shape[1]))
        for piece in (arr[i:i + step] for i in range(0, len(arr), step)):
            with deferred():  # a signal must not cut the queue's or the counter's locks
                with self._cond:  # back-pressure: wait while the writer is far behind
                    while (self._queued > 0 and self._queued + piece.nbytes > self.max_queued_bytes
                           and self._error is None and not pending()):
                        self._cond.wait(0.05)
                    self._queued += piece.nbytes
                self._queue.put(piece)
                self.rows += len(piece)
        self._raise_if_failed()

    def _write_inline(self, rows) -> None:
        """Format and write ``rows`` now, in the caller's thread (see :data:`WRITER_THREAD`)."""
        from ..interrupts import deferred

        try:
            with deferred():  # whole lines, or cut back to the last one
                self._write(rows if isinstance(rows, bytes) else rows_text(rows))
            if not isinstance(rows, bytes):
                self.rows += len(rows)
        except BaseException as exc:
            self._error = exc
        self._raise_if_failed()

    def record_text(self, t, column, value) -> None:
        from ..interrupts import deferred

        if self._inline and self._fd is not None:
            self._write_inline(_comment("text", [float(t), column, str(value)]).encode())
        elif self._queue is not None:
            with deferred():
                self._queue.put(_comment("text", [float(t), column, str(value)]))

    def finish(self, status, reason, stats) -> None:
        from ..interrupts import deferred

        with deferred():  # a signal now waits until the status is written and the files are in place
            self._finish(status, reason, stats)

    def _finish(self, status, reason, stats) -> None:
        if self._fd is None:
            return
        if self._thread is not None:
            self._queue.put(None)
            while self._thread.is_alive():
                self._thread.join(0.2)
            self._thread = None
        rows = self.rows
        if self._error is not None:
            exc = self._error
            rows = self._count_rows()
            text = f"writing the trace failed: {getattr(exc, 'strerror', None) or exc} ({rows} whole rows kept)"
            if "TraceWriteError" not in reason:
                reason = (reason + "; " if reason else "") + text
            if status == "ok":
                status = "failed"
            stats = dict(stats or {}, status=status, reason=reason)
        self.status, self.reason = status, reason
        trailer = (_comment("status", status) + _comment("reason", reason) + _comment("rows", rows)
                   + _comment("statistics", stats))
        try:
            self._write(trailer.encode())
        except OSError:
            try:  # the statistics are in the sidecar; the status line is what matters
                self._write((_comment("status", status) + _comment("reason", reason)).encode())
            except OSError:
                pass
        os.close(self._fd)
        self._fd = None
        self._write_sidecar({"status": status, "reason": reason, "rows": rows, "statistics": stats})
        from ..outputs import place

        self.note = place(self.part, self.path, status, part_sidecar=self.sidecar_part, sidecar=self.sidecar)

    def _count_rows(self) -> int:
        """Data rows in the part file (after a write failure, the bytes say what is there)."""
        with open(self.part, "rb") as fh:
            lines = [ln for ln in fh if ln.strip() and not ln.startswith(b"#")]
        return max(0, len(lines) - 1)

    def _write_sidecar(self, extra: dict, *, reserve: bool = False) -> None:
        """Write the (temporary) sidecar through a temporary file and a rename; with ``reserve``
        pad it with blanks, so that on a full disk the final status can overwrite it in place."""
        data = json_text(dict(self.meta, **self.extra, **extra), default=_json_default)
        if reserve:
            data += " " * self.SIDECAR_RESERVE + "\n"
        from ..outputs import write_text

        try:
            write_text(self.sidecar_part, data)
        except OSError:
            if reserve or not self.sidecar_part.exists():
                raise
            raw = data.encode()
            fd = os.open(self.sidecar_part, os.O_RDWR | os.O_NOFOLLOW)
            with os.fdopen(fd, "r+b") as fh:  # in place, inside the reserved blocks
                old = fh.seek(0, os.SEEK_END)
                fh.seek(0)
                fh.write(raw + b" " * max(0, old - len(raw)))
                fh.truncate(max(old, len(raw)))


def read_trace(path: Path) -> Trace:
    """Read a CSV trace written by :class:`CsvTrace` (partial or complete; a last row cut short by
    a crash is dropped)."""
    from ..outputs import settle_if_stale

    path = Path(path)
    settle_if_stale(path.parent)  # a run killed in that directory: mark it and put its trace in place
    if not path.is_file():
        raise UserError(f"{path}: no such trace file")
    meta: dict = {}
    text: dict[str, list[tuple[float, str]]] = {}
    columns: list[str] | None = None
    rows: list[list[float]] = []
    try:
        content = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not an rpr-cosim trace (binary or not UTF-8 text at byte {exc.start})") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read the trace ({exc.strerror or exc})") from None
    if "\0" in content:
        raise UserError(f"{path}: not an rpr-cosim trace (binary data)")
    lines = io.StringIO(content, newline="").readlines()
    last_data = max((i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")), default=-1)
    for lineno, line in enumerate(lines, 1):
        if line.startswith("#"):
            key, sep, value = line[1:].strip().partition(": ")
            if sep:
                try:
                    parsed = json.loads(value)
                except ValueError:
                    parsed = value
                if key == "text" and isinstance(parsed, list) and len(parsed) == 3:
                    text.setdefault(parsed[1], []).append((float(parsed[0]), str(parsed[2])))
                else:
                    meta[key] = parsed
            continue
        if columns is None:
            columns = next(csv.reader([line]))
            continue
        if line.strip():
            try:
                row = [float(x) for x in line.split(",")]
                if len(row) != len(columns):
                    raise ValueError
                rows.append(row)
            except ValueError:
                if lineno - 1 == last_data and not line.endswith("\n"):
                    continue  # a row cut short by a crash while it was being written
                raise UserError(f"{path}:{lineno}: expected {len(columns)} numbers separated by commas") from None
    if columns is None:
        raise UserError(f"{path}: no column header; is this an rpr-cosim trace?")
    data = np.array(rows, dtype=float).reshape(-1, len(columns))
    if "status" not in meta:  # no status line: the run died; its sidecar may say why
        meta.update(_sidecar_outcome(path))
    return Trace(columns, data, meta, meta.pop("status", ""), meta.pop("reason", ""), meta.pop("statistics", {}), text)


def _sidecar_outcome(path: Path) -> dict:
    """Status and reason of a trace without a status line, from its sidecar when that says the run
    did not end ok."""
    side = path.with_suffix(".json")
    try:
        data = json.loads(side.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("status") in (None, "ok"):
        return {}
    return {"status": str(data["status"]), "reason": str(data.get("reason", ""))}
