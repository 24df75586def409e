"""Compiling C at run time: a C source compiled once per source, compiler and flags, cached on
disk beside the FMU cache (``<cache root>/../master/<stem>_<hash>.so``, where the master loop's
library has always been kept; never committed) and loaded with ctypes.

The compiled master loops (:mod:`cosim.master.fastloop`, :mod:`cosim.master.adaptive_engine`,
:mod:`cosim.master.iterative_engine`) and the trace writer's number formatter
(:mod:`cosim.trace.text`) are built here, with the compiler the FMUs are built with
(:func:`fmus.compile.compiler`).  ``-std=c99`` keeps ``-ffp-contract=off`` (no fused
multiply-add), which the compiled loops need to agree bit for bit with their Python references.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from .compile import compiler, compiler_identity, compiler_version
from .errors import BuildError

#: Flags of every run-time library (part of the cache key).
FLAGS = ("-O2", "-shared", "-fPIC", "-std=c99", "-D_POSIX_C_SOURCE=199309L")


class NoCompiler(BuildError):
    """No working C compiler; the message is ``<compiler>: <why>``."""


def _cache_dir() -> Path:
    from .cache import cache_root

    return cache_root().parent / "master"


def _toolchain() -> tuple[str, str]:
    """The compiler and the key part that identifies it (path, size, time, version)."""
    try:
        cc = compiler()
    except BuildError:
        raise NoCompiler(f"{os.environ.get('CC') or 'gcc'}: not found") from None
    try:
        version = compiler_version(cc)
    except BuildError as exc:
        raise NoCompiler(f"{cc}: {exc}") from None
    return cc, f"{compiler_identity()}\n{version}"


def library_path(source: str, stem: str, flags: tuple[str, ...] = FLAGS, libs: tuple[str, ...] = ()) -> Path:
    """Where :func:`load` keeps the library of ``source`` (built if missing; ``libs``: linker
    arguments after the source, e.g. ``-lsundials_cvodes``).  Raises
    :class:`NoCompiler` without a working compiler, :class:`BuildError` (the compiler's log, 500
    characters) when the source does not compile."""
    cc, ident = _toolchain()
    key = hashlib.sha256("\0".join([source, ident, " ".join(flags), sys.platform]
                                   + ([" ".join(libs)] if libs else [])).encode()).hexdigest()[:20]
    from .cache import writable_root

    root = _cache_dir()
    if not (root / f"{stem}_{key}.so").exists():
        fallback = writable_root(root)
        root = fallback if fallback == root else fallback / "master"
        root.mkdir(parents=True, exist_ok=True)
    lib = root / f"{stem}_{key}.so"
    if not lib.exists():
        with tempfile.TemporaryDirectory(dir=root) as tmp:
            src = Path(tmp) / f"{stem}.c"
            src.write_text(source)
            out = Path(tmp) / lib.name
            try:
                res = subprocess.run([cc, *flags, "-o", str(out), str(src), *libs, "-lm"], capture_output=True, text=True)
            except OSError as exc:
                raise NoCompiler(f"{cc}: {exc}") from None
            if res.returncode != 0:
                raise BuildError(res.stderr.strip()[:500])
            os.replace(out, lib)  # atomic: concurrent builders of the same key agree
    return lib


def load(source: str, stem: str, flags: tuple[str, ...] = FLAGS) -> ctypes.CDLL:
    """Compile ``source`` (once per source, compiler and flags; cached on disk) and load it."""
    return ctypes.CDLL(str(library_path(source, stem, flags)))


__all__ = ["FLAGS", "NoCompiler", "library_path", "load"]
