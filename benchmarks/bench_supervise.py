"""What supervision costs (issue 20, item 1): a supervised run (the stepping in a forked child, the
parent watching the breadcrumb) against the same run in-process, and the breadcrumb's cost per
FMI call in the compiled loop and from Python.

1. Whole runs: ``cosim.run.execute.run`` of ``pid_step`` (7 catalog FMUs, cached) for a short
   and a longer stop time, supervised (the default) and with ``$RPR_COSIM_SUPERVISE=0``,
   alternated; medians and minima of ``--repeat`` runs each, in this process (imports and FMU
   builds are not part of the figure).
2. The compiled loop with the breadcrumb against the same loop compiled with the breadcrumb
   macros defined away (``FMI(key, c, expr)`` -> ``expr``), on a ring of trivial FMUs (the
   hostile FMU of the tests, well behaved: its doStep is a few nanoseconds, so the loop's own
   cost dominates and the breadcrumb's share is the largest it can be); per FMI call.
3. The Python breadcrumb (``crumb.enter`` + ``crumb.leave``) per call, by ``timeit``.
4. One request to a stepping child and its answer (:class:`cosim.run.supervise.Server`, the
   mechanism of supervised Dask runs: a pickle each way over a pipe, the child watched), a
   small message such as one step's inputs and outputs, against one whole step of ``pid_step``
   (eight FMUs) in-process: what a component run out of process (``isolation: process``, not
   built) would add to every communication step at the least.

    python3 benchmarks/bench_supervise.py [--repeat 7] [--steps 200000] [--only runs,loop,crumb,server]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import timeit
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from cosim.master import fastloop  # noqa: E402
from cosim.master.entries import RUN  # noqa: E402
from cosim.master.kernels import compile_loop  # noqa: E402
from cosim.run.execute import run  # noqa: E402
from cosim.slaves import crumb  # noqa: E402


def run_times(scene, sets, repeat: int) -> tuple[list[float], list[float]]:
    """Wall times [s] of ``repeat`` in-process and supervised runs, alternated (a busy machine's
    drift falls on both alike)."""
    plain, sup = [], []
    for _ in range(repeat):
        for flag, out in (("0", plain), ("1", sup)):
            os.environ["RPR_COSIM_SUPERVISE"] = flag
            t0 = time.perf_counter()
            res = run(scene, sets)
            out.append(time.perf_counter() - t0)
            assert res.ok, res.reason
    os.environ.pop("RPR_COSIM_SUPERVISE")
    return plain, sup


def loop_ns_per_call(steps: int, repeat: int) -> tuple[float, float, int]:
    """(with, without) breadcrumb: wall ns per FMI call of the compiled loop on trivial FMUs."""
    from hostile_fmu import build_hostile_fmu, hostile_scene

    folder = Path(tempfile.mkdtemp(prefix="bench-supervise-"))
    scene = hostile_scene(folder, build_hostile_fmu(folder), stop_time=steps * 1e-3)
    sets = ["master.output_interval=1"]
    os.environ["RPR_COSIM_SUPERVISE"] = "0"  # the loop alone, in this process
    from fmus.c_loader import FLAGS

    plain = compile_loop("fastloop.c", "rpr_loop_nocrumb", [RUN], (*FLAGS, "-DRPR_NO_CRUMB"))  # crumb.h's bare calls
    real = fastloop.library

    def wall(lib) -> float:
        fastloop.library = lambda: lib
        try:
            res = run(scene, sets, engine="compiled")
            assert res.ok, res.reason
            return res.stats["wall_s"]
        finally:
            fastloop.library = real

    runs: dict[str, list[float]] = {"with": [], "without": []}
    for _ in range(repeat):  # alternated, minima: the machine's drift falls on both alike
        runs["with"].append(wall(real()))
        runs["without"].append(wall(plain))
    with_crumb, without = min(runs["with"]), min(runs["without"])
    os.environ.pop("RPR_COSIM_SUPERVISE")
    calls = steps * 2 * 3  # two FMUs, set + doStep + get each per step
    return 1e9 * with_crumb / calls, 1e9 * without / calls, calls


def round_trip_us(repeat: int, n: int = 2000) -> tuple[float, float]:
    """(median, minimum) wall time [us] of one request and answer to a stepping child, over
    ``repeat`` rounds of ``n``; the message: a step's time, size and six values each way."""
    from cosim.run.supervise import Server

    server = Server(lambda request: request)
    try:
        server.call(None)
        rounds = []
        message = (1.0, 1e-3, [0.1] * 6)
        for _ in range(repeat):
            t0 = time.perf_counter()
            for _ in range(n):
                server.call(message)
            rounds.append((time.perf_counter() - t0) / n)
    finally:
        server.close()
    return 1e6 * statistics.median(rounds), 1e6 * min(rounds)


def step_us(scene, repeat: int, steps: int = 5000) -> tuple[float, float]:
    """(median, minimum) loop wall time per communication step [us] of ``scene`` in-process."""
    os.environ["RPR_COSIM_SUPERVISE"] = "0"
    try:
        per = []
        for _ in range(repeat):
            res = run(scene, [f"stop_time={steps * 1e-3}"])
            assert res.ok, res.reason
            per.append(res.stats["wall_s"] / res.stats["steps_done"])
    finally:
        os.environ.pop("RPR_COSIM_SUPERVISE")
    return 1e6 * statistics.median(per), 1e6 * min(per)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--steps", type=int, default=200_000)
    ap.add_argument("--only", default="runs,loop,crumb,server", help="comma-separated sections")
    args = ap.parse_args(argv)
    only = set(args.only.split(","))
    scene = ROOT / "scenarios" / "pid_step.yaml"
    run(scene, ["stop_time=0.01"])  # FMUs built and cached, loop compiled, imports done
    if "runs" in only:
        print(f"{'whole run of pid_step':<34} {'in-process s':>16} {'supervised s':>16} {'added ms':>14}")
        print(f"{'':<34} {'median    min':>16} {'median    min':>16} {'median    min':>14}")
        for stop in (0.01, 1.0):
            plain, sup = run_times(scene, [f"stop_time={stop}"], args.repeat)
            pm, ps, sm, ss = statistics.median(plain), min(plain), statistics.median(sup), min(sup)
            print(f"  stop_time = {stop:<5g} ({int(stop / 1e-3):>5} steps) {pm:>8.3f} {ps:>7.3f} {sm:>8.3f} "
                  f"{ss:>7.3f} {1e3 * (sm - pm):>+7.1f} {1e3 * (ss - ps):>+6.1f}")
    if "loop" in only:
        with_ns, without_ns, calls = loop_ns_per_call(args.steps, max(5, args.repeat))
        print(f"compiled loop, trivial FMUs, {calls:,} FMI calls (fastest of alternated runs): {with_ns:.2f} ns per "
              f"call with the breadcrumb, {without_ns:.2f} ns without ({with_ns - without_ns:+.2f} ns per call)")
    if "crumb" in only:
        k = crumb.key("bench")
        n = 200_000
        per = min(timeit.repeat(lambda: (crumb.enter(k, 7, 0.0), crumb.leave()), number=n, repeat=5)) / n
        print(f"Python breadcrumb (enter + leave): {1e9 * per:.0f} ns per FMI call made from Python")
    if "server" in only:
        rt, rt_min = round_trip_us(max(5, args.repeat))
        st, st_min = step_us(scene, max(5, args.repeat))
        print(f"one request and answer to a stepping child (supervise.Server): {rt:.1f} us median ({rt_min:.1f} min); "
              f"one whole step of pid_step in-process (8 FMUs, compiled loop): {st:.1f} us ({st_min:.1f}): "
              f"x{(st + rt) / st:.1f} per step with one component out of process, at the least")
    print(f"(medians of {args.repeat} runs; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
