"""``rpr-cosim study``: measured studies of master algorithms on a scene.

    rpr-cosim study stability SCENE.yaml --vary PATH=LO:HI [--steps LO:HI] [--n N]
                                        [--variant ALG/INPUTS ...] [--out DIR]
    rpr-cosim study precision SCENE.yaml [--steps H,H,...] [--rtols R,R,...] [--variant ALG/INPUTS ...]
                                        [--stop T] [--only GLOB ...] [--tol REL] [--workers N]
                                        [--no-peer] [--out DIR]
    rpr-cosim study fidelity SCENE.yaml [--tol REL] [--only GLOB ...] [--set PATH=VALUE ...]

``stability`` maps where each master algorithm variant stays stable over the communication step
and one scene parameter (both on log axes), writes ``<scene>_stability.csv`` (one row per cell,
with the reason of every unstable or failed run) and ``<scene>_stability.png`` (cells coloured
stable / unstable / failed, with the analytic boundary for linear scenes), and prints how the
measured map agrees with the analytic one.

``precision`` measures every variant against the scene's monolithic reference, fixed-step
algorithms over the communication step and variable-step ones (adaptive, ecco) over their
tolerance ``rtol``, plus the peer master ecospy where it is installed, through the batch runner
(``--workers``, each run's trace under ``<out>/runs/``, resumable); it writes
``<scene>_precision.csv`` (per run and per signal) and ``<scene>_precision.png`` (worst relative
error against wall time, one curve per variant), and prints the table, the observed orders and the
cheapest run within ``--tol`` (:mod:`cosim.study.precision`).

``fidelity`` runs every combination of the scene's fidelity levels (components of one model share a
level) against the most detailed one and prints error and cost per combination and the cheapest
within ``--tol``; ``fidelity: auto`` in a scene uses the same study (see
:mod:`cosim.study.fidelity`).
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from .verb import load_scene, say
from ..errors import UserError
from ..master import ALGORITHMS
from ..run.progress import progress_bar
from ..study.stability import parse_range, plot_map, stability_map
from ..outputs import OutputLock, check_out_dir, confined
from ..batch.overview import Progress
from ..study.precision import plot_study, precision_study
from ..study.fidelity import fidelity_study
from ..analysis.html_report import study_report

def _variants(texts: list[str]) -> list[tuple[str, str]]:
    """Algorithm variants to study: fixed-step algorithms only (a variable-step one chooses its own
    steps, so a sweep over the step says nothing about it; ``tests/test_algorithms.py`` measures it)."""

    fixed = [name for name, cls in ALGORITHMS.items() if not getattr(cls, "variable_step", False)]
    if not texts:
        return [(alg, inputs) for alg in fixed for inputs in ("hold", "linear")]
    out = []
    for t in texts:
        alg, _, inputs = t.partition("/")
        inputs = inputs or "hold"
        if alg not in fixed or inputs not in ("hold", "linear"):
            raise UserError(f"--variant {t}: expected ALG/INPUTS with ALG a fixed-step algorithm "
                            f"({', '.join(sorted(fixed))}) and INPUTS hold or linear")
        out.append((alg, inputs))
    return out


def _precision_variants(texts: list[str]) -> list[tuple[str, str]]:
    """Variants of the precision study: every registered algorithm; a variable-step one takes its
    own inputs (linear: it interpolates and extrapolates them itself), so only ``ALG`` or
    ``ALG/linear`` names it."""

    variable = [n for n, cls in ALGORITHMS.items() if getattr(cls, "variable_step", False)]
    if not texts:
        return [(alg, inputs) for alg in ALGORITHMS for inputs in (("linear",) if alg in variable else
                                                                   ("hold", "linear"))]
    out = []
    for t in texts:
        alg, _, inputs = t.partition("/")
        inputs = inputs or ("linear" if alg in variable else "hold")
        if alg not in ALGORITHMS or inputs not in ("hold", "linear") or (alg in variable and inputs != "linear"):
            raise UserError(f"--variant {t}: expected ALG/INPUTS with ALG one of {', '.join(ALGORITHMS)} and INPUTS "
                            f"hold or linear ({', '.join(variable)} choose their own: ALG or ALG/linear)")
        out.append((alg, inputs))
    return list(dict.fromkeys(out))


def _numbers(text: str, option: str, example: str) -> list[float]:
    """Comma-separated numbers of ``option``; a one-line UserError otherwise."""

    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        raise UserError(f"{option} {text}: expected comma-separated numbers, e.g. {example}") from None
    return values


def _stability(args: argparse.Namespace) -> int:

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
    check_out_dir(out)  # files stay under --out (cosim.outputs)
    with OutputLock(out):  # the lock of runs and batches: one writer per directory
        csv_path, png_path = confined(out, f"{smap.scene}_stability.csv"), confined(out, f"{smap.scene}_stability.png")
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
    say(f"table: {csv_path}\nchart: {png_path}")
    _report(args, csv_path)
    return 0


def _report(args: argparse.Namespace, table: Path) -> None:
    if args.report:

        say(f"report: {study_report(table)}")


def _precision(args: argparse.Namespace) -> int:

    steps = _numbers(args.steps, "--steps", "4e-3,2e-3,1e-3 (comma-separated steps in seconds)") \
        if args.steps else None
    rtols = _numbers(args.rtols, "--rtols", "1e-2,1e-3,1e-4") if args.rtols else None
    if rtols is not None and not all(r > 0 for r in rtols):
        raise UserError(f"--rtols {args.rtols}: expected positive relative tolerances, e.g. 1e-2,1e-3,1e-4")
    if args.stop is not None and not args.stop > 0:
        raise UserError(f"--stop {args.stop}: expected a positive simulated time [s]")
    if not args.tol > 0:
        raise UserError(f"--tol {args.tol}: expected a positive relative tolerance")
    if not args.workers >= 1:
        raise UserError(f"--workers {args.workers}: expected at least 1 process")

    name = load_scene(args).name  # the output directory is named after the scene
    out = args.out or Path("runs") / f"{name}_precision"
    check_out_dir(out)  # files stay under --out (cosim.outputs)

    def log(msg: str) -> None:
        say(msg, flush=True)

    with OutputLock(out):  # the lock of runs and batches: one writer per directory
        study = precision_study(args.scene, _precision_variants(args.variant), steps, rtols=rtols,
                                stop_time=args.stop, only=args.only or None, cache_dir=args.cache,
                                overrides=args.sets, out=out, workers=args.workers, batch_progress=Progress(),
                                peer=args.peer, log=log, progress=lambda m: log(f"  {m}"), tolerance=args.tol)
        csv_path = confined(out, f"{study.scene}_precision.csv")
        png_path = confined(out, f"{study.scene}_precision.png")
        study.write_csv(csv_path)
        plot_study(study, png_path)
    print(f"{study.scene}: {len(study.rows)} runs over {study.stop_time:g} s against the monolithic reference "
          f"({study.reference_wall_s:.3f} s)")
    events = any(math.isfinite(r.event_time) or r.missing_events for r in study.rows)
    print(f"{'variant':<22} {'step/tol':>11} {'status':>10} {'worst rel':>10} {'RMS rel':>10} {'signal':<22} "
          f"{'wall s':>8} {'doSteps':>8} {'rejected':>8} {'rollbacks':>9}" + (f" {'event s':>9}" if events else ""))
    for r in study.rows:
        print(("* " if r.chosen else "") + f"{r.algorithm + '/' + r.inputs:<22} {r.label:>11} {r.status:>10} {r.worst:>10.3e} {r.rms:>10.3e} "
              f"{r.worst_signal:<22} {r.wall_s:>8.3f} {r.do_steps:>8} {r.rejected:>8} {r.rollbacks:>9}"
              + (f" {r.event_time:>9.2e}" if events else "") + (f"  ({r.reason})" if r.reason else ""))
    if events:
        print("event scene: 'worst rel' is the value error between events, 'event s' the largest event-time error of "
              "the matched events (docs/explanation/events.md)")
    for v in study.variants():
        p = study.order(v)
        if math.isfinite(p):
            what = "slope of error over rtol" if any(r.variable for r in study.rows if (r.algorithm, r.inputs) == v) \
                else "observed order"
            print(f"{what} {v[0]}/{v[1]}: {p:.2f}")
    best = study.cheapest_within(args.tol)
    print(f"cheapest within {args.tol:g}: " + (f"{best.algorithm}/{best.inputs} at {best.label} "
                                               f"({best.worst:.2e}, {best.wall_s:.3f} s)" if best else "none"))
    ch = study.choice()
    if ch is not None:
        if ch.chosen == "?":
            print(f"tolerance default's choice: failed ({ch.reason})")
        else:
            ratio = f", {ch.wall_s / best.wall_s:.2f}x the cheapest's wall time" if best and ch.status == "ok" else ""
            print(f"tolerance default's choice: {ch.algorithm} ({ch.chosen}), {ch.status}, worst {ch.worst:.2e}, "
                  f"{ch.wall_s:.3f} s{ratio}")
    say(f"table: {csv_path}\nchart: {png_path}\nruns: {out / 'runs'}")
    _report(args, csv_path)
    return 0


def _fidelity(args: argparse.Namespace) -> int:

    if not args.tol > 0:
        raise UserError(f"--tol {args.tol}: expected a positive relative tolerance")
    study = fidelity_study(args.scene, args.sets, only=args.only or None, cache_dir=args.cache,
                           progress=lambda m: say(f"  {m}", flush=True), tolerance=args.tol)
    top = study.rows[0]
    print(f"{study.scene}: {len(study.rows)} fidelity combinations against the most detailed ({top.label})"
          + (f"; each run within master.tolerance {study.run_tolerance:g} of its own exact solution"
             + (" where it has an error estimate" if any(r.unestimated for r in study.rows) else "")
             if study.run_tolerance else ""))
    print(f"{'combination':<62} {'status':>10} {'worst rel':>10} {'signal':<22} {'wall s':>8} {'speed-up':>8}")
    for r in study.rows:
        if r.status == "invalid":  # a combination that cannot run: no figures, the reason
            print(f"{r.label:<62} invalid: {r.reason}")
            continue
        speed = top.wall_s / r.wall_s if r.status == "ok" and r.wall_s > 0 else float("nan")
        print(f"{r.label:<62} {r.status:>10} {r.worst:>10.3e} {r.worst_signal:<22} {r.wall_s:>8.3f} {speed:>8.1f}"
              + (f"  ({r.reason})" if r.status != "ok" and r.reason else "")
              + (f"  (compared without {', '.join(r.dropped)}: not recorded at these levels)" if r.dropped else "")
              + (f"  (no error estimate of its own: {r.unestimated})" if r.unestimated else ""))
    print(_fidelity_answer(study, args.tol))
    return 0


def _fidelity_answer(study, tol: float) -> str:
    """The study's last line: the cheapest combination within ``tol``; where that is the most
    detailed itself, the nearest cheaper one and how far off it is."""
    top, best = study.rows[0], study.cheapest_within(tol)
    if best is None:
        return f"cheapest within {tol:g}: none"
    if best is not top:
        return (f"cheapest within {tol:g}: {best.label} ({best.worst:.2e}, {top.wall_s / best.wall_s:.1f}x faster "
                f"than the most detailed)")
    others = [r for r in study.rows[1:] if r.status == "ok" and r.worst == r.worst]
    near = min(others, key=lambda r: r.worst, default=None)
    return (f"cheapest within {tol:g}: the most detailed, {top.label}: no cheaper combination is within it"
            + (f" (the nearest, {near.label}, is {near.worst:.2e} of range off on {near.worst_signal})"
               if near else ""))
