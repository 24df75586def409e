"""Users' components: translation and build time of the Modelica examples against the same
block written in Python.

For each pair (``scenarios/user/RackPinion.mo`` Drive.RackPinion vs ``scenarios/user/rack_pinion.py``;
``scenarios/user/DCMotor.mo`` Motors.DCMotor vs the catalog's ``dc_motor/full``) this script times

1. *block*: the Modelica text to a :class:`models.block.Block` (rumoca parse/flatten/DAE plus our
   translation, :func:`models.modelica.translate`; rumoca's part printed beside it), against
   calling the Python factory;
2. *FMU*: the cold build of the FMI 2.0 FMU into an empty cache (C generation, compile, pack),
   the same exporter for both;
3. *check*: that both blocks give the same ``ode``/``out`` at random points (max relative
   difference), so the figures compare the same model.

Each figure is the median of ``--repeat`` runs (a fresh cache per FMU build).

Usage: ``python3 benchmarks/bench_userblocks.py [--repeat N]``
"""
from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import fmus  # noqa: E402
import models.blocks as catalog  # noqa: E402
from models.modelica import translate  # noqa: E402

USER = ROOT / "scenarios" / "user"


def _python_gear():
    spec = importlib.util.spec_from_file_location("rack_pinion", USER / "rack_pinion.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.rack_pinion()


PAIRS = {
    "rack-and-pinion gear": ((USER / "RackPinion.mo", "Drive.RackPinion"), _python_gear),
    "DC motor (SPEC §6)": ((USER / "DCMotor.mo", "Motors.DCMotor"), lambda: catalog.make("dc_motor", "full")),
}


def _front_end(text: str, cls: str, filename: str):
    """rumoca alone: parse, flatten, DAE (what :func:`translate` asks of it)."""
    import rumoca

    m = rumoca.Session().loads(text, model=cls, filename=filename)
    return m.to_dict("dae"), m.to_dict("flat")


def _median(fn, repeat: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def _build(block, repeat: int) -> float:
    def once():
        with tempfile.TemporaryDirectory() as tmp:
            fmus.build_fmu(block, cache_dir=Path(tmp), progress=lambda m: None)
    return _median(once, repeat)[0]


def _difference(a, b) -> float:
    rng = np.random.default_rng(0)
    fa, fb = a.functions(), b.functions()
    order = [[v.name for v in b.inputs].index(v.name) for v in a.inputs]
    worst = 0.0
    for _ in range(50):
        x = rng.normal(size=b.x.numel())
        ub = rng.normal(size=b.u.numel())
        for f in ("ode", "out"):
            ya = np.array(fa[f](x, ub[order], a.param_defaults)).ravel()
            yb = np.array(fb[f](x, ub, b.param_defaults)).ravel()
            if f == "out":
                names_a, names_b = [v.name for v in a.outputs], [v.name for v in b.outputs]
                ya = np.array([ya[names_a.index(n)] for n in names_b])
            worst = max(worst, float(np.max(np.abs(ya - yb) / np.maximum(np.abs(yb), 1e-300))) if yb.size else 0.0)
    return worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"median of {args.repeat} runs; FMU: cold FMI 2.0 build into an empty cache")
    print(f"{'component':<22} {'written in':<9} {'block ms':>9} {'FMU s':>7} {'ratio':>7} {'same model':>11}")
    for label, ((mo, cls), python) in PAIRS.items():
        text = mo.read_text()
        t_mo, b_mo = _median(lambda: translate(text, cls, mo.name), args.repeat)
        t_fe, _ = _median(lambda: _front_end(text, cls, mo.name), args.repeat)
        t_py, b_py = _median(python, args.repeat)
        f_mo, f_py = _build(b_mo, args.repeat), _build(b_py, args.repeat)
        diff = _difference(b_mo, b_py)
        print(f"{label:<22} {'Modelica':<9} {t_mo * 1e3:>9.1f} {f_mo:>7.2f} {(t_mo + f_mo) / (t_py + f_py):>6.2f}x "
              f"{diff:>11.1e}   (rumoca's part of the block: {t_fe * 1e3:.1f} ms)")
        print(f"{'':<22} {'Python':<9} {t_py * 1e3:>9.1f} {f_py:>7.2f} {1.0:>6.2f}x")
    print("ratio: (block + FMU) of the Modelica component over its Python twin; same model: the largest "
          "relative difference of ode/out at 50 random points")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
