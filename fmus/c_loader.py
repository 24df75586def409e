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
from collections.abc import Mapping
from pathlib import Path

from .compile import compiler, compiler_identity, compiler_version
from .errors import BuildError

#: Flags of every run-time library (part of the cache key); its C is kept free of warnings
#: (``tests/test_native.py`` compiles it with ``-Werror``).
FLAGS = ("-O2", "-shared", "-fPIC", "-std=c99", "-D_POSIX_C_SOURCE=199309L", "-Wall", "-Wextra")


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


def _files(source: str | Mapping[str, str], stem: str) -> dict[str, str]:
    return {f"{stem}.c": source} if isinstance(source, str) else dict(source)


def library_path(source: str | Mapping[str, str], stem: str, flags: tuple[str, ...] = FLAGS,
                 libs: tuple[str, ...] = ()) -> Path:
    """Where :func:`load` keeps the library of ``source`` (built if missing): one C text, or
    files (name -> text) whose ``.c`` files are compiled together, their headers beside them;
    ``libs``: linker arguments after the sources (e.g. ``-lsundials_cvodes``).
    Raises :class:`NoCompiler` without a working compiler, :class:`BuildError` (the compiler's
    log, 500 characters) when the source does not compile."""
    cc, ident = _toolchain()
    files = _files(source, stem)
    text = "\0".join(f"{name}\0{files[name]}" for name in sorted(files))
    key = hashlib.sha256("\0".join([text, ident, " ".join(flags), sys.platform]
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
            for name, body in files.items():
                (Path(tmp) / name).write_text(body)
            sources = [str(Path(tmp) / name) for name in sorted(files) if name.endswith(".c")]
            out = Path(tmp) / lib.name
            try:
                res = subprocess.run([cc, *flags, f"-I{tmp}", "-o", str(out), *sources, *libs, "-lm"],
                                     capture_output=True, text=True)
            except OSError as exc:
                raise NoCompiler(f"{cc}: {exc}") from None
            if res.returncode != 0:
                raise BuildError(res.stderr.strip()[:500])
            os.replace(out, lib)  # atomic: concurrent builders of the same key agree
    return lib


def load(source: str | Mapping[str, str], stem: str, flags: tuple[str, ...] = FLAGS) -> ctypes.CDLL:
    """Compile ``source`` (one C text or files, see :func:`library_path`; once per source,
    compiler and flags; cached on disk) and load it."""
    return ctypes.CDLL(str(library_path(source, stem, flags)))


__all__ = ["FLAGS", "NoCompiler", "library_path", "load"]
