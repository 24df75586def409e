"""``rpr-cosim fit``: estimate a scene's parameters from a recording, write the calibrated scene
and check it as a co-simulation.

    rpr-cosim fit SCENE --data FILE --params 'rig.R,rig.k,rig.leg[*].raw_zero' [--signals A,B]
                  [--set PATH=VALUE ...] [--out DIR] [--max-evaluations N] [--substeps N] [--no-check]

Least squares on the scene's monolithic model (:mod:`cosim.fit`): the scene's recorded outputs
that the data has (or ``--signals``) against the data, each weighted by its range, from the
scene's values within the catalog bounds.  Prints each estimate with its 95 % interval, the
residual before and after, and the parameters the data cannot tell apart; writes
``OUT/<scene>_fitted.yaml`` (an overlay of SCENE) and ``OUT/fit.json``; then runs the calibrated
and the nominal scene as co-simulations and compares both with the data, with a plot of each
(``OUT/fitted_vs_data.png``, ``OUT/nominal_vs_data.png``; ``--no-check``: none of this).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from .verb import refuse, say, tagged
from ..errors import UserError
from ..fit import build, solve
from ..fit.confirm import check, lines as check_lines, plot
from ..fit.overlay import write_overlay
from ..fit.summary import as_dict, lines
from ..outputs import OutputLock, check_out_dir, safe_name
from ..scenario import SceneError, load


def _split(text: str | None) -> list[str]:
    """``a,b[1],c`` -> names; a comma inside brackets stays (``leg[1,2]`` is not a name anyway)."""
    return [s.strip() for s in (text or "").split(",") if s.strip()]


def _fit(args: argparse.Namespace) -> int:

    try:
        scene = load(args.scene, args.sets)
    except SceneError as exc:
        return refuse(exc, "fit", args.scene)
    if args.max_evaluations < 1 or (args.substeps is not None and args.substeps < 1):
        raise UserError("--max-evaluations and --substeps must be whole numbers >= 1")
    problem = build(scene, args.data, _split(args.params), signals=_split(args.signals) or None,
                    substeps=args.substeps)
    say(f"fit: {len(problem.unknowns)} parameters, {len(problem.signals)} signals, {len(problem.time)} instants")
    result = solve(problem, max_evaluations=args.max_evaluations, log=say)
    out = args.out or Path("runs") / safe_name(f"{scene.name}_fit")
    check_out_dir(out)
    with OutputLock(out, log=tagged("fit")):
        for line in lines(result):
            print(line)
        overlay = write_overlay(result, args.scene, out / f"{safe_name(scene.name)}_fitted.yaml", args.sets)
        print(f"  calibrated scene: {overlay}")
        record = as_dict(result)
        if not args.no_check:
            noise = dict(zip(problem.signals, map(float, result.signal_rms_end)))
            fitted = check("fitted", overlay, [], args.data, problem.signals, out / "fitted", log=tagged("run"))
            nominal = check("nominal", args.scene, args.sets, args.data, problem.signals, out / "nominal",
                            log=tagged("run"))
            for line in check_lines([fitted, nominal], noise):
                print(line)
            print(f"  plots: {plot(fitted, out / 'fitted_vs_data.png')}, {plot(nominal, out / 'nominal_vs_data.png')}")
            record["check"] = {c.label: {d.name: {"rms": d.rms, "max_abs": d.max_abs, "at": d.at}
                                         for d in c.differences} for c in (fitted, nominal)}
        (out / "fit.json").write_text(json.dumps(record, indent=1) + "\n")
        print(f"  report: {out / 'fit.json'}")
    return 0
