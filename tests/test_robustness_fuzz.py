"""Seeded fuzzing of the scene and batch loaders over random mutations of the shipped scenes and
batches (issues #7 and 20): whatever a mutated file says (deep nesting, complex keys, anchors,
FMUs that are FMI 1.0 fakes or hold two model descriptions), loading it either succeeds or
raises a one-line user error; it never escapes as any other exception (a traceback for the user).

The default run makes about 6,000 cases; ``RPR_COSIM_FUZZ_SCALE=N`` makes N times as many."""
from __future__ import annotations

import copy
import os
import random
import zipfile
from pathlib import Path

import pytest

from cosim.errors import user_error_types
from cosim.scenario import from_dict, load

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
# the shipped scenes (batch files, scenarios/batch_*.yaml, are a different format: tests/test_batch_spec.py)
SHIPPED = sorted(p.stem for p in SCENES.glob("*.yaml") if not p.stem.startswith("batch_"))
BATCHES = sorted(p.stem for p in SCENES.glob("batch_*.yaml"))


def _library_absent(name: str) -> bool:
    """A scene whose ``modelica_path`` names a directory that is not there (pid_step_msl without
    the project's ../shared): it cannot load here, and says so in one line."""
    import yaml

    raw = yaml.safe_load((SCENES / f"{name}.yaml").read_text()) or {}
    paths = raw.get("modelica_path") or []
    paths = paths.split(os.pathsep) if isinstance(paths, str) else paths
    return any(not (SCENES / str(p)).is_dir() for p in paths)


#: Shipped scenes whose Modelica library (../shared/third_party) is absent: their tree cases skip.
NO_LIBRARY = {n for n in SHIPPED if _library_absent(n)}
#: Multiplies the number of cases (the default keeps the suite quick).
SCALE = max(1, int(os.environ.get("RPR_COSIM_FUZZ_SCALE", "1") or 1))

#: Values a mutation puts somewhere: wrong types, extremes, names that try to leave a directory,
#: nested structures, YAML look-alikes.
ODD = [None, True, False, 0, -1, 1e308, -1e308, float("nan"), float("inf"), 1e-300, 2 ** 70, "", " ", "x" * 300,
       "../../etc/passwd", "/abs/path", "C:\\x", "nul\0byte", "é", "*", "[", "{a: 1}", "1e-3", "-> ", "<->",
       "mech.leg[9].s", "pid1.y -> pid1.y", [], {}, [1, 2], {"model": "pid"}, {"fmu": "missing.fmu"},
       [[[[[]]]]], {"a": {"b": {"c": None}}}, {"fmu": "fake_fmi1.fmu"}, {"fmu": "two_descriptions.fmu"},
       {"fmu": "climbs_out.fmu"}]
#: Text a mutation inserts into a file: odd characters, deep nesting (beyond what the YAML reader
#: recurses through), complex keys, anchors.
INSERTS = [":", "-", "{", "}", "[", "]", "&a ", "*a", "!!str ", "\t", "'", '"', "#", "?", "%", "@", "|", ">", ",", "é",
           "\x00", "1e999", "[" * 600 + "]" * 600, "{a: " * 300 + "1" + "}" * 300, "[" * 600,
           "\n? [a, b]\n: 1\n", "\n? {a: 1}\n: 2\n", " fake_fmi1.fmu", " two_descriptions.fmu"]


def hostile_archives(folder: Path) -> None:
    """The FMUs the mutations point at: an FMI 1.0 fake whose description lacks most attributes,
    an archive with two modelDescription.xml members, one with a member climbing out."""
    with zipfile.ZipFile(folder / "fake_fmi1.fmu", "w") as z:
        z.writestr("modelDescription.xml", '<?xml version="1.0"?><fmiModelDescription fmiVersion="1.0"/>')
    import warnings

    with zipfile.ZipFile(folder / "two_descriptions.fmu", "w") as z, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Duplicate name": the point of this archive
        z.writestr("modelDescription.xml", '<fmiModelDescription fmiVersion="2.0" modelName="a" guid="1"/>')
        z.writestr("modelDescription.xml", "<garbage")
    with zipfile.ZipFile(folder / "climbs_out.fmu", "w") as z:
        z.writestr("modelDescription.xml", '<fmiModelDescription fmiVersion="2.0" modelName="a" guid="1"/>')
        z.writestr("../../evil.so", "x")


def _paths(node, prefix=()):
    """Every (container, key) address in a plain tree."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield prefix + (i,)
            yield from _paths(v, prefix + (i,))


def _get(tree, path):
    for p in path:
        tree = tree[p]
    return tree


def mutate_tree(tree: dict, rng: random.Random) -> dict:
    """One to three random edits of a scene tree: replace, delete, duplicate or rename a node."""
    tree = copy.deepcopy(tree)
    for _ in range(rng.randint(1, 3)):
        paths = list(_paths(tree))
        if not paths:
            break
        path = rng.choice(paths)
        parent, key = _get(tree, path[:-1]), path[-1]
        op = rng.random()
        if op < 0.45:
            parent[key] = copy.deepcopy(rng.choice(ODD))
        elif op < 0.6:
            del parent[key]
        elif op < 0.75 and isinstance(parent, dict):
            parent[rng.choice([str(k) for k in ODD if isinstance(k, str)] or ["x"])] = parent.pop(key)
        elif op < 0.9 and isinstance(parent[key], (int, float)) and not isinstance(parent[key], bool):
            parent[key] = parent[key] * rng.choice([-1, 0, 1e-9, 1e9, 1e300])
        else:
            parent[key] = copy.deepcopy(_get(tree, rng.choice(paths)))
    return tree


def mutate_text(text: str, rng: random.Random) -> str:
    """One to three random text edits: delete, duplicate or swap lines, insert odd characters,
    anchors and aliases, tabs, cut the file."""
    lines = text.splitlines(keepends=True)
    for _ in range(rng.randint(1, 3)):
        i = rng.randrange(len(lines)) if lines else 0
        op = rng.random()
        if not lines:
            lines = ["x\n"]
        elif op < 0.2:
            del lines[i]
        elif op < 0.35:
            lines.insert(i, lines[rng.randrange(len(lines))])
        elif op < 0.5:
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        elif op < 0.7:
            pos = rng.randrange(len(lines[i]) + 1)
            lines[i] = lines[i][:pos] + rng.choice(INSERTS) + lines[i][pos:]
        elif op < 0.85:
            lines[i] = lines[i].replace(":", ": &x", 1) if ":" in lines[i] else lines[i]
            lines.append(f"extra: [*x, *x, *x]\n")
        else:
            lines = lines[:i]
    return "".join(lines)


def _accept(fn) -> None:
    try:
        fn()
    except user_error_types():
        pass


@pytest.fixture(scope="module")
def archives(tmp_path_factory):
    """A folder with the hostile FMUs (the base folder of the mutated trees)."""
    folder = tmp_path_factory.mktemp("archives")
    hostile_archives(folder)
    for p in SCENES.iterdir():  # the files the shipped scenes refer to (relative to their folder)
        if p.is_file() and not p.suffix == ".yaml":
            (folder / p.name).write_bytes(p.read_bytes())
    return folder


@pytest.fixture(scope="module")
def shipped_trees(tmp_path_factory):
    """The shipped scenes as validated plain trees; a hardware component's key file (which lives in
    the user's home on a real setup) points at a fresh key."""
    from cosim.scenario import Problem, load_raw
    from hardware.protocol import write_key

    key = write_key(tmp_path_factory.mktemp("key") / "board.key")
    trees = {}
    for name in SHIPPED:
        if name in NO_LIBRARY:
            continue
        raw = load_raw(SCENES / f"{name}.yaml", list[Problem]())
        sets = {f"components.{c}.hardware.key": str(key) for c, spec in (raw.get("components") or {}).items()
                if isinstance(spec, dict) and "hardware" in spec}
        trees[name] = load(SCENES / f"{name}.yaml", sets).data
    return trees


@pytest.mark.parametrize("scene", SHIPPED)
@pytest.mark.parametrize("seed", range(4))
def test_mutated_scene_trees_load_or_give_a_user_error(shipped_trees, archives, scene, seed):
    if scene in NO_LIBRARY:
        pytest.skip(f"{scene}: its modelica_path is not here (../shared/third_party absent)")
    rng = random.Random(f"tree-{scene}-{seed}")
    for case in range(90 * SCALE):
        tree = mutate_tree(shipped_trees[scene], rng)
        try:
            _accept(lambda: from_dict(tree, base_dir=archives))
        except Exception as exc:  # pragma: no cover - the failure message is the point
            raise AssertionError(f"seed {seed} case {case}: {type(exc).__name__}: {exc}\n{tree}") from exc


@pytest.mark.parametrize("scene", SHIPPED)
@pytest.mark.parametrize("seed", range(2))
def test_mutated_scene_files_load_or_give_a_user_error(tmp_path, scene, seed):
    rng = random.Random(f"text-{scene}-{seed}")
    hostile_archives(tmp_path)
    text = (SCENES / f"{scene}.yaml").read_text()
    # the comment header costs parsing time and is never what breaks: fuzz the body
    body = "".join(ln for ln in text.splitlines(keepends=True) if not ln.startswith("#"))
    for fmu in SCENES.glob("*.fmu"):
        (tmp_path / fmu.name).write_bytes(fmu.read_bytes())
    path = tmp_path / f"{scene}.yaml"
    for case in range(100 * SCALE):
        mutated = mutate_text(body, rng)
        path.write_bytes(mutated.encode("utf-8", errors="surrogatepass"))
        try:
            _accept(lambda: load(path))
        except Exception as exc:  # pragma: no cover
            raise AssertionError(f"seed {seed} case {case}: {type(exc).__name__}: {exc}\n{mutated}") from exc


@pytest.mark.parametrize("batch", BATCHES)
def test_mutated_batch_files_load_or_give_a_user_error(tmp_path, batch):
    """Batch files: the same text mutations, plus huge grids and sample counts (refused by the
    run limit in one line, before anything is expanded)."""
    from cosim.batch.spec import load_batch

    rng = random.Random(f"batch-{batch}")
    text = (SCENES / f"{batch}.yaml").read_text()
    body = "".join(ln for ln in text.splitlines(keepends=True) if not ln.startswith("#"))
    for p in SCENES.glob("*.yaml"):
        if not p.stem.startswith("batch_"):
            (tmp_path / p.name).write_text(p.read_text())
    hostile_archives(tmp_path)
    path = tmp_path / f"{batch}.yaml"
    extra = ["grid:\n" + "".join(f"  a{i}: {{path: stop_time, values: [{', '.join(map(str, range(1, 11)))}]}}\n"
                                   for i in range(10)),
             "random: {seed: 1, samples: 1000000000000, axes: {s: {path: stop_time, dist: uniform, low: 1, high: 2}}}\n",
             "name: ../../evil\n", "name: /abs/evil\n", "grid: {stop_time: {from: 1, to: 2, num: 1000000000000}}\n"]
    for case in range(40 * SCALE):
        mutated = mutate_text(body, rng)
        if rng.random() < 0.3:
            mutated += rng.choice(extra)
        path.write_bytes(mutated.encode("utf-8", errors="surrogatepass"))
        try:
            _accept(lambda: load_batch(path))
        except Exception as exc:  # pragma: no cover
            raise AssertionError(f"case {case}: {type(exc).__name__}: {exc}\n{mutated[:2000]}") from exc
