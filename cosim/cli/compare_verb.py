"""``rpr-cosim compare``: the differences between two traces.

    rpr-cosim compare TEST.csv REFERENCE.csv [--only PATTERN ...] [--plot FILE] [--tol REL]
                      [--allow-failed] [--allow-partial] [--events SIGNAL ...] [--event-tol S]

Prints, for every variable both traces recorded, the largest absolute difference, when it
occurs, the RMS and the error relative to the reference's range (REFERENCE is interpolated onto
TEST's instants).  With ``--tol`` the exit code is 1 when any relative error exceeds it, so the
command can gate a script.

A comparison is refused (exit 2; under ``--tol`` it fails with exit 1) when either run did not
end "ok" (its CSV status or JSON sidecar: failed, out_of_limits, unstable, interrupted, unfinished;
"stopped" at a component's own request counts as an end) unless
``--allow-failed``, when the traces overlap over less than either trace's time span (both
directions) unless ``--allow-partial``, and when the sidecars' scene hashes differ in what is
simulated (the differing entries are named) unless ``--allow-different-scenes``; runs of one scene
with different master settings are compared, with a note naming the settings.  Variables found in
only one trace are listed as not compared.

With ``--events`` (scenes with discontinuities, docs/explanation/events.md), each SIGNAL is an
event counter (whole numbers, e.g. ``rig.leg[2].impacts``) or a time-of-the-last-event signal
(e.g. ``mass.t_stick``) recorded in both traces: the events are matched in order and their
largest time difference printed, and the value errors are measured between events (outside a
window of that difference plus one output interval around each), where a max-norm would read a
jump placed a hair apart as an error the jump's size.  Under ``--tol`` a missing event fails, and
so does an event-time error beyond ``--event-tol`` seconds (default: the event time tolerance of
the runs' verdicts, REL times 0.1 s: 1e-4 s at 1e-3, docs/explanation/events.md).
"""
from __future__ import annotations

import argparse
import sys
from ..analysis.charts import plot_comparison
from ..master.estimate import event_time_tolerance
from ..errors import UserError
from ..trace.traces import read_trace
from ..batch.overview import compare_batch, format_batch_comparison
from ..analysis.trace_diff import VALID, compare_events, run_status



def _compare(args: argparse.Namespace) -> int:
    from ..analysis.trace_diff import comparability, compare, format_table

    if args.tol is not None and not args.tol > 0:
        raise UserError(f"--tol {args.tol}: expected a positive relative tolerance, e.g. 1e-3")
    if args.test.is_dir():
        return _compare_batch(args)
    test, ref = read_trace(args.test), read_trace(args.reference)
    checks = comparability(test, ref, test_path=args.test, ref_path=args.reference, patterns=args.only)
    problems = checks.problems(allow_failed=args.allow_failed, allow_partial=args.allow_partial,
                               allow_different_scenes=args.allow_different_scenes)
    if problems and args.tol is None:
        raise UserError("refused: " + "; ".join(problems))
    timings = []
    if args.events:

        timings, diffs = compare_events(test, ref, args.events, args.only)
    else:
        diffs = compare(test, ref, args.only)
    print(f"{args.test} against {args.reference}: {len(diffs)} variables"
          + (" (values between events)" if timings else ""))
    for tm in timings:
        miss = "; missing: " + ", ".join(f"{t:g} s (not in the {w})" for w, t in tm.missing) if tm.missing else ""
        print(f"events {tm.kind}: {tm.matched} matched, largest time error {tm.max_error:.3g} s at {tm.at:g} s{miss}")
    est = (test.stats or {}).get("estimate") or {}
    print(format_table(diffs, most=args.most, estimates=est.get("errors")))
    if est.get("worst") is not None:
        worst = max(diffs, key=lambda d: d.relative)
        print(f"estimated worst error {est['worst']:.2g} of range ({est['signal']}), measured {worst.relative:.2g} "
              f"({worst.name})")
    for note in checks.notes(allow_different_scenes=args.allow_different_scenes):
        print(f"note: {note}")
    if args.plot:
        units = {**ref.meta.get("units", {}), **test.meta.get("units", {})}  # recorded by rpr-cosim runs
        path = plot_comparison(test, ref, diffs, args.plot, labels=(args.test.stem, args.reference.stem), units=units)
        print(f"plot: {path}", file=sys.stderr)
    if args.tol is not None:
        for problem in problems:
            print(f"rpr-cosim compare: fails: {problem}", file=sys.stderr)
        bad = [d for d in diffs if not d.relative <= args.tol]
        if bad:
            print(f"rpr-cosim compare: {len(bad)} variable{'s' if len(bad) != 1 else ''} beyond the relative "
                  f"tolerance {args.tol:g} (worst: {max(bad, key=lambda d: d.relative).name})", file=sys.stderr)
            return 1
        if problems:
            return 1
        limit = args.event_tol if args.event_tol is not None else event_time_tolerance(args.tol)
        late = [tm for tm in timings if tm.missing or tm.max_error > limit]
        if late:
            print(f"rpr-cosim compare: events beyond the event time tolerance {limit:g} s or missing: "
                  f"{', '.join(tm.kind for tm in late)}", file=sys.stderr)
            return 1
    return 0


def _compare_batch(args: argparse.Namespace) -> int:
    """Many against one: every finished run of a batch against one reference trace."""

    ref = read_trace(args.reference)
    status, reason = run_status(ref, args.reference)
    problem = (f"{args.reference}: the run's status is {status!r}, not 'ok'" + (f" ({reason})" if reason else "")
               + "; use --allow-failed to compare against it anyway") if status not in VALID and not args.allow_failed else ""
    if problem and args.tol is None:
        raise UserError(f"refused: {problem}")
    axes, found = compare_batch(args.test, ref, args.only)
    print(f"{len(found)} runs of {args.test} against {args.reference} (worst variable of each, worst run first):")
    print(format_batch_comparison(axes, found, most=args.most))
    if args.tol is not None:
        bad = [r for r, diffs in found if not max(d.relative for d in diffs) <= args.tol]
        if bad:
            print(f"rpr-cosim compare: {len(bad)} run{'s' if len(bad) != 1 else ''} beyond the relative tolerance "
                  f"{args.tol:g}", file=sys.stderr)
            return 1
        if problem:
            print(f"rpr-cosim compare: fails: {problem}", file=sys.stderr)
            return 1
    return 0
