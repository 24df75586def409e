"""Time to answer of the README's main job (issue 32, item 11): ``rpr-cosim run
scenarios/pid_step.yaml --plot --animate --reference`` against the plain run of the same scene, on
a warm FMU cache, in one process each (``python -m cosim``), both measured in one invocation of
this script so that their ratio is taken under the same machine load; also the GIF alone
(:func:`cosim.analysis.animate.animate` on the plain run's trace, in this process).  Each command
also has its CPU time (its processes' user + system time): the wall time's ratio needs the
machine's second core, the CPU time's does not.

The commands run with Python's bytecode cache on (in a temporary ``PYTHONPYCACHEPREFIX``, filled
by the warm-up run), as an installed package has it, also when ``PYTHONDONTWRITEBYTECODE`` is set
here: compiling the project's modules in every process would add the same half second to both.

Target: the main job at most 3x the plain run (it was 13.2 s against 0.63 s, 21x, the GIF 11 s of it;
3.2-4.5x on 2026-12-05; 2.3-2.7x with the machine's cores free on 2026-12-07, the ratio of the CPU
times 3.7-4.1x, which a loaded machine's gives: docs/reference/results.md).

The plain run and the main job alternate (plain, main job, plain, ...); the line gives the
medians and the best of the repeats (the best is the one least disturbed by other jobs on a
shared machine), with the load average before and after.

Usage: ``python benchmarks/bench_main_job.py [--scene scenarios/pid_step.yaml] [--repeat 3]``
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET = 3.0


def timed(args: list[str], out: Path, pycache: Path) -> tuple[float, float]:
    """Wall time and CPU time [s] of ``python -m cosim run ... --out out`` in a fresh process
    (the CPU time of it and of the processes it waited for)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.update(PYTHONPATH=str(ROOT), PYTHONPYCACHEPREFIX=str(pycache))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cosim", "run", *args, "--out", str(out)], cwd=ROOT, env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="scenarios/pid_step.yaml")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from cosim.analysis.animate import animate
    from cosim.trace.traces import read_trace

    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-main-job-") as tmp:
        out = Path(tmp)
        main_job = [a.scene, "--plot", "--animate", "--reference"]
        timed(main_job, out / "warm", out / "pycache")  # fills the FMU cache, its recipe index and the bytecode cache
        plain, full, gif = [], [], []
        for k in range(a.repeat):
            plain.append(timed([a.scene], out / f"plain{k}", out / "pycache"))
            full.append(timed(main_job, out / f"full{k}", out / "pycache"))
            trace = read_trace(next((out / f"plain{k}").glob("*.csv")))
            t0 = time.perf_counter()
            animate(trace, out / f"gif{k}.gif", title="bench")
            gif.append(time.perf_counter() - t0)
    (p, pc), (f, fc) = ([statistics.median(x) for x in zip(*runs)] for runs in (plain, full))
    (bp, bpc), (bf, bfc) = ([min(x) for x in zip(*runs)] for runs in (plain, full))
    g = statistics.median(gif)
    print(f"{a.scene}: plain run {p:.2f} s, with --plot --animate --reference {f:.2f} s "
          f"({f / p:.2f}x the plain run, target {TARGET:g}x), the GIF alone {g:.2f} s; "
          f"CPU time {pc:.2f} s and {fc:.2f} s ({fc / pc:.2f}x) "
          f"(medians of {a.repeat}, fresh processes, warm cache, load average {load:.1f} to {os.getloadavg()[0]:.1f}); "
          f"best of {a.repeat}: {bp:.2f} s and {bf:.2f} s ({bf / bp:.2f}x), CPU {bpc:.2f} s and {bfc:.2f} s "
          f"({bfc / bpc:.2f}x)")


if __name__ == "__main__":
    main()
