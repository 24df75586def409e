"""The iterative master's figures: passes per step, error against an independent reference, cost.

1. ``scenarios/force_loop.yaml`` (an algebraic loop: quasistatic motors under PI force control
   driving the kinematic mechanism) with each iteration variant, against the scene's monolithic
   DAE reference (IDAS at rtol 1e-10, :mod:`cosim.run.reference`).
2. ``scenarios/two_mass.yaml`` at kc = 1000 N/m and a 5 ms step, where fixed-step Jacobi is
   unstable (analytic spectral radius 1.0121 per step, :mod:`models.coupling`), against the exact
   solution of the coupled linear blocks; every algorithm at that step.

Errors are the largest deviation of any recorded signal relative to its range; cost is the
stepping loop's wall time, doStep calls and rollbacks (state restores).

    python3 benchmarks/bench_iterative.py [--stop-loop 2] [--stop-mass 2]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from cosim.analysis.trace_diff import compare  # noqa: E402
from cosim.run.reference import reference  # noqa: E402
from cosim.run.execute import run  # noqa: E402
from cosim.study.stability import growth_per_step  # noqa: E402

LOOP_VARIANTS = (("newton (directional derivatives + Broyden)", "{}"),
                 ("newton (finite differences + Broyden)", "{jacobian: finite_difference}"),
                 ("fixed point, omega 0.15", "{method: fixed_point, omega: 0.15}"),
                 ("fixed point, omega 1", "{method: fixed_point}"))
KC, H = 1000.0, 0.005


def _cost(res) -> str:
    st = res.stats
    calls = sum(s["do_step_calls"] for s in st.get("slaves", {}).values())
    return f"{st['wall_s']:7.3f} s {calls:8d} doSteps {st.get('rollbacks', 0):8d} rollbacks"


def force_loop(stop: float) -> None:
    scene = ROOT / "scenarios" / "force_loop.yaml"
    ref = reference(scene, [f"stop_time={stop}"])
    print(f"force_loop over {stop:g} s at 1 ms; reference {ref.trace.meta.get('method')} {ref.stats['wall_s']:.3f} s")
    spans = {n: float(np.ptp(ref.trace[n])) for n in ref.trace.names}
    for label, opts in LOOP_VARIANTS:
        res = run(scene, [f"stop_time={stop}", "master.algorithm=iterative", f"master.options={opts}"])
        if res.status != "ok":
            print(f"  {label:44s} {res.status}: {res.reason[:110]}")
            continue
        err = max(d.max_abs / spans[d.name] for d in compare(res.trace, ref.trace) if spans[d.name] > 0)
        st = res.stats
        print(f"  {label:44s} passes/step {st['iterations_mean']:.2f} (max {st['iterations_max']}), "
              f"error {err:.1e} of range, {_cost(res)}")


def two_mass(stop: float) -> None:
    from test_iterative import _two_mass_exact

    scene = ROOT / "scenarios" / "two_mass.yaml"
    print(f"two_mass, kc = {KC:g} N/m, step {H * 1e3:g} ms, {stop:g} s")
    base = [f"components.mass2.params.kc={KC}", f"stop_time={stop}", f"master.step={H}", f"master.output_interval={H}"]
    for alg, inputs, extra in (("jacobi", "hold", []), ("jacobi", "linear", []), ("gauss_seidel", "hold", []),
                               ("gauss_seidel", "linear", []), ("iterative", "hold", []), ("iterative", "linear", []),
                               ("adaptive", "linear", [f"master.options={{h_max: {H}, rtol: 1e-3}}"])):
        res = run(scene, base + [f"master.algorithm={alg}", f"master.inputs={inputs}", *extra])
        g = growth_per_step(res.trace.data[:, 1:], 1.0)
        exact = _two_mass_exact(res.trace.time, KC)
        err = max(np.max(np.abs(res.trace[n] - r)) / np.ptp(r) for n, r in exact.items())
        verdict = "unstable" if res.status != "ok" or g > 1 else "stable"
        extra_txt = f" passes/step {res.stats['iterations_mean']:.2f}" if "iterations_mean" in res.stats else ""
        extra_txt += f" {res.stats['accepted_steps']} steps" if "accepted_steps" in res.stats else ""
        print(f"  {alg + '/' + inputs:22s} {verdict:8s} growth/row {g:.5f} error {err:9.2e} of range "
              f"{_cost(res)}{extra_txt}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stop-loop", type=float, default=2.0)
    ap.add_argument("--stop-mass", type=float, default=2.0)
    a = ap.parse_args()
    force_loop(a.stop_loop)
    two_mass(a.stop_mass)


if __name__ == "__main__":
    main()
