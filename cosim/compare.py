"""Differences between two traces of the same variables: a co-simulation against its monolithic
reference, one master algorithm or step against another, or a simulation against the rig.

The second trace (the reference) is interpolated linearly onto the first one's instants inside
the time span both cover; a variable's error is reported absolute and relative to the
reference's range over that span (max - min, or max |value| for a constant signal).
"""
from __future__ import annotations

import fnmatch
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import UserError
from .trace import Trace


@dataclass(frozen=True)
class Difference:
    """Error of one variable: largest absolute difference ``max_abs`` at time ``at`` [s], its RMS
    over the common span, and the reference's ``scale`` (range) it is measured against."""

    name: str
    max_abs: float
    at: float
    rms: float
    scale: float

    @property
    def relative(self) -> float:
        """``max_abs / scale`` (0 when both are 0, inf for a difference on a zero reference)."""
        if self.scale > 0:
            return self.max_abs / self.scale
        return 0.0 if self.max_abs == 0 else float("inf")


def common_names(test: Trace, ref: Trace, patterns: Sequence[str] | None = None) -> list[str]:
    """Variables recorded in both traces (in ``test``'s order), optionally filtered by glob
    ``patterns`` (e.g. ``mech.platform.*``); none in common is a :class:`UserError`."""
    names = [n for n in test.names if n in ref.columns]
    if patterns:
        names = [n for n in names if any(fnmatch.fnmatchcase(n, p.replace("[", "[[]")) for p in patterns)]
    if not names:
        what = f" matching {', '.join(patterns)}" if patterns else ""
        raise UserError(f"the traces have no variable{what} in common "
                        f"(first: {', '.join(test.names[:3])}...; second: {', '.join(ref.names[:3])}...)")
    return names


def aligned(test: Trace, ref: Trace, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, a, b)``: ``test``'s instants inside ``ref``'s span, and both traces' values of
    ``names`` there (``ref`` interpolated linearly), one column per name."""
    if len(test.data) == 0 or len(ref.data) == 0:
        raise UserError("a trace to compare has no rows")
    t = test.time
    keep = (t >= ref.time[0] - 1e-12) & (t <= ref.time[-1] + 1e-12)
    if not keep.any():
        raise UserError(f"the traces do not overlap in time ({t[0]:g}..{t[-1]:g} s against "
                        f"{ref.time[0]:g}..{ref.time[-1]:g} s)")
    t = t[keep]
    a = np.column_stack([test[n][keep] for n in names])
    b = np.column_stack([np.interp(t, ref.time, ref[n]) for n in names])
    return t, a, b


def compare(test: Trace, ref: Trace, patterns: Sequence[str] | None = None) -> list[Difference]:
    """The :class:`Difference` of every common variable (see the module docstring)."""
    names = common_names(test, ref, patterns)
    t, a, b = aligned(test, ref, names)
    d = np.abs(a - b)
    k = np.argmax(d, axis=0)
    span = b.max(axis=0) - b.min(axis=0)
    scale = np.where(span > 0, span, np.abs(b).max(axis=0))
    rms = np.sqrt(np.mean(d ** 2, axis=0))
    return [Difference(n, float(d[k[j], j]), float(t[k[j]]), float(rms[j]), float(scale[j]))
            for j, n in enumerate(names)]


def format_table(diffs: Sequence[Difference], *, most: int | None = None) -> str:
    """A text table, largest relative error first (``most`` rows at most)."""
    rows = sorted(diffs, key=lambda d: -d.relative)[:most]
    w = max([len(d.name) for d in rows] + [8])
    lines = [f"  {'variable':<{w}}  {'max |diff|':>11}  {'at t [s]':>9}  {'rms':>10}  {'range':>10}  {'max/range':>9}"]
    lines += [f"  {d.name:<{w}}  {d.max_abs:>11.3e}  {d.at:>9.4f}  {d.rms:>10.3e}  {d.scale:>10.3e}  {d.relative:>9.2e}"
              for d in rows]
    if most is not None and len(diffs) > most:
        lines.append(f"  ... {len(diffs) - most} more variables with smaller relative errors")
    return "\n".join(lines)


def plot_comparison(test: Trace, ref: Trace, diffs: Sequence[Difference], path: Path, *,
                    labels: tuple[str, str] = ("test", "reference"), most: int = 8,
                    units: dict[str, str] | None = None) -> Path:
    """PNG with, for the ``most`` variables of largest relative error, both traces (left) and
    their difference (right), in the variables' ``units`` (see :mod:`cosim.charts`)."""
    from .charts import plot_comparison as plot

    return plot(test, ref, diffs, path, labels=labels, most=most, units=units)


__all__ = ["Difference", "aligned", "common_names", "compare", "format_table", "plot_comparison"]
