"""The power-bond master (``ecco``) against fixed-step Gauss-Seidel on the thesis's closed-loop
scene, with the mechanism declared non-rollback (``components.mech.rollback: false``).

For each run: steps taken, smallest and largest step, the stepping loop's wall time, the platform
position [m] and orientation [rad] error against the monolithic CVODES reference (every 0.1 ms,
interpolated onto the run's instants), and for ecco the per-bond residuals (largest scaled residual
of a step, steps over tolerance, the run's net residual against the energy the bond carried).
Gauss-Seidel (linear inputs, compiled loop) at 1 ms and at the step that reaches ecco's position
error are the peers; all runs in one process, one after the other.

    python3 benchmarks/bench_ecco.py [--rtol 1e-3 ...] [--gs-steps 1e-3,2.5e-4]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.analysis.trace_diff import compare  # noqa: E402
from cosim.run.reference import reference  # noqa: E402
from cosim.run.execute import run  # noqa: E402

SCENE = ROOT / "scenarios" / "pid_step.yaml"
POSE = ["mech.platform.x", "mech.platform.y", "mech.platform.phi"]


def errors(res, ref) -> tuple[float, float]:
    d = {x.name: x.max_abs for x in compare(res.trace, ref, POSE)}
    return max(d[POSE[0]], d[POSE[1]]), d[POSE[2]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rtol", default="1e-3", help="ecco rtol values, comma-separated (atol = rtol * 1e-4 J)")
    ap.add_argument("--gs-steps", default="1e-3,5e-4,2.5e-4", help="Gauss-Seidel steps [s], comma-separated")
    args = ap.parse_args()
    ref = reference(SCENE, {"master.step": 1e-4, "master.output_interval": 1e-4}).trace
    print(f"{'run':<34} {'steps':>6} {'h_min':>9} {'h_max':>9} {'wall s':>7} {'pos m':>9} {'phi rad':>9}")
    for rtol in (float(x) for x in args.rtol.split(",")):
        res = run(SCENE, {"master.algorithm": "ecco", "components.mech.rollback": False,
                          "master.options.rtol": rtol, "master.options.atol": rtol * 1e-4})
        s = res.stats
        pos, phi = errors(res, ref)
        print(f"{f'ecco rtol={rtol:g} ({res.status})':<34} {s['accepted_steps']:>6} {s['smallest_step']:>9.2e} "
              f"{s['largest_step']:>9.2e} {s['wall_s']:>7.3f} {pos:>9.2e} {phi:>9.2e}")
        for name, b in s["bonds"].items():
            print(f"    {name:<30} max eps {b['max_scaled_residual']:6.2f}, over tolerance "
                  f"{b['steps_over_tolerance']}/{s['accepted_steps']}, net {b['energy_residual_sum_J']:+.2e} J of "
                  f"{b['energy_J']:.2e} J carried (scaled {b['run_scaled_residual']:.3f})")
    for h in (float(x) for x in args.gs_steps.split(",")):
        res = run(SCENE, {"master.step": h, "master.output_interval": max(h, 1e-3)})
        pos, phi = errors(res, ref)
        n, label = res.stats["steps_done"], f"gauss_seidel {h:g} s ({res.stats['engine']})"
        print(f"{label:<34} {n:>6} {h:>9.2e} {h:>9.2e} "
              f"{res.stats['wall_s']:>7.3f} {pos:>9.2e} {phi:>9.2e}")


if __name__ == "__main__":
    main()
