"""``build_fmu``: check, generate, hash, compile (on a cache miss) and pack one FMU."""
from __future__ import annotations

import json
import logging
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Mapping
from pathlib import Path

from models.block import Block

from . import codegen
from .cache import (EXPORTER_VERSION, KEY_LENGTH, atomic_write, cache_root, content_key, file_digest, verify,
                    writable_root)
from .compile import (CFLAGS, LDFLAGS, compile_library, compiler, compiler_version, exported_symbols,
                      large_functions_at_o1, library_suffix, optimisation, pack, platform_dirs)
from .errors import BuildError
from .model_description import build_description, model_description

log = logging.getLogger(__name__)

_PLACEHOLDER = "{00000000-0000-0000-0000-000000000000}"
_VERSIONS = {"2": "2.0", "2.0": "2.0", "3": "3.0", "3.0": "3.0"}


def _normalise_version(fmi_version: str) -> str:
    v = _VERSIONS.get(str(fmi_version).strip())
    if v is None:
        raise BuildError(f"fmi_version {fmi_version!r} is not supported; expected '2.0' or '3.0'")
    return v


def build_fmu(block: Block, *, fmi_version: str = "2.0", cache_dir: Path | None = None,
              params: Mapping[str, float] | None = None,
              progress: Callable[[str], None] | None = None) -> Path:
    """Return the path of a compiled co-simulation FMU of ``block`` (built on a cache miss).

    Parameters
    ----------
    block : the component; it is checked before any C is generated (:func:`fmus.codegen.check_block`).
    fmi_version : ``"2.0"`` (default) or ``"3.0"``.
    cache_dir : cache root; default ``$RPR_COSIM_CACHE`` or ``~/.cache/rpr-cosim/fmus``.
    params : overrides of parameter defaults, i.e. the FMU's parameter start values.
    progress : called with one-line progress messages (default: the ``fmus.build`` logger).

    Raises :class:`BuildError` for a malformed block or a failed compilation.  The build record
    (times in seconds, sizes) is in ``build.json`` beside the FMU (:func:`fmus.build_record`).
    """
    say = progress or log.info
    version = _normalise_version(fmi_version)
    t0 = time.perf_counter()
    blk = codegen.with_parameters(block, params)
    stepper = codegen.check_block(blk)
    ident = codegen.model_identifier(blk)
    gen = codegen.generate(blk, stepper, guid=_PLACEHOLDER, ident=ident)
    static = codegen.static_sources(version)
    files = {**gen.files, **static}
    c_sources = ["rpr_casadi.c", "rpr_core.c", codegen.WRAPPERS[version]]
    xml = model_description(gen.iface, fmi_version=version, guid=_PLACEHOLDER, model_identifier=ident,
                            sources=c_sources)
    code, at_o1 = large_functions_at_o1(files["rpr_casadi.c"])  # a huge function at -O1, the rest at -O2
    files["rpr_casadi.c"] = code
    opt = "-O2" if at_o1 else optimisation(len(code))
    t_gen = time.perf_counter() - t0
    c_bytes = len(files["rpr_casadi.c"])
    record = {"block": blk.name, "fidelity": blk.fidelity, "integrator": blk.integrator, "substeps": blk.substeps,
              "states": len(blk.states), "inputs": len(blk.inputs), "outputs": len(blk.outputs),
              "parameters": {p.name: p.default for p in blk.params}, "codegen_s": round(t_gen, 4),
              "functions_at_o1": at_o1,
              "c_bytes": c_bytes}
    return build_from_sources(ident, files, c_sources, xml, fmi_version=version, cache_dir=cache_dir, opt=opt,
                              record=record, progress=say, label=blk.name,
                              announce=f"generated {c_bytes / 1024:.0f} kB of C in {t_gen:.2f} s; compiling",
                              t_start=t0)


def build_from_sources(ident: str, files: Mapping[str, str], c_sources: list[str], xml: str, *,
                       fmi_version: str = "2.0", cache_dir: Path | None = None, opt: str = "-O2",
                       record: Mapping | None = None, progress: Callable[[str], None] | None = None,
                       label: str | None = None, announce: str = "compiling", t_start: float | None = None) -> Path:
    """Compile hand-written or generated C ``files`` (name -> text; ``c_sources`` are compiled,
    the rest are headers) with ``xml`` as ``modelDescription.xml`` into a cached FMU.

    The GUID placeholder ``{00000000-0000-0000-0000-000000000000}`` in the files and the XML is
    replaced by a GUID derived from the content key, so the same sources give the same FMU path
    and any change a new one.  ``record`` is added to ``build.json``.  Raises :class:`BuildError`."""
    say = progress or log.info
    t0 = time.perf_counter() if t_start is None else t_start
    version = _normalise_version(fmi_version)
    label = label or ident
    cc = compiler()
    key = content_key([("exporter", EXPORTER_VERSION), ("fmi", version), ("cflags", " ".join((opt, *CFLAGS))),
                       ("ldflags", " ".join(LDFLAGS)), ("cc", compiler_version(cc)), ("xml", xml),
                       *((f"src/{n}", t) for n, t in files.items())])
    guid = "{" + str(uuid.UUID(key[:32])) + "}"
    t_gen = time.perf_counter() - t0
    source_names = sorted(files)
    root = cache_root(cache_dir)
    target = root / key[:KEY_LENGTH] / f"{ident}.fmu"
    if not target.exists():
        fallback = writable_root(root, say)
        if fallback != root:
            root, target = fallback, fallback / key[:KEY_LENGTH] / f"{ident}.fmu"
    if target.exists():
        damage = verify(target)
        if not damage:
            say(f"{ident}: FMI {version} FMU up to date ({target}), checked in {time.perf_counter() - t0:.2f} s")
            return target
        say(f"{ident}: the cached FMU {target} is damaged ({damage}); rebuilding it")
        root = writable_root(root, say)
        target = root / key[:KEY_LENGTH] / f"{ident}.fmu"
    say(f"{ident}: {announce} (FMI {version})")
    files = {n: t.replace(_PLACEHOLDER, guid) for n, t in files.items()}
    xml = xml.replace(_PLACEHOLDER, guid)
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=".build-"))
    try:
        for name, text in files.items():
            (tmp / name).write_text(text)
        lib = tmp / f"{ident}{library_suffix()}"
        t1 = time.perf_counter()
        compile_library(tmp, c_sources, lib, block_name=label, opt=opt)
        t_cc = time.perf_counter() - t1
        prefix = "fmi2" if version == "2.0" else "fmi3"
        leaked = [s for s in exported_symbols(lib) if not s.startswith(prefix) and not s.startswith("_")]
        if leaked:
            raise BuildError(f"block {label}: the library exports non-FMI symbols ({', '.join(leaked[:5])})")
        plat2, plat3 = platform_dirs()
        plat = plat2 if version == "2.0" else plat3
        members: dict[str, bytes] = {"modelDescription.xml": xml.encode(),
                                     f"binaries/{plat}/{lib.name}": lib.read_bytes()}
        for name in source_names:
            members[f"sources/{name}"] = files[name].encode()
        if version == "3.0":
            members["sources/buildDescription.xml"] = build_description(ident, c_sources).encode()
        out = tmp / f"{ident}.fmu"
        pack(out, members)
        target.parent.mkdir(parents=True, exist_ok=True)
        total = time.perf_counter() - t0
        rec = {"block": label, **dict(record or {}), "model_identifier": ident, "fmi_version": version, "guid": guid,
               "key": key, "exporter_version": EXPORTER_VERSION, "compile_s": round(t_cc, 4),
               "total_s": round(total, 4), "optimisation": opt, "fmu_bytes": out.stat().st_size,
               "fmu_sha256": file_digest(out), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        atomic_write(target.with_name("build.json"), json.dumps(rec, indent=2).encode())
        out.replace(target)  # atomic: a concurrent build of the same key writes the same bytes
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    say(f"{ident}: built {target.name} in {total:.2f} s (C generation {t_gen:.2f} s, compile {t_cc:.2f} s)")
    return target
