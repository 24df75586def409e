"""SSP benchmark: what exporting and importing a scene costs, and FMPy's SSP loop beside ours.

For ``scenarios/pid_step.yaml`` (FMUs already cached) this prints

1. export: wall time of ``cosim.scenario.ssp_archive.export`` and the archive's size;
2. load: validating the scene from its YAML and from the archive (schema check, extraction into
   the FMU cache on the first load, description of each FMU);
3. run: the whole scene (5 s, Jacobi, held inputs, 1 ms) from YAML and from the archive with our
   compiled loop, and FMPy's ``fmpy.ssp.simulate_ssp`` on the same archive (its Python loop; it
   records every connector), as wall time and real-time factor; and whether the two traces are
   bit-identical (YAML against SSP) and FMPy's distance from ours (no initial exchange in FMPy,
   see README "SSP").

Usage: ``python3 benchmarks/bench_ssp.py [--stop S]``
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import load  # noqa: E402
from cosim.run.ssp_export import export  # noqa: E402

SCENE = ROOT / "scenarios" / "pid_step.yaml"


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stop", type=float, default=5.0, help="simulated time [s] (default 5)")
    args = ap.parse_args()
    over = {"stop_time": args.stop, "master.algorithm": "jacobi", "master.inputs": "hold"}
    run(SCENE, {"stop_time": 0.001})  # make sure the FMUs are cached
    with tempfile.TemporaryDirectory() as tmp:
        path, t_export = timed(lambda: export(load(SCENE), Path(tmp) / "pid_step.ssp"))
        print(f"export pid_step: {t_export:.3f} s, archive {path.stat().st_size / 1024:.0f} kB")
        _, t_yaml = timed(lambda: load(SCENE, over))
        _, t_first = timed(lambda: load(path, over))
        _, t_ssp = timed(lambda: load(path, over))
        print(f"load: YAML {t_yaml:.3f} s, SSP {t_ssp:.3f} s ({t_first:.3f} s on the first load)")
        a, wa = timed(lambda: run(SCENE, over))
        b, wb = timed(lambda: run(path, over))
        from fmpy.ssp.simulation import simulate_ssp
        from fmpy.ssp.ssd import read_ssv

        params = read_ssv(str(path), resource="resources/pid_step.ssv")
        c, wc = timed(lambda: simulate_ssp(str(path), stop_time=args.stop, step_size=1e-3, parameter_set=params))
        print("whole runs (load, FMU cache check or extraction, instantiation, stepping, recording):")
        for label, wall in (("ours from YAML", wa), ("ours from SSP", wb), ("FMPy simulate_ssp", wc)):
            print(f"run {args.stop:g} s Jacobi 1 ms: {label:<18} {wall:7.3f} s  real-time factor {args.stop / wall:7.1f}")
        print(f"FMPy / ours from SSP: {wc / wb:.1f}x the wall time")
        print(f"YAML and SSP traces bit-identical: {np.array_equal(a.trace.data, b.trace.data)}")
        d = max(np.abs(b.trace[n][1:] - c[n]).max() for n in b.trace.names if n in c.dtype.names)
        print(f"FMPy against ours (rows aligned, no initial exchange in FMPy): max |diff| {d:.3g}")


if __name__ == "__main__":
    main()
