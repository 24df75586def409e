"""``rpr-cosim analyze``: workspace, singularity and DSI analysis of the 3-RPR designs (thesis Ch. 4).

    rpr-cosim analyze [--config NAME|all] [--grid N] [--phi RAD] [--study configs|platform-size|all|none]
                      [--monte-carlo N] [--seed S] [--out DIR]

For each mapped design (default ``cross_leg``) it prints the workspace area (grid count and a
Monte Carlo estimate with its standard error) and the det J range, and saves heat maps of det J
and the four DSI with the singularity curves.  The studies print and save Table 4.5 (the four
configurations) and Table 4.9 with Figures 4.10-4.11 (platform size).  Tables go to stdout and to
CSV files in ``--out``; progress goes to stderr.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from ..errors import UserError
from models import analysis as A
from models.geometry import PRESETS, preset
from ..analysis import design_views as R

STUDIES = ("configs", "platform-size", "all", "none")


def _whole(option: str, text: str, lo: int, hi: int | None = None) -> int:
    try:
        value = int(str(text).strip())
    except ValueError:
        value = None
    if value is None or value < lo or (hi is not None and value > hi):
        rng = f"{lo}..{hi}" if hi is not None else f">= {lo}"
        raise UserError(f"{option} {text!r}: expected a whole number {rng}")
    return value


def _angle(option: str, text: str) -> float:
    try:
        value = float(str(text).strip())
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise UserError(f"{option} {text!r}: expected a finite angle in rad, e.g. 0 or 0.2")
    return value


def run(args: argparse.Namespace) -> int:


    names: list[str] = []
    for name in (n.strip() for n in args.config.split(",")):
        if name == "all":
            names += [n for n in A.CONFIGURATIONS if n not in names]
        elif name not in PRESETS:
            raise UserError(f"--config {name!r}: unknown configuration; expected one of "
                            f"{', '.join(PRESETS)} or all")
        elif name not in names:
            names.append(name)
    grid = None if args.grid is None else _whole("--grid", args.grid, 2, A.MAX_GRID)
    phi = _angle("--phi", args.phi)
    if args.study not in STUDIES:
        raise UserError(f"--study {args.study!r}: expected one of {', '.join(STUDIES)}")
    n_mc = _whole("--monte-carlo", args.monte_carlo, 0, 100_000_000)
    seed = _whole("--seed", args.seed, 0)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {str(out)!r}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)

    t_start = time.perf_counter()

    def progress(msg: str) -> None:
        print(f"[analyze {time.perf_counter() - t_start:5.1f}s] {msg}", file=sys.stderr, flush=True)

    def emit(table: R.Table, csv_name: str, csv_table: R.Table | None = None) -> None:
        print(R.format_table(table))
        print()
        path = R.write_csv(csv_table or table, out / csv_name)
        progress(f"wrote {path}")

    # --- maps of the chosen designs -----------------------------------------------------------
    results: list[R.WorkspaceResult] = []
    for name in names:
        m = preset(name)
        n = grid or A.THESIS_GRID.get(m.name, 500)
        progress(f"{name}: det J and DSI maps on a {n}x{n} grid over [-60, 60) cm, phi = {phi:g} rad")
        maps = A.dexterity_maps(m, A.thesis_grid(n), phi)
        locus = A.singularity_locus(maps)
        mc = None
        if n_mc:
            progress(f"{name}: Monte Carlo workspace area, {n_mc} samples (seed {seed})")
            mc = A.workspace_area_monte_carlo(m, n_mc, phi, rng=seed)
        result = R.WorkspaceResult(name, maps, locus, mc)
        results.append(result)
        progress(f"{name}: saving 5 heat maps")
        for path in R.save_maps(result, out):
            progress(f"wrote {path}")
    emit(R.workspace_table(results), "workspace.csv")
    for r in results:
        if r.maps.clipped:
            print(f"note: the workspace of {r.label} reaches the edge of the [-60, 60) cm window; "
                  "its area and averages cover the window only")

    # --- studies -----------------------------------------------------------------------------
    if args.study in ("configs", "all"):
        progress("Table 4.5: the four configurations " +
                 (f"on a {grid}x{grid} grid" if grid else "(N = 500; config3 N = 800)"))
        rows = A.compare_configurations(A.CONFIGURATIONS, grid, phi)
        emit(R.configurations_table(rows), "dsi_configurations.csv", R.configurations_csv_table(rows))
    else:
        rows = [A.summarize(r.maps, r.label) for r in results]
        emit(R.configurations_table(rows), "dsi_summary.csv", R.configurations_csv_table(rows))
    if args.study in ("platform-size", "all"):
        n = grid or A.PLATFORM_STUDY_GRID
        progress(f"Table 4.9: {len(A.PLATFORM_RATIOS)} platform sizes on a {n}x{n} grid")
        prow = A.platform_size_study(A.PLATFORM_RATIOS, A.PLATFORM_STUDY_SIDE, n, phi)
        emit(R.platform_size_table(prow, A.PLATFORM_STUDY_SIDE, n), "platform_size.csv")
        for path in R.save_platform_figures(prow, out):
            progress(f"wrote {path}")
    progress(f"done; results in {out}")
    return 0
