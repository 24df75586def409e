"""The cost of a Modelica Standard Library class as a component, cold and warm.

For each example class (default: Translational.Examples.Oscillator and Rotational.Examples.First)
this script times, in one process and in this order:

1. *whole library*: rumoca given the MSL directory as its root (what a front end that loads
   the library pays: every file parsed), the class compiled;
2. *closure*: finding the files the class reaches (:func:`cosim.scenario.modelica_sources.closure`:
   read, hash and scan them);
3. *cold*: rumoca on the view of those files only, into an empty compile cache;
4. *warm*: the same class again from the disk cache (the in-process memo cleared, as in a new
   process: a second run, a batch worker, a second component of the same class);
5. *translate*: rumoca's DAE to our :class:`models.block.Block` (sorting, solving, index
   reduction).

The FMU's C compile is not counted (it is the exporter's, cached by content like any block's).
Usage: ``python3 benchmarks/bench_modelica_msl.py [--msl DIR] [CLASS ...]``
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.scenario import modelica_sources as ms  # noqa: E402
from models.modelica import front_end, translate  # noqa: E402

DEFAULT = ["Modelica.Mechanics.Translational.Examples.Oscillator", "Modelica.Mechanics.Rotational.Examples.First"]


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--msl", type=Path, default=ROOT.parent / "shared" / "third_party" / "modelica-standard-library")
    ap.add_argument("classes", nargs="*", default=DEFAULT)
    args = ap.parse_args(argv)
    if not (args.msl / "Modelica" / "package.mo").is_file():
        print(f"no Modelica Standard Library at {args.msl} (give --msl DIR)", file=sys.stderr)
        return 2
    total = sum(1 for _ in args.msl.rglob("*.mo"))
    print(f"MSL: {total} files at {args.msl}")
    print(f"{'class':<58} {'whole lib':>9} {'closure':>8} {'files':>6} {'cold':>6} {'warm':>6} {'transl.':>7}  [s]")
    for cls in args.classes:
        wrapper = f"model RprBench\n  extends {cls};\nend RprBench;\n"
        _, whole = _timed(lambda: front_end(wrapper, "RprBench", "bench.mo", (str(args.msl),)))
        mc, closure = _timed(lambda: ms.modelica_class(cls, None, Path("."), [args.msl]))
        with tempfile.TemporaryDirectory() as cache:
            ms._MEMO.clear()
            _, cold = _timed(lambda: mc.compiled(cache=Path(cache)))
            ms._MEMO.clear()
            fe, warm = _timed(lambda: mc.compiled(cache=Path(cache)))
        _, trans = _timed(lambda: translate(mc.text, mc.model, mc.filename, compiled=fe, scan=False))
        print(f"{cls:<58} {whole:9.2f} {closure:8.2f} {len(mc.sources.files) + 1:6d} {cold:6.2f} {warm:6.2f} "
              f"{trans:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
