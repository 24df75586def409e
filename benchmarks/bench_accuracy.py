"""Speed against accuracy of the master algorithms on the thesis's closed-loop scene.

Each co-simulation (Jacobi and Gauss-Seidel, communication steps from 1 ms down) is compared with
the scene's monolithic reference (the same catalog blocks as one ODE under CVODES at rtol 1e-10,
:mod:`cosim.reference`); the error is the largest deviation of the platform position [m] over
the run, the cost the wall time of the stepping loop.  Printed as a table and drawn as an
error-against-time chart (log-log), with the monolithic solve's own wall time for scale.

    python3 benchmarks/bench_accuracy.py [--stop 2] [--out out/bench_accuracy.png] [--multibody]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.compare import compare  # noqa: E402
from cosim.reference import reference  # noqa: E402
from cosim.run import run  # noqa: E402

STEPS = (1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5)
ALGORITHMS = ("jacobi", "gauss_seidel")
POSE = ("mech.platform.x", "mech.platform.y", "mech.platform.phi")


def sweep(scene: str, stop: float, steps, algorithms, extra: list[str]) -> tuple[dict, list[dict]]:
    """The reference run and one row per (algorithm, step): errors against it and wall times."""
    sets = [f"stop_time={stop}", *extra]
    ref = reference(ROOT / "scenarios" / f"{scene}.yaml", sets)
    if not ref.ok:
        raise SystemExit(f"{scene}: the monolithic reference failed: {ref.reason}")
    rows = []
    for alg in algorithms:
        for h in steps:
            res = run(ROOT / "scenarios" / f"{scene}.yaml", [*sets, f"master.algorithm={alg}", f"master.step={h}"])
            row = {"scene": scene, "algorithm": alg, "step": h, "status": res.status, "wall_s": res.stats["wall_s"]}
            if len(res.trace.data) > 1:
                d = {x.name: x.max_abs for x in compare(res.trace, ref.trace, list(POSE))}
                row.update(pos=max(d[POSE[0]], d[POSE[1]]), phi=d[POSE[2]])
            rows.append(row)
            print(f"  {scene:<20} {alg:<13} {h:>9.3g} {res.status:>7} {row['wall_s']:>8.3f} "
                  f"{row.get('pos', float('nan')):>11.3e} {row.get('phi', float('nan')):>11.3e}", flush=True)
    return {"scene": scene, "wall_s": ref.stats["wall_s"]}, rows


def order(rows: list[dict]) -> dict[str, float]:
    """Observed order of convergence per algorithm: slope of log(error) against log(step)."""
    import numpy as np

    out = {}
    for alg in {r["algorithm"] for r in rows}:
        pts = [(r["step"], r["pos"]) for r in rows if r["algorithm"] == alg and "pos" in r and r["pos"] > 0]
        if len(pts) >= 2:
            h, e = np.log(np.array(pts)).T
            out[alg] = float(np.polyfit(h, e, 1)[0])
    return out


def chart(refs: list[dict], rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5), layout="constrained")
    for k, scene in enumerate(dict.fromkeys(r["scene"] for r in rows)):
        for alg, marker in zip(ALGORITHMS, "os"):
            pts = [r for r in rows if r["scene"] == scene and r["algorithm"] == alg and "pos" in r]
            if not pts:
                continue
            line, = ax.loglog([r["wall_s"] for r in pts], [r["pos"] for r in pts], marker=marker,
                              ls="-" if alg == "gauss_seidel" else "--", label=f"{scene}, {alg}")
            for r in pts:
                ax.annotate(f"{r['step'] * 1e3:g} ms", (r["wall_s"], r["pos"]), fontsize=7,
                            textcoords="offset points", xytext=(4, 3), color=line.get_color())
        ref = next(x for x in refs if x["scene"] == scene)
        ax.axvline(ref["wall_s"], color=f"C{k}", ls=":", lw=1)
        ax.annotate(f"monolithic CVODES\n({scene})", (ref["wall_s"], ax.get_ylim()[0]), fontsize=7,
                    rotation=90, va="bottom", ha="right")
    ax.set_xlabel("wall time of the run [s]")
    ax.set_ylabel("max platform position error [m]")
    ax.set_title("co-simulation against the monolithic reference")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stop", type=float, default=2.0, help="simulated time per run [s] (default 2)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_accuracy.png")
    ap.add_argument("--multibody", action="store_true", help="also sweep pid_step_multibody (slower)")
    args = ap.parse_args()
    print(f"  {'scene':<20} {'algorithm':<13} {'step s':>9} {'status':>7} {'wall s':>8} {'pos err m':>11} "
          f"{'phi err rad':>11}")
    refs, rows = [], []
    for scene, steps, algs in (("pid_step", STEPS, ALGORITHMS),
                               *((("pid_step_multibody", STEPS[:3], ("gauss_seidel",)),) if args.multibody else ())):
        ref, r = sweep(scene, args.stop, steps, algs, [])
        refs.append(ref)
        rows += r
        print(f"  {scene:<20} {'monolithic':<13} {'CVODES':>9} {'ok':>7} {ref['wall_s']:>8.3f}")
        for alg, p in sorted(order(r).items()):
            print(f"  {scene}: {alg} converges at order {p:.2f} in the step")
    print(f"chart: {chart(refs, rows, args.out)}")


if __name__ == "__main__":
    main()
