"""Accurate by default, and not dearer than it needs to be: each shipped scene at its defaults
(the master choosing from ``master.tolerance``, default 1e-3) against its monolithic reference,
and its wall time against the cheapest run within the same tolerance that ``rpr-cosim study
precision`` finds on the same scene, in the same process.

Per scene:

1. ``study precision`` (:func:`cosim.study.precision.precision_study`) sweeps the variants below
   at steps that divide the scene's output interval (the scene's step and halves: the same
   recorded instants as the default run; a step longer than the output interval cannot record
   it) and tolerances, measures every run against the monolithic reference (CVODES at rtol 1e-10,
   at the run's own instants for a variable-step run) and runs the scene the way its tolerance
   default runs it (the row ``choice``: the default run, measured the same way);
2. the default run's worst error is that row's: the largest deviation of any recorded signal from
   the reference over the whole run (start transient included), relative to the signal's range
   in the reference, and the signal;
3. wall times: the default run and the study's cheapest run within the tolerance, each run
   ``--repeat`` times alternately in this process through :func:`cosim.run.execute.run` (FMUs
   cached, so nothing is built), best of the repeats (the machine is shared and noisy: the best
   is the least disturbed).  Two measures: *loop*, the stepping loop of the final run (the run's
   ``wall_s``, what the study's chart and "cheapest" use), and *total*, the whole call: for the
   default its pilot runs, its companion run for the error estimate and the run; for the
   cheapest its companion and the run.  The ratio default / cheapest of both is printed.

    python3 benchmarks/bench_default.py [--scenes pid_step rig_step ...] [--repeat 5]

pid_step_multibody needs the multibody FMU (built once into the cache: minutes) and runs 0.5 s.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import load  # noqa: E402
from cosim.study.precision import PrecisionRow, is_variable_step, precision_study  # noqa: E402

#: (scene, stop time [s] or None for the scene's, variants, rtols, fixed steps as divisors of the
#: scene's output interval) swept by the study.
SCENES = [
    ("pid_step", None, [("adaptive", "linear"), ("ecco", "linear"), ("gauss_seidel", "linear"),
                        ("jacobi", "linear")], (1e-4, 3e-5, 1e-5, 3e-6, 1e-6), (1, 2, 4, 8)),
    ("pid_step_multibody", 0.5, [("adaptive", "linear"), ("ecco", "linear"), ("gauss_seidel", "linear")],
     (1e-4, 3e-5, 1e-5, 3e-6), (1, 2, 4, 8)),
    ("vw_compare", None, [("gauss_seidel", "linear"), ("jacobi", "linear")], (), (4, 8, 16, 32)),
    ("force_loop", None, [("iterative", "linear"), ("iterative", "hold")], (), (1, 2, 4, 8)),
    ("rig_step", None, [("adaptive", "hold"), ("gauss_seidel", "hold"), ("gauss_seidel", "linear"),
                        ("jacobi", "hold")], (1e-3, 1e-4, 1e-5), (1, 2, 4, 8)),
]


def overrides_of(row: PrecisionRow, stop: float, record: float) -> dict:
    """The scene overrides that run ``row``'s setting again (as the study ran it)."""
    over = {"stop_time": stop, "master.algorithm": row.algorithm, "master.inputs": row.inputs,
            "master.output_interval": record}
    if row.variable:
        over.update({"master.step": record, "master.options.rtol": row.tolerance})
    else:
        over["master.step"] = row.step
    return over


def timed(path: Path, over: dict) -> tuple[float, float, str]:
    """(loop wall time [s], total wall time [s], status) of one run of ``path`` with ``over``."""
    t0 = time.perf_counter()
    res = run(path, over)
    total = time.perf_counter() - t0
    return float(res.stats.get("wall_s", math.nan)), total, res.status


def bench(scene: str, stop: float | None, variants, rtols, divisors, repeat: int, say) -> dict:
    path = ROOT / "scenarios" / f"{scene}.yaml"
    base = load(path)
    record = base.master.record_every * base.master.step
    tol = base.master.tolerance
    steps = [record / k for k in divisors]
    rtols = [r for r in rtols if any(is_variable_step(a) for a, _ in variants)]
    study = precision_study(path, variants, steps, rtols=rtols, stop_time=stop, tolerance=tol)
    ch, cheap = study.choice(), study.cheapest_within(tol)
    row = {"scene": scene, "stop": study.stop_time, "tolerance": tol, "choice": ch, "cheapest": cheap,
           "study": study}
    if ch is None or cheap is None:
        return row
    default_over = {"stop_time": study.stop_time}
    cheap_over = overrides_of(cheap, study.stop_time, study.record)
    loops = {"default": [], "cheapest": []}
    totals = {"default": [], "cheapest": []}
    for k in range(repeat):
        for which, over in (("default", default_over), ("cheapest", cheap_over)):
            loop, total, status = timed(path, over)
            loops[which].append(loop)
            totals[which].append(total)
            say(f"  {scene}: {which} run {k + 1}/{repeat}: loop {loop:.4f} s, total {total:.3f} s, {status}")
    row.update({f"{w}_{m}": min(v[w]) for m, v in (("loop", loops), ("total", totals)) for w in v})
    return row


def fmt_choice(r: PrecisionRow) -> str:
    return f"{r.algorithm} ({r.chosen})"


def fmt_run(r: PrecisionRow) -> str:
    return f"{r.algorithm}/{r.inputs} {r.label}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", help="only these scenes")
    ap.add_argument("--repeat", type=int, default=5, help="timed repeats of each run (best of; default 5)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    args = ap.parse_args()
    say = (lambda m: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    rows = []
    for scene, stop, variants, rtols, divisors in SCENES:
        if args.scenes and scene not in args.scenes:
            continue
        say(f"{scene}: study precision ...")
        r = bench(scene, stop, variants, rtols, divisors, args.repeat, say)
        rows.append(r)
        for s in r["study"].rows:
            say(f"  {s.algorithm:<13} {s.inputs:<7} {s.label:<11} {s.status:<10} worst {s.worst:9.2e} "
                f"({s.worst_signal})  loop {s.wall_s:.4f} s")
    print(f"best of {args.repeat} runs each, in one process; loop: the stepping loop of the final run; total: the "
          f"whole run() call (default: pilots + companion + run; cheapest: companion + run)")
    print(f"| scene | stop s | choice | worst error / range (signal) | default loop s | default total s "
          f"| cheapest within tolerance (study precision) | its error | its loop s | its total s "
          f"| ratio loop | ratio total |")
    print("| --- | ---: | --- | --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        ch, cheap = r["choice"], r["cheapest"]
        if ch is None or cheap is None:
            why = "names its algorithm: no choice" if ch is None else "no run within the tolerance"
            print(f"| {r['scene']} | {r['stop']:g} | {why} |" + " |" * 9)
            continue
        flag = "" if ch.status == "ok" and ch.worst <= r["tolerance"] else f" **{ch.status}, over {r['tolerance']:g}**"
        print(f"| {r['scene']} | {r['stop']:g} | {fmt_choice(ch)} | {ch.worst:.2e} ({ch.worst_signal}){flag} "
              f"| {r['default_loop']:.4f} | {r['default_total']:.3f} | {fmt_run(cheap)} | {cheap.worst:.2e} "
              f"| {r['cheapest_loop']:.4f} | {r['cheapest_total']:.3f} "
              f"| {r['default_loop'] / r['cheapest_loop']:.2f} | {r['default_total'] / r['cheapest_total']:.2f} |")


if __name__ == "__main__":
    main()
