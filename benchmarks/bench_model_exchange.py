"""A model-exchange FMU (integrated by CVODES inside its compiled slave) against the same model as
a co-simulation FMU and against FMPy's model-exchange loop (CVODE with Python callbacks), at equal
error, in one run.  Model: the Reference FMU VanDerPol (FMI 3.0, built from
``../shared/third_party/Reference-FMUs`` as the tests do), 20 s, recorded every 0.01 s; its
co-simulation interface integrates with forward Euler at an internal step of at most 0.01 s.

Error: the worst of x0, x1 against FMPy's model-exchange run at rtol 1e-12, relative to each
signal's range.  Each method is swept over its accuracy knob (rtol, or the communication step
for co-simulation); the table lists every point, then the cheapest point of each method within
each error target.  Wall time: ours from instantiation to the end (the run's own ``init_s`` +
``wall_s``, no scene loading), FMPy's ``simulate_fmu`` call (it unpacks and loads the FMU too).

    python3 benchmarks/bench_model_exchange.py [--repeat 3]
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from conftest import REFERENCE_FMUS_SRC, _source_key, build_reference_fmus  # noqa: E402

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import from_dict  # noqa: E402
from fmus.cache import cache_root  # noqa: E402

STOP, GRID = 20.0, 0.01
NAMES = ("x0", "x1")


def me_only(src: Path, dst: Path) -> Path:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                data = re.sub(r"<CoSimulation\b[^>]*?/>|<CoSimulation\b[^>]*[^/]>.*?</CoSimulation>", "",
                              data.decode(), flags=re.S).encode()
            zout.writestr(item, data)
    return dst


def fmpy_me(fmu: Path, rtol: float):
    import fmpy

    return fmpy.simulate_fmu(str(fmu), fmi_type="ModelExchange", relative_tolerance=rtol, output_interval=GRID,
                             stop_time=STOP, output=list(NAMES))


def error(t, cols, ref) -> float:
    return max(float(np.max(np.abs(cols[n] - np.interp(t, ref["time"], ref[n])))) / float(np.ptp(ref[n]))
               for n in NAMES)


def ours(fmu: Path, step: float, rtol: float | None, ref) -> tuple[float, float]:
    comp = {"fmu": str(fmu), **({"rtol": rtol} if rtol else {})}
    scene = from_dict({"name": "b", "stop_time": STOP, "components": {"m": comp}, "outputs": [f"m.{n}" for n in NAMES],
                       "master": {"algorithm": "jacobi", "step": step, "output_interval": GRID, "estimate": False}})
    res = run(scene)
    assert res.status == "ok", res.reason
    return res.stats["wall_s"] + res.stats.get("init_s", 0.0), error(res.trace.time, {n: res.trace[f"m.{n}"] for n in NAMES}, ref)


def peer(fmu: Path, rtol: float, ref) -> tuple[float, float]:
    t0 = time.perf_counter()
    res = fmpy_me(fmu, rtol)
    wall = time.perf_counter() - t0
    t = np.asarray(res["time"])
    return wall, error(t, {n: np.asarray(res[n]) for n in NAMES}, ref)


def best(fn, repeat: int) -> tuple[float, float]:
    runs = [fn() for _ in range(repeat)]
    return min(r[0] for r in runs), runs[0][1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    fmus = build_reference_fmus(REFERENCE_FMUS_SRC, cache_root().parent / "reference-fmus" / _source_key(REFERENCE_FMUS_SRC))
    cs = fmus["3.0/VanDerPol"]
    with tempfile.TemporaryDirectory() as tmp:
        me = me_only(cs, Path(tmp) / "VanDerPolME.fmu")
        ref = fmpy_me(me, 1e-12)
        rows = []
        for rtol in (1e-4, 1e-5, 1e-6, 1e-7, 1e-8):
            rows.append(("model exchange (ours, CVODES in C)", f"rtol {rtol:g}", *best(lambda: ours(me, GRID, rtol, ref), args.repeat)))
        for rtol in (1e-4, 1e-5, 1e-6, 1e-7, 1e-8):
            rows.append(("FMPy model exchange (CVODE, Python callbacks)", f"rtol {rtol:g}", *best(lambda: peer(me, rtol, ref), args.repeat)))
        for step in (1e-2, 1e-3, 1e-4, 1e-5):
            rows.append(("co-simulation FMU (its forward Euler)", f"step {step:g} s", *best(lambda: ours(cs, step, None, ref), 1)))
    print(f"VanDerPol (FMI 3.0), {STOP:g} s recorded every {GRID:g} s; error: worst of x0, x1 against FMPy ME at "
          f"rtol 1e-12, relative to range; wall: best of {args.repeat} (co-simulation: 1) [s]")
    print(f"{'method':<48} {'setting':<12} {'error':>9} {'wall s':>8}")
    for name, setting, wall, err in rows:
        print(f"{name:<48} {setting:<12} {err:>9.2e} {wall:>8.3f}")
    for target in (1e-3, 1e-5):
        print(f"cheapest within {target:g} of range:")
        base = None
        for method in dict.fromkeys(r[0] for r in rows):
            ok = [r for r in rows if r[0] == method and r[3] <= target]
            if not ok:
                print(f"  {method:<48} none of its settings")
                continue
            pick = min(ok, key=lambda r: r[2])
            base = base or pick[2]
            print(f"  {method:<48} {pick[1]:<12} {pick[2]:>8.3f} s ({pick[2] / base:.2f}x ours)")


if __name__ == "__main__":
    main()
