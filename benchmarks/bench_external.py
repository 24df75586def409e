"""libcosim's quarter truck (two third-party FMUs, ``quarter_truck/OspSystemStructure.xml``): our
wall time against libcosimpy's ECCO and fixed step on the same file, at equal error.

Reference: a converged fine-step run (our Jacobi at 1e-5 s: the FMUs' own solvers step 1e-5 s, so
no finer coupling step changes them; the check printed below is its distance to a 2e-5 s run).
Error: the largest deviation of the chassis and wheel positions [m] from the reference, sampled
every 10 ms over the stop time, as a fraction of the reference's range.  Runs, one after the other
in one process (libcosimpy in a child process: it prints the FMUs' banners):

* libcosimpy ECCO as the file configures it, and libcosimpy fixed step at 1e-4 s and 2e-4 s
* ours: the master's choice for the YAML scene (gauss_seidel, compiled loop) at 1e-4 s and 2e-4 s, jacobi at 1e-4 s
  (libcosim's fixed-step convention), and ecco from the OSP file

    python3 benchmarks/bench_external.py [--stop 10]
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import load  # noqa: E402

DATA = ROOT.parent / "shared" / "third_party" / "libcosim-test-data" / "fmi2" / "quarter_truck"
if not DATA.is_dir():
    DATA = Path("/work/shared/third_party/libcosim-test-data/fmi2/quarter_truck")
NAMES = ["chassis.position", "wheel.position"]

PEER = """
import json, sys, numpy as np
sys.path.insert(0, {tests!r})
import libcosim_peer
from xml.etree import ElementTree
osp, stop, step = {osp!r}, {stop!r}, {step!r}
if step:
    text = open(osp + "/OspSystemStructure.xml").read()
    text = text.replace("<Algorithm>ecco</Algorithm>", "<Algorithm>fixedStep</Algorithm>").replace(
        "<BaseStepSize>0.0001</BaseStepSize>", "<BaseStepSize>" + repr(step) + "</BaseStepSize>")
    open(osp + "/OspSystemStructure.xml", "w").write(text)
r = libcosim_peer.run(osp, list(np.arange(1, round(stop / 0.01) + 1) * 0.01), {names!r})
print("@@" + json.dumps({{k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in r.items()}}))
"""


def libcosim(tmp: Path, stop: float, step: float | None) -> dict:
    d = tmp / f"lc_{step or 'ecco'}"
    shutil.copytree(DATA, d)
    code = PEER.format(tests=str(ROOT / "tests"), osp=str(d), stop=stop, step=step, names=NAMES)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    r = json.loads(next(x for x in out.splitlines() if x.startswith("@@"))[2:])
    return {k: np.asarray(v) if isinstance(v, list) else v for k, v in r.items()}


def ours(tmp: Path, stop: float, algorithm: str | None, step: float) -> dict:
    d = tmp / "ours"
    if not d.is_dir():
        shutil.copytree(DATA, d)
    sets = [f"stop_time={stop}", f"master.step={step}"]
    if algorithm:
        sets += [f"master.algorithm={algorithm}", "master.options=null"]
    sc = load(d / "OspSystemStructure.xml", sets)
    t0 = time.perf_counter()
    res = run(sc)
    wall = time.perf_counter() - t0
    assert res.ok, res.reason
    t = np.arange(1, round(stop / 0.01) + 1) * 0.01
    return {"wall_s": wall, "stepping_s": res.stats["wall_s"], "t": t,
            **{n: np.interp(t, res.trace.time, res.trace[n]) for n in NAMES}}


def error(r: dict, ref: dict) -> float:
    return max(float(np.max(np.abs(r[n] - ref[n])) / np.ptp(ref[n])) for n in NAMES)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stop", type=float, default=10.0, help="stop time [s] (default 10)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        ref = ours(tmp, args.stop, "jacobi", 1e-5)
        ref2 = ours(tmp, args.stop, "jacobi", 2e-5)
        print(f"reference: jacobi at 1e-5 s; against 2e-5 s: {100 * error(ref2, ref):.3g} % of range")
        rows = [("libcosimpy ECCO (the file's configuration)", libcosim(tmp, args.stop, None)),
                ("libcosimpy fixed step 1e-4 s", libcosim(tmp, args.stop, 1e-4)),
                ("libcosimpy fixed step 2e-4 s", libcosim(tmp, args.stop, 2e-4)),
                ("ours gauss_seidel 1e-4 s (the master's choice)", ours(tmp, args.stop, "gauss_seidel", 1e-4)),
                ("ours gauss_seidel 2e-4 s", ours(tmp, args.stop, "gauss_seidel", 2e-4)),
                ("ours jacobi 1e-4 s", ours(tmp, args.stop, "jacobi", 1e-4)),
                ("ours ecco (the file's configuration)", ours(tmp, args.stop, None, 1e-4))]
        lc_ecco = rows[0][1]["wall_s"]
        print(f"{'run':<46} {'wall s':>8} {'error % range':>14} {'vs libcosim ECCO':>17}")
        for label, r in rows:
            print(f"{label:<46} {r['wall_s']:>8.3f} {100 * error(r, ref):>14.3g} {lc_ecco / r['wall_s']:>16.2f}x")


if __name__ == "__main__":
    main()
