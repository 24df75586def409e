"""Seeded fuzzing of the scene loader over random mutations of the shipped scenes (issue #7):
whatever a mutated scene says, loading it either succeeds or raises a one-line user error; it
never escapes as any other exception (a traceback for the user)."""
from __future__ import annotations

import copy
import random
from pathlib import Path

import pytest

from cosim.errors import user_error_types
from cosim.scenario import from_dict, load

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
SHIPPED = sorted(p.stem for p in SCENES.glob("*.yaml"))

#: Values a mutation puts somewhere: wrong types, extremes, names that try to leave a directory,
#: nested structures, YAML look-alikes.
ODD = [None, True, False, 0, -1, 1e308, -1e308, float("nan"), float("inf"), 1e-300, 2 ** 70, "", " ", "x" * 300,
       "../../etc/passwd", "/abs/path", "C:\\x", "nul\0byte", "é", "*", "[", "{a: 1}", "1e-3", "-> ", "<->",
       "mech.leg[9].s", "pid1.y -> pid1.y", [], {}, [1, 2], {"model": "pid"}, {"fmu": "missing.fmu"},
       [[[[[]]]]], {"a": {"b": {"c": None}}}]


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
            lines[i] = lines[i][:pos] + rng.choice([":", "-", "{", "}", "[", "]", "&a ", "*a", "!!str ", "\t", "'", '"',
                                                    "#", "?", "%", "@", "|", ">", ",", "é", "\x00", "1e999"]) + lines[i][pos:]
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
def shipped_trees():
    return {name: load(SCENES / f"{name}.yaml").data for name in SHIPPED}


@pytest.mark.parametrize("scene", SHIPPED)
@pytest.mark.parametrize("seed", range(4))
def test_mutated_scene_trees_load_or_give_a_user_error(shipped_trees, scene, seed):
    rng = random.Random(f"tree-{scene}-{seed}")
    for case in range(90):
        tree = mutate_tree(shipped_trees[scene], rng)
        try:
            _accept(lambda: from_dict(tree, base_dir=SCENES))
        except Exception as exc:  # pragma: no cover - the failure message is the point
            raise AssertionError(f"seed {seed} case {case}: {type(exc).__name__}: {exc}\n{tree}") from exc


@pytest.mark.parametrize("scene", SHIPPED)
@pytest.mark.parametrize("seed", range(2))
def test_mutated_scene_files_load_or_give_a_user_error(tmp_path, scene, seed):
    rng = random.Random(f"text-{scene}-{seed}")
    text = (SCENES / f"{scene}.yaml").read_text()
    # the comment header costs parsing time and is never what breaks: fuzz the body
    body = "".join(ln for ln in text.splitlines(keepends=True) if not ln.startswith("#"))
    for fmu in SCENES.glob("*.fmu"):
        (tmp_path / fmu.name).write_bytes(fmu.read_bytes())
    path = tmp_path / f"{scene}.yaml"
    for case in range(100):
        mutated = mutate_text(body, rng)
        path.write_bytes(mutated.encode("utf-8", errors="surrogatepass"))
        try:
            _accept(lambda: load(path))
        except Exception as exc:  # pragma: no cover
            raise AssertionError(f"seed {seed} case {case}: {type(exc).__name__}: {exc}\n{mutated}") from exc
