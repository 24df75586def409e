"""Traces: outputs at communication points, recorded by observers apart from stepping.

An observer (:class:`cosim.trace.observer.Observer`) gets ``start(columns, meta)``, then
``record(rows)`` any number of times (a 2-D array, column 0 is time [s], the others the recorded
variables named ``component.variable``), then ``finish(status, reason, stats)`` exactly once, also
after a failure or an interrupt.

Trace files come in four formats (:data:`TRACE_FORMATS`), all streamed as the run goes, with a
sidecar ``<name>.json`` holding the metadata (scene hash, algorithm, step, package versions, the
scene's units) and, rewritten at the end, the outcome (status, reason, statistics), so an
interrupted or failed run leaves its partial trace and the reason on disk:

- ``csv`` (the default): a plain CSV, one header line (``time`` and the variables) then one row
  per recorded instant, which spreadsheets and ``pandas.read_csv(path)`` open as they are;
  String and Binary values go to the sidecar (``"text"``).
- ``commented-csv``: the same rows between comment lines ``# key: <JSON>`` carrying the
  metadata before the data and the outcome after it, String and Binary values as comment lines
  ``# text: [t, "component.variable", "value"]`` among the rows (the format of earlier versions).
- ``parquet`` (:class:`ParquetTrace`, pyarrow): one float64 column per variable, written by row
  groups, the metadata and the outcome in the Parquet schema's key-value metadata.
- ``npy`` (:class:`NpyTrace`, the batch default): the rows as they are recorded, float64 bytes
  after a NumPy ``.npy`` header (``numpy.load(path)`` gives the array, column 0 time [s]), the
  column names under ``"columns"`` of the sidecar; no text to format, so a run costs what
  its stepping costs (benchmarks/bench_batch.py).

:func:`read_trace` reads every one of them back (and CSVs from other tools).
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
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from .observer import Observer
from .text import json_text, rows_text
from ..errors import UserError
from ..outputs import NPY_HEADER_BYTES, create_new, npy_header, part_path, place, settle_if_stale, write_text
from ..readers import TRACE_ENV, loads_json, open_regular, read_json
from ..interrupts import deferred, pending

FORMAT = "rpr-cosim trace 1"
#: The trace file formats a run can write (see the module docstring); the first is the default.
TRACE_FORMATS = ("csv", "commented-csv", "parquet", "npy")
#: File suffix of each trace format.
_SUFFIX = {"csv": ".csv", "commented-csv": ".csv", "parquet": ".parquet", "npy": ".npy"}
#: Key of the rpr-cosim metadata in a Parquet trace's schema (JSON); the outcome is under
#: ``PARQUET_OUTCOME_KEY``, added when the run ends.
PARQUET_META_KEY = b"rpr-cosim"
PARQUET_OUTCOME_KEY = b"rpr-cosim.outcome"


def trace_suffix(fmt: str) -> str:
    """The file suffix of a trace written in ``fmt`` (one of :data:`TRACE_FORMATS`)."""
    if fmt not in TRACE_FORMATS:
        raise UserError(f"trace format {fmt!r}: expected one of {', '.join(TRACE_FORMATS)}")
    return _SUFFIX[fmt]


def trace_writer(path: Path, fmt: str = "csv", **kwargs) -> "CsvTrace":
    """The observer writing a trace to ``path`` in ``fmt`` (:data:`TRACE_FORMATS`)."""
    trace_suffix(fmt)
    if fmt == "parquet":
        return ParquetTrace(path, **kwargs)
    if fmt == "npy":
        return NpyTrace(path, **kwargs)
    return CsvTrace(path, commented=fmt == "commented-csv", **kwargs)


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
    """Streams the rows to ``path`` (CSV, shortest round-trip decimal text) and writes a sidecar
    ``path.with_suffix('.json')`` with the metadata; with ``commented`` the metadata and outcome
    are also comment lines of the CSV (module docstring), else the CSV is plain.

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
                 max_queued_bytes: int = 1 << 20, commented: bool = False) -> None:
        """``extra``: data for the sidecar only (e.g. the whole scene), kept out of the CSV header."""

        self.commented = bool(commented)
        self._text: list[list] = []  # String/Binary changes of a plain trace, for the sidecar
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

        self._fd = create_new(self.part)  # never through a link planted under the part's name
        buf = io.StringIO()
        if self.commented:
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

        try:
            with deferred():  # whole lines, or cut back to the last one
                self._write(rows if isinstance(rows, bytes) else rows_text(rows))
            if not isinstance(rows, bytes):
                self.rows += len(rows)
        except BaseException as exc:
            self._error = exc
        self._raise_if_failed()

    def record_text(self, t, column, value) -> None:

        if not self.commented:
            self._text.append([float(t), column, str(value)])
            return
        if self._inline and self._fd is not None:
            self._write_inline(_comment("text", [float(t), column, str(value)]).encode())
        elif self._queue is not None:
            with deferred():
                self._queue.put(_comment("text", [float(t), column, str(value)]))

    def finish(self, status, reason, stats) -> None:

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
            rows = self._count_rows()
            status, reason, stats = self._failed(status, reason, stats, f" ({rows} whole rows kept)")
        self.status, self.reason = status, reason
        if self.commented:
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
        self._finish_sidecar(status, reason, rows, stats)

    def _failed(self, status: str, reason: str, stats: dict, kept: str = "") -> tuple[str, str, dict]:
        """The outcome of a run whose trace could not be written (``self._error``): its reason
        gains the write error (and ``kept``, what is left of the file), "ok" becomes "failed"."""
        text = f"writing the trace failed: {getattr(self._error, 'strerror', None) or self._error}{kept}"
        if "TraceWriteError" not in reason:
            reason = (reason + "; " if reason else "") + text
        if status == "ok":
            status = "failed"
        return status, reason, dict(stats or {}, status=status, reason=reason)

    def _finish_sidecar(self, status: str, reason: str, rows: int, stats: dict) -> None:
        """The final sidecar, then the files moved into place (:func:`cosim.outputs.place`)."""
        end = {"status": status, "reason": reason, "rows": rows, "statistics": stats}
        if self._text:
            end["text"] = self._text
        self._write_sidecar(end)

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


class ParquetTrace(CsvTrace):
    """Writes the rows to ``path`` as Parquet (pyarrow, imported when a run writes one): a float64
    column per variable, a row group per :meth:`record` call of at least ``group_rows`` rows
    (smaller calls are gathered), the metadata as JSON under :data:`PARQUET_META_KEY` of the
    schema and the outcome under :data:`PARQUET_OUTCOME_KEY`, added at the end.  The sidecar,
    temporary names and placing are :class:`CsvTrace`'s; the rows are written in the caller's
    thread (pyarrow's encoder releases the GIL).  A run killed before the end leaves a Parquet
    file without its footer, which cannot be read: use CSV where a partial trace matters."""

    def __init__(self, path: Path, *, group_rows: int = 4096, **kwargs) -> None:
        kwargs.pop("commented", None)
        super().__init__(path, **kwargs)
        self.group_rows = int(group_rows)
        self._pending: list[np.ndarray] = []
        self._pending_rows = 0
        self._pq = None
        self._writer = None
        self._schema = None

    def start(self, columns, meta) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        self._pq = pq
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.meta = dict(meta, format=FORMAT, versions=package_versions(),
                         started=time.strftime("%Y-%m-%dT%H:%M:%S%z"), trace=self.path.name)
        self.columns = list(columns)
        self._schema = pa.schema([pa.field(c, pa.float64()) for c in self.columns],
                                 metadata={PARQUET_META_KEY: json.dumps(self.meta, default=_json_default)})

        os.close(create_new(self.part))  # a link planted under the part's name is replaced, not followed
        try:
            self._writer = pq.ParquetWriter(str(self.part), self._schema, compression="zstd")
            self._fd = -1  # "started" for the base class
            self._write_sidecar({"status": "running", "reason": "", "pid": os.getpid(), "columns": self.columns},
                                reserve=True)
        except OSError as exc:
            self._writer = None
            self._fd = None
            raise TraceWriteError(f"cannot write the trace {self.part}: {exc.strerror or exc}") from None

    def record(self, rows) -> None:
        self._raise_if_failed()
        if not len(rows):
            return
        self._pending.append(np.array(rows, dtype=float, copy=True))
        self._pending_rows += len(rows)
        self.rows += len(rows)
        if self._pending_rows >= self.group_rows:
            self._flush()
        self._raise_if_failed()

    def _flush(self) -> None:
        if not self._pending or self._writer is None:
            return
        import pyarrow as pa

        block = np.vstack(self._pending)
        self._pending, self._pending_rows = [], 0
        try:
            with deferred():
                self._writer.write_table(pa.Table.from_arrays([pa.array(block[:, j]) for j in range(block.shape[1])],
                                                              schema=self._schema))
        except BaseException as exc:  # reported by record() and finish(); stops the run
            self._error = exc

    def record_text(self, t, column, value) -> None:
        self._text.append([float(t), column, str(value)])

    def _count_rows(self) -> int:
        return self.rows

    def _finish(self, status, reason, stats) -> None:
        if self._fd is None:
            return
        self._flush()
        rows = self.rows
        if self._error is not None:
            status, reason, stats = self._failed(status, reason, stats)
        self.status, self.reason = status, reason
        outcome = {"status": status, "reason": reason, "rows": rows, "statistics": stats}
        if self._text:
            outcome["text"] = self._text
        try:
            self._writer.add_key_value_metadata({PARQUET_OUTCOME_KEY: json.dumps(outcome, default=_json_default)})
            self._writer.close()
        except OSError:
            pass
        self._writer = None
        self._fd = None
        self._finish_sidecar(status, reason, rows, stats)


class NpyTrace(CsvTrace):
    """Writes the rows to ``path`` as a NumPy ``.npy`` file: a header of
    :data:`cosim.outputs.NPY_HEADER_BYTES` bytes (format 1.0, ``<f8``, C order, the shape
    ``(rows, columns)``), then each recorded row's float64 values, little-endian, column 0 time
    [s].  The column names are the sidecar's ``"columns"`` (with the metadata and outcome, as for
    a plain CSV); String and Binary values go to the sidecar's ``"text"``.

    The rows are written as they come, in the caller's thread (copying bytes, nothing to format).
    The header says 0 rows until :meth:`finish` writes the count over it; a run killed before
    that leaves whole rows that :func:`read_trace` reads by the file's size, and that
    :mod:`cosim.outputs` (settling a dead run) counts into the header.  Temporary names, placing
    and the sidecar are :class:`CsvTrace`'s."""

    def __init__(self, path: Path, **kwargs) -> None:
        kwargs.pop("commented", None)
        super().__init__(path, **kwargs)

    def start(self, columns, meta) -> None:

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.meta = dict(meta, format=FORMAT, versions=package_versions(),
                         started=time.strftime("%Y-%m-%dT%H:%M:%S%z"), trace=self.path.name)
        self.columns = list(columns)
        self.extra["columns"] = self.columns  # in every sidecar written, the final one too
        self._fd = create_new(self.part)
        try:
            self._write(npy_header(0, len(self.columns)))
            self._write_sidecar({"status": "running", "reason": "", "pid": os.getpid()}, reserve=True)
        except OSError as exc:
            os.close(self._fd)
            self._fd = None
            self.part.unlink(missing_ok=True)
            self.sidecar_part.unlink(missing_ok=True)
            raise TraceWriteError(f"cannot write the trace {self.path}: {exc.strerror or exc}") from None
        self._inline = True

    def record(self, rows) -> None:

        self._raise_if_failed()
        if not len(rows) or self._error is not None:
            return
        block = np.ascontiguousarray(rows, dtype="<f8")
        try:
            with deferred():  # whole rows, or cut back to the last one
                self._write(block.tobytes())
            self.rows += len(block)
        except BaseException as exc:
            self._error = exc
        self._raise_if_failed()

    def _count_rows(self) -> int:

        return max(0, self.part.stat().st_size - NPY_HEADER_BYTES) // (8 * len(self.columns))

    def _finish(self, status, reason, stats) -> None:
        if self._fd is None:
            return

        rows = self.rows
        if self._error is not None:
            rows = self._count_rows()
            status, reason, stats = self._failed(status, reason, stats, f" ({rows} whole rows kept)")
        self.status, self.reason = status, reason
        try:
            os.pwrite(self._fd, npy_header(rows, len(self.columns)), 0)
        except OSError:
            pass  # the header keeps 0 rows: read_trace counts the whole rows by the file's size
        os.close(self._fd)
        self._fd = None
        self._finish_sidecar(status, reason, rows, stats)


#: Sidecar keys that are the outcome or bookkeeping, not metadata of the trace.
_SIDECAR_OUTCOME = ("status", "reason", "rows", "statistics", "text", "pid", "columns", "scene_data")


#: Longest line of a CSV trace [bytes] (a header of 10,000 long names fits).
MAX_LINE_BYTES = 16 * 2 ** 20
#: Rows parsed at once (memory: the rows' float64 values plus one block of text).
_BLOCK_ROWS = 20000
#: Types of the metadata keys the workbench reads back (a comment line or sidecar key of another
#: type is refused in one line; other keys are kept as they are).
META_TYPES: dict[str, tuple[type, ...]] = {
    "status": (str,), "reason": (str,), "statistics": (dict,), "units": (dict,), "scene": (str,),
    "scene_hash": (str,), "algorithm": (str,), "started": (str,), "method": (str,), "trace": (str,),
    "overrides": (list,), "scene_data": (dict,), "rows": (int,), "connections": (list,),
    "start_time": (int, float), "stop_time": (int, float)}


def check_meta(key: str, value, where: str) -> None:
    """One-line :class:`UserError` naming ``where`` when a metadata ``value`` is not of the type
    the workbench expects under ``key`` (:data:`META_TYPES`)."""
    types = META_TYPES.get(key)
    if types is None or value is None:
        return
    if not isinstance(value, types) or isinstance(value, bool):
        raise UserError(f"{where}: metadata {key!r} must be {' or '.join(_TYPE_NAMES[t] for t in types)}, "
                        f"got {type(value).__name__}")
    if key == "units" and not all(isinstance(v, str) for v in value.values()):
        raise UserError(f"{where}: metadata 'units' must map variables to unit strings")


_TYPE_NAMES = {str: "a string", dict: "a JSON object", list: "a JSON array", int: "a whole number",
               float: "a number"}


def read_trace(path: Path) -> Trace:
    """Read a trace in any of :data:`TRACE_FORMATS` (partial or complete; a last CSV row cut
    short by a crash is dropped), or a plain CSV from another tool (first column time).

    Bounded (:mod:`cosim.readers`): a regular file of at most ``$RPR_COSIM_MAX_TRACE``
    (default 4 GB, what a run may write), lines of at most :data:`MAX_LINE_BYTES`, read a block of rows at a time into one array grown in place (about
    0.45 byte of memory per byte of CSV), metadata lines depth-bounded JSON of the types of
    :data:`META_TYPES`; anything else is a one-line :class:`UserError`."""

    path = Path(path)
    settle_if_stale(path.parent)  # a run killed in that directory: mark it and put its trace in place
    if not path.exists():
        raise UserError(f"{path}: no such trace file")
    if path.suffix == ".parquet":
        with open_regular(path, "trace", env=TRACE_ENV):
            pass
        return _read_parquet(path)
    with open_regular(path, "trace", env=TRACE_ENV) as fh:
        columns, data, meta, text = _read_npy(fh, path) if path.suffix == ".npy" else _read_csv(fh, path)
    if not meta:  # a plain CSV: its metadata and outcome are in the sidecar, when there is one
        side = _sidecar(path)
        if side.get("trace") == path.name or side.get("format") == FORMAT:
            meta = {k: v for k, v in side.items() if k not in _SIDECAR_OUTCOME and k != "format"}
            for k, v in meta.items():
                check_meta(k, v, str(path.with_suffix(".json")))
            text = _text_events(side.get("text"), str(path.with_suffix(".json")))
            if side.get("status") not in (None, "running"):
                for k in ("status", "reason", "statistics"):
                    check_meta(k, side.get(k), str(path.with_suffix(".json")))
                meta.update(status=side["status"], reason=side.get("reason", ""),
                            statistics=side.get("statistics", {}))
    if "status" not in meta:  # no status line: the run died; its sidecar may say why
        meta.update(_sidecar_outcome(path))
    return Trace(columns, data, meta, meta.pop("status", ""), meta.pop("reason", "") or "",
                 meta.pop("statistics", {}) or {}, text)


def _text_events(items, where: str) -> dict[str, list[tuple[float, str]]]:
    """String/Binary changes ``[[t, column, value], ...]`` of a sidecar or Parquet outcome."""
    text: dict[str, list[tuple[float, str]]] = {}
    if items in (None, []):
        return text
    if not isinstance(items, list):
        raise UserError(f"{where}: 'text' must be a list of [time, \"component.variable\", \"value\"]")
    for item in items:
        t, column, value = _text_event(item, where)
        text.setdefault(column, []).append((t, value))
    return text


def _text_event(item, where: str) -> tuple[float, str, str]:
    if (isinstance(item, list) and len(item) == 3 and isinstance(item[0], (int, float))
            and not isinstance(item[0], bool) and isinstance(item[1], str)):
        return float(item[0]), item[1], str(item[2])
    raise UserError(f"{where}: a text event must be [time, \"component.variable\", \"value\"], got "
                    f"{str(item)[:60]}")


def _read_csv(fh, path: Path) -> tuple[list[str], np.ndarray, dict, dict]:
    """Columns, rows, metadata and text events of a CSV trace read from the binary file ``fh``."""
    import warnings


    meta: dict = {}
    text: dict[str, list[tuple[float, str]]] = {}
    columns: list[str] | None = None
    rows = _Rows(os.fstat(fh.fileno()).st_size)
    pending: list[tuple[int, bytes]] = []
    offset = 0

    def flush() -> None:
        if not pending:
            return
        joined = b",".join(ln.strip() for _, ln in pending)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                vals = np.fromstring(joined.decode("ascii", "replace"), dtype=float, sep=",")
            except ValueError:  # a cell that is not a number: the line-by-line parse names its line
                vals = np.zeros(0)
        if vals.size != len(pending) * len(columns) or any(ln.count(b",") != len(columns) - 1 for _, ln in pending):
            vals = np.array([_row(ln, lineno, len(columns), path) for lineno, ln in pending], dtype=float)
        rows.add(vals.reshape(-1, len(columns)), offset)
        pending.clear()

    lineno = 0
    while True:
        raw = fh.readline(MAX_LINE_BYTES + 1)
        if not raw:
            break
        lineno += 1
        if b"\0" in raw:
            raise UserError(f"{path}: not an rpr-cosim trace (binary data)")
        if len(raw) > MAX_LINE_BYTES:
            raise UserError(f"{path}:{lineno}: a line longer than {MAX_LINE_BYTES:,} bytes; not an rpr-cosim trace")
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise UserError(f"{path}: not an rpr-cosim trace (binary or not UTF-8 text at byte "
                            f"{offset + exc.start})") from None
        offset += len(raw)
        if line.startswith("#"):
            key, sep, value = line[1:].strip().partition(": ")
            if sep:
                where = f"{path}:{lineno}"
                try:
                    parsed = loads_json(value, where)
                except UserError as exc:
                    if "nested" in str(exc):
                        raise
                    parsed = value
                if key == "text":
                    t, column, v = _text_event(parsed, where)
                    text.setdefault(column, []).append((t, v))
                else:
                    check_meta(key, parsed, where)
                    meta[key] = parsed
            continue
        if columns is None:
            columns = next(csv.reader([line]), None) or ["time"]
            continue
        if line.strip():
            if not raw.endswith(b"\n"):  # the last line: cut short by a crash while it was written?
                try:
                    _row(raw, lineno, len(columns), path)
                except UserError:
                    continue
            pending.append((lineno, raw))
            if len(pending) >= _BLOCK_ROWS:
                flush()
    if columns is None:
        raise UserError(f"{path}: no column header; is this an rpr-cosim trace?")
    flush()
    data = rows.array(len(columns))
    return columns, data, meta, text


class _Rows:
    """The rows of a trace gathered into one array grown in place: sized from the file's bytes
    per row so far, so that the whole is about one copy of the values (no list of blocks
    stacked at the end, which would hold two)."""

    def __init__(self, file_bytes: int) -> None:
        self.file_bytes, self.n, self.buf = file_bytes, 0, None

    def add(self, block: np.ndarray, read_bytes: int) -> None:
        need = self.n + len(block)
        if self.buf is None or need > len(self.buf):
            per_row = max(1.0, read_bytes / need)
            guess = max(need, int(1.02 * self.file_bytes / per_row) + 1)
            grown = np.empty((guess if self.buf is None else max(guess, int(1.25 * need)), block.shape[1]))
            if self.buf is not None:
                grown[:self.n] = self.buf[:self.n]
            self.buf = grown
        self.buf[self.n:need] = block
        self.n = need

    def array(self, ncols: int) -> np.ndarray:
        if self.buf is None:
            return np.zeros((0, ncols))
        self.buf.resize((self.n, ncols), refcheck=False)  # the unused tail freed in place (realloc)
        return self.buf


def _row(raw: bytes, lineno: int, n: int, path: Path) -> list[float]:
    try:
        row = [float(x) for x in raw.split(b",")]
    except ValueError:
        row = []
    if len(row) != n:
        raise UserError(f"{path}:{lineno}: expected {n} numbers separated by commas")
    return row


def _read_npy(fh, path: Path) -> tuple[list[str], np.ndarray, dict, dict]:
    """An ``.npy`` trace (:class:`NpyTrace`): the array and the column names of its sidecar
    (metadata and outcome are read from the sidecar by :func:`read_trace`).  Whole rows after the
    header are read, also when the header's count is short (a run that died)."""
    from numpy.lib import format as npf

    side = _sidecar(path)
    columns = side.get("columns")
    if not (isinstance(columns, list) and columns and all(isinstance(c, str) for c in columns)):
        raise UserError(f"{path}: an .npy trace needs its sidecar {path.with_suffix('.json').name} with the "
                        f"column names under \"columns\" (a list of strings)")
    try:
        version = npf.read_magic(fh)
        shape, fortran, dtype = (npf.read_array_header_1_0 if version == (1, 0) else npf.read_array_header_2_0)(fh)
    except ValueError as exc:
        raise UserError(f"{path}: not a readable .npy file ({exc})") from None
    if dtype != np.dtype("<f8") or fortran or len(shape) != 2 or shape[1] != len(columns):
        raise UserError(f"{path}: expected a 2-D little-endian float64 array in C order with {len(columns)} "
                        f"columns (the sidecar's), found {dtype.str} {'Fortran' if fortran else 'C'} order shape {shape}")
    offset = fh.tell()
    rows = (os.fstat(fh.fileno()).st_size - offset) // (8 * len(columns))
    data = np.fromfile(fh, dtype="<f8", count=rows * len(columns)).reshape(rows, len(columns))
    return list(columns), data.astype(float, copy=False), {}, {}


def _read_parquet(path: Path) -> Trace:
    """A Parquet trace (:class:`ParquetTrace`), or any Parquet file of float columns whose first
    column is time."""
    try:
        import pyarrow.parquet as pq

        pf = pq.ParquetFile(path)
        table = pf.read()
    except ImportError:
        raise UserError(f"{path}: reading Parquet needs pyarrow (pip install pyarrow)") from None
    except Exception as exc:  # pyarrow's ArrowInvalid and OSError: not (or not a whole) Parquet file
        raise UserError(f"{path}: not a readable Parquet trace ({exc})") from None

    kv = pf.metadata.metadata or {}  # the file's key-value metadata: the schema's and the outcome added at the end
    meta = loads_json(kv[PARQUET_META_KEY], f"{path} (metadata)") if PARQUET_META_KEY in kv else {}
    outcome = (loads_json(kv[PARQUET_OUTCOME_KEY], f"{path} (outcome)") if PARQUET_OUTCOME_KEY in kv
               else _sidecar_outcome(path))
    if not isinstance(meta, dict) or not isinstance(outcome, dict):
        raise UserError(f"{path}: the rpr-cosim metadata of the Parquet trace must be JSON objects")
    for k, v in (*meta.items(), *((k, outcome.get(k)) for k in ("status", "reason", "statistics"))):
        check_meta(k, v, str(path))
    text = _text_events(outcome.get("text"), str(path))
    columns = list(table.column_names)
    try:
        data = np.column_stack([table.column(c).to_numpy(zero_copy_only=False).astype(float) for c in columns]) \
            if table.num_rows else np.zeros((0, len(columns)))
    except (TypeError, ValueError) as exc:
        raise UserError(f"{path}: expected numeric columns in the Parquet trace ({exc})") from None
    meta.pop("format", None)
    return Trace(columns, data, meta, outcome.get("status") or "", outcome.get("reason") or "",
                 outcome.get("statistics") or {}, text)


def _sidecar(path: Path) -> dict:
    """The sidecar ``<path>.json`` of a trace, or {} when there is none (one that is there but
    not a regular file, too large, too deeply nested or not JSON: :class:`UserError`)."""

    side = path.with_suffix(".json")
    if not side.exists():
        return {}
    data = read_json(side, "sidecar")
    return data if isinstance(data, dict) else {}


def _sidecar_outcome(path: Path) -> dict:
    """Status and reason of a trace without a status line, from its sidecar when that says the run
    did not end ok."""
    data = _sidecar(path)
    if data.get("status") in (None, "ok"):
        return {}
    return {"status": str(data["status"]), "reason": str(data.get("reason", ""))}
