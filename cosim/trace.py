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
from pathlib import Path

import numpy as np

from .errors import UserError

FORMAT = "rpr-cosim trace 1"


def package_versions() -> dict[str, str]:
    """Versions of Python and the packages a run depends on."""
    from importlib import metadata

    out = {"python": platform.python_version()}
    for dist in ("rpr-cosim", "numpy", "scipy", "casadi", "fmpy", "PyYAML"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
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


class CsvTrace(Observer):
    """Streams the rows to ``path`` (CSV, shortest round-trip decimal text) with the metadata
    in comment lines and a sidecar ``path.with_suffix('.json')``.

    Formatting floats as text costs about 1 µs per value in Python, more than a compiled macro
    step; so rows are formatted and written by a background thread, which runs while the
    compiled loop (which releases the GIL) steps the next chunk.  :meth:`finish` drains it."""

    def __init__(self, path: Path, *, flush_every_s: float = 0.5, extra: dict | None = None) -> None:
        """``extra``: data for the sidecar only (e.g. the whole scene), kept out of the CSV header."""
        self.path = Path(path)
        self.extra = dict(extra or {})
        self.sidecar = self.path.with_suffix(".json")
        self.flush_every_s = flush_every_s
        self._fh: io.TextIOBase | None = None
        self.rows = 0
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def start(self, columns, meta) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.meta = dict(meta, format=FORMAT, versions=package_versions(),
                         started=time.strftime("%Y-%m-%dT%H:%M:%S%z"), trace=self.path.name)
        self._fh = open(self.path, "w", newline="")
        self._fh.write(f"# {FORMAT}\n")
        for k, v in self.meta.items():
            if k != "format":
                self._fh.write(_comment(k, v))
        w = csv.writer(self._fh, lineterminator="\n")
        w.writerow(columns)
        self._fh.flush()
        self._write_sidecar({"status": "running", "reason": "", "columns": list(columns)})
        self._queue = queue.Queue()
        self._thread = threading.Thread(target=self._writer, name=f"trace-writer {self.path.name}", daemon=True)
        self._thread.start()

    def _writer(self) -> None:
        last_flush = time.monotonic()
        while True:
            rows = self._queue.get()
            if rows is None:
                return
            try:
                if isinstance(rows, str):  # a text event, in order with the rows
                    self._fh.write(rows)
                    continue
                self._fh.write("\n".join(",".join(map(repr, r)) for r in rows.tolist()))
                self._fh.write("\n")
                now = time.monotonic()
                if now - last_flush > self.flush_every_s:
                    self._fh.flush()
                    last_flush = now
            except BaseException as exc:  # reported by finish(); the run itself goes on
                self._error = exc

    def record(self, rows) -> None:
        if not len(rows):
            return
        self._queue.put(np.array(rows, dtype=float, copy=True))
        self.rows += len(rows)

    def record_text(self, t, column, value) -> None:
        if self._queue is not None:
            self._queue.put(_comment("text", [float(t), column, str(value)]))

    def finish(self, status, reason, stats) -> None:
        if self._fh is None:
            return
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        if self._error is not None:
            reason = (reason + "; " if reason else "") + f"trace writer failed: {self._error}"
        self._fh.write(_comment("status", status))
        self._fh.write(_comment("reason", reason))
        self._fh.write(_comment("rows", self.rows))
        self._fh.write(_comment("statistics", stats))
        self._fh.close()
        self._fh = None
        self._write_sidecar({"status": status, "reason": reason, "rows": self.rows, "statistics": stats})

    def _write_sidecar(self, extra: dict) -> None:
        data = dict(self.meta, **self.extra, **extra)
        tmp = self.sidecar.with_name(f".{self.sidecar.name}.tmp")
        tmp.write_text(json.dumps(data, indent=2, default=_json_default))
        os.replace(tmp, self.sidecar)


def read_trace(path: Path) -> Trace:
    """Read a CSV trace written by :class:`CsvTrace` (partial or complete; a last row cut short by
    a crash is dropped)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such trace file")
    meta: dict = {}
    text: dict[str, list[tuple[float, str]]] = {}
    columns: list[str] | None = None
    rows: list[list[float]] = []
    with open(path, newline="") as fh:
        lines = fh.readlines()
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
    return Trace(columns, data, meta, meta.pop("status", ""), meta.pop("reason", ""), meta.pop("statistics", {}), text)
