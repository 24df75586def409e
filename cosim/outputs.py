"""Where a run may write, and how: confinement, one writer per directory, atomic placement.

* :func:`safe_name` is the only way a scene's ``name`` becomes a file name: a plain name of
  letters, digits, ``_``, ``-`` and ``.`` (no path separator, no ``..``, not hidden, at most
  :data:`MAX_NAME` characters); anything else is a :class:`UserError`.
* :func:`confined` resolves a file name under an output directory and refuses a path that leaves
  it (symbolic links included).
* :func:`check_out_dir` refuses, in one line and before anything is built, an ``--out`` that is a
  file or cannot be written.
* :class:`OutputLock` (``<out>/.rpr-cosim.lock``, ``flock`` plus the holder's pid) lets one run
  write into a directory at a time; a lock left by a dead process is stale: its sidecars that
  still say "running" are marked "killed" (:func:`settle_stale`).
* :func:`place` moves a finished trace (written under a temporary name) into place; the earlier
  run of the same name goes whole (trace, sidecar, plot, animation, report, reference): a good
  one is kept as ``<name>.prev.*`` instead of being replaced by a run that is not ok, any other
  is removed, so a directory never mixes two runs' files.
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import socket
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import UserError
from .readers import read_json

#: Longest scene name accepted as a file name stem [characters].
MAX_NAME = 100
#: The lock file of an output directory, for runs, batches and studies alike.
LOCK_NAME = ".rpr-cosim.lock"
#: Endings of the names rpr-cosim gives files of its own next to a scene's (``<name>.prev.csv``,
#: ``<name>_reference.csv``, ...): a scene name ending so could collide with another's files.
RESERVED_ENDINGS = (".prev", ".part", ".tmp", ".lock", "_reference", "_vs_reference")
_SAFE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")


# --- names and paths ----------------------------------------------------------------------------
def name_problem(name: object) -> str | None:
    """Why ``name`` cannot be a file name stem, or None when it can."""
    if not isinstance(name, str) or not name:
        return f"name must be a non-empty text, got {name!r}"
    shown = name if len(name) <= 40 else name[:37] + "..."
    if len(name) > MAX_NAME:
        return f"name {shown!r} is {len(name)} characters long; at most {MAX_NAME} are allowed"
    if "/" in name or "\\" in name or ".." in name or not _SAFE.match(name):
        return (f"name {shown!r} must be a plain file name: letters, digits, '_', '-' and '.', not starting "
                f"with '.' or '-', no '/' and no '..' (it names the trace files under --out)")
    ending = next((e for e in RESERVED_ENDINGS if name.lower().endswith(e)), None)
    if ending:
        return (f"name {shown!r} ends with {ending!r}, which rpr-cosim uses for files of its own next to a "
                f"scene's ({name[:-len(ending)] or 'x'}{ending}.csv could be another scene's); choose another name")
    return None


def safe_name(name: object) -> str:
    """``name`` if it is a plain file name stem (see :func:`name_problem`), else :class:`UserError`."""
    problem = name_problem(name)
    if problem:
        raise UserError(problem)
    return str(name)


def stem_name(stem: str) -> str:
    """A file stem turned into a safe scene name (unsafe characters become ``_``)."""
    s = re.sub(r"[^A-Za-z0-9_.\-]", "_", stem).replace("..", "_").lstrip(".-")[:MAX_NAME]
    return s or "scene"


def confined(out_dir: Path, filename: str) -> Path:
    """``out_dir / filename`` after checking that it resolves inside ``out_dir`` (symbolic links
    included).  The path returned is the name itself, not a link's target: every file is created
    afresh or renamed into place (:func:`create_new`, :func:`place`), which replaces a link of
    that name instead of writing through it."""
    root = Path(out_dir).resolve()
    path = root / filename
    folder = path.parent.resolve()
    resolved = path.resolve()
    for p in (folder / "x", resolved):
        if path.name in ("", ".", "..") or (p.parent != root and root not in p.parents):
            raise UserError(f"refusing to write {filename!r}: it resolves to {resolved}, outside the output "
                            f"directory {root}")
    return folder / path.name


def check_out_dir(out_dir: Path) -> Path:
    """Create ``out_dir`` (and parents) and check it can be written; one-line :class:`UserError`
    for a path that is a file, a directory that cannot be written or created."""
    out = Path(out_dir)
    for p in [out, *out.parents]:
        if p.exists() and not p.is_dir():
            raise UserError(f"--out {out}: {p} is a file, not a directory; choose another output directory")
        if p.exists():
            break
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot create the output directory ({exc.strerror or exc})") from None
    try:  # a real write: permissions, read-only file systems and ACLs all answer here
        with tempfile.TemporaryFile(dir=out, prefix=".rpr-cosim-probe-"):
            pass
    except OSError as exc:
        raise UserError(f"--out {out}: the output directory is not writable ({exc.strerror or exc}); "
                        f"choose another one or fix its permissions") from None
    return out


# --- one writer per directory -------------------------------------------------------------------
def pid_alive(pid: int) -> bool:
    """True when a process ``pid`` exists on this machine."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _read_lock(path: Path) -> dict:
    try:
        return json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        return {}


_HELD: dict[Path, list] = {}  # this process's locks: resolved dir -> [fd, depth]


class OutputLock:
    """Exclusive use of an output directory by this process (re-entrant within it).

    ``with OutputLock(out):`` takes ``<out>/.rpr-cosim.lock`` (``flock``; the kernel drops it when
    the process dies), writes this process's pid into it and, when the previous holder died
    without releasing it, settles that run's files first (:func:`settle_stale`).  Another live
    run holding it is a :class:`UserError` naming its pid."""

    #: How long a lock whose holder died is waited for (its forked children still hold it) [s].
    GRACE_S = 3.0

    def __init__(self, out_dir: Path, *, log=None):
        self.dir = Path(out_dir)
        self.log = log
        self.notes: list[str] = []

    def __enter__(self) -> OutputLock:
        key = self.dir.resolve()
        if key in _HELD:
            _HELD[key][1] += 1
            return self
        path = key / LOCK_NAME
        deadline = time.monotonic() + self.GRACE_S
        for attempt in range(100):
            fd = _open_lock(path)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise
                if attempt < 3:  # a reader's brief shared lock (:func:`holder`) is not a run
                    time.sleep(0.05)
                    continue
                held = _read_lock(path)
                pid = held.get("pid")
                if isinstance(pid, int) and not pid_alive(pid) and time.monotonic() < deadline:
                    time.sleep(0.05)  # a killed batch's workers hold it until they notice (~0.2 s)
                    continue
                raise UserError(f"output directory {self.dir} is in use by another run (pid {held.get('pid', '?')}"
                                f"{', ' + held['command'] if held.get('command') else ''}, started "
                                f"{held.get('started', '?')}); wait for it to end or choose another --out") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)  # the file was replaced while we waited: take the new one
        else:  # pragma: no cover - would need 100 replacements in a row
            raise UserError(f"output directory {self.dir}: could not take {LOCK_NAME}")
        previous = _read_lock(path)
        if previous.get("pid") and previous.get("pid") != os.getpid():
            self.notes += settle_stale(key, previous)
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                  "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                  "command": " ".join(sys.argv[:3])}).encode(), 0)
        _HELD[key] = [fd, 1]
        for n in self.notes:
            if self.log:
                self.log(n)
        return self

    def __exit__(self, *exc) -> None:
        key = self.dir.resolve()
        entry = _HELD.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] > 0:
            return
        del _HELD[key]
        fd = entry[0]
        try:
            os.ftruncate(fd, 0)
            os.unlink(key / LOCK_NAME)
        except OSError:
            pass
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def _open_lock(path: Path) -> int:
    """The lock file opened (created if needed) without following a symbolic link; a link planted
    under its name is removed (a lock is never a link)."""
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0), 0o644)
    except OSError as exc:
        if exc.errno != errno.ELOOP:
            raise
    os.unlink(path)
    return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0), 0o644)


def holder(out_dir: Path) -> int | None:
    """The pid of the live process holding ``out_dir``'s lock, or None."""
    path = Path(out_dir) / LOCK_NAME
    if not path.exists():
        return None
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return _read_lock(path).get("pid") or -1
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _warn(message: str) -> None:
    import logging

    logging.getLogger("cosim.outputs").warning(message)


def settle_if_stale(out_dir: Path, log=None) -> list[str]:
    """When ``out_dir`` has a lock left by a dead run, settle that run (:func:`settle_stale`) and
    remove the lock; returns the notes (nothing happens in a directory one cannot write)."""
    path = Path(out_dir) / LOCK_NAME
    try:
        if not path.is_file() or not _read_lock(path).get("pid") or holder(out_dir) is not None:
            return []
        with OutputLock(out_dir, log=log or _warn) as lock:
            return lock.notes
    except (OSError, UserError):
        return []


# --- files that cannot be redirected ------------------------------------------------------------
#: Flags of every file a run creates: never through a symbolic link, never an existing file.
NEW_FILE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)


def create_new(path: Path, mode: int = 0o644) -> int:
    """A file descriptor of ``path`` created afresh: whatever was there under that name (an old
    temporary file, a planted symbolic link) is unlinked first, never followed or truncated."""
    path = Path(path)
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except IsADirectoryError:
        raise UserError(f"refusing to write {path}: a directory of that name is in the way") from None
    except OSError as exc:
        if exc.errno in (errno.EISDIR, errno.EPERM) and path.is_dir():
            raise UserError(f"refusing to write {path}: a directory of that name is in the way") from None
        raise
    return os.open(path, NEW_FILE, mode)


def write_bytes(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all: a new temporary file (:func:`create_new`) renamed over
    it (a rename replaces a symbolic link, it never writes through it)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = create_new(tmp)
    try:
        view, done = memoryview(data), 0
        while done < len(data):
            done += os.write(fd, view[done:])
    except BaseException:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    os.close(fd)
    os.replace(tmp, path)


def write_text(path: Path, text: str) -> None:
    """:func:`write_bytes` of UTF-8 ``text``."""
    write_bytes(path, text.encode())


# --- temporary names and placement --------------------------------------------------------------
def part_path(path: Path) -> Path:
    """The temporary name a file is written under until its run ends: ``.<name>.part``."""
    path = Path(path)
    return path.with_name(f".{path.name}.part")


def final_path(part: Path) -> Path:
    """Inverse of :func:`part_path`."""
    name = part.name
    return part.with_name(name[1:-len(".part")])


def _head(path: Path, n: int = 4 << 20) -> bytes | None:
    """The first ``n`` bytes of ``path`` (None when absent; b"" for a link or an unreadable file)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except FileNotFoundError:
        return None
    except OSError:
        return b""
    with os.fdopen(fd, "rb") as fh:
        return fh.read(n)


def check_ours(trace: Path) -> None:
    """:class:`UserError` when a run's trace ``trace`` or its sidecar would replace a file that is
    not an rpr-cosim trace or sidecar (a batch's ``results.csv`` or ``batch.json``, a study's table,
    anything else): a run only ever replaces its own earlier outputs.  A trace is ours when it
    says so (a commented CSV) or its sidecar does (a plain CSV, Parquet)."""
    trace = Path(trace)
    side = trace.with_suffix(".json")
    side_head = _head(side)
    side_ours = side_head is not None and b'"format": "rpr-cosim trace' in side_head
    for path, head, ours in ((trace, _head(trace, 64), None), (side, side_head, side_ours)):
        if head is None:
            continue
        if ours is None:
            ours = head.startswith(b"# rpr-cosim trace") or (side_ours and not path.is_symlink())
        if not ours:
            raise UserError(f"refusing to replace {path}: it is not an rpr-cosim trace (another tool's file, or a "
                            f"batch's or study's own); choose another --out or another scene name")


@contextmanager
def staged(final: Path) -> Iterator[Path]:
    """A path to write ``final`` under (``.<stem>.part<suffix>``, created afresh by
    :func:`create_new`, the suffix kept for writers that go by it) that is moved into place when
    the block ends normally; after an exception (a signal) it is removed and an earlier
    ``final`` stays as it was."""
    final = Path(final)
    part = final.with_name(f".{final.stem}.part{final.suffix}")
    os.close(create_new(part))
    try:
        yield part
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    os.replace(part, final)


def amend_status(trace: Path, status: str, reason: str) -> None:
    """Give a finished run (trace ``<out>/<name>.csv`` and its sidecar) a new final ``status`` and
    ``reason`` (e.g. an animation interrupted after the run): status lines appended to the trace,
    the sidecar rewritten (:func:`write_text`)."""
    trace = Path(trace)
    if (_head(trace, 1) or b"") == b"#":  # a commented CSV carries its status too; other formats: the sidecar
        fd = os.open(trace, os.O_WRONLY | os.O_APPEND | os.O_NOFOLLOW)
        with os.fdopen(fd, "a") as fh:
            fh.write(f"# status: {json.dumps(status)}\n# reason: {json.dumps(reason)}\n")
    side = trace.with_suffix(".json")
    data = _json_file(side)
    data = data if isinstance(data, dict) else {}
    data.update(status=status, reason=reason)
    write_text(side, json.dumps(data, indent=2))


def prev_path(path: Path) -> Path:
    """Where a good earlier file of the same name is kept: ``<stem>.prev<suffix>``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.prev{path.suffix}")


def _status_of(sidecar: Path) -> str:
    data = _json_file(sidecar)
    return str(data.get("status", "")) if isinstance(data, dict) else ""


def _json_file(path: Path):
    """The JSON of a sidecar or lock file, or None when it is missing, not a regular file, too
    large, too deeply nested or not JSON (:mod:`cosim.readers`)."""

    try:
        return read_json(path, "sidecar")
    except UserError:
        return None


#: What a run named N writes into its output directory besides its trace: the files of one run's
#: set (``N`` + each ending).  A rerun replaces the whole set or keeps it whole (:func:`place`).
RUN_SET_ENDINGS = (".csv", ".parquet", ".npy", ".json", ".png", ".gif", ".html", "_reference.csv",
                   "_reference.parquet", "_reference.npy", "_reference.json", "_vs_reference.png")
#: Suffixes of trace files (:data:`cosim.trace.traces.TRACE_FORMATS`).
TRACE_SUFFIXES = (".csv", ".parquet", ".npy")
#: Bytes of an ``.npy`` trace's header (magic, version, length, the header dict padded with
#: blanks): fixed, so that the row count can be written over it when the run ends.
NPY_HEADER_BYTES = 128


def check_set(out_dir: Path, stem: str) -> None:
    """:class:`UserError` when a name of the run set ``stem`` (:data:`RUN_SET_ENDINGS`), or of
    the ``.prev`` set an earlier run moves to, is a directory: the run could neither replace it
    nor move it aside (:func:`place`), and would fail after writing its trace.  Checked before
    the run writes anything."""
    out_dir = Path(out_dir)
    for s in (stem, f"{stem}.prev"):
        for ending in RUN_SET_ENDINGS:
            path = out_dir / f"{s}{ending}"
            if path.is_dir() and not path.is_symlink():
                raise UserError(f"{path} is a directory, where a run of {stem!r} keeps a file of its own; remove or "
                                f"rename it, or choose another --out")


def npy_header(rows: int, cols: int) -> bytes:
    """The header of an ``.npy`` trace (NumPy format 1.0) of ``rows`` x ``cols`` float64 values,
    little-endian, C order, :data:`NPY_HEADER_BYTES` long."""
    text = f"{{'descr': '<f8', 'fortran_order': False, 'shape': ({int(rows)}, {int(cols)}), }}"
    room = NPY_HEADER_BYTES - 10
    return b"\x93NUMPY\x01\x00" + room.to_bytes(2, "little") + text.ljust(room - 1).encode("latin1") + b"\n"


def trim_npy(path: Path, cols: int) -> int:
    """Cut an ``.npy`` trace left by a dead run to whole rows of ``cols`` values and write their
    count into its header; returns the rows kept."""
    size = path.stat().st_size
    rows = max(0, size - NPY_HEADER_BYTES) // (8 * max(1, cols))
    with os.fdopen(os.open(path, os.O_RDWR | os.O_NOFOLLOW), "rb+") as fh:
        fh.truncate(NPY_HEADER_BYTES + 8 * cols * rows)
        fh.seek(0)
        fh.write(npy_header(rows, cols))
    return rows


def run_set(out_dir: Path, stem: str) -> list[Path]:
    """The files of the run named ``stem`` in ``out_dir`` (:data:`RUN_SET_ENDINGS`) that exist."""
    out_dir = Path(out_dir)
    return [out_dir / f"{stem}{e}" for e in RUN_SET_ENDINGS if os.path.lexists(out_dir / f"{stem}{e}")]


def place(part: Path, final: Path, status: str, *, part_sidecar: Path | None = None,
          sidecar: Path | None = None) -> str:
    """Move a finished trace ``part`` (and its sidecar) to ``final``; returns a note saying what
    happened to the earlier run of that name ("" when there was none).

    Policy: the name always holds the latest run, and a directory holds whole runs, never a mix
    of two (a new trace beside an older run's plot, report or reference).  The earlier run's set
    (:func:`run_set`: trace, sidecar, plot, animation, report, reference) moves whole to
    ``<stem>.prev.*`` when its sidecar says "ok" (replacing the older ``.prev`` set whole);
    a set that was not ok is removed, so a good ``.prev`` set from before it stays.  A failing
    rerun therefore never destroys the last good run, and the note says where it is."""
    note = ""
    final = Path(final)
    stem, folder = final.stem, final.parent
    earlier = run_set(folder, stem)
    if earlier:
        side = sidecar if sidecar is not None else final.with_suffix(".json")
        old_status = _status_of(side) if side.exists() else ""
        trace = next((p for p in earlier if p.suffix in TRACE_SUFFIXES and p.stem == stem), final)
        others = len([p for p in earlier if p not in (trace, final.with_suffix(".json"))])
        if old_status == "ok":
            for old in run_set(folder, f"{stem}.prev"):
                old.unlink()
            for old in earlier:
                os.replace(old, folder / f"{stem}.prev{old.name[len(stem):]}")
            note = (f"kept the earlier good trace as {prev_path(trace).name}"
                    + ("" if status == "ok" else f" (this run is {status})")
                    + (f"; its run's {others} other file{'s' if others != 1 else ''} too, as {stem}.prev.*"
                       if others > 0 else ""))
        else:
            for old in earlier:
                old.unlink()
            note = (f"replaced the earlier trace {trace.name} (its status was {old_status or 'unknown'})"
                    + (f"; its run's {others} other file{'s' if others != 1 else ''} removed" if others > 0 else ""))
    os.replace(part, final)
    if part_sidecar is not None and part_sidecar.exists() and sidecar is not None:
        os.replace(part_sidecar, sidecar)
    return note


def trim_to_whole_rows(path: Path) -> int:
    """Cut a file after its last newline (a row cut by a crash goes); returns the bytes removed."""
    size = path.stat().st_size
    if size == 0:
        return 0
    with os.fdopen(os.open(path, os.O_RDWR | os.O_NOFOLLOW), "rb+") as fh:
        back = min(size, 1 << 16)
        fh.seek(size - back)
        tail = fh.read(back)
        cut = tail.rfind(b"\n")
        keep = size - back + cut + 1 if cut >= 0 else (0 if back == size else size)
        if keep < size:
            fh.truncate(keep)
        return size - keep


def settle_stale(out_dir: Path, previous: dict | None = None) -> list[str]:
    """Finish the files a dead run left in ``out_dir``: every ``.<name>.json.part`` (or sidecar)
    still saying "running" is marked "killed" with a reason, its trace is trimmed to whole rows,
    given the status lines and moved into place (:func:`place`).  Returns one note per run."""
    out_dir = Path(out_dir)
    who = f"pid {previous['pid']}" if previous and previous.get("pid") else "its process"
    notes = []
    for side in sorted(out_dir.glob(".*.json.part")) + sorted(out_dir.glob("*.json")):
        data = _json_file(side)
        if not isinstance(data, dict) or data.get("status") != "running":
            continue
        pid = data.get("pid") if isinstance(data.get("pid"), int) and data.get("pid") > 0 else None
        if pid and pid != os.getpid() and pid_alive(pid) and holder(out_dir) == pid:
            continue
        reason = (f"killed: the run ({who}) ended without finishing (SIGKILL, power loss or crash); "
                  f"found by pid {os.getpid()} at {time.strftime('%Y-%m-%dT%H:%M:%S%z')}")
        rows, moved = _settle_side(out_dir, side, data, "killed", reason)
        final_side = final_path(side) if side.name.endswith(".part") else side
        note = f"{out_dir / final_side.name}: an earlier run was killed; marked \"killed\" ({rows} whole rows kept)"
        notes.append(note + (f"; {moved}" if moved else ""))
    return notes


def _settle_side(out_dir: Path, side: Path, data: dict, status: str, reason: str) -> tuple[int, str]:
    """Give the run of sidecar ``side`` (its JSON ``data``) its final ``status`` and ``reason``:
    the trace cut to whole rows, the status lines appended, both moved into place.  Returns the
    rows kept and :func:`place`'s note."""
    trace_name = data.get("trace") or ""
    if not isinstance(trace_name, str) or Path(trace_name).name != trace_name or trace_name.startswith(".") \
            or Path(trace_name).suffix not in TRACE_SUFFIXES:
        trace_name = ""  # a name read from a sidecar is data: only a plain trace name beside it counts
    final_side = final_path(side) if side.name.endswith(".part") else side
    csv_final = out_dir / trace_name if trace_name else final_side.with_suffix(".csv")
    csv_part = part_path(csv_final)
    csv_now = csv_part if csv_part.exists() else csv_final
    rows = 0
    columns = data.get("columns")
    if csv_now.exists() and csv_final.suffix == ".npy" and isinstance(columns, list) and columns:
        rows = trim_npy(csv_now, len(columns))
    elif csv_now.exists() and csv_final.suffix == ".csv":  # a Parquet trace without its footer stays as it is
        trim_to_whole_rows(csv_now)
        with os.fdopen(os.open(csv_now, os.O_RDONLY | os.O_NOFOLLOW), "rb") as fh:
            commented = fh.read(1) == b"#"
        if commented:  # a plain CSV keeps one header line and rows: the status is in the sidecar
            fd = os.open(csv_now, os.O_WRONLY | os.O_APPEND | os.O_NOFOLLOW)
            with os.fdopen(fd, "a") as fh:
                fh.write(f"# status: {json.dumps(status)}\n# reason: {json.dumps(reason)}\n")
        with open(csv_now) as fh:
            rows = max(0, sum(1 for ln in fh if ln.strip() and not ln.startswith("#")) - 1)
    data.update(status=status, reason=reason, rows=rows)
    write_text(side, json.dumps(data, indent=2))
    moved = ""
    if csv_now == csv_part:
        moved = place(csv_part, csv_final, status, part_sidecar=side, sidecar=final_side)
    return rows, moved


def settle_run(trace: Path, status: str, reason: str) -> tuple[int, str] | None:
    """Finish the run whose trace is ``trace`` (``<out>/<name>.csv``) when its process died while
    it was running (a supervised run, :mod:`cosim.run.supervise`): the same as
    :func:`settle_stale` with the supervisor's ``status`` and ``reason``.  Returns (rows kept,
    placement note), or None when that run left no sidecar saying "running"."""
    trace = Path(trace)
    for side in (part_path(trace.with_suffix(".json")), trace.with_suffix(".json")):
        data = _json_file(side)
        if isinstance(data, dict) and data.get("status") == "running":
            return _settle_side(trace.parent, side, data, status, reason)
    return None
