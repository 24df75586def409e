"""Events benchmark (issue 30): the cost of locating one event inside an FMU's doStep, and the
event scenes against their smooth variants at equal tolerance.

1. **One event.**  The pendulum against a stop (catalog ``pendulum``/``stop``) with restitution 1
   bounces forever.  Each raw ``fmi2DoStep`` (ctypes) is timed; the median of the steps that hold
   an impact minus the median of those that do not is the cost of one event (location on the
   dense output, the retaken step, the update and the restart), printed also as a multiple of
   one plain ``doStep`` of the same FMU.
2. **Scenes at equal tolerance.**  ``rig_end_stop`` (located impacts, restitution 0) beside
   ``rig_end_stop_clamp`` (the rig's default clamped stops, located too) and ``stick_slip`` (stick
   and slip modes) against ``stick_slip_smooth`` (tanh/Stribeck law), each run as it runs by default:
   its error estimate on and within the tolerance 1e-3 of range (the master choosing its settings
   where the scene names no algorithm; ``stick_slip_smooth`` steps 0.1 ms where ``stick_slip``
   steps 0.5 ms).  Wall time of the stepping loop and of the whole run (pilots and companion),
   best of ``--repeat``, of its monolithic reference, and the worst error of its signals against
   its own reference (between events: windows of the event-time error plus one output interval).

Usage: ``python3 benchmarks/bench_events.py [--steps N] [--repeat R] [--skip-scenes] [--skip-event-cost]
[--scene NAME ...]``
"""
from __future__ import annotations

import argparse
import ctypes
import sys
import time
from pathlib import Path

from fmpy import extract, read_model_description
from fmpy.fmi2 import FMU2Slave

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fmus import build_fmu  # noqa: E402
from models.blocks import make  # noqa: E402


def _slave(path: Path) -> tuple[FMU2Slave, dict]:
    md = read_model_description(str(path))
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=extract(str(path)), modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="bench")
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    return fmu, {v.name: v.valueReference for v in md.modelVariables}


def step_times(path: Path, steps: int, h: float) -> tuple[list[float], list[float]]:
    """Wall time [s] of each raw fmi2DoStep of ``h``: those whose step holds an impact, the rest."""
    fmu, vr = _slave(path)
    do_step = fmu.dll.fmi2DoStep
    do_step.argtypes = [ctypes.c_void_p, ctypes.c_double, ctypes.c_double, ctypes.c_int]
    do_step.restype = ctypes.c_int
    comp, seen, with_event, without = fmu.component, 0.0, [], []
    for k in range(steps):
        t0 = time.perf_counter()
        status = do_step(comp, k * h, h, 1)
        wall = time.perf_counter() - t0
        if status != 0:
            raise RuntimeError(f"doStep failed at t = {k * h} s")
        n = fmu.getReal([vr["impacts"]])[0]
        (with_event if n > seen else without).append(wall)
        seen = n
    fmu.terminate()
    fmu.freeInstance()
    return with_event, without


def one_event(steps: int, repeat: int) -> None:
    import statistics

    h = 1e-2
    print(f"1. cost of one event: pendulum (L = 0.5 m, from 1 rad, restitution 1, 10 substeps), {steps} steps "
          f"of {h} s, each timed; median of the steps that hold an impact against those that do not")
    for integrator in ("rk4", "radau"):
        path = build_fmu(make("pendulum", "stop", integrator=integrator, e=1.0))
        best = None
        for _ in range(repeat):
            ev, plain = step_times(path, steps, h)
            m_ev, m_plain = statistics.median(ev), statistics.median(plain)
            if best is None or m_ev - m_plain < best[0] - best[1]:
                best = (m_ev, m_plain, len(ev))
        m_ev, m_plain, n = best
        print(f"   {integrator:6s} {n} impacts: a doStep {m_plain * 1e6:7.2f} us without, {m_ev * 1e6:7.2f} us with one; "
              f"one event {(m_ev - m_plain) * 1e6:7.2f} us ({(m_ev - m_plain) / m_plain:.1f} doSteps)")


def scenes(repeat: int, only: list[str] | None = None) -> None:
    from cosim.analysis.trace_diff import (compare, compare_between_events, times_from_clock, times_from_counter,
                                        windows)
    from cosim.run.execute import run
    from cosim.run.reference import reference

    print("2. event scenes against their smooth variants at equal tolerance: each as it runs by default (its error "
          "estimate on, within the tolerance 1e-3 of range; the master choosing where the scene names no algorithm); "
          f"wall time best of {repeat}: the stepping loop and the whole run (pilots and companion included); worst "
          "error of the listed signals against each one's own monolithic reference, relative to range, between "
          "events for the event scenes")

    def arrivals(tr):
        return [times_from_counter(tr, f"rig.leg[{i}].impacts") for i in (1, 2, 3)]

    def switches(tr):
        return [times_from_clock(tr, "mass.t_stick"), times_from_clock(tr, "mass.t_slip")]

    legs, mass = ["rig.leg*.s", "pid*.y"], ["mass.x", "mass.v", "mass.friction", "pid.y"]
    table = (("rig_end_stop", legs, arrivals), ("rig_end_stop_clamp", legs, arrivals), ("stick_slip", mass, switches),
             ("stick_slip_smooth", mass, None))
    for name, signals, times in table:
        if not only or name in only:
            path = ROOT / "scenarios" / f"{name}.yaml"
            run(path)  # build the FMUs (cached) before timing
            best = None
            for _ in range(repeat):
                t0 = time.perf_counter()
                res = run(path)
                total = time.perf_counter() - t0
                if best is None or total < best[1]:
                    best = (res, total)
            res, total = best
            t0 = time.perf_counter()
            ref = reference(path)
            t_ref = time.perf_counter() - t0
            if times is not None:
                w = windows(list(zip(times(res.trace), times(ref.trace))), 1e-3)
                diffs = compare_between_events(res.trace, ref.trace, w, signals)
            else:
                diffs = compare(res.trace, ref.trace, signals)
            worst = max(diffs, key=lambda d: d.relative)
            st = res.stats
            how = st.get("choice", {}).get("settings") or {}
            setting = f"{st['algorithm']} step {st['step']:g} s" + "".join(f", {k} {v:g}" if isinstance(v, float)
                                                                          else f", {k} {v}" for k, v in how.items())
            est = (st.get("estimate") or {}).get("worst")
            n_ev = ref.stats.get("events", {}).get("count", 0)
            print(f"   {name:20s} {res.status:4s} {setting}: {st['steps_done']} steps, loop {st['wall_s']:6.3f} s, "
                  f"run {total:6.2f} s; estimated {est:.1e}, against the reference {worst.relative:.1e} "
                  f"({worst.name}); reference {t_ref:5.2f} s ({n_ev} events)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--skip-scenes", action="store_true")
    ap.add_argument("--skip-event-cost", action="store_true", help="skip part 1 (the cost of one event)")
    ap.add_argument("--scene", action="append", help="part 2 for this scene only (repeatable)")
    args = ap.parse_args()
    if not args.skip_event_cost:
        one_event(args.steps, args.repeat)
    if not args.skip_scenes:
        scenes(args.repeat, args.scene)


if __name__ == "__main__":
    main()
