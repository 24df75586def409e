"""``rpr-cosim compare``: the differences between two traces.

    rpr-cosim compare TEST.csv REFERENCE.csv [--only PATTERN ...] [--plot FILE] [--tol REL]

Prints, for every variable both traces recorded, the largest absolute difference, when it
occurs, the RMS and the error relative to the reference's range (REFERENCE is interpolated onto
TEST's instants).  With ``--tol`` the exit code is 1 when any relative error exceeds it, so the
command can gate a script.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="differences between two traces (e.g. co-simulation vs reference or rig)",
                       description="Compare two rpr-cosim traces variable by variable.")
    p.add_argument("test", type=Path, help="trace under test (CSV written by rpr-cosim), or the output directory "
                                           "of a batch: then every run of it is compared with REFERENCE")
    p.add_argument("reference", type=Path, help="reference trace, interpolated onto the first one's instants")
    p.add_argument("--only", action="append", default=[], metavar="PATTERN",
                   help="compare only variables matching this glob, e.g. 'mech.platform.*'; repeatable")
    p.add_argument("--plot", type=Path, metavar="FILE", help="also write a PNG of the worst variables")
    p.add_argument("--tol", type=float, metavar="REL",
                   help="exit with code 1 when a relative error (max |diff| / range) exceeds REL")
    p.add_argument("--most", type=int, default=None, metavar="N", help="show the N worst variables only")
    p.set_defaults(handler=_compare)


def _compare(args: argparse.Namespace) -> int:
    from .compare import compare, format_table, plot_comparison
    from .errors import UserError
    from .trace import read_trace

    if args.tol is not None and not args.tol > 0:
        raise UserError(f"--tol {args.tol}: expected a positive relative tolerance, e.g. 1e-3")
    if args.test.is_dir():
        return _compare_batch(args)
    test, ref = read_trace(args.test), read_trace(args.reference)
    diffs = compare(test, ref, args.only)
    print(f"{args.test} against {args.reference}: {len(diffs)} variables")
    print(format_table(diffs, most=args.most))
    if args.plot:
        units = {**ref.meta.get("units", {}), **test.meta.get("units", {})}  # recorded by rpr-cosim runs
        path = plot_comparison(test, ref, diffs, args.plot, labels=(args.test.stem, args.reference.stem), units=units)
        print(f"plot: {path}", file=sys.stderr)
    if args.tol is not None:
        bad = [d for d in diffs if not d.relative <= args.tol]
        if bad:
            print(f"rpr-cosim compare: {len(bad)} variable{'s' if len(bad) != 1 else ''} beyond the relative "
                  f"tolerance {args.tol:g} (worst: {max(bad, key=lambda d: d.relative).name})", file=sys.stderr)
            return 1
    return 0


def _compare_batch(args: argparse.Namespace) -> int:
    """Many against one: every finished run of a batch against one reference trace."""
    from .batch.report import compare_batch, format_batch_comparison
    from .trace import read_trace

    axes, found = compare_batch(args.test, read_trace(args.reference), args.only)
    print(f"{len(found)} runs of {args.test} against {args.reference} (worst variable of each, worst run first):")
    print(format_batch_comparison(axes, found, most=args.most))
    if args.tol is not None:
        bad = [r for r, diffs in found if not max(d.relative for d in diffs) <= args.tol]
        if bad:
            print(f"rpr-cosim compare: {len(bad)} run{'s' if len(bad) != 1 else ''} beyond the relative tolerance "
                  f"{args.tol:g}", file=sys.stderr)
            return 1
    return 0
