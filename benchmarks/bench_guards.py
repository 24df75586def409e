"""Cost of the physical guards (cosim.guards): the stepping-loop wall time of the shipped scenes
with the default guards against the same run with ``guards: off``, interleaved, best of N; and
the guard's own check time per block of rows.

    python3 benchmarks/bench_guards.py [--repeat 7] [--stop 20]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.guards import scene_guard  # noqa: E402
from cosim.run import run  # noqa: E402
from cosim.scenario import load  # noqa: E402


def loop_wall(scene: Path, sets: list[str]) -> float:
    res = run(scene, sets)
    assert res.ok, res.reason
    return res.stats["wall_s"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--stop", type=float, default=20.0, help="stop_time of pid_step [s]")
    args = ap.parse_args()
    scenes = {"pid_step": (ROOT / "scenarios" / "pid_step.yaml", [f"stop_time={args.stop:g}"]),
              "vw_compare": (ROOT / "scenarios" / "vw_compare.yaml", [])}
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
