"""``rpr-cosim batch``: many runs of a scene (sweeps, Monte Carlo), resumable.

    rpr-cosim batch BATCH.yaml [--workers N] [--scheduler ADDRESS | --dask] [--out DIR]
                               [--sort COLUMN] [--descending] [--no-plots] [--check]
                               [--format npy|csv|commented-csv|parquet] [--report]

Runs go to local worker processes (one per core by default), to a Dask cluster at ADDRESS, or to
a Dask LocalCluster of N workers (``--dask``).  Results: ``DIR/results.csv`` (one row per run),
``DIR/runs/<run id>/`` (each run's trace), ``DIR/plots/`` (default ``DIR`` = ``runs/<batch>``);
traces are ``.npy`` (float64 rows, column names in the sidecar; nothing to format, so a run costs
what its stepping costs), ``--format csv`` writes CSV traces, ``--format parquet`` Parquet traces
and also ``DIR/results.parquet``; ``--report`` writes
``DIR/report.html`` (and each run's ``runs/<run id>/report.html``).
Running the same command again skips the runs already in the table, so an interrupted batch
resumes where it stopped.  A batch file with problems prints one line per problem and exits
with code 2 before any run; runs that fail are rows with their reason (exit code 0).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .verb import refuse, say, tagged
from ..batch import BatchError, load_batch, plan, run_batch
from ..study.fidelity import resolve_auto
from ..batch.executors import executor
from ..batch.overview import Progress, format_results, format_spread, make_plots
from ..errors import UserError
from .report_verb import write_report


def _batch(args: argparse.Namespace) -> int:

    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers {args.workers}: expected 1 or more")
    if args.scheduler and args.dask:
        raise UserError("--scheduler and --dask exclude each other: --dask starts a local cluster")
    try:
        batch = load_batch(args.batch, auto_fidelity=resolve_auto)
        for note in batch.notes:
            say(str(note))
        if args.sort is not None:
            from ..batch.results import base_columns

            cols = base_columns([a.name for a in batch.axes], batch.metric_columns)
            if args.sort not in cols:
                from ..scenario import suggest

                raise UserError(f"--sort {args.sort!r} is not a column{suggest(args.sort, cols)} "
                                f"(metrics: {', '.join(batch.metric_columns) or 'none'})")
        if args.check:
            return _check(batch, plan)
        ex = executor(args.workers, scheduler=args.scheduler, dask=args.dask)
        out = args.out or Path("runs") / batch.name
        try:
            res = run_batch(batch, out=out, executor=ex, cache_dir=args.cache, reuse=not args.no_reuse,
                            progress=Progress(), log=tagged("fmu"), trace_format=args.trace_format)
        except KeyboardInterrupt:
            say(f"rpr-cosim batch: interrupted; the finished runs are in {out / 'results.csv'}; run the same "
                f"command again to do the others")
            raise
    except BatchError as exc:
        return refuse(exc, "batch", args.batch)
    _summary(batch, res, args)
    return 0


def _check(batch, plan) -> int:
    runs, dups = plan(batch)
    axes = [a.name for a in batch.axes]
    print(f"batch {batch.name}: {len(runs)} runs of {batch.scene_path} ({', '.join(axes)}); "
          f"metrics: {', '.join(batch.metric_columns) or 'none'}")
    for r in runs[:10]:
        print(f"  {r.run_id}  " + ", ".join(f"{k}={v!r}" for k, v in r.point.values.items()))
    if len(runs) > 10:
        print(f"  ... {len(runs) - 10} more")
    for a, b in dups:
        print(f"  run {b} resolves to the same scene as run {a}; it runs once")
    return 0


def _summary(batch, res, args) -> None:

    axes = [a.name for a in batch.axes]
    sort = args.sort or batch.sort or (batch.metric_columns[0] if batch.metric_columns else None)
    n_ok = sum(r["outcome"] == "ok" for r in res.rows)
    print(f"batch {batch.name}: {len(res.rows)} runs ({n_ok} ok, {len(res.rows) - n_ok} not ok); this time "
          f"{res.ran} ran, {res.skipped} were in the table already; {res.wall_s:.1f} s")
    for a, b in res.duplicates:
        print(f"  run {b} resolves to the same scene as run {a}; it ran once")
    if sort:
        print(f"sorted by {sort}{' (largest first)' if args.descending else ''}:")
    print(format_results(res.rows, axes, batch.metric_columns, sort, most=args.most, descending=args.descending))
    if batch.random and batch.metric_columns:
        print(f"spread over the {batch.samples} samples per point:" if (batch.grid or batch.zip)
              else f"spread over {n_ok} ok runs:")
        print(format_spread(res.rows, batch.metric_columns))
    print(f"results: {res.out / 'results.csv'}")
    if args.trace_format == "parquet":
        print(f"results: {res.out / 'results.parquet'}")
    if args.report and res.rows:

        say(f"report: {write_report(res.out)}")
    if not args.no_plots and res.rows:
        for p in make_plots(batch, res.out, res.rows, sort):
            say(f"plot: {p}")
