"""``rpr-cosim study``: measured studies of master algorithms on a scene.

    rpr-cosim study stability SCENE.yaml --vary PATH=LO:HI [--steps LO:HI] [--n N]
                                        [--variant ALG/INPUTS ...] [--out DIR]

``stability`` maps where each master algorithm variant stays stable over the communication step
and one scene parameter (both on log axes), writes ``<scene>_stability.csv`` (one row per cell,
with the reason of every unstable or failed run) and ``<scene>_stability.png`` (cells coloured
stable / unstable / failed, with the analytic boundary for linear scenes), and prints how the
measured map agrees with the analytic one.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("study", help="measured studies of master algorithms (stability maps)",
                       description="Studies that run a scene many times and chart the outcome.")
    studies = p.add_subparsers(dest="study", metavar="STUDY")
    studies.required = True
    s = studies.add_parser("stability", help="stable/unstable map over communication step x one scene parameter",
                           description="Run the scene over a log grid of communication steps and values of one "
                                       "parameter, for each master algorithm variant, and chart where it is stable.")
    s.add_argument("scene", type=Path, help="scene file, e.g. scenarios/two_mass.yaml")
    s.add_argument("--vary", required=True, metavar="PATH=LO:HI",
                   help="scene parameter and its range (log axis), e.g. components.mass2.params.kc=1:1e4")
    s.add_argument("--steps", default="1e-3:0.5", metavar="LO:HI", help="communication steps [s] (log axis; "
                                                                         "default 1e-3:0.5)")
    s.add_argument("--n", type=int, default=12, metavar="N", help="grid points per axis (default 12)")
    s.add_argument("--variant", action="append", default=[], metavar="ALG/INPUTS",
                   help="algorithm variant, e.g. jacobi/hold or gauss_seidel/linear; repeatable "
                        "(default: jacobi and gauss_seidel, hold and linear)")
    s.add_argument("--out", type=Path, help="output directory (default runs/<scene>_stability)")
    s.add_argument("--cache", type=Path, help="FMU cache directory")
    s.set_defaults(handler=_stability)


def _variants(texts: list[str]) -> list[tuple[str, str]]:
    from .errors import UserError
    from .master import ALGORITHMS
    from .study.stability import DEFAULT_VARIANTS

    if not texts:
        return list(DEFAULT_VARIANTS)
    out = []
    for t in texts:
        alg, _, inputs = t.partition("/")
        inputs = inputs or "hold"
        if alg not in ALGORITHMS or inputs not in ("hold", "linear"):
            raise UserError(f"--variant {t}: expected ALG/INPUTS with ALG one of {', '.join(sorted(ALGORITHMS))} "
                            f"and INPUTS hold or linear")
        out.append((alg, inputs))
    return out


def _stability(args: argparse.Namespace) -> int:
    from .errors import UserError
    from .run import progress_bar
    from .study.stability import parse_range, plot_map, stability_map

    path, sep, rng = args.vary.partition("=")
    if not sep:
        raise UserError(f"--vary {args.vary}: expected PATH=LO:HI, e.g. components.mass2.params.kc=1:1e4")
    if not 2 <= args.n <= 200:
        raise UserError(f"--n {args.n}: expected 2 to 200 grid points per axis")
    values, steps = parse_range(rng, "--vary"), parse_range(args.steps, "--steps")
    variants = _variants(args.variant)
    smap = stability_map(args.scene, path, values, steps, n_values=args.n, n_steps=args.n, variants=variants,
                         cache_dir=args.cache, progress=progress_bar())
    out = args.out or Path("runs") / f"{smap.scene}_stability"
    out.mkdir(parents=True, exist_ok=True)
    csv_path, png_path = out / f"{smap.scene}_stability.csv", out / f"{smap.scene}_stability.png"
    smap.write_csv(csv_path)
    plot_map(smap, png_path, args.scene)
    print(f"{smap.scene}: {len(smap.cells)} runs over step x {path}")
    print(f"{'variant':<24} {'stable':>7} {'unstable':>9} {'failed':>7}  {'agree with analytic':>20}")
    for v in smap.variants:
        cells = [c for c in smap.cells if (c.algorithm, c.inputs) == v]
        count = {k: sum(c.outcome == k for c in cells) for k in ("stable", "unstable", "failed")}
        agree = (f"{sum((c.outcome == 'stable') == (c.rho <= 1) for c in cells)}/{len(cells)}"
                 if smap.analytic else "-")
        print(f"{v[0] + '/' + v[1]:<24} {count['stable']:>7} {count['unstable']:>9} {count['failed']:>7}  {agree:>20}")
    if not smap.analytic:
        print(f"no analytic boundary: {smap.analytic_note}")
    print(f"table: {csv_path}\nchart: {png_path}", file=sys.stderr)
    return 0
