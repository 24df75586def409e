"""Speed against accuracy of the master algorithms on the thesis's closed-loop scene.

Each co-simulation (Jacobi and Gauss-Seidel, inputs held or linear over a step, communication
steps from 4 ms down) is compared with
the scene's monolithic reference (the same catalog blocks as one ODE under CVODES at rtol 1e-10,
:mod:`cosim.run.reference`); the error is the largest deviation of the platform position [m] over
the run, the cost the wall time of the stepping loop.  Printed as a table and drawn as an
error-against-time chart (log-log), with the monolithic solve's own wall time for scale.

Like with like: a co-simulation's wall time is its stepping loop (FMUs built, instantiated and
initialised beforehand); the monolithic time is likewise the CVODES solve alone, over the same
output instants, with the integrator built beforehand (best of three; the build time is printed
beside it).

    python3 benchmarks/bench_accuracy.py [--stop 2] [--out out/bench_accuracy.png] [--multibody]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.analysis.trace_diff import compare  # noqa: E402
from cosim.run.reference import reference  # noqa: E402
from cosim.run.execute import run  # noqa: E402

STEPS = (4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5)
ALGORITHMS = ("jacobi", "gauss_seidel")
INPUTS = ("hold", "linear")
POSE = ("mech.platform.x", "mech.platform.y", "mech.platform.phi")


def sweep(scene: str, stop: float, steps, algorithms, inputs, extra: list[str]) -> tuple[dict, list[dict]]:
    """The reference run and one row per (algorithm, inputs, step): errors against it and wall
    times.  A run that fails (e.g. diverges at a large step) is a row with its status."""
    sets = [f"stop_time={stop}", *extra]
    ref = reference(ROOT / "scenarios" / f"{scene}.yaml", sets)
    if not ref.ok:
        raise SystemExit(f"{scene}: the monolithic reference failed: {ref.reason}")
    rows = []
    for alg in algorithms:
        for mode in inputs:
            for h in steps:
                res = run(ROOT / "scenarios" / f"{scene}.yaml",
                          [*sets, f"master.algorithm={alg}", f"master.inputs={mode}", f"master.step={h}",
                           f"master.output_interval={max(h, 1e-3)}"])
                row = {"scene": scene, "algorithm": alg, "inputs": mode, "step": h, "status": res.status,
                       "wall_s": res.stats["wall_s"]}
                if res.ok:
                    d = {x.name: x.max_abs for x in compare(res.trace, ref.trace, list(POSE))}
                    row.update(pos=max(d[POSE[0]], d[POSE[1]]), phi=d[POSE[2]])
                rows.append(row)
                print(f"  {scene:<20} {alg:<13} {mode:<7} {h:>9.3g} {res.status:>7} {row['wall_s']:>8.3f} "
                      f"{row.get('pos', float('nan')):>11.3e} {row.get('phi', float('nan')):>11.3e}", flush=True)
    solve, build = monolithic_cost(scene, sets)
    return {"scene": scene, "wall_s": solve, "build_s": build}, rows


def monolithic_cost(scene: str, sets: list[str], repeat: int = 3) -> tuple[float, float]:
    """Wall time [s] of the scene's monolithic CVODES solve over its output instants (best of
    ``repeat``), and of building that integrator (once)."""
    import time

    import casadi as ca
    import numpy as np

    from cosim.run.reference import ATOL, RTOL, composite
    from cosim.scenario import load

    sc = load(ROOT / "scenarios" / f"{scene}.yaml", sets)
    comp = composite(sc)
    dt = sc.master.record_every * sc.master.step
    ts = dt * np.arange(1, sc.n_steps // sc.master.record_every + 1)
    t0 = time.perf_counter()
    solver = ca.integrator("monolithic", "cvodes", {"x": comp.x, "ode": comp.ode}, 0.0, ts,
                           {"reltol": RTOL, "abstol": ATOL, "max_num_steps": 10 ** 7})
    build = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        solver(x0=comp.x0)
        best = min(best, time.perf_counter() - t0)
    return best, build


def order(rows: list[dict]) -> dict[tuple[str, str], float]:
    """Observed order of convergence per (algorithm, inputs): slope of log(error) against
    log(step), fitted over the successful runs at steps up to 1 ms."""
    import numpy as np

    out = {}
    for key in dict.fromkeys((r["algorithm"], r["inputs"]) for r in rows):
        pts = [(r["step"], r["pos"]) for r in rows
               if (r["algorithm"], r["inputs"]) == key and r.get("pos", 0) > 0 and r["step"] <= 1e-3]
        if len(pts) >= 2:
            h, e = np.log(np.array(pts)).T
            out[key] = float(np.polyfit(h, e, 1)[0])
    return out


def chart(refs: list[dict], rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5), layout="constrained")
    for k, scene in enumerate(dict.fromkeys(r["scene"] for r in rows)):
        for alg, mode in ((a, m) for m in INPUTS for a in ALGORITHMS):
            pts = [r for r in rows if r["scene"] == scene and r["algorithm"] == alg and r["inputs"] == mode and "pos" in r]
            if not pts:
                continue
            line, = ax.loglog([r["wall_s"] for r in pts], [r["pos"] for r in pts], marker="os"[mode == "linear"],
                              ls="-" if alg == "gauss_seidel" else "--", label=f"{scene}, {alg}, {mode}")
            for r in pts:
                ax.annotate(f"{r['step'] * 1e3:g} ms", (r["wall_s"], r["pos"]), fontsize=7,
                            textcoords="offset points", xytext=(4, 3), color=line.get_color())
        ref = next(x for x in refs if x["scene"] == scene)
        ax.axvline(ref["wall_s"], color=f"C{k}", ls=":", lw=1)
        ax.annotate(f"monolithic CVODES solve\n({scene})", (ref["wall_s"], ax.get_ylim()[0]), fontsize=7,
                    rotation=90, va="bottom", ha="right")
    ax.set_xlabel("wall time [s]: stepping loop, or CVODES solve (building excluded in both)")
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
    print(f"  {'scene':<20} {'algorithm':<13} {'inputs':<7} {'step s':>9} {'status':>7} {'wall s':>8} "
          f"{'pos err m':>11} {'phi err rad':>11}")
    refs, rows = [], []
    for scene, steps, algs in (("pid_step", STEPS, ALGORITHMS),
                               *((("pid_step_multibody", STEPS[1:5], ("gauss_seidel",)),) if args.multibody else ())):
        ref, r = sweep(scene, args.stop, steps, algs, INPUTS, [])
        refs.append(ref)
        rows += r
        print(f"  {scene:<20} {'monolithic':<13} {'':<7} {'CVODES':>9} {'ok':>7} {ref['wall_s']:>8.3f}"
              f"   (solve only; building the integrator took {ref['build_s']:.3f} s more)")
        for (alg, mode), p in sorted(order(r).items()):
            print(f"  {scene}: {alg}, {mode} inputs: order {p:.2f} in the step (steps <= 1 ms)")
    print(f"chart: {chart(refs, rows, args.out)}")


if __name__ == "__main__":
    main()
