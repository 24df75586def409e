"""The package layering (pyproject.toml ``[tool.importlinter]``): models below fmus below hardware
below cosim, and inside cosim the verbs over the studies, batches, runs, analysis, scenes, master,
traces and slaves.  import-linter reads every import, those inside functions too, so an import
cycle or an import upward fails here."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _lint_imports() -> str:
    exe = Path(sys.executable).with_name("lint-imports")
    if not exe.exists():
        found = shutil.which("lint-imports")
        if found is None:
            pytest.fail("import-linter is not installed (pip install -e '.[test]')")
        exe = Path(found)
    return str(exe)


def test_import_contracts_are_kept():
    res = subprocess.run([_lint_imports(), "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "BROKEN" not in res.stdout and "2 kept, 0 broken" in res.stdout


def test_an_upward_import_breaks_a_contract(tmp_path):
    """The contract is not vacuous: a copy of the tree where the scene loader imports the run-time
    (the cycle that the regrouping removed) is refused."""
    tree = tmp_path / "tree"
    for pkg in ("models", "fmus", "hardware", "cosim"):
        shutil.copytree(ROOT / pkg, tree / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    shutil.copy(ROOT / "pyproject.toml", tree / "pyproject.toml")
    loading = tree / "cosim" / "scenario" / "loading.py"
    loading.write_text(loading.read_text() + "\n\ndef _upward():\n    from ..run import execute  # noqa: F401\n")
    env = {"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"}
    res = subprocess.run([_lint_imports(), "--no-cache"], cwd=tree, capture_output=True, text=True, env=env)
    assert res.returncode != 0
    assert "cosim.scenario is not allowed to import cosim.run" in res.stdout
