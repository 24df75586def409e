"""The driver loop's cost, in CPU time, against another checkout: a check that a change to the run
loop left the fixed-step master's cost per FMU step and the guards' cost per row unchanged, usable
on a loaded machine (wall-time benchmarks such as bench_master.py swing by 2-4x there; the CPU
time of the stepping process does not count the time other processes hold the cores).

Two figures, each measured alternately in this tree and in ``--against`` (another checkout, e.g.
the main branch before the change), ``--rounds`` times, each round in fresh processes:

- per-FMU step cost [us] of the compiled fixed-step loop on bench_master.py's ring of 4 RK4 lag
  FMUs (Jacobi, Gauss-Seidel, Jacobi without per-slave timing, Gauss-Seidel with linear inputs):
  CPU time of ``simulate`` for 220000 steps minus that for 20000 steps (start-up cancels), per
  200000 steps and FMU, best of 5;
- the guards' check [us per row] of pid_step's rows in blocks of 64, 1024 and 5001 rows (all four
  guards, bench_guards.py's last section), best of 5 x 50 checks.

With ``--kernels``, instead: the compiled variable-step and iterative kernels' cost on all-FMU
scenes [us CPU per coupling pass (iterative) or accepted step (ecco, adaptive)], each the CPU time
of the scene's ``simulate`` (in process, no supervision) to its stop time minus that to a
hundredth of it, best of 5: iterative on two_mass (kc 1000 N/m, 5 ms, 100 s) and force_loop (40 s),
ecco on pid_step with the mechanism non-rollback (5 s), adaptive on pid_step (3 s).

    python3 benchmarks/bench_loop.py --against ../main [--rounds 4] [--kernels]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = (("jacobi", True, "hold"), ("gauss_seidel", True, "hold"), ("jacobi", False, "hold"),
         ("gauss_seidel", True, "linear"))


def _label(alg: str, timing: bool, inputs: str) -> str:
    return f"{alg}{'' if timing else ', no timing'}, {inputs}"


def measure(root: Path) -> dict[str, float]:
    """The figures of the module docstring in this process, of the checkout ``root`` (first on
    ``sys.path``: its cosim, fmus, bench_master.py and scenes)."""
    sys.path[:0] = [str(root), str(root / "benchmarks")]
    import bench_master as bm  # noqa: E402  (the ring and its FMU)
    import fmus  # noqa: E402
    from cosim.master import CoupledSystem, simulate  # noqa: E402
    from cosim.run.execute import run  # noqa: E402
    from cosim.run.row_guards import scene_guard  # noqa: E402
    from cosim.scenario import load  # noqa: E402

    path = fmus.build_fmu(bm.lag_block())

    def cpu(alg: str, steps: int, timing: bool, inputs: str) -> float:
        slaves, links = bm.ring(4, path)
        system = CoupledSystem(slaves, links, [(0, "y")])
        t0 = time.process_time()
        st = simulate(system, alg, step_ns=1_000_000, n_steps=steps, engine="compiled", timing=timing,
                      start_values=[{"x": 1.0}] + [{} for _ in range(3)], inputs=inputs)
        assert st.status == "ok" and st.engine == "compiled", st.reason
        return time.process_time() - t0

    out = {}
    for alg, timing, inputs in CASES:
        long_ = min(cpu(alg, 220_000, timing, inputs) for _ in range(5))
        short = min(cpu(alg, 20_000, timing, inputs) for _ in range(5))
        out[f"per-FMU step [us], {_label(alg, timing, inputs)}"] = 1e6 * (long_ - short) / 200_000 / 4
    scene = load(root / "scenarios" / "pid_step.yaml")
    rows = run(scene).trace.data
    for n in (64, 1024, 5001):
        best = None
        for _ in range(5):
            g = scene_guard(scene)
            g.bind(scene.outputs)
            g.check(rows[:n])
            t0 = time.process_time()
            for _ in range(50):
                g.check(rows[:n])
            dt = (time.process_time() - t0) / 50
            best = dt if best is None else min(best, dt)
        out[f"guards [us per row], blocks of {n} rows"] = 1e6 * best / n
    return out


KERNEL_CASES = (  # (figure, scene, overrides, stop time [s], the statistic counted)
    ("iterative, two_mass [us per pass]", "two_mass.yaml",
     {"master.algorithm": "iterative", "components.mass2.params.kc": 1000.0, "master.step": 0.005}, 100.0,
     "iterations_total"),
    ("iterative, force_loop [us per pass]", "force_loop.yaml", {"master.algorithm": "iterative"}, 40.0,
     "iterations_total"),
    ("ecco, pid_step [us per step]", "pid_step.yaml", {"master.algorithm": "ecco", "components.mech.rollback": False},
     5.0, "accepted_steps"),
    ("adaptive, pid_step [us per step]", "pid_step.yaml", {"master.algorithm": "adaptive"}, 3.0, "accepted_steps"),
)


def measure_kernels(root: Path) -> dict[str, float]:
    """The ``--kernels`` figures (module docstring) of the checkout ``root``, in this process."""
    sys.path[:0] = [str(root)]
    from cosim.run.execute import build_components, couple, simulate_scene  # noqa: E402
    from cosim.scenario import load  # noqa: E402
    from cosim.scenario.recipes import slave_description  # noqa: E402
    from cosim.slaves.fmu_slave import FmuSlave  # noqa: E402

    def cpu(scene_file: str, sets: dict, stop: float, count: str) -> tuple[float, float]:
        scene = load(root / "scenarios" / scene_file, {**sets, "stop_time": stop})
        paths = build_components(scene)
        slaves = [FmuSlave(n, paths[n], c.description if c.kind == "fmu" else slave_description(c, paths[n]))
                  for n, c in scene.components.items()]
        try:
            t0 = time.process_time()
            st = simulate_scene(scene, couple(scene, slaves), [], "compiled", None)
            dt = time.process_time() - t0
        finally:
            for s in slaves:
                s.release()
        assert st.engine == "compiled", st.engine
        return dt, st.as_dict()[count]

    out = {}
    for label, scene_file, sets, stop, count in KERNEL_CASES:
        long_, n_long = min(cpu(scene_file, sets, stop, count) for _ in range(5))
        short, n_short = min(cpu(scene_file, sets, stop / 100, count) for _ in range(5))
        out[label] = 1e6 * (long_ - short) / (n_long - n_short)
    return out


def in_tree(tree: Path, kernels: bool = False) -> dict[str, float]:
    """:func:`measure` (``kernels``: :func:`measure_kernels`) of ``tree`` in a fresh process (this
    file's code, that tree's modules)."""
    fn = "measure_kernels" if kernels else "measure"
    code = (f"import json, runpy; m = runpy.run_path({str(Path(__file__).resolve())!r}, run_name='bench_loop'); "
            f"print(json.dumps(m[{fn!r}](__import__('pathlib').Path({str(tree)!r}))))")
    res = subprocess.run([sys.executable, "-c", code], cwd=tree, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(tree)})
    if res.returncode != 0:
        raise SystemExit(f"bench_loop in {tree} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", type=Path, required=True, help="another checkout (e.g. the main branch)")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--kernels", action="store_true", help="the variable-step and iterative kernels instead")
    args = ap.parse_args()
    here, there = ROOT, args.against.resolve()
    runs: dict[str, list[dict[str, float]]] = {"this tree": [], "against": []}
    for _ in range(args.rounds):
        runs["against"].append(in_tree(there, args.kernels))
        runs["this tree"].append(in_tree(here, args.kernels))
    print(f"CPU time, {args.rounds} alternating rounds; this tree {here}, against {there}:")
    print(f"  {'figure':<52} {'against (best, median)':>24} {'this tree (best, median)':>26} {'best ratio':>10}")
    for key in runs["against"][0]:
        a = [r[key] for r in runs["against"]]
        b = [r[key] for r in runs["this tree"]]
        print(f"  {key:<52} {min(a):>11.4f} {statistics.median(a):>11.4f}  {min(b):>12.4f} {statistics.median(b):>12.4f}"
              f" {min(b) / min(a):>10.2f}")


if __name__ == "__main__":
    main()
