"""The FMU cache's recipe index (:mod:`fmus.index`).

Checked against the full path (blocks built with CasADi, FMUs found by the content of their
generated C): a scene validated from the index has the same components, interfaces, parameters
and start rules; the indexed FMU description equals the FMU's own modelDescription.xml; a change
to any fingerprinted input (a C template, a model source, the exporter version, a package
version, the compiler) or to the recipe misses; a missing or damaged FMU behind an entry is
rebuilt with the cache's message.
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pytest

import fmus.index as index
from cosim import scenario
from cosim.scenario.recipes import description_from_data
from cosim.run.execute import run
from cosim.slaves.description import describe_fmu
from fmus.cache import ENV_VAR, verify

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenarios" / "two_mass.yaml"
SHORT = ["stop_time=0.02", "master.tolerance=none"]  # no verdict: 20 ms of two_mass is about the index, not accuracy


def _run_logged(scene=SCENE, cache_dir=None):
    lines: list[str] = []
    res = run(scene, SHORT, cache_dir=cache_dir, log=lines.append)
    return res, lines


@pytest.fixture(scope="module")
def indexed(cache):
    """The session cache with two_mass's FMUs built and indexed; ``$RPR_COSIM_CACHE`` points to it."""
    mp = pytest.MonkeyPatch()
    mp.setenv(ENV_VAR, str(cache))
    res, _ = _run_logged(cache_dir=cache)
    assert res.ok, res.reason
    yield cache
    mp.undo()


@pytest.fixture
def fresh_fingerprint():
    index.fingerprint.cache_clear()
    yield
    index.fingerprint.cache_clear()


def _recipe(comp: str) -> tuple:
    spec = {"mass1": {"coupling": "none"}, "mass2": {"coupling": "spring"}}[comp]
    return "oscillator", None, spec, {}, "2.0"


def test_a_second_run_is_served_from_the_index(indexed):
    res, lines = _run_logged(cache_dir=indexed)
    assert res.ok
    assert sum("from the recipe index" in m for m in lines) == 2, lines
    assert all(isinstance(c.block, index.IndexedBlock) for c in res.scene.components.values())


@pytest.mark.parametrize("name", ["mass1", "mass2"])
def test_scene_from_the_index_equals_the_full_validation(indexed, name):
    import models.blocks

    fast = scenario.load(SCENE).components[name]
    full = scenario.load(SCENE, catalog=models.blocks).components[name]
    assert isinstance(fast.block, index.IndexedBlock) and not isinstance(full.block, index.IndexedBlock)
    assert (fast.model, fast.fidelity, fast.options, fast.params, fast.start) == \
           (full.model, full.fidelity, full.options, full.params, full.start)
    assert fast.description == full.description  # variables, feedthrough, flanges, sample period
    for attr in ("name", "fidelity", "params", "inputs", "outputs", "states", "flanges", "ratings", "integrator",
                 "substeps", "sample_period"):
        assert getattr(fast.block, attr) == getattr(full.block, attr), attr
    assert fast.block.feedthrough() == full.block.feedthrough()
    from cosim.scenario.check_components import _exact_start

    exact = {s.name for s in full.block.states if _exact_start(full.block, s.name)}
    assert set(fast.block.exact_start) == exact
    assert list(fast.block.param_vector(**fast.params)) == list(full.block.param_vector(**full.params))


@pytest.mark.parametrize("name", ["mass1", "mass2"])
def test_indexed_fmu_description_equals_the_model_description(indexed, name):
    hit = index.lookup(*_recipe(name))
    assert hit is not None
    block, _ = hit
    assert verify(block.fmu) == ""
    assert description_from_data(block.fmu_description) == describe_fmu(block.fmu)


def _copy_sources(dest: Path) -> Path:
    for pkg in index._PACKAGES:
        shutil.copytree(index.SOURCE_ROOT / pkg, dest / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    return dest


def _touch_c_template(root: Path) -> None:
    path = root / "fmus" / "c" / "rpr_core.c"
    path.write_text(path.read_text() + "\n/* changed */\n")


def _touch_model(root: Path) -> None:
    path = root / "models" / "blocks" / "oscillator.py"
    path.write_text(path.read_text() + "\n# changed\n")


CHANGES = {
    "c_template": lambda mp, tmp: mp.setattr(index, "SOURCE_ROOT", _copy_and(tmp, _touch_c_template)),
    "model_source": lambda mp, tmp: mp.setattr(index, "SOURCE_ROOT", _copy_and(tmp, _touch_model)),
    "exporter_version": lambda mp, tmp: mp.setattr(index, "EXPORTER_VERSION", index.EXPORTER_VERSION + ".x"),
    "casadi_version": lambda mp, tmp: mp.setattr(
        index, "installed_version", _other_version("casadi", index.installed_version)),
    "compiler": lambda mp, tmp: mp.setenv("CC", shutil.which("cc") if _differs("cc") else "/bin/true"),
}


def _copy_and(tmp: Path, change) -> Path:
    root = _copy_sources(tmp / "src")
    change(root)
    return root


def _other_version(dist: str, real):
    return lambda d, m=None: "0.0.0-other" if d == dist else real(d, m)


def _differs(cc: str) -> bool:
    import os

    found, gcc = shutil.which(cc), shutil.which("gcc")
    return bool(found and gcc and os.path.realpath(found) != os.path.realpath(gcc))


def test_an_unchanged_copy_of_the_sources_hits(indexed, tmp_path, monkeypatch, fresh_fingerprint):
    """The control of the next test: copying the sources alone keeps the fingerprint."""
    monkeypatch.setattr(index, "SOURCE_ROOT", _copy_sources(tmp_path / "src"))
    assert index.lookup(*_recipe("mass2")) is not None


@pytest.mark.parametrize("change", sorted(CHANGES))
def test_a_changed_fingerprint_input_misses(indexed, tmp_path, monkeypatch, fresh_fingerprint, change):
    before = index.fingerprint()
    index.fingerprint.cache_clear()
    CHANGES[change](monkeypatch, tmp_path)
    assert index.fingerprint() != before
    assert index.lookup(*_recipe("mass2")) is None


@pytest.mark.parametrize("options", [{"coupling": "spring", "integrator": "radau"},
                                     {"coupling": "spring", "substeps": 41}, {"coupling": "none"}])
def test_a_changed_recipe_misses(indexed, options):
    assert index.lookup("oscillator", None, {"coupling": "spring"}, {}, "2.0") is not None  # the control
    hit = index.lookup("oscillator", None, options, {}, "2.0")
    if options == {"coupling": "none"}:  # another component's recipe: its own entry, another FMU
        assert hit is not None and hit[0].fmu != index.lookup(*_recipe("mass2"))[0].fmu
    else:
        assert hit is None
    assert index.lookup("oscillator", "linear", {"coupling": "spring"}, {}, "3.0") is None  # FMI 3.0


@pytest.fixture(scope="module")
def private_cache(tmp_path_factory):
    """A cache of its own (the tests below damage it), two_mass built and indexed there."""
    cache = tmp_path_factory.mktemp("index-cache")
    mp = pytest.MonkeyPatch()
    mp.setenv(ENV_VAR, str(cache))
    res, _ = _run_logged(cache_dir=cache)
    assert res.ok
    yield cache
    mp.undo()


@pytest.mark.parametrize("damage", ["missing", "truncated", "bytes changed"])
def test_a_missing_or_damaged_fmu_behind_an_entry_is_rebuilt(private_cache, monkeypatch, damage):
    monkeypatch.setenv(ENV_VAR, str(private_cache))
    fmu = index.lookup(*_recipe("mass2"))[0].fmu
    if damage == "missing":
        fmu.unlink()
    elif damage == "truncated":
        fmu.write_bytes(fmu.read_bytes()[:-100])
    else:
        data = bytearray(fmu.read_bytes())
        data[len(data) // 2] ^= 0xFF
        fmu.write_bytes(bytes(data))
    res, lines = _run_logged(cache_dir=private_cache)
    assert res.ok, res.reason
    said = " | ".join(m for m in lines if m.startswith("mass2:"))
    if damage == "missing":
        assert "compiling" in said and "from the recipe index" not in said, said
    else:
        assert "is damaged" in said and "rebuilding it" in said, said
    assert fmu.is_file() and verify(fmu) == ""
    again, lines = _run_logged(cache_dir=private_cache)  # repaired: served from the index again
    assert again.ok and any(m.startswith("mass2:") and "from the recipe index" in m for m in lines), lines


def test_indexed_block_builds_the_real_block_on_demand(indexed):
    block = scenario.load(SCENE).components["mass2"].block
    assert block._real is None
    real = index.real_block(block)
    assert dataclasses.is_dataclass(real) and real.params == block.params
    assert block.ode.shape == real.ode.shape  # anything else comes from the real block
