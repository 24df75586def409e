"""The native engine's figures: compiled ``iterative`` per coupling pass against compiled
Gauss-Seidel per step, and compiled ``ecco`` against compiled Gauss-Seidel at equal position error.

1. Cost per coupling pass.  A pass of ``iterative`` steps every slave whose inputs changed from
   its saved state (restore, set, doStep, get) and updates the unknowns; a Gauss-Seidel step is
   one pass without the iteration's own work.  On ``two_mass`` (kc = 1000 N/m, 5 ms: Jacobi is
   unstable there) and ``force_loop`` (the algebraic loop, 1 ms) the stepping loop's wall time per
   pass (``wall_s / iterations_total``) of iterative, Python and compiled, is divided by the wall
   time per step of compiled Gauss-Seidel on the same FMUs, connections, inputs and step.  force_loop's
   Gauss-Seidel peer steps the loop once per step in the same order (a Gauss-Seidel subclass that
   accepts the loop: one pass, unconverged; its values are not the point, its cost is).
   Target (issue 18): compiled iterative at most 3x.
2. ecco on pid_step (the mechanism declared non-rollback) at its default tolerance, Python and
   compiled, against compiled Gauss-Seidel (linear inputs) at several steps: position error
   against the monolithic CVODES reference, and Gauss-Seidel's wall time at ecco's position error
   (log-log interpolation between the two steps around it).  Target: ecco no slower.

    python3 benchmarks/bench_native.py [--stop-mass 20] [--stop-loop 2] [--gs-steps 1e-3,5e-4,2.5e-4,1.25e-4]
"""
from __future__ import annotations

import argparse
import math
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from cosim.analysis.trace_diff import compare  # noqa: E402
from cosim.master import simulate  # noqa: E402
from cosim.master.algorithm import register  # noqa: E402
from cosim.master.algorithms.gauss_seidel import GaussSeidel  # noqa: E402
from cosim.run.execute import build_components, couple, run  # noqa: E402
from cosim.run.reference import reference  # noqa: E402
from cosim.scenario import load  # noqa: E402
from cosim.slaves.fmu_slave import FmuSlave  # noqa: E402
import oracles  # noqa: E402 - the Python twins of the kernels (tests/oracles), as engine 'oracle'

oracles.register()

SCENARIOS = ROOT / "scenarios"
POSE = ["mech.platform.x", "mech.platform.y", "mech.platform.phi"]


@register
class _LoopPass(GaussSeidel):
    """One Gauss-Seidel pass per step over a scene with an algebraic loop (the cost peer only)."""

    name = "gauss_seidel_one_pass"
    solves_algebraic_loops = True


def _loop_pass_wall(scene_path: Path, sets: dict) -> tuple[float, int]:
    """Compiled Gauss-Seidel over force_loop's system (the scene's order): wall s, steps."""
    from cosim.scenario.recipes import slave_description

    scene = load(scene_path, sets)
    paths = build_components(scene)
    slaves = [FmuSlave(n, paths[n], c.description if c.kind == "fmu" else slave_description(c, paths[n]))
              for n, c in scene.components.items()]
    system = couple(scene, slaves)
    try:
        st = simulate(system, _LoopPass.name, step_ns=scene.master.step_ns, n_steps=scene.n_steps,
                      record_every=scene.master.record_every, inputs=scene.master.inputs, engine="compiled",
                      start_values=[c.start_values() for c in scene.components.values()])
    finally:
        for s in slaves:
            s.release()
    return st.wall_s, st.steps_done


def passes(stop_mass: float, stop_loop: float) -> None:
    print("1. cost per coupling pass: iterative (wall / passes) over compiled Gauss-Seidel (wall / steps)")
    mass = {"components.mass2.params.kc": 1000.0, "stop_time": stop_mass, "master.step": 0.005,
            "master.output_interval": 0.005}
    loop = {"stop_time": stop_loop, "master.algorithm": "iterative"}
    for label, scene, sets in (("two_mass", "two_mass.yaml", mass), ("force_loop", "force_loop.yaml", loop)):
        path = SCENARIOS / scene
        if label == "two_mass":
            gs = run(path, {**sets, "master.algorithm": "gauss_seidel"}, engine="compiled")  # the scene's inputs
            gs_wall, gs_steps = gs.stats["wall_s"], gs.stats["steps_done"]
        else:
            gs_wall, gs_steps = _loop_pass_wall(path, sets)
        per_gs = gs_wall / gs_steps
        print(f"  {label}: compiled gauss_seidel {gs_steps} steps {gs_wall:.4f} s = {per_gs * 1e6:.2f} us/step")
        for engine in ("oracle", "compiled"):
            res = run(path, {**sets, "master.algorithm": "iterative"}, engine=engine)
            st = res.stats
            per = st["wall_s"] / st["iterations_total"]
            print(f"    iterative {engine:<8} {res.status:<3} {st['iterations_total']:6d} passes "
                  f"({st['iterations_mean']:.2f}/step) {st['wall_s']:8.4f} s = {per * 1e6:8.2f} us/pass = "
                  f"{per / per_gs:6.2f}x gauss_seidel per step")


def _pos_error(res, ref) -> float:
    d = {x.name: x.max_abs for x in compare(res.trace, ref, POSE)}
    return max(d[POSE[0]], d[POSE[1]])


def ecco(gs_steps: list[float]) -> None:
    print("2. ecco on pid_step (mechanism non-rollback) against compiled gauss_seidel at equal position error")
    scene = SCENARIOS / "pid_step.yaml"
    t0 = time.perf_counter()
    ref = reference(scene, {"master.step": 1e-4, "master.output_interval": 1e-4}).trace
    print(f"  reference (monolithic CVODES) {time.perf_counter() - t0:.1f} s")
    points = []
    for h in gs_steps:
        res = run(scene, {"master.step": h, "master.output_interval": max(h, 1e-3)}, engine="compiled")
        err = _pos_error(res, ref)
        points.append((err, res.stats["wall_s"]))
        print(f"  gauss_seidel {h:8.2e} s compiled: {res.stats['steps_done']:6d} steps {res.stats['wall_s']:7.3f} s "
              f"position error {err:9.2e} m")
    for engine in ("oracle", "compiled"):
        res = run(scene, {"master.algorithm": "ecco", "components.mech.rollback": False}, engine=engine)
        err, wall = _pos_error(res, ref), res.stats["wall_s"]
        peer = _interpolate(points, err)
        verdict = f"gauss_seidel at that error {peer:.3f} s: ecco {wall / peer:.2f}x" if peer else "outside the range"
        print(f"  ecco {engine:<8} {res.status}: {res.stats['accepted_steps']:6d} steps {wall:7.3f} s position error "
              f"{err:9.2e} m; {verdict}")


def _interpolate(points: list[tuple[float, float]], err: float) -> float | None:
    """Wall time at position error ``err`` by log-log interpolation between measured points."""
    pts = sorted(points)
    for (e0, w0), (e1, w1) in zip(pts, pts[1:]):
        if e0 <= err <= e1 and e0 > 0:
            f = (math.log(err) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(w0) + f * (math.log(w1) - math.log(w0)))
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stop-mass", type=float, default=20.0)
    ap.add_argument("--stop-loop", type=float, default=2.0)
    ap.add_argument("--gs-steps", default="1e-3,5e-4,2.5e-4,1.25e-4")
    ap.add_argument("--only", choices=("passes", "ecco"))
    a = ap.parse_args()
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.processor() or platform.machine()}, "
          f"python {platform.python_version()}")
    if a.only != "ecco":
        passes(a.stop_mass, a.stop_loop)
    if a.only != "passes":
        ecco([float(x) for x in a.gs_steps.split(",")])


if __name__ == "__main__":
    main()
