"""Bounded, typed readers of the files users and strangers hand a run (issue 33): a file is read
only when it is a regular file under a stated size (never a device such as ``/dev/zero``, a FIFO
that would block, or a directory), and JSON is parsed only when its nesting is within a stated
depth, so that every reader ends in one line (:class:`~cosim.errors.UserError`) instead of a
hang, a ``MemoryError`` or a ``RecursionError``.

Limits (a number of bytes, or ``500MB``, ``2GB``):

- ``$RPR_COSIM_MAX_FILE_BYTES``: a scene, a block's Python file, a sidecar, a batch's tables and
  other metadata files (default 64 MB);
- ``$RPR_COSIM_MAX_TRACE``: a trace file that ``compare``, ``report`` and the batch
  summaries read, the same limit as a run's trace may reach (default 4 GB; reading keeps the
  values, about 0.45 byte of memory per byte of CSV text);
- :data:`MAX_JSON_DEPTH`: arrays and objects nested in one JSON document (sidecars, trace
  metadata lines, the guards annotation of an SSP file).
"""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path

from .errors import UserError

MAX_FILE_BYTES = 64 * 10 ** 6
MAX_TRACE_BYTES = 4 * 10 ** 9
FILE_ENV = "RPR_COSIM_MAX_FILE_BYTES"
TRACE_ENV = "RPR_COSIM_MAX_TRACE"
#: Most arrays and objects nested in one JSON document (the workbench writes 4 levels).
MAX_JSON_DEPTH = 64


def byte_limit(env: str, default: int, unit: str = "bytes (e.g. 2GB)") -> int:
    """``$env`` as a number of bytes (``2GB`` style accepted), else ``default``; ``unit`` names
    what is counted in the message for a bad value."""
    raw = os.environ.get(env, "").strip()
    if not raw:
        return default
    text = raw.upper().rstrip("B")
    scale = 1000 ** " KMGT".index(text[-1]) if text and text[-1] in "KMGT" else 1
    try:
        n = int(float(text[:-1] if scale > 1 else text) * scale)
    except ValueError:
        n = 0
    if n < 1:
        raise UserError(f"${env}: expected a positive number of {unit}, got {raw!r}")
    return n


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def open_regular(path: Path, what: str, limit: int | None = None, env: str = FILE_ENV):
    """``path`` opened for reading in binary mode, after checking (on the open descriptor, so no
    swap in between) that it is a regular file of at most ``limit`` bytes (default
    ``$RPR_COSIM_MAX_FILE_BYTES``); one-line :class:`UserError` naming ``what`` otherwise.  A
    FIFO is opened without blocking and refused."""
    if limit is None:
        limit = byte_limit(env, MAX_FILE_BYTES if env == FILE_ENV else MAX_TRACE_BYTES)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise UserError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise UserError(f"{path}: the {what} is {_kind(st.st_mode)}, not a regular file")
        if st.st_size > limit:
            raise UserError(f"{path}: the {what} has {st.st_size:,} bytes, more than the limit of {limit:,} "
                            f"(${env})")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: Path, what: str, limit: int | None = None, env: str = FILE_ENV) -> bytes:
    """The bytes of ``path`` (:func:`open_regular`'s checks; a file that grew past the limit
    since it was checked is refused too)."""
    if limit is None:
        limit = byte_limit(env, MAX_FILE_BYTES if env == FILE_ENV else MAX_TRACE_BYTES)
    with open_regular(path, what, limit, env) as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise UserError(f"{path}: the {what} has more than the limit of {limit:,} bytes (${env})")
    return data


def json_depth(text: str | bytes) -> int:
    """How deeply arrays and objects nest in the JSON ``text`` (brackets inside strings not
    counted), without parsing it."""
    import re

    import numpy as np

    raw = text.encode("utf-8", "surrogatepass") if isinstance(text, str) else bytes(text)
    if b"[" not in raw and b"{" not in raw:
        return 0
    raw = re.sub(rb'"(?:[^"\\]|\\.)*"', b"", raw)
    a = np.frombuffer(raw, dtype=np.uint8)
    step = (a == ord("[")).astype(np.int64) + (a == ord("{")) - (a == ord("]")) - (a == ord("}"))
    return int(np.cumsum(step).max(initial=0))


def loads_json(text: str | bytes, where: str, max_depth: int = MAX_JSON_DEPTH):
    """``json.loads(text)`` when its nesting is at most ``max_depth``; one-line
    :class:`UserError` naming ``where`` for excess nesting or invalid JSON."""
    depth = json_depth(text)
    if depth > max_depth:
        raise UserError(f"{where}: JSON nested {depth:,} levels deep, more than the limit of {max_depth}")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise UserError(f"{where}: not valid JSON ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") \
            from None


def read_json(path: Path, what: str = "JSON file", limit: int | None = None):
    """A JSON file read through :func:`read_regular` and :func:`loads_json`."""
    return loads_json(read_regular(path, what, limit), str(path))


__all__ = ["MAX_JSON_DEPTH", "byte_limit", "json_depth", "loads_json", "open_regular", "read_json", "read_regular"]
