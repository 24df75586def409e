"""Cost of FMI types beyond scalar Float64, measured in one run on the Reference FMU Feedthrough
(FMI 3.0, built from ``../shared/third_party/Reference-FMUs`` as the tests do):

- the Float64 variables only (compiled loop, the fast path);
- every numeric variable of every type recorded (typed ports, Python loop);
- the same, Python loop with Float64 only (what the typed ports add to the Python loop);
- FMPy's ``simulate_fmu`` recording the same variables (the peer).

    python3 benchmarks/bench_types.py [--steps 20000] [--repeat 3]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from conftest import REFERENCE_FMUS_SRC, _source_key, build_reference_fmus  # noqa: E402

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import from_dict  # noqa: E402
from fmus.cache import cache_root  # noqa: E402
import oracles  # noqa: E402 - the Python twins of the kernels (tests/oracles), as engine 'oracle'

oracles.register()


def ours(fmu: Path, steps: int, outputs: list[str], engine: str) -> float:
    """Wall time per macro step [µs] of the stepping loop."""
    res = run(from_dict({"name": "b", "stop_time": steps * 1e-3, "master": {"step": 1e-3, "engine": engine},
                         "components": {"f": {"fmu": str(fmu)}}, "outputs": outputs}))
    assert res.status == "ok" and res.stats["engine"] == engine, (res.status, res.reason, res.stats["engine"])
    return res.stats["wall_s"] / steps * 1e6


def fmpy_peer(fmu: Path, steps: int, names: list[str]) -> float:
    import fmpy

    t0 = time.perf_counter()
    fmpy.simulate_fmu(str(fmu), fmi_type="CoSimulation", output_interval=1e-3, stop_time=steps * 1e-3, output=names)
    return (time.perf_counter() - t0) / steps * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    fmus = build_reference_fmus(REFERENCE_FMUS_SRC, cache_root().parent / "reference-fmus" / _source_key(REFERENCE_FMUS_SRC))
    fmu = fmus["3.0/Feedthrough"]
    import fmpy

    md = fmpy.read_model_description(str(fmu))
    numeric = [v.name for v in md.modelVariables if v.causality == "output" and v.type not in ("String", "Binary")]
    floats = [v.name for v in md.modelVariables if v.causality == "output" and v.type == "Float64"]
    rows = {
        f"Float64 outputs ({len(floats)}), compiled loop": lambda: ours(fmu, args.steps, [f"f.{n}" for n in floats], "compiled"),
        f"Float64 outputs ({len(floats)}), Python oracle loop": lambda: ours(fmu, args.steps, [f"f.{n}" for n in floats], "oracle"),
        f"all numeric outputs ({len(numeric)}), Python oracle loop": lambda: ours(fmu, args.steps, [f"f.{n}" for n in numeric], "oracle"),
        f"FMPy simulate_fmu, same {len(numeric)} outputs": lambda: fmpy_peer(fmu, args.steps, numeric),
    }
    best = {k: min(f() for _ in range(args.repeat)) for k, f in rows.items()}
    print(f"Reference FMU Feedthrough (FMI 3.0), {args.steps} steps of 1 ms, best of {args.repeat}: us per step")
    for k, v in best.items():
        print(f"  {k:<45} {v:8.2f}")
    keys = list(best)
    print(f"  typed ports / Float64 only, Python loop   {best[keys[2]] / best[keys[1]]:8.1f}x")
    print(f"  FMPy / rpr-cosim with every type          {best[keys[3]] / best[keys[2]]:8.1f}x")


if __name__ == "__main__":
    main()
