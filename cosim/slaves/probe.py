"""What an external FMU really does, measured once and cached by the FMU's hash: its direct
feedthrough (for an FMU that declares no output dependencies), and the findings of the XML and
behavioural checks (:mod:`cosim.slaves.xmlcheck`, :mod:`cosim.slaves.behaviour`).

Cache: one JSON file per FMU (``<FMU cache>/checks/<sha256 of the .fmu>.json``), one key per
check; a check is run again only when its entry is missing or its ``version`` changed.
"""
from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from .description import SlaveDescription
from fmus import cache_root
from fmus.cache import file_digest
from .fmu_slave import FmuSlave
from ..errors import UserError

#: bump to measure every FMU again after a change of what a check does
VERSIONS = {"feedthrough": 1, "xml": 1, "behaviour": 4}


def _cache_file(digest: str) -> Path:

    return cache_root(None) / "checks" / f"{digest}.json"


def cached(path: Path, key: str, compute: Callable[[], object]) -> tuple[object, bool]:
    """``compute()`` for the FMU ``path``, from the cache when it holds it: (value, from_cache).
    The value must be JSON data.  A cache that cannot be written is skipped."""

    digest = file_digest(path)
    file = _cache_file(digest)
    try:
        data = json.loads(file.read_text())
    except (OSError, ValueError):
        data = {}
    entry = data.get(key)
    if isinstance(entry, dict) and entry.get("version") == VERSIONS[key]:
        return entry["value"], True
    value = compute()
    data[key] = {"version": VERSIONS[key], "value": value}
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=file.parent)
        with os.fdopen(fd, "w") as fh:
            json.dump(data, fh)
        os.replace(tmp, file)
    except OSError:
        pass
    return value, False


def _perturbed(var, value):
    """A value of ``var``'s type clearly different from ``value``."""
    if var.type == "Boolean":
        return not bool(value)
    if var.type in ("Real", "Float32", "Float64"):
        return float(value) + 1.0 + abs(float(value))
    return int(value) + 1


#: the scalar types a perturbation can move (strings and binaries are left alone)
_NUMERIC = ("Real", "Float32", "Float64", "Integer", "Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32",
            "Int64", "UInt64", "Boolean", "Enumeration")


def measure_feedthrough(path: Path, desc: SlaveDescription) -> dict[str, list[str]]:
    """Direct feedthrough as the FMU shows it: on a scratch instance at its first communication
    point (after initialisation, before any step) each scalar input is perturbed in turn and the
    outputs that move are recorded; the input is put back before the next.  Outputs of other
    than scalar numeric type are assumed to depend on every input."""

    ins = [v for v in desc.variables.values() if v.causality == "input" and v.type in _NUMERIC and not v.shape]
    outs = [v for v in desc.variables.values() if v.causality == "output"]
    probe_outs = [v for v in outs if v.type in _NUMERIC and not v.shape]
    ft: dict[str, list[str]] = {v.name: [u.name for u in desc.variables.values() if u.causality == "input"]
                                for v in outs if v not in probe_outs}
    ft.update({v.name: [] for v in probe_outs})
    slave = FmuSlave("probe", path, desc)
    slave.instantiate()
    try:
        start = desc.default_experiment.get("start", 0.0)
        slave.enter_initialization(start, start + 1.0)
        slave.exit_initialization()

        def read() -> list:
            return [slave.get_values(v.type, [v.vr], 1)[0] for v in probe_outs]

        base = read()
        for u in ins:
            x = slave.get_values(u.type, [u.vr], 1)[0]
            slave.set_values(u.name, _perturbed(u, x))
            moved = read()
            slave.set_values(u.name, x)
            for v, a, b in zip(probe_outs, base, moved):
                if a != b:
                    ft[v.name].append(u.name)
    finally:
        slave.terminate()
        slave.release()
    return ft


def undeclared_dependencies(desc: SlaveDescription) -> bool:
    """True when the FMU lists no output dependencies at all (FMI then means: every output
    depends on every input), so its real feedthrough is worth measuring."""
    return desc.kind == "fmu" and not desc.dependencies_declared and bool(desc.of("input")) and bool(desc.of("output"))


def feedthrough(path: Path, desc: SlaveDescription) -> tuple[dict[str, list[str]], bool]:
    """The measured feedthrough of ``path`` (cached by hash) and whether it came from the cache."""

    def measure() -> dict[str, list[str]]:
        try:
            return measure_feedthrough(path, desc)
        except UserError:
            raise
        except Exception as exc:  # fmpy's bare exceptions from a failing get/set
            raise UserError(f"{Path(path).name}: {exc}") from None

    value, hit = cached(path, "feedthrough", measure)
    return {k: list(v) for k, v in value.items()}, hit
