"""The fit checked as the user will use it: the calibrated scene (and the nominal one) run as
co-simulations under the master and compared with the data, as ``rpr-cosim compare`` does (the
data interpolated onto the run's instants; per signal the largest and RMS difference)."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from ..analysis.trace_diff import Difference, compare
from ..errors import UserError
from ..run.execute import RunResult, run
from ..trace.traces import Trace, read_trace
from ..analysis.charts import plot_comparison


@dataclass
class Check:
    label: str
    run: RunResult
    differences: list[Difference]
    data: Trace


def plot(check_: Check, path: Path) -> Path:
    """PNG of the run against the data, the worst signals first (as ``compare --plot``)."""

    units = {**check_.data.meta.get("units", {}), **check_.run.trace.meta.get("units", {})}
    return plot_comparison(check_.run.trace, check_.data, check_.differences, path,
                           labels=(check_.label, "data"), units=units)


def check(label: str, scene: Path, overrides: Sequence[str], data: Path, signals: Sequence[str], out_dir: Path,
          log: Callable[[str], None] | None = None) -> Check:
    """Run ``scene`` with ``overrides`` into ``out_dir`` and compare ``signals`` with ``data``."""
    res = run(scene, list(overrides), out_dir=out_dir, log=log)
    if res.status not in ("ok", "inaccurate"):
        raise UserError(f"the {label} co-simulation ended {res.status}: {res.reason}")
    recorded = read_trace(data)
    diffs = compare(res.trace, recorded, None)
    return Check(label, res, [d for d in diffs if d.name in signals], recorded)


def lines(checks: Sequence[Check], noise: dict[str, float]) -> list[str]:
    """Per signal: the fit's residual RMS (the noise level), then each run's RMS and largest difference."""
    out = ["  co-simulation against the data (RMS / largest difference; the fit's residual RMS is the noise level):"]
    head = f"    {'signal':<20} {'noise':>10}" + "".join(f" {c.label + ' RMS':>16} {'max':>10}" for c in checks)
    out.append(head)
    by = [{d.name: d for d in c.differences} for c in checks]
    for name in noise:
        row = f"    {name:<20} {noise[name]:>10.4g}"
        for b in by:
            d = b.get(name)
            row += f" {d.rms:>16.4g} {d.max_abs:>10.4g}" if d else f" {'-':>16} {'-':>10}"
        out.append(row)
    return out


__all__ = ["Check", "check", "lines", "plot"]
