"""The text of trace files, fast: CSV rows (:func:`rows_text`) and the sidecar's JSON
(:func:`json_text`).

CSV rows: every value as Python's ``repr`` writes it (the shortest decimal that
reads back to the same float64), produced for a whole block at once.

Formatting floats one by one in Python costs about 0.7 µs per value, as much as stepping a
short scene; :func:`rows_text` has orjson format the block (a compiled shortest round-trip
formatter, ~0.05 µs per value) and rewrites the only notation it writes differently from
``repr`` -- magnitudes below 1e-4: ``0.00006`` and ``1e-7`` become ``6e-05`` and ``1e-07`` --
so the bytes are exactly those of ``",".join(map(repr, row))``.  Blocks with NaN or infinity
(orjson writes ``null``) and installations without orjson take the ``repr`` path.

The rewrite (rows apart, the two notations) is one pass of a few lines of C (:data:`C_FILE`,
compiled once and cached like the master loop, :func:`fmus.c_loader.load`): ~1 ns
per byte, where doing it with Python's bytes and regular expressions cost twice orjson's own
time.  Without a C compiler the same rewrite runs in Python.
"""
from __future__ import annotations

import ctypes
import json
import re
from functools import lru_cache
from pathlib import Path

import numpy as np
from fmus.errors import BuildError
from fmus.c_loader import load

try:
    import orjson
except ModuleNotFoundError:  # pragma: no cover - orjson is a dependency; the repr path is exact too
    orjson = None

_ONE_DIGIT_EXPONENT = re.compile(rb"e-([1-9])(?![0-9])")  # 1e-7 -> 1e-07
# 0.000061 -> 6.1e-05, 0.00006 -> 6e-05 (a literal first: the search skips ahead quickly)
_FIXED_E5 = re.compile(rb"0\.0000(?<![0-9.]0\.0000)([1-9])([0-9]*)")


def _e5(m: re.Match) -> bytes:
    return m[1] + (b"." + m[2] if m[2] else b"") + b"e-05"


def repr_text(rows: np.ndarray) -> bytes:
    """The reference formatting: ``repr`` of each value, commas, one line per row."""
    return "".join(",".join(map(repr, r)) + "\n" for r in np.asarray(rows, dtype=float).tolist()).encode()


#: The rewrite in C (orjson's text of a 2-D array -> CSV lines in repr's notation).
C_FILE = Path(__file__).with_name("csv_rows.c")


@lru_cache(maxsize=1)
def _c_rows():
    """The compiled :data:`C_FILE` function, or None without a working C compiler."""

    try:
        fn = load({C_FILE.name: C_FILE.read_text()}, "rpr_text").rpr_csv_rows
    except (BuildError, OSError):
        return None
    fn.restype = ctypes.c_size_t
    fn.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    return fn


def rows_text(rows: np.ndarray) -> bytes:
    """``rows`` (2-D, float64) as CSV lines, byte for byte what :func:`repr_text` gives."""
    a = np.ascontiguousarray(rows, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"rows must be a 2-D array, got shape {a.shape}")
    if not a.size:
        return b"\n" * a.shape[0]
    if orjson is None or not np.isfinite(a).all():
        return repr_text(a)
    text = orjson.dumps(a, option=orjson.OPT_SERIALIZE_NUMPY)
    fn = _c_rows()
    if fn is not None:
        n = len(text) - 4
        out = np.empty(n + n // 2 + 16, dtype=np.uint8)
        m = fn(ctypes.cast(ctypes.c_char_p(text), ctypes.c_void_p).value + 2, n, out.ctypes.data)
        return out[:m].tobytes()
    lines = text[2:-2].split(b"],[")
    mag = np.abs(a)
    for i in np.flatnonzero(((mag > 0) & (mag < 1e-4)).any(axis=1)).tolist():  # rows to rewrite (few)
        lines[i] = _as_repr(lines[i])
    lines.append(b"")
    return b"\n".join(lines)


def _as_repr(line: bytes) -> bytes:
    """A line of orjson's numbers in ``repr``'s notation (magnitudes below 1e-4 differ)."""
    if b"e-" in line:
        line = _ONE_DIGIT_EXPONENT.sub(rb"e-0\1", line)
    if b"0.0000" in line:
        line = _FIXED_E5.sub(_e5, line)
    return line


def json_text(obj, default=None) -> str:
    """``json.dumps(obj, indent=2, default=default)`` up to notation: the same layout and values
    (orjson writes non-ASCII characters as they are and 1e-05 as 0.00001), ~20x faster.  Objects
    with NaN or infinities (JSON has no such numbers; Python's json writes NaN, Infinity) and
    anything orjson refuses go through :mod:`json`."""
    if orjson is not None:
        try:
            json.dumps(obj, allow_nan=False, default=default)  # C encoder (no indent): a quick check
            return orjson.dumps(obj, default=default, option=orjson.OPT_INDENT_2 | orjson.OPT_NON_STR_KEYS
                                | orjson.OPT_SERIALIZE_NUMPY).decode()
        except (ValueError, TypeError):  # NaN or infinity; types or keys either does not take
            pass
    return json.dumps(obj, indent=2, default=default)


__all__ = ["json_text", "repr_text", "rows_text"]
