"""The content-addressed FMU cache.

An FMU lives at ``<root>/<key>/<model identifier>.fmu`` beside a ``build.json`` record, where
``key`` hashes the generated C, the ``modelDescription.xml``, the exporter version, the compiler
and its flags: the same block always maps to the same file, and any change to the equations,
parameter defaults, integrator or exporter gives a new one.  Builds write into a private temporary
directory under the root and move the finished file into place with an atomic rename, so
concurrent builds of the same block (threads, processes, batch workers) are safe.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

#: Bump when the C core, the wrapper conventions or the generated layout change meaning.
EXPORTER_VERSION = "1.1"
ENV_VAR = "RPR_COSIM_CACHE"
KEY_LENGTH = 24


def cache_root(cache_dir: Path | str | None = None, *, create: bool = True) -> Path:
    """``cache_dir``, else ``$RPR_COSIM_CACHE``, else ``~/.cache/rpr-cosim/fmus`` (created when
    possible and ``create``; a root that cannot be created is returned as is: reading it finds
    nothing)."""
    if cache_dir is not None:
        root = Path(cache_dir)
    elif os.environ.get(ENV_VAR):
        root = Path(os.environ[ENV_VAR])
    else:
        root = Path.home() / ".cache" / "rpr-cosim" / "fmus"
    if not create:
        return root
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:
        pass
    return root


def temporary_root() -> Path:
    """The fallback cache when the configured one cannot be written: one per user, in the
    system's temporary directory."""
    root = Path(tempfile.gettempdir()) / f"rpr-cosim-fmus-{os.getuid() if hasattr(os, 'getuid') else 'user'}"
    root.mkdir(parents=True, exist_ok=True)
    return root


_WARNED: set[str] = set()


def writable_root(root: Path, warn=None) -> Path:
    """``root`` when new entries can be written there, else :func:`temporary_root` (with a
    one-line warning through ``warn``)."""
    try:
        root.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=root, prefix=".probe-").close()
        return root
    except OSError as exc:
        tmp = temporary_root()
        if warn and str(root) not in _WARNED:
            _WARNED.add(str(root))
            warn(f"warning: the FMU cache {root} is not writable ({exc.strerror or exc}); "
                 f"building into the temporary cache {tmp} instead")
        return tmp


def stream_digest(read: Callable[[int], bytes]) -> str:
    """SHA-256 (hex) of what ``read(n)`` returns, 1 MiB at a time, until it returns nothing."""
    h = hashlib.sha256()
    while block := read(1 << 20):
        h.update(block)
    return h.hexdigest()


def file_digest(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    with open(path, "rb") as fh:
        return stream_digest(fh.read)


def verify(fmu: Path) -> str:
    """Why the cached ``fmu`` cannot be served ("" when it is intact): its size and SHA-256 must
    match those recorded in ``build.json`` at build time.  An entry from before hashes were
    recorded is checked as a zip (every member's CRC) and, when intact, given its hash."""
    import zipfile

    fmu = Path(fmu)
    rec = build_record(fmu)
    try:
        size = fmu.stat().st_size
    except OSError as exc:
        return f"cannot read it ({exc.strerror or exc})"
    if not rec:
        return "its build record (build.json) is missing or unreadable"
    if rec.get("fmu_bytes") is not None and rec["fmu_bytes"] != size:
        return f"it is {size} bytes, the build recorded {rec['fmu_bytes']}"
    if rec.get("fmu_sha256"):
        return "" if file_digest(fmu) == rec["fmu_sha256"] else "its SHA-256 differs from the one recorded at build"
    try:
        with zipfile.ZipFile(fmu) as z:
            bad = z.testzip()
    except (OSError, zipfile.BadZipFile) as exc:
        return f"it is not a readable zip ({exc})"
    if bad is not None:
        return f"its member {bad} is corrupt"
    try:  # an entry from an older build: record its hash now
        atomic_write(fmu.with_name("build.json"), json.dumps(dict(rec, fmu_sha256=file_digest(fmu)), indent=2).encode())
    except OSError:
        pass
    return ""


def content_key(parts: Iterable[tuple[str, str | bytes]]) -> str:
    """SHA-256 (hex) over named parts, order-independent."""
    h = hashlib.sha256()
    for name, data in sorted(parts, key=lambda kv: kv[0]):
        raw = data.encode() if isinstance(data, str) else data
        h.update(name.encode() + b"\0" + len(raw).to_bytes(8, "little") + raw)
    return h.hexdigest()


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def build_record(fmu: Path) -> dict:
    """The ``build.json`` record written beside a cached FMU (empty if there is none)."""
    rec = Path(fmu).with_name("build.json")
    try:
        return json.loads(rec.read_text())
    except (OSError, ValueError):
        return {}


def cached_fmus(cache_dir: Path | str | None = None) -> list[tuple[Path, dict]]:
    """Every FMU in the cache with its build record, newest first."""
    root = cache_root(cache_dir)
    found = [(p, build_record(p)) for p in root.glob("*/*.fmu")]
    return sorted(found, key=lambda pr: pr[0].stat().st_mtime, reverse=True)
