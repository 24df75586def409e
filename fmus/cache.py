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
from collections.abc import Iterable
from pathlib import Path

#: Bump when the C core, the wrapper conventions or the generated layout change meaning.
EXPORTER_VERSION = "1.1"
ENV_VAR = "RPR_COSIM_CACHE"
KEY_LENGTH = 24


def cache_root(cache_dir: Path | str | None = None) -> Path:
    """``cache_dir``, else ``$RPR_COSIM_CACHE``, else ``~/.cache/rpr-cosim/fmus`` (created)."""
    if cache_dir is not None:
        root = Path(cache_dir)
    elif os.environ.get(ENV_VAR):
        root = Path(os.environ[ENV_VAR])
    else:
        root = Path.home() / ".cache" / "rpr-cosim" / "fmus"
    root.mkdir(parents=True, exist_ok=True)
    return root


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
