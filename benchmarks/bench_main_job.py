"""Time to answer of the README's main job (issue 32, item 11): ``rpr-cosim run
scenarios/pid_step.yaml --plot --animate --reference`` against the plain run of the same scene, on
a warm FMU cache, in one process each (``python -m cosim``), both measured in one invocation of
this script so that their ratio is taken under the same machine load; also the GIF alone
(:func:`cosim.analysis.animate.animate` on the plain run's trace, in this process).

Target: the main job at most 3x the plain run (it was 13.2 s against 0.63 s, 21x, the GIF 11 s of it).

Usage: ``python benchmarks/bench_main_job.py [--scene scenarios/pid_step.yaml] [--repeat 3]``
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET = 3.0


def timed(args: list[str], out: Path) -> float:
    """Wall time [s] of ``python -m cosim run ... --out out`` in a fresh process."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cosim", "run", *args, "--out", str(out)], cwd=ROOT, env=env, check=False,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="scenarios/pid_step.yaml")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from cosim.analysis.animate import animate
    from cosim.trace.traces import read_trace

    with tempfile.TemporaryDirectory(prefix="bench-main-job-") as tmp:
        out = Path(tmp)
        timed([a.scene], out / "warm")  # fills the FMU cache and its recipe index
        plain, full, gif = [], [], []
        for k in range(a.repeat):
            plain.append(timed([a.scene], out / f"plain{k}"))
            full.append(timed([a.scene, "--plot", "--animate", "--reference"], out / f"full{k}"))
            trace = read_trace(next((out / f"plain{k}").glob("*.csv")))
            t0 = time.perf_counter()
            animate(trace, out / f"gif{k}.gif", title="bench")
            gif.append(time.perf_counter() - t0)
    p, f, g = (statistics.median(x) for x in (plain, full, gif))
    print(f"{a.scene}: plain run {p:.2f} s, with --plot --animate --reference {f:.2f} s "
          f"({f / p:.2f}x the plain run, target {TARGET:g}x), the GIF alone {g:.2f} s "
          f"(medians of {a.repeat}, fresh processes, warm cache)")


if __name__ == "__main__":
    main()
