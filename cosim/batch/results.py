"""The results table of a batch: ``<out>/results.csv``, one row per finished run, that pandas
(``pandas.read_csv``) and a spreadsheet open.

Columns: ``run_id`` (the first 16 hex digits of the resolved scene's hash; the run's files are in
``runs/<run_id>/``), ``index`` (position in the batch), one column per axis (its value),
``outcome`` (ok, failed, stopped) and ``reason``, one column per metric, then the statistics
``steps`` (macro steps done), ``simulated_s``, ``init_s`` (instantiation and initialisation),
``loop_s`` (the stepping loop), ``real_time_factor``, ``run_s`` (all of :func:`cosim.run.run`:
initialisation, loop, trace files), ``wall_s`` (the whole run on its worker: instances, run,
reference, metrics), ``attempts`` (2 when a worker died and the run was retried) and
``worker`` (host:pid).

With ``--format parquet`` the table is also written as ``<out>/results.parquet`` when the batch
ends (:func:`write_parquet`; axes, metrics and statistics as typed columns, the batch's description
as JSON under ``rpr-cosim`` in the schema's metadata); the CSV stays the table that resumes.

Rows are appended as runs finish, each with one ``write`` and an ``fsync``, so an interrupted
batch (Ctrl-C, kill -9, power loss) keeps every finished run; a row cut short by a crash is
dropped when the table is opened again, and its run is redone.
"""
from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..errors import UserError
from ..readers import read_regular
from ..outputs import create_new

STAT_COLUMNS = ("steps", "simulated_s", "init_s", "loop_s", "real_time_factor", "run_s", "wall_s", "attempts",
                "worker")
TEXT_COLUMNS = frozenset({"run_id", "outcome", "reason", "worker"})
INT_COLUMNS = frozenset({"index", "steps", "attempts"})


def base_columns(axes: Sequence[str], metrics: Sequence[str]) -> list[str]:
    """The table's header for a batch with these axis and metric columns."""
    return ["run_id", "index", *axes, "outcome", "reason", *metrics, *STAT_COLUMNS]


def _text(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    return str(v)


def _value(col: str, text: str) -> Any:
    if col in TEXT_COLUMNS:
        return text
    if text == "":
        return None
    try:
        return int(text) if col in INT_COLUMNS else float(text)
    except ValueError:
        return text


class ResultsTable:
    """``results.csv`` opened for appending (see the module docstring)."""

    def __init__(self, path: Path, columns: Sequence[str]):
        self.path = Path(path)
        self.columns = list(columns)
        self.rows: list[dict[str, Any]] = []
        self._fd: int | None = None

    def open(self) -> ResultsTable:
        """Create the table with its header, or read the rows already in it (checking the header
        and dropping a last row cut short)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.is_symlink():
            raise UserError(f"{self.path} is a symbolic link; a batch writes its results table only into a file "
                            f"of its own (remove the link or choose another --out)")
        if self.path.is_file() and self.path.stat().st_size:
            self._repair()
            header, self.rows = read_rows(self.path)
            if header != self.columns:
                raise UserError(f"{self.path} was written by a batch with other columns (its axes or metrics "
                                f"changed: {', '.join(sorted(set(header) ^ set(self.columns))) or 'order'}); "
                                f"choose another --out")
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_NOFOLLOW)
        else:

            self._fd = create_new(self.path)
            self._write(self.columns)
        return self

    def _repair(self) -> None:
        with os.fdopen(os.open(self.path, os.O_RDWR | os.O_NOFOLLOW), "rb+") as fh:
            data = fh.read()
            if data and not data.endswith(b"\n"):
                fh.truncate(data.rfind(b"\n") + 1)

    def _write(self, values: Sequence[Any]) -> None:
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow([_text(v) for v in values])
        os.write(self._fd, buf.getvalue().encode())
        os.fsync(self._fd)

    @property
    def done(self) -> set[str]:
        """Run ids with a row."""
        return {r["run_id"] for r in self.rows}

    def append(self, row: dict[str, Any]) -> None:
        """Write one run's row (missing columns empty) and make it durable."""
        unknown = set(row) - set(self.columns)
        if unknown:
            raise ValueError(f"not columns of the table: {sorted(unknown)}")
        self._write([row.get(c) for c in self.columns])
        self.rows.append({c: _value(c, _text(row.get(c))) for c in self.columns})

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> ResultsTable:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()


def read_rows(path: Path) -> tuple[list[str], list[dict[str, Any]]]:
    """Header and rows of a results table (numbers as numbers; a row cut short is dropped)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no results table (run the batch first)")

    try:
        text = read_regular(path, "results table").decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not a results table (not UTF-8 text at byte {exc.start})") from None
    if "run_id" not in text.split("\n", 1)[0].split(","):
        raise UserError(f"{path}: not a results table (no run_id column)")
    if text and not text.endswith("\n"):
        text = text[:text.rfind("\n") + 1]
    lines = list(csv.reader(io.StringIO(text)))
    if not lines:
        raise UserError(f"{path}: empty results table")
    header = lines[0]
    rows = []
    for n, cells in enumerate(lines[1:], 2):
        if len(cells) != len(header):
            raise UserError(f"{path}:{n}: expected {len(header)} cells, found {len(cells)}")
        rows.append({c: _value(c, v) for c, v in zip(header, cells)})
    return header, rows


def write_parquet(path: Path, columns: Sequence[str], rows: Sequence[dict[str, Any]], meta: dict) -> Path:
    """The results table as Parquet (pyarrow): text columns as strings, the others as float64
    (integers as int64), ``meta`` (JSON) under ``rpr-cosim`` in the schema's metadata."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    fields, arrays = [], []
    for c in columns:
        values = [r.get(c) for r in rows]
        if c in TEXT_COLUMNS:
            kind = pa.string()
            values = [None if v is None else str(v) for v in values]
        elif c in INT_COLUMNS:
            kind = pa.int64()
        else:
            kind = pa.float64()
            values = [v if isinstance(v, (int, float)) or v is None else float("nan") for v in values]
        fields.append(pa.field(c, kind))
        arrays.append(pa.array(values, type=kind))
    schema = pa.schema(fields, metadata={b"rpr-cosim": json.dumps(meta, default=str)})
    tmp = Path(path).with_name(f".{Path(path).name}.part")
    pq.write_table(pa.Table.from_arrays(arrays, schema=schema), str(tmp))
    os.replace(tmp, path)
    return Path(path)


def read_table(path: Path) -> tuple[list[str], list[dict[str, Any]]]:
    """Header and rows of a results table written as CSV (:func:`read_rows`) or Parquet."""
    path = Path(path)
    if path.suffix != ".parquet":
        return read_rows(path)
    if not path.is_file():
        raise UserError(f"{path}: no results table (run the batch first)")
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except Exception as exc:  # ArrowInvalid, OSError
        raise UserError(f"{path}: not a readable Parquet results table ({exc})") from None
    header = list(table.column_names)
    return header, [{c: (None if isinstance(v, float) and math.isnan(v) and c in INT_COLUMNS else v)
                     for c, v in r.items()} for r in table.to_pylist()]


__all__ = ["ResultsTable", "STAT_COLUMNS", "base_columns", "read_rows", "read_table", "write_parquet"]
