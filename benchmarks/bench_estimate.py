"""How good is every run's own error estimate?  Against the truth: the monolithic reference.

For each case (a shipped scene, an algorithm, its inputs, a step or tolerance) the run's own
estimate of its worst error (:mod:`cosim.master.estimate`, per recorded signal relative to its
range, the worst signal) is set beside the true worst error: the largest deviation of any
recorded signal from the scene's monolithic reference (CVODES at rtol 1e-10; at the run's own
instants for a variable-step run, so no interpolation enters), relative to the reference's range
(``rpr-cosim compare``), at least :data:`cosim.master.estimate.FLAT` like the estimate's.  The ratio estimate / truth is printed per case, and the summary counts
the cases within a factor of 3 (or above the truth) and the worst underestimate.

A case where both the estimate and the truth are at least half of a signal's range is "both
unstable": the run is all error there, it is reported "unstable" (the verdict is right), and a
ratio of two numbers that only say "the signal is lost" means nothing; it counts as agreeing.

    python3 benchmarks/bench_estimate.py [--quick] [--out docs/accuracy_cases.csv]
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.analysis.trace_diff import compare  # noqa: E402
from cosim.master.estimate import UNSTABLE  # noqa: E402
from cosim.run.execute import run  # noqa: E402
from cosim.run.reference import reference  # noqa: E402


def fixed(alg: str, inputs: str, steps) -> list[list[str]]:
    """Fixed-step cases, recorded every 1 ms or every step when longer."""
    return [[f"master.algorithm={alg}", f"master.inputs={inputs}", f"master.step={h}",
             f"master.output_interval={max(h, 1e-3)}"] for h in steps]


def variable(alg: str, rtols) -> list[list[str]]:
    return [[f"master.algorithm={alg}", f"master.options.rtol={r}"] for r in rtols]


#: (scene, stop time [s], [overrides per case]).  The quick set is the first case of each group.
CASES = [
    ("two_mass", 10.0, fixed("jacobi", "hold", (1e-3, 2e-3, 5e-3)) + fixed("gauss_seidel", "hold", (2e-3, 5e-3, 1e-2))
     + fixed("jacobi", "linear", (1e-3, 2e-3)) + fixed("gauss_seidel", "linear", (5e-3, 1e-2))
     + fixed("iterative", "hold", (5e-3, 2e-2)) + variable("adaptive", (1e-3, 1e-4, 1e-5))
     + [["master.algorithm=jacobi", "master.step=1e-2", "master.output_interval=1e-2"]]),  # the default: unstable
    ("pid_step", 1.0, fixed("gauss_seidel", "linear", (1e-3, 5e-4, 2.5e-4)) + fixed("gauss_seidel", "hold", (1e-3, 2.5e-4))
     + fixed("jacobi", "linear", (5e-4, 2.5e-4)) + fixed("iterative", "linear", (1e-3,))
     + variable("adaptive", (1e-4, 3e-5, 1e-5, 3e-6)) + variable("ecco", (1e-3, 1e-4))),
    ("rig_step", 1.0, fixed("gauss_seidel", "hold", (1e-3, 5e-4)) + fixed("gauss_seidel", "linear", (1e-3,))
     + fixed("jacobi", "hold", (1e-3,)) + variable("adaptive", (1e-3, 1e-4, 1e-5))),
    ("force_loop", 1.0, fixed("iterative", "linear", (1e-3, 2e-3, 5e-3)) + fixed("iterative", "hold", (1e-3, 5e-3))),
    ("vw_compare", 1.0, fixed("gauss_seidel", "linear", (1e-3, 2e-3)) + fixed("jacobi", "hold", (1e-3,))),
]


def case(scene: str, stop: float, sets: list[str], cache) -> dict:
    """One run, its estimate and its true error against the reference."""
    path = ROOT / "scenarios" / f"{scene}.yaml"
    sets = [f"stop_time={stop}", *sets]
    row = {"scene": scene, "settings": " ".join(s.split("=", 1)[0].rsplit(".", 1)[-1] + "=" + s.split("=", 1)[1]
                                                for s in sets[1:])}
    t0 = time.perf_counter()
    res = run(path, sets, cache_dir=cache)
    row["run_s"] = time.perf_counter() - t0
    row["status"] = res.status
    est = res.stats.get("estimate") or {}
    row["estimate"], row["est_signal"] = est.get("worst"), est.get("signal", "")
    irregular = res.stats.get("smallest_step") is not None
    ref = reference(res.scene, times=res.trace.time if irregular else None)
    diffs = compare(res.trace, ref.trace)
    # relative to the reference's range, at least the estimate's floor FLAT (a signal flat by design)
    worst = max(diffs, key=lambda d: d.relative)
    row["true"], row["true_signal"] = worst.relative, worst.name
    e, t = row["estimate"], row["true"]
    if e is None:
        row["ratio"], row["verdict"] = math.nan, "no estimate"
    elif e >= UNSTABLE and t >= UNSTABLE:
        row["ratio"], row["verdict"] = e / t if t > 0 else math.inf, "both unstable"
    else:
        row["ratio"] = e / t if t > 0 else math.inf
        row["verdict"] = ("within 3x" if 1 / 3 <= row["ratio"] <= 3 else "above 3x" if row["ratio"] > 3
                          else "below 10x" if row["ratio"] < 0.1 else "below 3x")
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the first case of each scene only")
    ap.add_argument("--out", type=Path, help="also write the table as CSV")
    ap.add_argument("--cache", type=Path, help="FMU cache directory")
    ap.add_argument("--scenes", nargs="*", help="only these scenes")
    args = ap.parse_args()
    rows = []
    print(f"{'scene':<11} {'settings':<44} {'status':<10} {'estimate':>9} {'true':>9} {'ratio':>7}  verdict")
    for scene, stop, cases in CASES:
        if args.scenes and scene not in args.scenes:
            continue
        for sets in cases[:1] if args.quick else cases:
            r = case(scene, stop, sets, args.cache)
            rows.append(r)
            est = f"{r['estimate']:.2e}" if r["estimate"] is not None else "-"
            print(f"{r['scene']:<11} {r['settings']:<44} {r['status']:<10} {est:>9} {r['true']:>9.2e} "
                  f"{r['ratio']:>7.2f}  {r['verdict']}", flush=True)
    agree = sum(r["verdict"] in ("within 3x", "above 3x", "both unstable") for r in rows)
    within = sum(r["verdict"] in ("within 3x", "both unstable") for r in rows)
    low = [r["ratio"] for r in rows if r["verdict"] not in ("no estimate", "both unstable")]
    print(f"\n{len(rows)} cases: {within} within a factor 3 ({100 * within / max(1, len(rows)):.0f} %), {agree} within "
          f"a factor 3 or above the truth ({100 * agree / max(1, len(rows)):.0f} %); smallest ratio estimate/truth "
          f"{min(low) if low else math.nan:.2f}, largest {max(low) if low else math.nan:.2f}; "
          f"{sum(r['verdict'] == 'no estimate' for r in rows)} without an estimate")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with args.out.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
