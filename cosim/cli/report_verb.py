"""``rpr-cosim report``: an interactive, self-contained HTML report of a run, batch or study.

    rpr-cosim report OUT [-o FILE] [--runs]

``OUT`` is what a verb wrote: a trace file (``runs/pid_step/pid_step.csv`` or ``.parquet``) or
a run's directory (its one trace) -> the run's report beside the trace (``<name>.html``); a batch
directory (``results.csv`` and ``batch.json``) -> ``OUT/report.html`` (with ``--runs`` also each run's own
report, ``runs/<run id>/<name>.html``, linked from the batch's); a study table
(``<scene>_precision.csv``, ``<scene>_stability.csv``) or its directory -> ``<table>.html``.
The file opens offline (Plotly embedded, :mod:`cosim.analysis.html_report`).
"""
from __future__ import annotations

import argparse
import re
from pathlib import Path
from ..errors import UserError
from ..readers import read_json
from ..outputs import confined
from ..analysis.html_report import batch_report, run_report_from_files, study_report
from ..scenario.geometry import manipulator_for
from ..batch.overview import batch_meta, metric_units, run_trace_path
from ..batch.results import read_rows



def _report(args: argparse.Namespace) -> int:
    path = write_report(args.out, args.output, runs=args.runs)
    print(f"report: {path}")
    return 0


def _traces_in(d: Path) -> list[Path]:
    return sorted(p for p in (*d.glob("*.csv"), *d.glob("*.parquet"), *d.glob("*.npy"))
                  if not p.stem.endswith("_reference") and not p.stem.endswith(".prev") and _is_trace(p))


def _is_trace(p: Path) -> bool:

    try:
        data = read_json(p.with_suffix(".json"), "sidecar")
    except UserError:
        return False
    return isinstance(data, dict) and "scene_hash" in data


def write_report(out: Path, output: Path | None = None, *, runs: bool = False) -> Path:
    """The report of ``out`` (see the module docstring); returns the file written.  ``output``
    may be absolute or relative (to the working directory), whatever ``out`` is; a batch's own
    run reports (``runs``) are written only inside the batch's ``runs/`` folder."""

    out = Path(out)
    output = Path(output).absolute() if output is not None else None
    if not out.exists():
        raise UserError(f"{out}: no such file or directory")
    if out.is_dir() and (out / "results.csv").is_file() and (out / "batch.json").is_file():
        return _batch(out.absolute(), output or confined(out, "report.html"), runs)
    tables = [out] if out.is_file() and re.search(r"_(precision|stability)\.csv$", out.name) else (
        sorted([*out.glob("*_precision.csv"), *out.glob("*_stability.csv")]) if out.is_dir() else [])
    if tables:

        return study_report(tables[0], output or tables[0].with_suffix(".html"))
    if out.is_dir():
        found = _traces_in(out)
        if not found:
            raise UserError(f"{out}: no trace, batch (results.csv + batch.json) or study table to report")
        out = found[0]
    return run_file_report(out, output)


def run_file_report(trace_path: Path, output: Path | None = None, library_dir: Path | None = None) -> Path:
    """A run's report from its trace file and sidecar: units from the trace, setpoints from the
    recorded connections, the manipulator from the scene kept in the sidecar."""


    trace_path = Path(trace_path)
    side_path = trace_path.with_suffix(".json")
    side = read_json(side_path, "sidecar") if side_path.exists() else {}
    comps = ((side.get("scene_data") or {}).get("components") or {}) if isinstance(side, dict) else {}
    m = None
    for c in comps.values():
        if isinstance(c, dict) and c.get("model") == "mechanism":
            try:
                m = manipulator_for(c.get("options") or {}, c.get("params") or {})
            except (KeyError, TypeError, ValueError):
                m = None
            break
    conns = side.get("connections") if isinstance(side, dict) else None
    pairs = setpoints_of(conns if isinstance(conns, list) else [])
    return run_report_from_files(trace_path, output, pairs=pairs, manipulator=m, library_dir=library_dir)


def setpoints_of(connections: list[str]) -> dict[str, str]:
    """Setpoint signal -> the signal it commands, from the trace's recorded connections
    (``"src.var -> dst.setpoint"``, ``"src.var -> dst.measurement"``), as
    :func:`cosim.analysis.charts.setpoint_pairs` finds them in a scene."""
    src: dict[tuple[str, str], str] = {}
    for text in connections:
        m = re.match(r"\s*(\S+)\s*->\s*([^.\s]+)\.(\S+)", str(text))
        if m:
            src[(m.group(2), m.group(3))] = m.group(1)
    return {src[(d, "setpoint")]: src[(d, "measurement")] for d, v in src if v == "setpoint"
            and (d, "measurement") in src}


def _batch(out: Path, output: Path, runs: bool = False) -> Path:
    """The batch's report; its run ids (data read from ``results.csv``) name directories inside
    ``out/runs`` only (:func:`cosim.batch.overview.run_dir`), checked for every row before anything
    is written."""
    import os


    columns, rows = read_rows(out / "results.csv")
    meta = batch_meta(out)
    found = {str(r["run_id"]): run_trace_path(out, str(r["run_id"])) for r in rows}  # every id checked first
    traces, reports = {}, {}
    for rid, p in found.items():
        if p is None:
            continue
        traces[rid] = p
        html_file = confined(p.parent, p.with_suffix(".html").name)
        if runs:
            run_file_report(p, html_file, library_dir=output.parent)  # one Plotly library for the batch
        if html_file.is_file():
            rel = os.path.relpath(html_file, output.parent)
            reports[rid] = rel if not rel.startswith("..") else html_file.absolute().as_uri()
    units = {**meta["axis_units"], **metric_units(out, rows, meta["metrics"])}
    return batch_report(output, rows, columns, meta["axes"], meta["metrics"], traces,
                        title=f"batch {meta['batch']}", run_reports=reports, units=units)
