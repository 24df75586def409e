"""Equal error, wall time: the adaptive master against fixed-step Gauss-Seidel on ``pid_step``.

Issue 10's performance target: at equal error against the monolithic reference (every recorded
variable within ``--tol`` = 1e-3 of its range over the whole run, start transient included), the
wall time of the best algorithm against fixed-step Gauss-Seidel (linear inputs, compiled loop) at
the step that reaches the same error; target at least 10x less.

1. The reference is the scene's monolithic CVODES solution (:mod:`cosim.run.reference`), every
   microsecond through the first 20 ms (the motors' 0.44 ms electrical transient) and every
   0.1 ms after, as in ``tests/test_algorithms.py``; the error of a run is its worst variable's
   largest deviation over its own recorded instants, relative to that variable's range.
2. Fixed step: the largest step dividing the stop time whose run (recorded every step) meets the
   tolerance, by bisection over those steps.
3. Adaptive: the largest ``rtol`` on a grid of 2^(1/4) ratios whose run meets the tolerance.
4. Both, at those settings, back to back ``--repeat`` times (best wall time of each; the wall time
   is the stepping loop, FMUs built and initialised before, as for every master benchmark; the
   fixed-step runs recorded every millisecond only, fewer rows than the adaptive run records), and
   the adaptive run's Python loop once for the master's own cost per step.

    python benchmarks/bench_work_precision.py [--tol 1e-3] [--repeat 5] [--stop 5]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402

from cosim.analysis.trace_diff import compare  # noqa: E402
from cosim.run.reference import reference  # noqa: E402
from cosim.run.execute import run  # noqa: E402
from cosim.trace.traces import Trace  # noqa: E402
import oracles  # noqa: E402 - the Python twins of the kernels (tests/oracles), as engine 'oracle'

oracles.register()

SCENE = ROOT / "scenarios" / "pid_step.yaml"
FINE_UNTIL = 0.02  # [s] the reference every microsecond up to here


def references(stop: float) -> tuple[Trace, Trace]:
    """The monolithic reference: every microsecond through the start, every 0.1 ms after."""
    fine = reference(SCENE, {"stop_time": FINE_UNTIL, "master.step": 1e-6, "master.output_interval": 1e-6})
    coarse = reference(SCENE, {"stop_time": stop, "master.step": 1e-4, "master.output_interval": 1e-4})
    for r in (fine, coarse):
        if not r.ok:
            raise SystemExit(f"the monolithic reference failed: {r.reason}")
    return fine.trace, coarse.trace


def worst_error(tr: Trace, fine: Trace, coarse: Trace) -> tuple[float, str]:
    """Largest deviation of any recorded variable relative to its range (the reference's, whole
    run), and that variable."""
    span = {n: float(np.ptp(coarse[n])) for n in coarse.names}
    worst: dict[str, float] = {}
    for ref, a, b in ((fine, 0.0, FINE_UNTIL), (coarse, FINE_UNTIL, coarse.time[-1])):
        keep = (tr.time >= a) & (tr.time <= b)
        for d in compare(Trace(tr.columns, tr.data[keep]), ref):
            if span[d.name] > 0:
                worst[d.name] = max(worst.get(d.name, 0.0), d.max_abs / span[d.name])
    name = max(worst, key=worst.get)
    return worst[name], name


def fixed(step: float, stop: float, output_interval: float | None = None):
    """Fixed-step Gauss-Seidel with linear inputs, recorded every step unless ``output_interval``."""
    return run(SCENE, {"stop_time": stop, "master.algorithm": "gauss_seidel", "master.inputs": "linear",
                       "master.step": step, "master.output_interval": output_interval or step})


def adaptive(rtol: float, stop: float, engine: str = "compiled"):
    return run(SCENE, {"stop_time": stop, "master.algorithm": "adaptive", "master.options": {"rtol": rtol}},
               engine=engine)


def steps_dividing(stop: float, lo: float, hi: float) -> list[float]:
    """Steps in [lo, hi] [s] that are whole nanoseconds and divide ``stop``, ascending."""
    total = round(stop * 1e9)
    out = []
    for n in range(max(1, math.ceil(stop / hi)), math.floor(stop / lo) + 1):
        if total % n == 0:
            out.append(total // n / 1e9)
    return sorted(out)


def largest_passing(candidates: list, passes) -> tuple[object, dict]:
    """Bisection for the largest candidate (ascending list, error growing along it) that passes;
    ``passes(c)`` returns (ok, info).  Returns (candidate, info) or (None, {})."""
    lo, hi, best = 0, len(candidates) - 1, (None, {})
    while lo <= hi:
        mid = (lo + hi) // 2
        ok, info = passes(candidates[mid])
        if ok:
            best, lo = (candidates[mid], info), mid + 1
        else:
            hi = mid - 1
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tol", type=float, default=1e-3, help="error relative to range on every variable (1e-3)")
    ap.add_argument("--repeat", type=int, default=5, help="back-to-back timing runs of each (best of)")
    ap.add_argument("--stop", type=float, default=5.0, help="simulated time [s] (default 5, the scene's)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    fine, coarse = references(args.stop)
    print(f"reference: {time.perf_counter() - t0:.1f} s")

    tried: dict[float, float] = {}  # fixed step -> worst error

    def check(label: str, res) -> tuple[bool, dict]:
        err, name = worst_error(res.trace, fine, coarse) if res.ok else (math.inf, res.reason)
        st = res.stats
        if res.stats["algorithm"] == "gauss_seidel":
            tried[res.stats["step"]] = err
        print(f"  {label:<34} {res.status:>8} wall {st['wall_s']:8.3f} s  worst {err:9.3e} ({name})", flush=True)
        return err <= args.tol, {"err": err, "name": name}

    print(f"fixed-step Gauss-Seidel, linear inputs: the largest step within {args.tol:g} of range")
    h, h_info = largest_passing(steps_dividing(args.stop, 1e-5, 4e-4),
                                lambda h: check(f"step {h * 1e6:g} us", fixed(h, args.stop)))
    print(f"adaptive: the largest rtol within {args.tol:g} of range")
    grid = [1e-6 * 2 ** (k / 4) for k in range(0, 45)]
    rtol, r_info = largest_passing(grid, lambda r: check(f"rtol {r:.3g}", adaptive(r, args.stop)))
    if h is None or rtol is None:
        raise SystemExit("no setting met the tolerance")

    print(f"back to back, {args.repeat} times each")
    walls: dict[str, list[float]] = {"fixed": [], "adaptive": []}
    stats = {}
    for _ in range(args.repeat):
        # the fixed step recorded every millisecond only (its error was measured at every step above):
        # fewer rows than the adaptive run's, so recording does not count against it
        for key, fn in (("fixed", lambda: fixed(h, args.stop, 1e-3)), ("adaptive", lambda: adaptive(rtol, args.stop))):
            res = fn()
            walls[key].append(res.stats["wall_s"])
            stats[key] = res.stats
    slow = adaptive(rtol, args.stop, engine="oracle").stats
    fa, ad = min(walls["fixed"]), min(walls["adaptive"])
    attempts = stats["adaptive"]["accepted_steps"] + stats["adaptive"]["rejected_steps"]
    n_fixed = stats["fixed"]["steps_done"]
    print()
    print(f"{'':<38} {'steps':>9} {'wall s':>9} {'master us/step':>15} {'worst err':>10}")
    print(f"{'gauss_seidel linear, step %g us' % (h * 1e6):<38} {n_fixed:>9,} {fa:>9.4f} "
          f"{stats['fixed']['master_s'] / n_fixed * 1e6:>15.3f} {h_info['err']:>10.3e}")
    print(f"{'adaptive rtol %.3g, compiled' % rtol:<38} {attempts:>9,} {ad:>9.4f} "
          f"{stats['adaptive']['master_s'] / attempts * 1e6:>15.3f} {r_info['err']:>10.3e}")
    print(f"{'adaptive rtol %.3g, Python loop' % rtol:<38} {attempts:>9,} {slow['wall_s']:>9.4f} "
          f"{slow['master_s'] / attempts * 1e6:>15.3f}")
    print(f"  (adaptive: {stats['adaptive']['accepted_steps']:,} accepted + {stats['adaptive']['rejected_steps']:,} "
          f"rejected steps, {stats['adaptive']['smallest_step']:.3g} s to {stats['adaptive']['largest_step']:.3g} s)")
    ratio = fa / ad
    print(f"fixed-step / adaptive wall time at equal error: {ratio:.1f}x "
          f"(target >= 10x: {'met' if ratio >= 10 else 'NOT met'}); all runs: fixed "
          f"{', '.join(f'{w:.3f}' for w in walls['fixed'])}, adaptive {', '.join(f'{w:.3f}' for w in walls['adaptive'])}")
    above = [x for x in tried if x > h and math.isfinite(tried[x])]
    if above:  # a step between the dividing ones: the error's power law through the bracketing runs
        h2 = min(above)
        q = math.log(tried[h2] / tried[h]) / math.log(h2 / h)
        h_eq = h * (args.tol / tried[h]) ** (1 / q)
        print(f"  the step reaching exactly {args.tol:g} (error ~ h^{q:.2f} between {h * 1e6:g} and {h2 * 1e6:g} us) "
              f"would be {h_eq * 1e6:.1f} us: {fa * h / h_eq:.4f} s, {ratio * h / h_eq:.1f}x")


if __name__ == "__main__":
    main()
