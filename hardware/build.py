"""Programs and libraries of the rig built from C for this machine or a cross target, cached by
content beside the FMUs (:mod:`fmus.cache`), compiled by :mod:`fmus.compile`.

An entry lives at ``<cache root>/<key>/<name>`` with a ``build.json`` record, where ``key``
hashes the sources, the target, the compiler's version and the flags: the same sources always
map to the same file.  Builds go to a private temporary directory and are moved into place with
an atomic rename, so concurrent builds (test workers, two shells) are safe.
"""
from __future__ import annotations

import json
import logging
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Mapping

from fmus.cache import KEY_LENGTH, atomic_write, cache_root, content_key, file_digest, writable_root
from fmus.compile import CFLAGS, LDFLAGS, PROGRAM_CFLAGS, compile_library, compile_program, compiler, compiler_version

log = logging.getLogger("hardware.build")
#: Bump when the build's conventions change meaning.
BUILD_VERSION = "1"


def build_program(name: str, files: Mapping[str, str], sources: list[str], *, target: str = "host",
                  static: bool = False, library: bool = False, cache_dir: Path | None = None,
                  progress: Callable[[str], None] | None = None) -> Path:
    """The program (or, with ``library``, shared library) ``name`` compiled from ``files``
    (name -> text; ``sources`` are compiled, the rest are headers) for ``target``; cached."""
    say = progress or log.info
    cc = compiler(target)
    flags = " ".join((CFLAGS + LDFLAGS) if library else PROGRAM_CFLAGS) + (" -static" if static else "")
    key = content_key([("version", BUILD_VERSION), ("target", target), ("flags", flags), ("kind", str(library)),
                       ("cc", compiler_version(cc)), *((f"src/{n}", t) for n, t in files.items())])
    root = cache_root(cache_dir)
    target_path = root / f"{name}-{key[:KEY_LENGTH]}" / name
    if target_path.is_file():
        return target_path
    root = writable_root(root, say)
    target_path = root / f"{name}-{key[:KEY_LENGTH]}" / name
    t0 = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=".build-"))
    try:
        for n, text in files.items():
            (tmp / n).write_text(text)
        out = tmp / name
        if library:
            compile_library(tmp, sources, out, block_name=name, target=target)
        else:
            compile_program(tmp, sources, out, name=name, target=target, static=static)
        target_path.parent.mkdir(parents=True, exist_ok=True)
        rec = {"program": name, "target": target, "static": static, "library": library, "key": key,
               "compiler": compiler_version(cc), "compile_s": round(time.perf_counter() - t0, 4),
               "sha256": file_digest(out), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        atomic_write(target_path.with_name("build.json"), json.dumps(rec, indent=2).encode())
        out.chmod(0o755)
        out.replace(target_path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    say(f"{name}: built for {target} in {time.perf_counter() - t0:.2f} s ({target_path})")
    return target_path
