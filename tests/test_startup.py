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


RUN_PROBE = """
import sys
from cosim.cli import main
code = main({argv!r})
heavy = ("casadi", "matplotlib", "scipy", "models.block", "models.blocks", "fmus.build", "fmus.codegen", "lxml")
print("EXIT", code)
print("HEAVY", " ".join(m for m in heavy if m in sys.modules))
"""


def _cli_in_probe(argv: list[str], cache: Path) -> tuple[int, list[str]]:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               RPR_COSIM_CACHE=str(cache))
    res = subprocess.run([sys.executable, "-c", RUN_PROBE.format(argv=argv)], capture_output=True, text=True,
                         env=env, cwd=ROOT, check=True)
    lines = res.stdout.splitlines()
    code = int(next(x for x in lines if x.startswith("EXIT ")).split()[1])
    heavy = next(x for x in lines if x.startswith("HEAVY")).split()[1:]
    return code, heavy


def test_a_run_with_cached_fmus_imports_no_symbolic_or_plotting_package(cache, tmp_path):
    """The second run of pid_step finds every FMU through the recipe index (fmus.index): no block
    is built, no C generated, the setpoint's workspace check and the singularity guard replay
    stored numpy programs; CasADi, scipy, matplotlib, the exporter and lxml stay unimported."""
    argv = ["run", str(ROOT / "scenarios" / "pid_step.yaml"), "--set", "stop_time=0.01"]
    first, _ = _cli_in_probe(argv + ["--out", str(tmp_path / "first")], cache)  # builds or finds, and indexes
    assert first == 0
    second, heavy = _cli_in_probe(argv + ["--out", str(tmp_path / "second")], cache)
    assert second == 0
    assert heavy == [], f"a cached run imported {heavy}"


def test_the_run_chart_and_animation_are_drawn_outside_the_command_process(cache, tmp_path):
    """``run --plot --animate`` (issue 32, item 11): matplotlib is imported by the drawing process
    (cosim/analysis/drawing.py), which imports it while the run steps, never by the command's
    own process; the chart and the GIF are written."""
    argv = ["run", str(ROOT / "scenarios" / "pid_step.yaml"), "--set", "stop_time=0.01", "--plot", "--animate",
            "--out", str(tmp_path)]
    code, heavy = _cli_in_probe(argv, cache)
    assert code == 0 and "matplotlib" not in heavy, heavy
    assert (tmp_path / "pid_step.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "pid_step.gif").read_bytes()[:6] == b"GIF89a"
