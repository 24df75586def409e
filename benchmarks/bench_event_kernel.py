"""FMI 3.0 event mode in the fixed-step kernels (cosim/master/fastloop.c and iterative_engine.c,
``event_step``) against the Python loop: the Reference FMUs' BouncingBall driving Feedthrough (both
in event mode: each bounce cuts the step for both, the one that stepped past it restored through
its FMU state; under iterative every one, and the coupling iterated again to the bounce), 1 ms
step, under Jacobi, Gauss-Seidel and iterative; and iterative on a loop of two event-mode lags
(one cut connection, Newton) beside the ball.  Wall time of the stepping loop (``wall_s`` of the run statistics),
best of ``--repeat``, and its share per macro step; the two engines' traces are checked equal.

    RPR_REFERENCE_FMUS_SRC=... python3 benchmarks/bench_event_kernel.py [--stop 5] [--repeat 3]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from conftest import REFERENCE_FMUS_SRC, _source_key, build_lag_fmus, build_reference_fmus  # noqa: E402

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import from_dict  # noqa: E402
from fmus.cache import cache_root  # noqa: E402


def _measure(scene: dict, algorithm: str, repeat: int) -> tuple[float, float, dict, bool]:
    """Best stepping-loop wall time [s] on the Python loop and compiled, the compiled run's
    statistics, and whether the two traces are equal."""
    best, traces, stats = {}, {}, {}
    for engine in ("oracle", "compiled"):  # (conftest registers the oracle)
        for _ in range(repeat):
            res = run(from_dict({**scene, "master": {"algorithm": algorithm, "step": 1e-3, "estimate": False,
                                                     "engine": engine}}))
            assert res.status == "ok" and res.stats["engine"] == engine, res.reason
            best[engine] = min(best.get(engine, np.inf), res.stats["wall_s"])
        traces[engine], stats = res.trace, res.stats
    return best["oracle"], best["compiled"], stats, np.array_equal(traces["oracle"].data, traces["compiled"].data)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--stop", type=float, default=5.0, help="stop time [s]")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    root = cache_root().parent
    fmus = build_reference_fmus(REFERENCE_FMUS_SRC, root / "reference-fmus" / _source_key(REFERENCE_FMUS_SRC))
    comps = {"ball": {"fmu": str(fmus["3.0/BouncingBall"])}, "f": {"fmu": str(fmus["3.0/Feedthrough"])}}
    scene = {"name": "pair", "components": comps, "connections": ["ball.v -> f.Float64_continuous_input"],
             "stop_time": args.stop, "outputs": ["ball.h", "ball.v", "f.Float64_continuous_output"]}
    steps = round(args.stop / 1e-3)
    print(f"BouncingBall -> Feedthrough, 1 ms step, {steps} steps; best of {args.repeat}, stepping loop wall time")
    for algorithm in ("jacobi", "gauss_seidel", "iterative"):
        py, cc, stats, same = _measure(scene, algorithm, args.repeat)
        py, cc = py / steps * 1e6, cc / steps * 1e6
        print(f"  {algorithm:13s} {stats['events']['handled']} events   Python oracle loop {py:8.2f} us/step   compiled "
              f"{cc:7.2f} us/step   ({py / cc:.1f}x)   traces equal: {same}")
    # iterative on a loop: two event-mode lags (tests/data/me_lag, FMI 3.0 co-simulation), one cut connection
    # iterated by Newton (finite differences), beside the ball, whose bounces cut every component's step
    (lags := root / "lag-fmus" / _source_key(REFERENCE_FMUS_SRC)).mkdir(parents=True, exist_ok=True)
    lag = str(build_lag_fmus(REFERENCE_FMUS_SRC, lags)["3cs"])
    comps = {"ball": {"fmu": str(fmus["3.0/BouncingBall"])},
             "a": {"fmu": lag, "params": {"k": 1.0, "g": -1.0}, "start": {"x": 1.0}},
             "b": {"fmu": lag, "params": {"k": 2.0, "g": 1.0}}}
    loop = {"name": "loop", "components": comps, "connections": ["a.x -> b.u", "b.x -> a.u"],
            "stop_time": args.stop, "outputs": ["ball.h", "a.x", "b.x"]}
    py, cc, stats, same = _measure(loop, "iterative", args.repeat)
    py, cc = py / steps * 1e6, cc / steps * 1e6
    print(f"BouncingBall beside a loop of two lags (iterative, {stats['iterations_mean']:.2f} passes per step): "
          f"{stats['events']['handled']} events   Python oracle loop {py:8.2f} us/step   compiled {cc:7.2f} us/step   "
          f"({py / cc:.1f}x)   traces equal: {same}")


if __name__ == "__main__":
    main()
