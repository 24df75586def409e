"""Multirate against single rate: error against the monolithic reference and wall time.

Each case runs ``study precision`` (Gauss-Seidel, linear inputs) over a few macro steps, once at a
single rate and once with some components at ``rate`` doSteps per macro step (``--set
components.X.rate=R``), and prints worst error relative to range, the stepping loop's wall time
(the smallest of ``--repeat`` runs) and doSteps, then the cheapest run of each within the
tolerance of the multirate runs' best error.

    nice python benchmarks/bench_multirate.py [--repeat 3] [--only pid_step_rk4]
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.study.precision import precision_study  # noqa: E402

RK4_PIDS = [f"components.pid{i}.options.integrator=rk4" for i in (1, 2, 3)]
PID_RATES = [f"components.pid{i}.rate=4" for i in (1, 2, 3)]
#: name -> (scene, stop [s], steps [s], overrides of both, overrides of the multirate runs)
CASES = {
    "pid_step": ("pid_step.yaml", 2.0, [4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4], [], ["components.mech.rate=4"]),
    "pid_step_rk4": ("pid_step.yaml", 2.0, [4e-3, 2e-3, 1e-3, 5e-4], RK4_PIDS, PID_RATES),
    "pid_step_multibody": ("pid_step_multibody.yaml", 0.5, [2e-3, 1e-3, 5e-4, 2.5e-4], [], ["components.mech.rate=4"]),
}


def measure(scene: str, stop: float, steps: list[float], sets: list[str], repeat: int) -> list:
    """Rows of the study, wall time the smallest over ``repeat`` studies."""
    best = None
    for _ in range(repeat):
        st = precision_study(ROOT / "scenarios" / scene, [("gauss_seidel", "linear")], steps, stop_time=stop,
                             overrides=sets)
        if best is None:
            best = st.rows
        else:
            for a, b in zip(best, st.rows):
                a.wall_s = min(a.wall_s, b.wall_s)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", action="append", choices=list(CASES))
    args = ap.parse_args()
    for name in args.only or CASES:
        scene, stop, steps, common, multi = CASES[name]
        single = measure(scene, stop, steps, common, args.repeat)
        multirate = measure(scene, stop, steps, common + multi, args.repeat)
        print(f"\n{name} ({scene}, {stop:g} s, gauss_seidel/linear{', ' + ' '.join(common) if common else ''}); "
              f"multirate: {' '.join(multi)}")
        print(f"{'step ms':>8} | {'single: worst':>13} {'wall s':>8} {'doSteps':>8} | "
              f"{'multirate: worst':>16} {'wall s':>8} {'doSteps':>8}")
        for a, b in zip(single, multirate):
            fa = f"{a.worst:13.3e}" if a.status == "ok" else f"{a.status:>13}"
            fb = f"{b.worst:16.3e}" if b.status == "ok" else f"{b.status:>16}"
            print(f"{a.step * 1e3:8.3g} | {fa} {a.wall_s:8.4f} {a.do_steps:8d} | {fb} {b.wall_s:8.4f} {b.do_steps:8d}")
        ok = [r for r in multirate if r.status == "ok"]
        if not ok:
            continue
        for r in sorted(ok, key=lambda r: r.step, reverse=True)[:3]:
            tol = r.worst * 1.05
            cand = [s for s in single if s.status == "ok" and s.worst <= tol]
            peer = min(cand, key=lambda s: s.wall_s) if cand else None
            ratio = peer.wall_s / r.wall_s if peer and r.wall_s > 0 else math.nan
            print(f"  multirate at {r.step * 1e3:g} ms: worst {r.worst:.3e} in {r.wall_s:.4f} s; single rate within "
                  f"that error: " + (f"{peer.step * 1e3:g} ms, {peer.worst:.3e} in {peer.wall_s:.4f} s "
                                     f"(single / multirate wall time {ratio:.2f})" if peer else "none of the steps run"))


if __name__ == "__main__":
    main()
