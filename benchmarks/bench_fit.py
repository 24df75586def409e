"""``rpr-cosim fit`` against the obvious alternative: the same least squares (SciPy's trust-region
reflective solver, same bounds, same weighting, same start) with finite-difference gradients on
the co-simulation (each residual one run of the scene under the master, as a user scripting
``scipy.optimize.least_squares`` around ``rpr-cosim run`` would do).

Data: 5 s at 1 kHz from the virtual board (:mod:`hardware.record`, the ``motor`` plant) with R, k, b
20 %, -15 %, +30 % off the nominal ones and the three pots' gains -11 %, +10 %, -6 % off, 1.5 counts
of ADC noise and 10 mA on the currents.  Six parameters: R, k, b and the pots' ``raw_full``.
Printed in one run: wall time, residual evaluations (and Jacobians), the estimates' worst error
against the truth, and the ratio of the wall times.

    python3 benchmarks/bench_fit.py [--seconds 5] [--max-evaluations 60]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.fit import build, solve  # noqa: E402
from cosim.run import run  # noqa: E402
from cosim.scenario import load  # noqa: E402
from hardware.convert import Calibration  # noqa: E402
from hardware.record import record  # noqa: E402
from hardware.virtual import PlantOptions  # noqa: E402

SCENE = ROOT / "scenarios" / "calibrate" / "rig_motor.yaml"
PARAMS = ["rig.R", "rig.k", "rig.b", "rig.leg[1].raw_full", "rig.leg[2].raw_full", "rig.leg[3].raw_full"]
TRUE = np.array([4.8, 0.0085, 9.75e-6, 3300.0, 4100.0, 3500.0])


def finite_differences(problem, sets: list[str], max_evaluations: int):
    """The same least squares, each residual a co-simulation, gradients by forward differences."""
    from scipy.optimize import least_squares

    count = {"runs": 0}
    names = [u.path for u in problem.unknowns]

    def residual(theta):
        count["runs"] += 1
        over = sets + [f"components.{n.split('.', 1)[0]}.params.{n.split('.', 1)[1]}={float(v)!r}"
                       for n, v in zip(names, theta)]
        res = run(SCENE, over + ["master.estimate=false"])
        y = np.column_stack([res.trace[s] for s in problem.signals])
        return ((y - problem.data) / problem.scale).ravel(order="F")

    lo = np.array([u.lower for u in problem.unknowns])
    hi = np.array([u.upper for u in problem.unknowns])
    t0 = time.perf_counter()
    sol = least_squares(residual, problem.start, jac="2-point", bounds=(lo, hi), method="trf", x_scale="jac",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=max_evaluations)
    return sol.x, time.perf_counter() - t0, count["runs"], sol.message


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--max-evaluations", type=int, default=60, help="cap of the finite-difference fit's iterations")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "rig_recording.csv"
        opts = PlantOptions(fidelity="motor", noise=1.5, seed=11, params={"R": 4.8, "k": 0.0085, "b": 9.75e-6},
                            calibration=tuple(Calibration(raw_full=f) for f in TRUE[3:]))
        t0 = time.perf_counter()
        record(data, opts, seconds=args.seconds, current_noise=0.01)
        print(f"recording: {args.seconds:g} s at 1 kHz in {time.perf_counter() - t0:.1f} s (virtual board, synthetic time)")
        sets = [f"components.rec.replay={data}", f"stop_time={args.seconds}"]
        t0 = time.perf_counter()
        problem = build(load(SCENE, sets), data, PARAMS)
        t_build = time.perf_counter() - t0
        exact = solve(problem)
        err_exact = np.max(np.abs(exact.theta - TRUE) / TRUE)
        print(f"exact Jacobian (CasADi, RK4 x{problem.substeps}): {t_build + exact.wall_s:.2f} s "
              f"({t_build:.2f} s building), {exact.evaluations} evaluations + {exact.jacobians} Jacobians, "
              f"worst error {err_exact:.2%} of the truth")
        theta, wall, runs, message = finite_differences(problem, sets, args.max_evaluations)
        err_fd = np.max(np.abs(theta - TRUE) / TRUE)
        print(f"finite differences on the co-simulation: {wall:.2f} s, {runs} co-simulation runs, worst error "
              f"{err_fd:.2%} of the truth ({message})")
        print(f"ratio: finite differences / exact = {wall / (t_build + exact.wall_s):.1f}x wall time, "
              f"{runs / (exact.evaluations + exact.jacobians):.1f}x model evaluations")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
