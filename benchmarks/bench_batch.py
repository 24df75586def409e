"""Batch execution: speed-up of 2 workers against 1, the batch machinery's overhead per run
against the runs themselves, and FMU instance reuse (FMI reset) against loading every FMU again.

The batch: ``pid_step`` (eight FMUs, 1 ms Gauss-Seidel with linear inputs) over a 4 x 4 grid of
the three PIDs' Kp and Kd, 16 runs, on local worker processes, each run writing its trace and
sidecar.  Each figure is the best of ``--repeat`` batches into fresh directories, after one
warm-up batch (so the FMUs are built and the worker server process is up in every case).

- speed-up: wall time of the execution (everything after the scenes are resolved and the FMUs
  built: starting workers, runs, rows) on 1 worker over 2 workers (target >= 1.8x on 2 cores).
- overhead per run (1 worker): execution wall time minus the runs themselves (each run's
  :func:`cosim.run.run`: initialisation, stepping, streaming its trace files; ``run_s`` in the
  table), divided by the runs; split into the worker's share (instance hand-out, metrics) and
  the parent's (process start, sending tasks, writing rows with fsync).  Targets: under 5 % of the runs, under 50 ms
  per run for short scenes (also measured at stop_time 0.5 s).
- reuse: initialisation time per run (``init_s``: instantiate or reset, start values,
  initialisation) with instances kept and reset against loading the FMUs for every run.

    python3 benchmarks/bench_batch.py [--repeat 3] [--stop 5.0]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.batch import load_batch, run_batch  # noqa: E402
from cosim.batch.executors import LocalExecutor  # noqa: E402

BATCH = """\
name: bench
scene: {scene}
set: {{stop_time: {stop}}}
grid:
  Kp: {{path: "components.pid*.params.Kp", values: [20, 30, 45, 60]}}
  Kd: {{path: "components.pid*.params.Kd", values: [10, 15, 20, 30]}}
metrics:
  mech.platform.phi: {{target: 0.2, measure: [overshoot, end_error]}}
"""


def batch_file(tmp: Path, stop: float) -> Path:
    p = tmp / f"bench_{stop:g}.yaml"
    p.write_text(BATCH.format(scene=ROOT / "scenarios" / "pid_step.yaml", stop=stop))
    return p


def one(batch, tmp: Path, workers: int, reuse: bool = True) -> dict:
    out = Path(tempfile.mkdtemp(dir=tmp))
    res = run_batch(batch, out=out, executor=LocalExecutor(workers), reuse=reuse)
    assert res.ran == len(res.rows) and res.failed == 0, res.rows
    rows = res.rows
    execution = res.wall_s - res.prepare_s
    sim = sum(r["run_s"] for r in rows)
    return {"execution": execution, "sim": sim, "worker": sum(r["wall_s"] for r in rows) - sim,
            "loop": sum(r["loop_s"] for r in rows), "trace": sum(r["run_s"] - r["init_s"] - r["loop_s"] for r in rows),
            "init": sum(r["init_s"] for r in rows) / len(rows), "n": len(rows), "wall": res.wall_s,
            "prepare": res.prepare_s}


def best(batch, tmp: Path, workers: int, repeat: int, reuse: bool = True) -> dict:
    return min((one(batch, tmp, workers, reuse) for _ in range(repeat)), key=lambda m: m["execution"])


def overhead(m: dict) -> str:
    per = (m["execution"] - m["sim"]) / m["n"]
    worker = m["worker"] / m["n"]
    n = m["n"]
    return (f"{1e3 * per:.1f} ms per run = {100 * per * n / m['sim']:.1f} % of the runs' own "
            f"{1e3 * m['sim'] / n:.1f} ms (of which stepping {1e3 * m['loop'] / n:.1f} ms, trace files "
            f"{1e3 * m['trace'] / n:.1f} ms); worker side {1e3 * worker:.1f} ms (instances, metrics), "
            f"parent side {1e3 * (per - worker):.1f} ms (processes, tasks, rows)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--stop", type=float, default=5.0, help="stop_time of the runs [s]")
    args = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        batch = load_batch(batch_file(tmp, args.stop))
        short = load_batch(batch_file(tmp, 0.5))
        t0 = time.perf_counter()
        one(batch, tmp, 2)  # warm-up: FMUs, worker server
        print(f"warm-up batch: {time.perf_counter() - t0:.2f} s")
        m1 = best(batch, tmp, 1, args.repeat)
        m2 = best(batch, tmp, 2, args.repeat)
        print(f"16 runs of pid_step ({args.stop:g} s each), execution: 1 worker {m1['execution']:.2f} s, "
              f"2 workers {m2['execution']:.2f} s: speed-up {m1['execution'] / m2['execution']:.2f}x "
              f"(whole batch incl. resolving scenes and FMU checks {m1['prepare']:.2f} s: "
              f"{m1['wall']:.2f} s vs {m2['wall']:.2f} s)")
        print(f"overhead, 1 worker, {args.stop:g} s runs: {overhead(m1)}")
        ms = best(short, tmp, 1, args.repeat)
        print(f"overhead, 1 worker, 0.5 s runs: {overhead(ms)}")
        mr = best(batch, tmp, 1, args.repeat, reuse=False)
        print(f"initialisation per run: instances kept and reset {1e3 * m1['init']:.1f} ms, FMUs loaded for every "
              f"run {1e3 * mr['init']:.1f} ms ({mr['init'] / m1['init']:.0f}x); execution of the 16 runs "
              f"{m1['execution']:.2f} s vs {mr['execution']:.2f} s ({mr['execution'] / m1['execution']:.2f}x)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
