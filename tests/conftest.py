"""Shared session fixtures.

``reference_fmus``: the Modelica Reference FMUs (FMI 2.0 and 3.0 co-simulation), built once from
their source with CMake and gcc into a cache directory keyed by a hash of that source (the
source tree is only read).  A failing build fails the tests that need it; a missing source tree
skips them, except under CI (``CI`` set), where it fails too.
"""
from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

import oracles

# the Python twins of the compiled kernels, as master.engine: oracle (tests/oracles)
oracles.register()

# One BLAS thread: the suite's matrices are tiny, and OpenBLAS's thread pool on a loaded two-core
# machine made scipy.linalg.expm of a 2x2 matrix take ~20 ms instead of ~0.1 ms (measured).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

#: where the Reference FMUs' source lives (override with $RPR_REFERENCE_FMUS_SRC)
REFERENCE_FMUS_SRC = Path(os.environ.get("RPR_REFERENCE_FMUS_SRC", Path(__file__).resolve().parents[1].parent
                                         / "shared" / "third_party" / "Reference-FMUs"))


def _source_key(src: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(src.rglob("*")):
        if p.is_file() and ".git" not in p.parts:
            h.update(str(p.relative_to(src)).encode() + b"\0" + p.read_bytes())
    for tool in ("cmake", os.environ.get("CC", "gcc")):
        try:
            h.update(subprocess.run([tool, "--version"], capture_output=True, text=True).stdout.encode())
        except OSError:
            pass
    return h.hexdigest()[:16]


def build_reference_fmus(src: Path, dest: Path) -> dict[str, Path]:
    """Build the Reference FMUs of ``src`` for FMI 2.0 and 3.0 into ``dest`` (unless already
    there); returns ``{"2.0/Name": path, "3.0/Name": path}``.  Raises RuntimeError with the build
    log's tail when CMake or the compiler fails."""
    if not dest.is_dir():
        dest.parent.mkdir(parents=True, exist_ok=True)
        arch = {"amd64": "x86_64", "arm64": "aarch64"}.get(platform.machine().lower(), platform.machine())
        with tempfile.TemporaryDirectory(dir=dest.parent, prefix=".build-") as tmp:
            out = Path(tmp) / "fmus"
            for v in (2, 3):
                build = Path(tmp) / f"fmi{v}"
                steps = [["cmake", "-S", str(src), "-B", str(build), f"-DFMI_VERSION={v}",
                          f"-DFMI_ARCHITECTURE={arch}", f"-DCMAKE_INSTALL_PREFIX={build / 'install'}"],
                         ["cmake", "--build", str(build), "--target", "install", "-j2"]]
                for cmd in steps:
                    try:
                        res = subprocess.run(cmd, capture_output=True, text=True)
                    except OSError as exc:
                        raise RuntimeError(f"building the Reference FMUs: {cmd[0]}: {exc}") from None
                    if res.returncode != 0:
                        raise RuntimeError(f"building the Reference FMUs (FMI {v}) failed: {' '.join(cmd)}\n"
                                           f"{(res.stdout + res.stderr)[-3000:]}")
                (out / f"{v}.0").mkdir(parents=True)
                for fmu in (build / "install").glob("*.fmu"):
                    shutil.copy2(fmu, out / f"{v}.0" / fmu.name)
            try:
                os.replace(out, dest)
            except OSError:  # another session finished first: use its build
                if not dest.is_dir():
                    raise
    return {f"{d.name}/{f.stem}": f for d in dest.iterdir() for f in d.glob("*.fmu")}


def build_lag_fmus(src: Path, dest: Path) -> dict[str, Path]:
    """tests/data/me_lag (a first-order lag with an input, model exchange only) built on the
    Reference FMUs' framework of ``src`` (its include/ and src/) with the C compiler into ``dest``:
    ``{"2": Lag.fmu, "2_nostate": ..., "3": ..., "3_nostate": ..., "3cs": ...}`` (``_nostate``: its
    FMU-state capability removed from the XML; ``3cs``: FMI 3.0 co-simulation with event mode).  Raises RuntimeError with the compiler's message."""
    import re
    import zipfile

    lag = Path(__file__).with_name("data") / "me_lag"
    fmus = {}
    for v in ("2", "3"):
        lib = dest / f"Lag{v}.so"
        cmd = [shutil.which(os.environ.get("CC", "gcc")) or "cc", "-shared", "-fPIC", "-O2", f"-DFMI_VERSION={v}",
               "-DDISABLE_PREFIX", f"-I{src / 'include'}", f"-I{lag}", str(src / "src" / f"fmi{v}Functions.c"),
               str(src / "src" / "cosimulation.c"), str(lag / "model.c"), "-o", str(lib)]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"building tests/data/me_lag failed: {res.stderr[-2000:]}")
        xml = (lag / f"FMI{v}.xml").read_text()
        for suffix, text in (("", xml), ("_nostate", re.sub(r'canGetAndSetFMU(s|S)tate="true"',
                                                             r'canGetAndSetFMU\1tate="false"', xml))):
            fmu = dest / f"Lag{v}{suffix}.fmu"
            with zipfile.ZipFile(fmu, "w") as z:
                z.writestr("modelDescription.xml", text)
                z.write(lib, f"binaries/{'linux64' if v == '2' else 'x86_64-linux'}/Lag.so")
            fmus[f"{v}{suffix}"] = fmu
    cs = dest / "Lag3cs.fmu"  # the same FMI 3.0 binary as a co-simulation FMU with event mode (FMI3cs.xml)
    with zipfile.ZipFile(cs, "w") as z:
        z.writestr("modelDescription.xml", (lag / "FMI3cs.xml").read_text())
        z.write(dest / "Lag3.so", "binaries/x86_64-linux/Lag.so")
    fmus["3cs"] = cs
    return fmus


@pytest.fixture(scope="session")
def lag_fmus(tmp_path_factory) -> dict[str, Path]:
    """:func:`build_lag_fmus` once per session (skips without the Reference FMUs' source)."""
    if not (REFERENCE_FMUS_SRC / "src" / "cosimulation.c").is_file():
        pytest.skip(f"the Reference FMUs' source is not at {REFERENCE_FMUS_SRC} (set RPR_REFERENCE_FMUS_SRC)")
    return build_lag_fmus(REFERENCE_FMUS_SRC, tmp_path_factory.mktemp("lag"))


@pytest.fixture(scope="session")
def reference_fmus() -> dict[str, Path]:
    """``{"2.0/BouncingBall": path, "3.0/StateSpace": path, ...}``, built once per source."""
    if not (REFERENCE_FMUS_SRC / "CMakeLists.txt").is_file():
        msg = f"the Reference FMUs' source is not at {REFERENCE_FMUS_SRC} (set RPR_REFERENCE_FMUS_SRC)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    from fmus.cache import cache_root

    dest = cache_root().parent / "reference-fmus" / _source_key(REFERENCE_FMUS_SRC)
    try:
        return build_reference_fmus(REFERENCE_FMUS_SRC, dest)
    except RuntimeError as exc:
        pytest.fail(str(exc))


@pytest.fixture(scope="session")
def cache(tmp_path_factory) -> Path:
    """One FMU cache directory for the whole session (each FMU is built once and shared)."""
    return tmp_path_factory.getbasetemp() / "fmu-cache"


@pytest.fixture(scope="session")
def dask_scheduler():
    """One Dask LocalCluster for the session: two single-threaded worker processes."""
    dask = pytest.importorskip("dask")
    distributed = pytest.importorskip("distributed")
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                           host="127.0.0.1", dashboard_address="127.0.0.1:0")
    yield cluster.scheduler_address
    cluster.close()
