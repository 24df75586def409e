"""The fit's report as text (the verb prints it) and as plain data (``fit.json``)."""
from __future__ import annotations

import math

import numpy as np

from .solve import CORRELATED, FitResult

#: A 95 % interval wider than this fraction of the estimate: poorly determined.
WIDE = 0.1


def _interval(half: float, value: float) -> str:
    if not math.isfinite(half):
        return "not identifiable"
    rel = f" ({half / abs(value):.1%})" if value else ""
    return f"+-{half:.3g}{rel}"


def _unit(unit: str) -> str:
    return "" if unit in ("", "1") else unit


def lines(result: FitResult) -> list[str]:
    """The estimates, residuals and what the data cannot tell apart, one item a line."""
    pb = result.problem
    out = [f"fit of {len(result.estimates)} parameters of {pb.scene.name} to {pb.data_path.name}: "
           f"{len(pb.time)} instants x {len(pb.signals)} signals, RK4 x{pb.substeps} per interval; "
           f"{result.evaluations} evaluations, {result.jacobians} Jacobians, {result.wall_s:.2f} s ({result.message})"]
    width = max(len(e.unknown.path) for e in result.estimates)
    out.append(f"  {'parameter':<{width}}  {'start':>12}  {'estimate':>12}  {'95 % interval':>22}  unit")
    for e in result.estimates:
        bound = "  at a bound" if e.unknown.path in result.at_bound else ""
        out.append(f"  {e.unknown.path:<{width}}  {e.unknown.start:>12.6g}  {e.value:>12.6g}  "
                   f"{_interval(e.half_width, e.value):>22}  {_unit(e.unknown.unit)}{bound}")
    out.append(f"  residual (weighted RMS, relative to each signal's range): {result.rms_start:.4g} -> "
               f"{result.rms_end:.4g}")
    for s, unit, a, b in zip(pb.signals, pb.units, result.signal_rms_start, result.signal_rms_end):
        out.append(f"    {s}: RMS {a:.4g} -> {b:.4g} {_unit(unit)}".rstrip())
    for group in result.unseen:
        out.append(f"  cannot tell apart (the data do not see a combination of them): {', '.join(group)}")
    loose = {e.unknown.path for e in result.estimates if not e.relative <= WIDE}
    for a, b, rho in result.confounded:
        if any(a in g and b in g for g in result.unseen):
            continue
        verdict = "cannot tell apart" if a in loose or b in loose else "correlated, each determined nonetheless"
        out.append(f"  {verdict}: {a} and {b} (correlation {rho:+.4f})")
    return out


def as_dict(result: FitResult) -> dict:
    pb = result.problem
    names = [e.unknown.path for e in result.estimates]
    finite = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731  (JSON has no inf)
    return {"scene": pb.scene.name, "data": str(pb.data_path), "signals": pb.signals, "instants": len(pb.time),
            "substeps": pb.substeps, "evaluations": result.evaluations, "jacobians": result.jacobians,
            "wall_s": result.wall_s, "message": result.message,
            "estimates": [{"parameter": e.unknown.path, "unit": e.unknown.unit, "start": e.unknown.start,
                           "value": e.value, "ci95": finite(e.half_width), "at_bound": e.unknown.path in result.at_bound}
                          for e in result.estimates],
            "residual": {"weighted_rms_start": result.rms_start, "weighted_rms_end": result.rms_end,
                         "rms_start": dict(zip(pb.signals, map(float, result.signal_rms_start))),
                         "rms_end": dict(zip(pb.signals, map(float, result.signal_rms_end)))},
            "correlation": {"parameters": names, "matrix": np.round(result.correlation, 6).tolist()},
            "cannot_tell_apart": result.unseen,
            "correlated": [{"a": a, "b": b, "correlation": rho} for a, b, rho in result.confounded],
            "correlated_above": CORRELATED}


__all__ = ["as_dict", "lines"]
