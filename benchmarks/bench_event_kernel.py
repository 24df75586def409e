"""FMI 3.0 event mode in the fixed-step kernels (cosim/master/fastloop.c and iterative_engine.c,
``event_step``) against the Python loop: the Reference FMUs' BouncingBall driving Feedthrough (both
in event mode: each bounce cuts the step for both, the one that stepped past it restored through
its FMU state; under iterative every one, and the coupling iterated again to the bounce), 1 ms
step, under Jacobi, Gauss-Seidel and iterative.  Wall time of the stepping loop (``wall_s`` of the run statistics),
best of ``--repeat``, and its share per macro step; the two engines' traces are checked equal.

    RPR_REFERENCE_FMUS_SRC=... python3 benchmarks/bench_event_kernel.py [--stop 5] [--repeat 3]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from conftest import REFERENCE_FMUS_SRC, _source_key, build_reference_fmus  # noqa: E402

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import from_dict  # noqa: E402
from fmus.cache import cache_root  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--stop", type=float, default=5.0, help="stop time [s]")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    fmus = build_reference_fmus(REFERENCE_FMUS_SRC, cache_root().parent / "reference-fmus"
                                / _source_key(REFERENCE_FMUS_SRC))
    comps = {"ball": {"fmu": str(fmus["3.0/BouncingBall"])}, "f": {"fmu": str(fmus["3.0/Feedthrough"])}}
    scene = {"name": "pair", "components": comps, "connections": ["ball.v -> f.Float64_continuous_input"],
             "stop_time": args.stop, "outputs": ["ball.h", "ball.v", "f.Float64_continuous_output"]}
    steps = round(args.stop / 1e-3)
    print(f"BouncingBall -> Feedthrough, 1 ms step, {steps} steps; best of {args.repeat}, stepping loop wall time")
    for algorithm in ("jacobi", "gauss_seidel", "iterative"):
        best, traces, events = {}, {}, 0
        for engine in ("python", "compiled"):
            for _ in range(args.repeat):
                res = run(from_dict({**scene, "master": {"algorithm": algorithm, "step": 1e-3, "estimate": False,
                                                         "engine": engine}}))
                assert res.status == "ok" and res.stats["engine"] == engine, res.reason
                best[engine] = min(best.get(engine, np.inf), res.stats["wall_s"])
            traces[engine], events = res.trace, res.stats["events"]["handled"]
        same = np.array_equal(traces["python"].data, traces["compiled"].data)
        py, cc = (best[e] / steps * 1e6 for e in ("python", "compiled"))
        print(f"  {algorithm:13s} {events} events   Python loop {py:8.2f} us/step   compiled {cc:7.2f} us/step   "
              f"({py / cc:.1f}x)   traces equal: {same}")


if __name__ == "__main__":
    main()
