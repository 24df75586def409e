"""Per-FMU step cost of the masters, side by side in one run, the master's own share of it, and
the real-time factor of the thesis's scenes.

The FMUs: a ring of N first-order lags ``x' = (u - x) / T`` (RK4, one state, output ``y = x``:
no feedthrough, so the ring has no algebraic loop), built once by :func:`fmus.build_fmu`.  The
*per-FMU step cost* is the wall time of the stepping loop per macro step per FMU: the FMU's own
``fmi2SetReal`` + ``fmi2DoStep`` (its RK4 step) plus what the master adds (reading the output,
moving values, bookkeeping).  The FMU's own part is measured alone, by a C driver that dlopens
the same library and loops set + doStep (``benchmarks/bench_fmu.py``); the difference is printed
as the master's own share.  Every master runs the same FMUs, the same connections and the same
number of steps (fixed-step Jacobi exchange semantics):

- rpr-cosim, compiled loop (Jacobi and Gauss-Seidel; with and without per-slave timing)
- rpr-cosim, the Python oracle loop (tests/oracles, the kernel's bit-for-bit twin)
- fmpy's Python loop: ``FMU2Slave.setReal / doStep / getReal`` per FMU per step
- ecospy (C++ master, PyPI ``ecospy``; needs Debian's ``libtbb12``), ``step(n)``

Targets (DESIGN): within 2x of ecospy and at least 5x below fmpy's loop.  Then the real-time
factor (simulated / wall time of the stepping loop) of pid_step (rigid and multibody) and
vw_compare.

    python3 benchmarks/bench_master.py [--fmus 4] [--steps 20000] [--repeat 3] [--no-scenes]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import casadi as ca

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import fmus  # noqa: E402
from cosim.master import CoupledSystem, Link, simulate  # noqa: E402
from cosim.slaves.fmu_slave import FmuSlave  # noqa: E402
from models.block import Block, Param, Var  # noqa: E402

sys.path.insert(0, str(ROOT / "tests"))
import oracles  # noqa: E402 - the Python twins of the kernels (tests/oracles), as engine 'oracle'

oracles.register()


def lag_block() -> Block:
    p, x, u = ca.SX.sym("p", 1), ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return Block.build("bench_lag", description="first-order lag (benchmark)",
                       params=[Param("T", 0.05, "s", 1e-9, math.inf, "time constant")],
                       inputs=[Var("u")], outputs=[Var("y")], states=[Var("x")], p=p, u=u, x=x,
                       ode=(u - x) / p[0], out=x, start=ca.DM([0.0]), integrator="rk4")


def ring(n: int, path: Path) -> tuple[list[FmuSlave], list[Link]]:
    slaves = [FmuSlave(f"lag{i}", path) for i in range(n)]
    links = [Link((i - 1) % n, "y", i, "u") for i in range(n)]
    return slaves, links


def bench_ours(path: Path, n: int, steps: int, alg: str, engine: str, timing: bool = True,
               inputs: str = "hold") -> float:
    slaves, links = ring(n, path)
    system = CoupledSystem(slaves, links, [(0, "y")])
    st = simulate(system, alg, step_ns=1_000_000, n_steps=steps, engine=engine, timing=timing,
                  start_values=[{"x": 1.0}] + [{} for _ in range(n - 1)], inputs=inputs)
    assert st.status == "ok" and st.engine == engine, (st.status, st.reason)
    return st.wall_s


def bench_fmpy(path: Path, n: int, steps: int) -> float:
    import fmpy
    from fmpy.fmi2 import FMU2Slave

    md = fmpy.read_model_description(str(path))
    unzip = fmpy.extract(str(path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    fs = []
    for i in range(n):
        f = FMU2Slave(guid=md.guid, unzipDirectory=unzip, modelIdentifier=md.coSimulation.modelIdentifier,
                      instanceName=f"lag{i}")
        f.instantiate()
        f.setupExperiment(startTime=0.0)
        f.enterInitializationMode()
        if i == 0:
            f.setReal([vr["x"]], [1.0])
        f.exitInitializationMode()
        fs.append(f)
    vu, vy = [vr["u"]], [vr["y"]]
    y = [f.getReal(vy)[0] for f in fs]
    h = 1e-3
    t0 = time.perf_counter()
    for k in range(steps):
        t = k * h
        for i, f in enumerate(fs):
            f.setReal(vu, [y[i - 1]])
        for f in fs:
            f.doStep(t, h)
        y = [f.getReal(vy)[0] for f in fs]
    wall = time.perf_counter() - t0
    for f in fs:
        f.terminate()
        f.freeInstance()
    return wall


def bench_ecospy(path: Path, n: int, steps: int) -> float | None:
    try:
        from ecospy import EcosSimulation, EcosSimulationStructure
    except (ImportError, OSError) as exc:
        print(f"  ecospy unavailable: {exc}", file=sys.stderr)
        return None
    ss = EcosSimulationStructure()
    for i in range(n):
        ss.add_model(f"lag{i}", str(path))
    for i in range(n):
        ss.make_real_connection(f"lag{(i - 1) % n}::y", f"lag{i}::u")
    ss.add_parameter_set("start", {"lag0::x": 1.0})
    sim = EcosSimulation(structure=ss, step_size=1e-3)
    sim.init(parameter_set="start")
    t0 = time.perf_counter()
    sim.step(steps)
    wall = time.perf_counter() - t0
    sim.terminate()
    return wall


def fmu_alone(path: Path, steps: int, repeat: int) -> float:
    """us per (fmi2SetReal, fmi2DoStep) of one lag FMU driven by a C loop, no master: the FMU's
    own step cost (best of ``repeat``)."""
    import tempfile

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import subprocess

    from bench_fmu import DRIVER, _input, time_c

    work = Path(tempfile.mkdtemp(prefix="bench-master-"))
    (work / "driver.c").write_text(DRIVER)
    subprocess.run(["gcc", "-O2", str(work / "driver.c"), "-o", str(work / "driver"), "-ldl", "-lm"], check=True)
    vr_u, amp = _input(lag_block())
    return min(time_c(path, work / "driver", 1e-3, steps, vr_u, amp) for _ in range(repeat))


def scenes() -> None:
    from cosim.run.execute import run

    print("\nreal-time factor of the thesis's scenes (compiled loop; stepping loop only, FMUs prebuilt):")
    print(f"  {'scene':<22} {'algorithm':<13} {'inputs':<7} {'step s':>7} {'steps':>6} {'wall s':>8} {'RTF':>8} "
          f"{'us/step':>8} {'master us/step':>15}")
    for scene, sets in (("pid_step", []), ("pid_step", ["master.algorithm=jacobi"]),
                        ("pid_step", ["master.step=1e-4", "master.inputs=hold"]), ("pid_step_multibody", []),
                        ("vw_compare", ["master.algorithm=gauss_seidel"])):
        res = run(ROOT / "scenarios" / f"{scene}.yaml", sets)
        st = res.stats
        n = max(1, st["steps_done"])
        print(f"  {scene:<22} {st['algorithm']:<13} {res.scene.master.inputs:<7} {st['step']:>7.0e} {n:>6} "
              f"{st['wall_s']:>8.3f} {st['real_time_factor']:>8.1f} {1e6 * st['wall_s'] / n:>8.2f} "
              f"{1e6 * st['master_s'] / n:>15.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fmus", type=int, default=4)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-scenes", action="store_true")
    args = ap.parse_args()
    path = fmus.build_fmu(lag_block())
    n, steps = args.fmus, args.steps
    runs = {
        "rpr-cosim compiled, Jacobi": lambda: bench_ours(path, n, steps, "jacobi", "compiled"),
        "rpr-cosim compiled, Gauss-Seidel": lambda: bench_ours(path, n, steps, "gauss_seidel", "compiled"),
        "rpr-cosim compiled, Jacobi, no timing": lambda: bench_ours(path, n, steps, "jacobi", "compiled", False),
        "rpr-cosim compiled, Gauss-Seidel, linear": lambda: bench_ours(path, n, steps, "gauss_seidel", "compiled",
                                                                       inputs="linear"),
        "rpr-cosim Python oracle, Jacobi": lambda: bench_ours(path, n, max(1000, steps // 10), "jacobi", "oracle"),
        "fmpy FMU2Slave loop": lambda: bench_fmpy(path, n, max(1000, steps // 10)),
        "ecospy": lambda: bench_ecospy(path, n, steps),
    }
    per = {}
    own = fmu_alone(path, steps, args.repeat)
    print(f"ring of {n} RK4 lag FMUs (FMI 2.0), 1 ms step; best of {args.repeat}; per-FMU step cost "
          f"[us per macro step per FMU], and minus the FMU's own set + doStep alone ({own:.3f} us, C driver):")
    for name, fn in runs.items():
        n_steps = max(1000, steps // 10) if ("Python" in name or "fmpy" in name) else steps
        best = None
        for _ in range(args.repeat):
            w = fn()
            if w is None:
                break
            best = w if best is None else min(best, w)
        if best is None:
            continue
        per[name] = 1e6 * best / n_steps / n
        print(f"  {name:<40} {per[name]:8.3f}   master's own share {per[name] - own:8.3f}")
    ours = per["rpr-cosim compiled, Jacobi"]
    print("\nratios (same FMUs, same run):")
    if "ecospy" in per:
        r = ours / per["ecospy"]
        print(f"  rpr-cosim compiled / ecospy          {r:6.2f}   (target <= 2)   {'met' if r <= 2 else 'NOT met'}")
    r = per["fmpy FMU2Slave loop"] / ours
    print(f"  fmpy loop / rpr-cosim compiled       {r:6.1f}   (target >= 5)   {'met' if r >= 5 else 'NOT met'}")
    print(f"  rpr-cosim Python oracle / compiled   {per['rpr-cosim Python oracle, Jacobi'] / ours:6.1f}")
    if not args.no_scenes:
        scenes()


if __name__ == "__main__":
    main()
