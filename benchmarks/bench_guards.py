"""The physical guards (cosim.run.row_guards) on the shipped scenes: how far each scene stays from every
limit (largest |value| against its rating, leg range against the stroke, smallest |det J|), the
stepping-loop wall time with the default guards against ``guards: off`` (interleaved, best of N),
and the guard's own check time per block of rows.

    python3 benchmarks/bench_guards.py [--repeat 7] [--stop 20] [--no-timing]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from cosim.scenario.guard_settings import det_j
from cosim.run.row_guards import scene_guard  # noqa: E402
from cosim.run.execute import run  # noqa: E402
from cosim.scenario import load  # noqa: E402


def loop_wall(scene: Path, sets: list[str]) -> float:
    res = run(scene, sets)
    assert res.ok, res.reason
    return res.stats["wall_s"]


def margins(path: Path) -> None:
    """Run ``path`` recording every guarded variable and print its extremes against its limit."""
    scene = load(path)
    guard = scene_guard(scene)
    watched = [f"{c}.{v}" for c, v in guard.watch]
    res = run(scene, {"outputs": watched})
    tr = res.trace
    print(f"{scene.name}: {res.status}")
    for lim in guard.limits:
        col = tr[lim.name]
        print(f"  {lim.name:<20} {lim.kind:<7} {col.min():>9.4g} .. {col.max():<9.4g} {lim.unit:<2} limit "
              f"[{lim.low:g}, {lim.high:g}]")
    for mech in guard.mechanisms:
        det = det_j(None, np.vstack([tr[n] for n in mech.names]), mech.g)
        print(f"  {mech.name:<20} det J   {det.min():>9.4g} .. {det.max():<9.4g} m  smallest |det J| "
              f"{np.abs(det).min():.4g} m (limit {scene.guards.min_det:g} m)")
    print(f"  largest |value| of the {len(tr.names)} guarded variables: {np.abs(tr.data[:, 1:]).max():.4g} "
          f"(limit {scene.guards.max_abs:g})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--stop", type=float, default=20.0, help="stop_time of pid_step [s]")
    ap.add_argument("--no-timing", action="store_true", help="print the margins only")
    args = ap.parse_args()
    for name in ("pid_step", "pid_step_multibody", "vw_compare"):
        margins(ROOT / "scenarios" / f"{name}.yaml")
    if args.no_timing:
        return
    scenes = {"pid_step": (ROOT / "scenarios" / "pid_step.yaml", [f"stop_time={args.stop:g}"]),
              "vw_compare": (ROOT / "scenarios" / "vw_compare.yaml", ["master.algorithm=gauss_seidel"])}
    print(f"{'scene':<12} {'guards on [s]':>14} {'off [s]':>9} {'overhead':>9}   (best of {args.repeat}, interleaved)")
    for name, (path, sets) in scenes.items():
        on, off = [], []
        for _ in range(args.repeat):
            on.append(loop_wall(path, sets))
            off.append(loop_wall(path, sets + ["guards=off"]))
        print(f"{name:<12} {min(on):>14.4f} {min(off):>9.4f} {100 * (min(on) / min(off) - 1):>8.1f}%")
    scene = load(scenes["pid_step"][0])
    rows = run(scene).trace.data
    print("guard check per block of pid_step rows (all four guards):")
    for n in (64, 1024, 5001):
        g = scene_guard(scene)
        g.bind(scene.outputs)
        g.check(rows[:n])
        t0 = time.perf_counter()
        for _ in range(50):
            g.check(rows[:n])
        dt = (time.perf_counter() - t0) / 50
        print(f"  {n:>5} rows: {1e3 * dt:7.3f} ms ({1e6 * dt / n:6.2f} us per row)")


if __name__ == "__main__":
    main()
