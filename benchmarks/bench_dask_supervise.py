"""What supervising Dask batch runs costs (issue 20, item 1): the same batch on a Dask
``LocalCluster`` whose worker steps each run in a forked, watched child (the default) against
one whose worker steps it in its own thread (``$RPR_COSIM_SUPERVISE=0`` on the worker).

The batch: ``pid_step`` (eight FMUs, 1 ms Gauss-Seidel) over a grid of the three PIDs' Kp,
``--runs`` runs, each writing its trace and sidecar, on one single-threaded worker per cluster
(so the two clusters do not compete for the two cores while one runs).  Both clusters run one
warm-up batch first (the FMUs are cached, the worker imports done); then the two take turns,
``--repeat`` batches each.  Printed per run: the batch's wall time over its runs, and the rows'
own figures: ``wall_s`` (the worker's time for the run, fork and child included) and ``init_s``
(instantiate or reset, start values, initialisation: a supervised run's child loads its FMUs
afresh, an unsupervised worker resets the instances it kept).

    python3 benchmarks/bench_dask_supervise.py [--repeat 5] [--runs 16] [--stop 0.2]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.batch import load_batch, run_batch  # noqa: E402
from cosim.batch.executors import DaskExecutor  # noqa: E402


def batch_file(folder: Path, runs: int, stop: float) -> Path:
    values = ", ".join(f"{20 + 2 * i}" for i in range(runs))
    path = folder / "b.yaml"
    path.write_text(f"name: dask_bench\nscene: {ROOT / 'scenarios' / 'pid_step.yaml'}\n"
                    f"set: {{master.algorithm: gauss_seidel, stop_time: {stop}}}\n"
                    f"grid:\n  Kp: {{path: 'components.pid*.params.Kp', values: [{values}]}}\n"
                    f"metrics:\n  mech.platform.phi: [max]\n")
    return path


def one_batch(path: Path, address: str, folder: Path) -> tuple[float, list[dict]]:
    out = Path(tempfile.mkdtemp(dir=folder))
    t0 = time.perf_counter()
    res = run_batch(load_batch(path), out=out, executor=DaskExecutor(address))
    wall = time.perf_counter() - t0
    assert res.failed == 0, [r["reason"] for r in res.rows if r["outcome"] != "ok"]
    return wall, res.rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--runs", type=int, default=16)
    ap.add_argument("--stop", type=float, default=0.2)
    args = ap.parse_args(argv)
    import dask
    import distributed

    folder = Path(tempfile.mkdtemp(prefix="bench-dask-supervise-"))
    path = batch_file(folder, args.runs, args.stop)
    clusters = {}
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        for label, env in (("in the worker", {"RPR_COSIM_SUPERVISE": "0"}), ("supervised", {})):
            clusters[label] = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                                       dashboard_address=None, env=env)
    try:
        figures: dict[str, dict[str, list[float]]] = {k: {"batch": [], "wall": [], "init": []} for k in clusters}
        for label, cluster in clusters.items():
            one_batch(path, cluster.scheduler_address, folder)  # warm-up
        for _ in range(args.repeat):
            for label, cluster in clusters.items():
                wall, rows = one_batch(path, cluster.scheduler_address, folder)
                figures[label]["batch"].append(wall / args.runs)
                figures[label]["wall"].append(statistics.median(r["wall_s"] for r in rows))
                figures[label]["init"].append(statistics.median(r["init_s"] for r in rows))
    finally:
        for cluster in clusters.values():
            cluster.close()
    steps = round(args.stop / 1e-3)
    print(f"Dask batch of {args.runs} runs of pid_step ({steps} steps each), one single-threaded worker; "
          f"medians (minima) of {args.repeat} batches, per run [ms]:")
    print(f"{'':<16} {'batch wall / run':>18} {'row wall_s':>18} {'row init_s':>18}")
    for label, f in figures.items():
        cells = [f"{1e3 * statistics.median(v):8.1f} ({1e3 * min(v):6.1f})" for v in (f["batch"], f["wall"], f["init"])]
        print(f"{label:<16} " + " ".join(f"{c:>18}" for c in cells))
    a, b = figures["in the worker"], figures["supervised"]
    print(f"supervision adds {1e3 * (statistics.median(b['batch']) - statistics.median(a['batch'])):+.1f} ms per run "
          f"(batch wall, medians; {1e3 * (min(b['batch']) - min(a['batch'])):+.1f} ms minima)")
    print(f"(load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
