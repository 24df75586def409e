"""Differences between two traces of the same variables: a co-simulation against its monolithic
reference, one master algorithm or step against another, or a simulation against the rig.

The second trace (the reference) is interpolated linearly onto the first one's instants inside
the time span both cover; a variable's error is reported absolute and relative to the
reference's range over that span (max - min, or max |value| for a constant signal), at least
:data:`cosim.master.estimate.FLAT` as the tolerance and the error estimate measure it (a platform
angle a path keeps at 0 moves 1e-18 rad: an error of 5e-9 rad on it is not 3e9 of its range).

:func:`comparability` says whether such numbers can be trusted: both runs must have ended "ok"
(the CSV's final status and its JSON sidecar; "stopped" at a component's own request counts),
the overlap must cover both traces' spans (a test run of 0-2 s against a reference of 0-0.2 s is
as partial as the reverse), the two runs must simulate the same scene (scene hashes that differ
are explained by the scene entries that differ: components, parameters, connections and inputs
make them different scenes; the master's settings, outputs and times are how one scene was
run, which is what comparisons are for), and the variables only one trace has are listed.
"""
from __future__ import annotations

import difflib
import fnmatch
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..master.estimate import FLAT, EventMatch, match_modes
from ..trace.traces import Trace
from .tables import text_table
from ..readers import read_json


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
        """``max_abs / max(scale, FLAT)`` (the module docstring)."""
        return self.max_abs / max(self.scale, FLAT)


def matches(name: str, pattern: str) -> bool:
    """``name`` matches the ``--only`` glob ``pattern``: ``*``, ``?`` and classes such as ``[xy]``
    as in a shell, or with its brackets read literally (``mech.leg[1].s``, ``leg[*].s``)."""
    return fnmatch.fnmatchcase(name, pattern) or fnmatch.fnmatchcase(name, pattern.replace("[", "[[]"))


def common_names(test: Trace, ref: Trace, patterns: Sequence[str] | None = None) -> list[str]:
    """Variables recorded in both traces (in ``test``'s order), optionally filtered by glob
    ``patterns`` (e.g. ``mech.platform.*``); none in common is a :class:`UserError`."""
    names = [n for n in test.names if n in ref.columns]
    if patterns:
        names = [n for n in names if any(matches(n, p) for p in patterns)]
    if not names:
        what = f" matching {', '.join(patterns)}" if patterns else ""
        hint = "".join(_closest(p, [n for n in test.names if n in ref.columns]) for p in patterns or ())
        raise UserError(f"the traces have no variable{what} in common{hint} "
                        f"(first: {', '.join(test.names[:3])}...; second: {', '.join(ref.names[:3])}...)")
    return names


def _closest(pattern: str, names: Sequence[str]) -> str:
    """``"; did you mean 'X'?"`` for an ``--only`` pattern that matches nothing: its component
    replaced by the closest component of ``names`` (``mech.platfrom.*`` is not, but ``mehc.*``
    is), else the closest whole name; ``""`` when none is close."""
    components = sorted({n.split(".", 1)[0] for n in names})
    head, dot, rest = pattern.partition(".")
    if dot and not any(fnmatch.fnmatchcase(c, head) for c in components):
        close = difflib.get_close_matches(head, components, n=1, cutoff=0.5)
        if close:
            return f"; did you mean {close[0] + dot + rest!r}?"
    close = difflib.get_close_matches(pattern, list(names), n=1, cutoff=0.5)
    return f"; did you mean {close[0]!r}?" if close else ""


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


# --- is the comparison honest? ---------------------------------------------------------------------
def run_status(trace: Trace, path: Path | None = None) -> tuple[str, str]:
    """``(status, reason)`` of the run that wrote ``trace``: the status line at the end of an
    rpr-cosim CSV and the sidecar ``<path>.json``; a trace with rpr-cosim metadata but no final
    status (a run killed while writing) is ``"unfinished"``, a trace from another tool
    ``"unknown"``.  Two sources that disagree give the one that is not ``"ok"``."""
    found: list[tuple[str, str]] = []
    if trace.status:
        found.append((trace.status, trace.reason))
    data = _sidecar(path)
    if data is not None and isinstance(data.get("status"), str):
        found.append((data["status"], str(data.get("reason", ""))))
    bad = [f for f in found if f[0] != "ok"]
    if bad:
        return bad[0]
    if found:
        return found[0]
    written_by_us = any(k in trace.meta for k in ("versions", "started", "scene_hash"))
    return ("unfinished", "the trace has no final status (the run did not end)") if written_by_us else ("unknown", "")


#: Run statuses whose trace is a result: a normal end, a component's own request to stop (FMI
#: terminateSimulation; the overlap rule still applies), or a trace from another tool.
VALID = ("ok", "stopped", "unknown")


@dataclass
class Comparability:
    """What stands between two traces and an honest comparison: the runs' statuses, the time
    ``overlap`` [s] against the reference's ``span`` [s], and the variables only one of them has
    (``only_test``, ``only_ref``).  :meth:`problems` lists what makes the numbers untrustworthy."""

    test_status: tuple[str, str]
    ref_status: tuple[str, str]
    overlap: tuple[float, float] | None
    span: tuple[float, float]
    only_test: list[str] = field(default_factory=list)
    only_ref: list[str] = field(default_factory=list)
    labels: tuple[str, str] = ("test", "reference")
    tolerance: float = 0.0  # [s] slack on the span's ends (half the coarser sampling interval)
    test_span: tuple[float, float] | None = None
    hashes: tuple[str, str] = ("", "")
    scene_diffs: list[str] = field(default_factory=list)  # entries that make them different scenes
    run_diffs: list[str] = field(default_factory=list)  # how the same scene was run differently

    def _short(self, span: tuple[float, float]) -> bool:
        if self.overlap is None:
            return True
        tol = self.tolerance
        return self.overlap[0] > span[0] + tol or self.overlap[1] < span[1] - tol

    @property
    def partial(self) -> bool:
        """The overlap misses part of either trace's span (by more than half a sample)."""
        return self._short(self.span) or (self.test_span is not None and self._short(self.test_span))

    @property
    def different_scenes(self) -> bool:
        """The sidecars' scene hashes differ in what is simulated (or cannot be explained)."""
        a, b = self.hashes
        return bool(a and b and a != b and (self.scene_diffs or not self.run_diffs))

    def problems(self, *, allow_failed: bool = False, allow_partial: bool = False,
                 allow_different_scenes: bool = False) -> list[str]:
        """One line per reason not to trust the comparison (each says how to override it)."""
        out = []
        if not allow_failed:
            for label, (status, reason) in zip(self.labels, (self.test_status, self.ref_status)):
                if status not in VALID:
                    out.append(f"{label}: the run's status is {status!r}, not 'ok'" + (f" ({reason})" if reason else "")
                               + "; use --allow-failed to compare it anyway")
        if not allow_partial and self.partial:
            a, b = self.overlap or (float("nan"), float("nan"))
            short = [(label, span) for label, span in (("the reference", self.span), ("the test", self.test_span))
                     if span is not None and self._short(span)]
            what = []
            for label, (r0, r1) in short:
                frac = max(0.0, b - a) / (r1 - r0) if r1 > r0 and self.overlap else 0.0
                what.append(f"{100 * frac:.3g} % of {label}'s span {r0:g}..{r1:g} s")
            out.append(f"the traces overlap over {a:g}..{b:g} s, {' and '.join(what)}; use --allow-partial to "
                       f"compare the overlap only")
        if not allow_different_scenes and self.different_scenes:
            ha, hb = self.hashes
            out.append(f"the runs are of different scenes (scene hash {ha[:12]} against {hb[:12]}): "
                       f"{self._scene_why()}; use --allow-different-scenes to compare them anyway")
        return out

    def _scene_why(self) -> str:
        return ("; ".join(self.scene_diffs[:6]) + (f"; ... ({len(self.scene_diffs)} in all)"
                                                   if len(self.scene_diffs) > 6 else "")) \
            if self.scene_diffs else "the sidecars do not record the scenes"

    def notes(self, *, allow_different_scenes: bool = False) -> list[str]:
        """Informative lines: unmatched variables, an unknown status, different scenes compared as
        asked (``allow_different_scenes``), how one scene was run differently."""
        out = []
        for label, names in ((self.labels[0], self.only_test), (self.labels[1], self.only_ref)):
            if names:
                shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
                out.append(f"not compared (only in {label}): {shown}")
        for label, (status, reason) in zip(self.labels, (self.test_status, self.ref_status)):
            if status == "unknown":
                out.append(f"{label}: no run status recorded (not an rpr-cosim trace?); its validity is not checked")
            elif status == "stopped":
                out.append(f"{label}: the run ended at a component's request ({reason})")
        if allow_different_scenes and self.different_scenes:
            ha, hb = self.hashes
            out.append(f"different scenes, compared as asked (scene hash {ha[:12]} against {hb[:12]}): "
                       f"{self._scene_why()}")
        if self.run_diffs and self.hashes[0] != self.hashes[1]:
            out.append(("and run differently: " if self.different_scenes else "the same scene run differently: ")
                       + "; ".join(self.run_diffs[:6])
                       + (f"; ... ({len(self.run_diffs)} in all)" if len(self.run_diffs) > 6 else ""))
        return out


#: Scene entries that say how a scene is run and recorded, not what it simulates: differences
#: there are what comparisons are for (and the time spans are checked by the overlap).
HOW_KEYS = ("master", "name", "description", "outputs", "output_interval", "start_time", "stop_time", "report",
            "trace_format", "realtime", "guards")


def _flat(node, prefix: str = "") -> dict[str, object]:
    if isinstance(node, dict):
        out: dict[str, object] = {}
        for k, v in node.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
        return out or {prefix: {}}
    return {prefix: node}


def scene_differences(a: dict, b: dict) -> tuple[list[str], list[str]]:
    """``(what, how)``: the entries of two scenes (a sidecar's ``scene_data``) that differ, as
    ``"components.pid1.params.Kp = 40 against 30"``, split into what is simulated and how
    (:data:`HOW_KEYS`)."""
    fa, fb = _flat(a), _flat(b)
    what, how = [], []
    for key in sorted(set(fa) | set(fb)):
        va, vb = fa.get(key, "(none)"), fb.get(key, "(none)")
        if va != vb:
            line = f"{key} = {str(va)[:40]} against {str(vb)[:40]}"
            (how if key.split(".", 1)[0] in HOW_KEYS else what).append(line)
    return what, how


def _sidecar(path: Path | str | None) -> dict | None:
    """The sidecar ``<path>.json`` of a trace as a mapping (None: no path, no file, unreadable)."""
    if path is None:
        return None
    side = Path(path).with_suffix(".json")
    try:
        got = read_json(side, "sidecar") if side.is_file() else None
    except UserError:
        return None
    return got if isinstance(got, dict) else None


def _scene_of(trace: Trace, path: Path | None) -> tuple[str, dict | None]:
    """The scene hash of a trace and its sidecar's ``scene_data`` (None without one)."""
    h = trace.meta.get("scene_hash")
    data = None
    got = _sidecar(path)
    if got is not None:
        data = got.get("scene_data") if isinstance(got.get("scene_data"), dict) else None
        h = h or got.get("scene_hash")
    return (h if isinstance(h, str) else ""), data


def comparability(test: Trace, ref: Trace, *, test_path: Path | None = None, ref_path: Path | None = None,
                  patterns: Sequence[str] | None = None, labels: tuple[str, str] | None = None) -> Comparability:
    """The :class:`Comparability` of ``test`` against ``ref`` (paths find the sidecars; ``patterns``
    restrict the unmatched-variable report like ``--only``)."""

    def wanted(n: str) -> bool:
        return not patterns or any(matches(n, p) for p in patterns)

    only_test = [n for n in test.names if n not in ref.columns and wanted(n)]
    only_ref = [n for n in ref.names if n not in test.columns and wanted(n)]
    if len(ref.data):
        span = (float(ref.time[0]), float(ref.time[-1]))
    else:
        span = (float("nan"), float("nan"))
    overlap = None
    if len(test.data) and len(ref.data):
        a, b = max(test.time[0], ref.time[0]), min(test.time[-1], ref.time[-1])
        overlap = (float(a), float(b)) if b >= a else None
    dts = [float(np.median(np.diff(tr.time))) for tr in (test, ref) if len(tr.data) > 1]
    tol = 0.5 * max(dts, default=0.0) + 1e-9 * max(1.0, abs(span[1]) if np.isfinite(span[1]) else 1.0)
    test_span = (float(test.time[0]), float(test.time[-1])) if len(test.data) else None
    (ha, sa), (hb, sb) = _scene_of(test, test_path), _scene_of(ref, ref_path)
    what, how = scene_differences(sa, sb) if sa is not None and sb is not None and ha != hb else ([], [])
    return Comparability(run_status(test, test_path), run_status(ref, ref_path), overlap, span, only_test, only_ref,
                         labels or (str(test_path or "test"), str(ref_path or "reference")), tol, test_span,
                         (ha, hb), what, how)


def format_table(diffs: Sequence[Difference], *, most: int | None = None,
                 estimates: dict[str, float] | None = None) -> str:
    """A text table, largest relative error first (``most`` rows at most); with ``estimates`` (the
    first trace's own error estimate per signal, relative to its range, :mod:`cosim.master.estimate`)
    a column of them beside the measured relative error."""

    rows = sorted(diffs, key=lambda d: -d.relative)[:most]
    est = estimates or {}
    columns = ["variable", "max |diff|", "at t [s]", "rms", "range", "max/range"] + (["estimated"] if est else [])
    cells = []
    for d in rows:
        row = [d.name, f"{d.max_abs:.3e}", f"{d.at:.4f}", f"{d.rms:.3e}", f"{d.scale:.3e}", f"{d.relative:.2e}"]
        if est:
            row.append(f"{est[d.name]:.2e}" if est.get(d.name) is not None else "")
        cells.append(row)
    lines = [text_table(columns, cells)]
    if any(d.scale < FLAT for d in rows):
        lines.append(f"  (a range below {FLAT:g} counts as {FLAT:g}, as the tolerance and the error estimate take it)")
    if most is not None and len(diffs) > most:
        lines.append(f"  ... {len(diffs) - most} more variables with smaller relative errors")
    return "\n".join(lines)


__all__ = ["Comparability", "Difference", "aligned", "common_names", "comparability", "compare", "format_table",
           "run_status", "scene_differences"]


# --- across events (docs/explanation/events.md, "Measures across jumps") ---------------------------
@dataclass(frozen=True)
class EventTiming:
    """The events of one kind matched in order between a test and a reference trace: the largest
    time difference ``max_error`` [s] (at the test's event time ``at``), the count matched, and
    the events only one trace has (``missing``: ``("test" | "reference", time)``)."""

    kind: str
    matched: int
    max_error: float
    at: float
    missing: tuple[tuple[str, float], ...] = ()


def times_from_clock(trace: Trace, name: str) -> np.ndarray:
    """Event times [s] kept by a time-of-the-last-event signal ``name`` (a block's mode such as
    ``mass.t_stick``): its successive distinct values, exact whatever the output grid."""
    v = np.asarray(trace[name], dtype=float)
    keep = np.concatenate([[False], np.diff(v) != 0])
    return v[keep]


def times_from_counter(trace: Trace, name: str) -> np.ndarray:
    """Event times [s] from an event counter ``name`` (e.g. ``rig.leg[2].impacts``): the first
    instant of the trace at which it has grown, once per event counted (to the output interval)."""
    v = np.asarray(trace[name], dtype=float)
    rises = np.nonzero(np.diff(v) > 0)[0] + 1
    return np.repeat(trace.time[rises], np.rint(np.diff(v)[rises - 1]).astype(int))


def match_events(kind: str, test_times: Sequence[float], ref_times: Sequence[float]) -> EventTiming:
    """The k-th event of ``test_times`` against the k-th of ``ref_times`` (both increasing)."""
    a, b = np.asarray(test_times, dtype=float), np.asarray(ref_times, dtype=float)
    n = min(len(a), len(b))
    d = np.abs(a[:n] - b[:n])
    k = int(np.argmax(d)) if n else 0
    missing = tuple(("reference", float(t)) for t in a[n:]) + tuple(("test", float(t)) for t in b[n:])
    return EventTiming(kind, n, float(d[k]) if n else 0.0, float(a[k]) if n else math.nan, missing)


def windows(timings: Sequence[tuple[Sequence[float], Sequence[float]]], interval: float) -> list[tuple[float, float]]:
    """The windows ``[t_e - delta_e, t_e + delta_e]`` around each matched event, with
    ``delta_e = |t_test - t_ref| + interval`` (one output interval), covering both traces' times."""
    out = []
    for test_times, ref_times in timings:
        for a, b in zip(test_times, ref_times):
            delta = abs(a - b) + interval
            out.append((min(a, b) - delta, max(a, b) + delta))
    return out


def compare_between_events(test: Trace, ref: Trace, event_windows: Sequence[tuple[float, float]],
                           patterns: Sequence[str] | None = None) -> list[Difference]:
    """:func:`compare` over the instants outside ``event_windows`` (:func:`windows`): the value
    error between events, where a jump placed a hair apart in the two traces is not read as an
    error the jump's size.  The reference's rows at an event (left and right limits at one time)
    are interpolated from the side of the instant compared."""
    names = common_names(test, ref, patterns)
    t = test.time
    keep = (t >= ref.time[0] - 1e-12) & (t <= ref.time[-1] + 1e-12)
    for lo, hi in event_windows:
        keep &= ~((t >= lo) & (t <= hi))
    if not keep.any():
        raise UserError("no instant of the test trace lies between the events' windows")
    t = t[keep]
    a = np.column_stack([test[n][keep] for n in names])
    b = np.column_stack([np.interp(t, ref.time, ref[n]) for n in names])
    d = np.abs(a - b)
    k = np.argmax(d, axis=0)
    full = np.column_stack([ref[n] for n in names])
    span = full.max(axis=0) - full.min(axis=0)
    scale = np.where(span > 0, span, np.abs(full).max(axis=0))
    rms = np.sqrt(np.mean(d ** 2, axis=0))
    return [Difference(n, float(d[k[j], j]), float(t[k[j]]), float(rms[j]), float(scale[j]))
            for j, n in enumerate(names)]


def event_times(trace: Trace, name: str) -> np.ndarray:
    """Event times [s] recorded by ``name``: an event counter when every value is a whole number
    (:func:`times_from_counter`), else a time-of-the-last-event signal (:func:`times_from_clock`)."""
    if name not in trace.columns:
        raise UserError(f"event signal {name!r} is not in the trace (recorded: {', '.join(trace.names[:6])}...)")
    v = np.asarray(trace[name], dtype=float)
    return times_from_counter(trace, name) if np.all(v == np.rint(v)) else times_from_clock(trace, name)


def compare_events(test: Trace, ref: Trace, names: Sequence[str], patterns: Sequence[str] | None = None,
                   interval: float | None = None) -> tuple[list[EventTiming], list[Difference]]:
    """Both measures across events: the :class:`EventTiming` of each event signal in ``names``
    (matched in order) and the value error between the events (:func:`compare_between_events`,
    windows of the event-time error plus ``interval``, by default the test trace's largest
    output interval)."""
    pairs = [(event_times(test, n), event_times(ref, n)) for n in names]
    timings = [match_events(n, a, b) for n, (a, b) in zip(names, pairs)]
    if interval is None:
        t = test.time
        interval = float(np.max(np.diff(t))) if len(t) > 1 else 0.0
    return timings, compare_between_events(test, ref, windows(pairs, interval), patterns)


def compare_modes(test: Trace, ref: Trace, modes: Sequence[str], patterns: Sequence[str] | None = None,
                  ) -> tuple[list[Difference], EventMatch | None]:
    """Both measures across events where the event signals are the recorded ``modes`` (discrete
    variables, :func:`cosim.run.execute.event_modes`): the k-th change of each in ``test`` matched
    with the k-th in ``ref`` (:func:`cosim.master.estimate.match_modes`, windows of the difference
    plus the test's largest output interval) and the value error between events; the plain
    :func:`compare` and None where none of them is in both traces or changes."""
    names = [m for m in modes if m in test.columns and m in ref.columns]
    ev = None
    if names and len(test.time) > 1:
        interval = float(np.max(np.diff(test.time)))
        x = np.column_stack([np.asarray(test[n], dtype=float) for n in names])
        xc = np.column_stack([np.asarray(ref[n], dtype=float) for n in names])
        ev = match_modes(test.time, x, ref.time, xc, names, range(len(names)), 1.0, interval)
    if ev is None or not (ev.matched or ev.missing):
        return compare(test, ref, patterns), None
    return compare_between_events(test, ref, ev.windows, patterns), ev
