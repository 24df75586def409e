"""Start-up stays light: the CLI's entry point and its help import neither CasADi nor matplotlib
nor scipy (checked in a fresh interpreter; the timings are in benchmarks/bench_startup.py)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROBE = """
import sys
{code}
print(" ".join(m for m in ("casadi", "matplotlib", "scipy") if m in sys.modules))
"""


@pytest.mark.parametrize("code", ["import cosim.cli", "import cosim.cli; cosim.cli.build_parser()"],
                         ids=["import", "parser"])
def test_cli_start_up_imports_no_heavy_package(code):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    res = subprocess.run([sys.executable, "-c", PROBE.format(code=code)], capture_output=True, text=True,
                         env=env, check=True)
    assert res.stdout.split() == [], f"{code!r} imported {res.stdout.strip()}"
