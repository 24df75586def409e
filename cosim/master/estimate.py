"""How wrong a run is, from the run itself: the error estimate of every recorded signal and the
verdict it gives (:func:`judge`).

Method (Richardson extrapolation against a companion run): the run's error against the exact
coupled solution is, to leading order, ``e(x) = C x^p`` in its accuracy parameter ``x`` (the
communication step of a fixed-step algorithm, the tolerance of a variable-step one).  A companion
run of the same scene at ``r x`` (half the step, a quarter of the tolerance:
:mod:`cosim.run.companion`) then differs from the run by ``e(x) - e(r x) = (1 - r^p) e(x)``, so
``|y_run - y_companion| / |1 - r^p|`` estimates
the run's own error, signal by signal and instant by instant, including the start transient and
whatever a coupling defect does downstream of where it enters (a local defect alone says nothing
about that).  The estimate of a signal is the largest such difference over the run, relative to
the signal's range in the run (max - min, at least :data:`FLAT`), the measure ``rpr-cosim
compare`` reports against a reference.

``p`` is the order the coupling has: 1 with held inputs, between 1 and 2 with linear inputs
(2 in smooth stretches, 1 where a step is long against a time constant), 0.4 to 0.7 in the
tolerance of ``adaptive`` and ``ecco`` (``rpr-cosim study precision`` prints the observed orders);
the divisor ``|1 - r^p|`` uses the middle of the step's range, so a run whose true order is at
either end is estimated within a factor of 1.3, and the low end of the tolerance's, so that a
tolerance is estimated high rather than low (within 1.45x above at the high end; docs/accuracy.md
has the measured table).

A coupling that has gone unstable diverges, and a companion at half the step diverges slower or
not at all: their difference is then of the order of the signal's range, and the run is not "ok" but
"unstable" (:data:`UNSTABLE`).  With a tolerance, an estimate more than :data:`INACCURATE` times
over it is "inaccurate".
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..trace.observer import Observer

#: The smallest range an error is measured against [the signal's SI unit]: a signal that moves
#: less over the run (a platform angle that a path keeps at 0 but the solvers' rounding nudges
#: by 1e-8 rad) has no range to speak of, and an error of 1e-5 rad on it is not "10^3 of its
#: range" but 0.1 of this floor.
FLAT = 1e-4
#: The share of a difference between irregular traces the interpolation's doubt leaves in any case
#: (a kink may explain most of a difference, never all of it for sure).
DOUBT_KEEPS = 0.1
#: An estimate of this fraction of a signal's range or more: the coupling has gone unstable.
UNSTABLE = 0.5
#: An estimate more than this many times over the tolerance: the run is "inaccurate".
INACCURATE = 10.0
#: The event time tolerance is the tolerance times this span [s]: 1e-4 s at the default 1e-3 of
#: range, the bound the events design page states for stick intervals (docs/explanation/events.md).
EVENT_TIME_SPAN = 0.1
#: A discrete variable that changes at more than this share of the recorded rows is a sampled
#: value (an external FMU's held output), not a mode whose changes are events to match.
SAMPLED_SHARE = 0.1
#: A held sampled value is a quantiser's output when it takes at least this many levels over the
#: run, every change a whole number of its smallest one (an ADC code, the length read back from it).
QUANTISED_LEVELS = 10


def event_time_tolerance(tolerance: float | None) -> float | None:
    """The event time tolerance [s] of a run judged at ``tolerance`` (of range): :data:`EVENT_TIME_SPAN` times it."""
    return None if tolerance is None else tolerance * EVENT_TIME_SPAN


@dataclass
class ErrorEstimate:
    """The estimated error of a run: per recorded signal relative to its range (``errors``), the
    ``worst`` one on ``signal`` at time ``at`` [s]; ``method`` says how it was measured;
    ``worst`` is None when nothing could be estimated (``method`` says why)."""

    worst: float | None
    signal: str = ""
    at: float = math.nan
    errors: dict[str, float] = field(default_factory=dict)
    method: str = ""
    #: events: the estimated event-time error [s] of the matched events (None: no event), the mode
    #: it is worst on, how many were matched, and the modes whose event counts differ (run, companion)
    event_time: float | None = None
    event_signal: str = ""
    events: int = 0
    missing: dict[str, tuple[int, int]] = field(default_factory=dict)

    def as_dict(self) -> dict:
        out = {"worst": self.worst, "signal": self.signal, "at": None if math.isnan(self.at) else self.at,
               "method": self.method, "errors": self.errors}
        if self.events or self.missing:
            out["events"] = {"matched": self.events, "time_error": self.event_time, "signal": self.event_signal,
                             "missing": {k: list(v) for k, v in self.missing.items()}}
        return out

    def summary(self) -> str:
        """``estimated worst error 6e-4 of range, mech.platform.y`` (or why there is none)."""
        if self.worst is None:
            return f"no error estimate ({self.method})"
        text = f"estimated worst error {self.worst:.2g} of range, {self.signal} (at t = {self.at:.6g} s)"
        if self.event_time is not None:
            text += f"; event times within {self.event_time:.2g} s ({self.events} events, {self.event_signal})"
        if self.missing:
            text += "; events missing in one of the two runs: " + ", ".join(
                f"{k} {a} against {b}" for k, (a, b) in self.missing.items())
        return text


def divisor(ratio: float, order: float) -> float:
    """``|ratio^order - 1|``: the difference between the run's error and its companion's (at
    ``ratio`` times the run's step or tolerance), over the run's."""
    return abs(ratio ** order - 1.0)


def scale(x: np.ndarray) -> float:
    """What an error of the signal ``x`` is measured against: its range (max - min), at least
    :data:`FLAT`; inf when it has no finite value."""
    finite = x[np.isfinite(x)]
    if not len(finite):
        return math.inf
    return max(float(finite.max() - finite.min()), FLAT)


def pchip(x: np.ndarray, y: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Monotone piecewise-cubic Hermite interpolation (Fritsch and Carlson) of ``y`` (one column
    per signal) over increasing ``x`` at ``at``: exact at the nodes, no overshoot at a jump
    (numpy only: the run path imports no scipy)."""
    h = np.diff(x)[:, None]
    delta = np.diff(y, axis=0) / h
    d = np.zeros_like(y)
    if len(x) > 2:
        w1, w2 = 2 * h[1:] + h[:-1], h[1:] + 2 * h[:-1]
        same = (np.sign(delta[:-1]) * np.sign(delta[1:])) > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            harm = (w1 + w2) / (w1 / delta[:-1] + w2 / delta[1:])
        d[1:-1] = np.where(same, harm, 0.0)
    d[0], d[-1] = delta[0], delta[-1]
    k = np.clip(np.searchsorted(x, at, side="right") - 1, 0, len(x) - 2)
    hk = h[k]
    s = ((at - x[k])[:, None]) / hk
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * y[k] + h10 * hk * d[k] + h01 * y[k + 1] + h11 * hk * d[k + 1]


def interpolation_doubt(x: np.ndarray, y: np.ndarray, at: np.ndarray, interp: np.ndarray) -> np.ndarray:
    """How far the interpolant ``interp`` of ``y`` (over ``x``) at ``at`` may be from the signal
    itself, per column: the cubic's distance from the chord, plus the most a kink inside the
    interval can put the signal off the chord, ``|s_next - s_prev| (t - x_k)(x_k+1 - t) / h_k``
    from the slopes of the neighbouring intervals (a PID output leaving its limit between two
    accepted steps; for a smooth signal a few times the chord's own error).  0 at the nodes."""
    k = np.clip(np.searchsorted(x, at, side="right") - 1, 0, len(x) - 2)
    h = np.diff(x)
    slope = np.diff(y, axis=0) / h[:, None]
    prev, nxt = slope[np.maximum(k - 1, 0)], slope[np.minimum(k + 1, len(h) - 1)]
    w = ((at - x[k]) * (x[k + 1] - at) / h[k]).clip(min=0.0)[:, None]
    chord = y[k] + (at - x[k])[:, None] * slope[k]
    return np.abs(interp - chord) + np.abs(nxt - prev) * w


def event_instants(t: np.ndarray) -> np.ndarray:
    """The event times a trace marks itself: instants recorded twice in a row (the left and the
    right limit of an event, docs/explanation/events.md)."""
    t = np.asarray(t, dtype=float)
    if len(t) < 3:
        return np.zeros(0)
    return t[1:-1][np.diff(t[:-1]) == 0]  # (a stop request may repeat the last instant: not an event)


def outside_events(at: np.ndarray, events: Sequence[float], spacing: float) -> np.ndarray:
    """Mask of the instants ``at`` outside ``[t_e - 2 spacing, t_e + 2 spacing]`` around each event:
    there the run and its companion may place a jump a step apart, and a difference across it is
    the jump's size, not an error (the value error between events of the events design page; the
    window is two of the sparser trace's steps, the event-time difference two such runs can have)."""
    keep = np.ones(len(at), dtype=bool)
    for te in events:
        keep &= np.abs(at - te) > 2 * spacing
    return keep


def mode_changes(t: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, bool]:
    """The event times [s] a recorded mode (a discrete variable) marks: the rows where its value
    changes, and whether they are exact: a *clock* (a mode set to ``time`` at its event, e.g.
    ``t_stick``) holds the event time itself, anything else (a counter, a stuck flag) gives the
    first row after the event, exact to the recorded interval."""
    ok = np.isfinite(col)
    t, col = t[ok], col[ok]
    k = np.flatnonzero(np.diff(col) != 0) + 1
    if not len(k):
        return np.zeros(0), False
    v, lo, hi = col[k], t[k - 1], t[k]
    eps = 1e-9 * max(1.0, float(np.abs(t).max()))
    clock = bool(np.all((v >= lo - eps) & (v <= hi + eps)))
    return (v.astype(float) if clock else hi.astype(float)), clock


@dataclass
class EventMatch:
    """The matched events of a run and its companion: the estimated event-time error [s] (the
    largest difference over the divisor; a non-clock mode's difference less its resolution, one
    recorded interval), its mode, the count matched, the windows around them where values are not
    compared, and the modes whose counts differ."""

    time_error: float | None = None
    signal: str = ""
    matched: int = 0
    windows: list[tuple[float, float]] = field(default_factory=list)
    missing: dict[str, tuple[int, int]] = field(default_factory=dict)


def match_modes(t: np.ndarray, x: np.ndarray, tc: np.ndarray, xc: np.ndarray, names: Sequence[str],
                modes: Sequence[int], div: float, interval: float) -> EventMatch:
    """Match the k-th event of each recorded mode (columns ``modes``) in the run with the k-th in
    its companion (docs/explanation/events.md, "Measures across jumps"): the event-time error and
    the windows ``[t_e - d, t_e + d]``, ``d = |t_run - t_companion| + interval`` per matched event;
    a mode whose counts differ is listed as missing events, its every event windowed."""
    out = EventMatch()
    for j in modes:
        a, exact = mode_changes(t, x[:, j])
        b, exact_c = mode_changes(tc, xc[:, j])
        if max(len(a), len(b)) > SAMPLED_SHARE * min(len(t), len(tc)):  # changes at most rows: a sampled value
            continue
        if len(a) != len(b):
            out.missing[names[j]] = (len(a), len(b))
            out.windows += [(te - interval, te + interval) for te in (*a, *b)]
            continue
        if not len(a):
            continue
        dt = np.abs(a - b)
        d = dt if exact and exact_c else np.maximum(dt - interval, 0.0)
        out.windows += [(lo - interval, hi + interval) for lo, hi in zip(np.minimum(a, b), np.maximum(a, b))]
        out.matched += len(a)
        e = float(d.max()) / div
        if out.time_error is None or e > out.time_error:
            out.time_error, out.signal = e, names[j]
    return out


def quantum(col: np.ndarray) -> float | None:
    """The quantum of a held sampled value (an ADC code, the length read back from it): its
    smallest change between rows when every change is a whole number of it and the value spans at
    least :data:`QUANTISED_LEVELS` of them; None for anything else (a held PWM voltage that
    follows a controller, a two-level flag)."""
    col = col[np.isfinite(col)]
    steps = np.abs(np.diff(col))
    steps = steps[steps > 1e-12 * max(1.0, float(np.abs(col).max(initial=0.0)))]
    if not len(steps):
        return None
    q = float(steps.min())
    whole = np.allclose(steps / q, np.rint(steps / q), rtol=0.0, atol=1e-6)
    return q if whole and float(col.max() - col.min()) >= QUANTISED_LEVELS * q else None


def one_count_apart(at: np.ndarray, diff: np.ndarray, sparse_x: np.ndarray, dense_x: np.ndarray,
                    held: Sequence[int], spacing: float) -> tuple[np.ndarray, int]:
    """Mask of the instants ``at`` where the held sampled values (columns ``held``) are compared:
    outside ``[t - 2 spacing, t + 2 spacing]`` around each instant where a quantised one
    (:func:`quantum`) differs by exactly one quantum between the run and its companion (``diff``
    at ``at``: a level crossed at a neighbouring sample, or a leg resting on a level whose code
    dithers: where the quantiser's input sits on a level at a sample, no step settles which code
    it reads), and the count of such instants.  A difference of two quanta or more is never left out."""
    flips = np.zeros(len(at), dtype=bool)
    for j in held:
        q = quantum(sparse_x[:, j])
        qc = quantum(dense_x[:, j])
        q = q if q is not None and qc is not None and math.isclose(q, qc, rel_tol=1e-6) else None
        if q is not None:
            flips |= np.abs(diff[:, j] / q - 1.0) < 1e-6
    keep = np.ones(len(at), dtype=bool)
    for te in at[flips]:
        keep &= np.abs(at - te) > 2 * spacing
    return keep, int(flips.sum())


def richardson(t: np.ndarray, x: np.ndarray, tc: np.ndarray, xc: np.ndarray, names: Sequence[str],
               div: float, method: str, events: Sequence[float] = (), modes: Sequence[int] = (),
               held: Sequence[int] = ()) -> ErrorEstimate:
    """The estimate from a run (instants ``t``, values ``x``, one column per name) and its companion
    (``tc``, ``xc``): their largest difference over ``div`` per signal, relative to the run's range.
    They are compared at the instants of the sparser one inside both spans, the denser one
    interpolated there (monotone cubic: exact at shared instants, no overshoot at a jump), less
    the interpolation's own doubt there (:func:`interpolation_doubt`), which leaves at least
    :data:`DOUBT_KEEPS` of the difference.  Around ``events`` (times [s]: the run's reported
    events and the instants either trace records twice) the instants within two of the sparser
    trace's steps are left out (:func:`outside_events`).  ``modes``: the columns of recorded modes;
    their events are matched (:func:`match_modes`), the event-time error estimated and the values
    around each matched pair left out.  ``held``: the columns of sampled components' held values;
    they are compared to one quantum of the quantised ones (:func:`one_count_apart`)."""
    lo, hi = max(t[0], tc[0]), min(t[-1], tc[-1])
    if len(t) < 2 or len(tc) < 2 or hi <= lo:
        return ErrorEstimate(None, method=f"{method}: the run and its companion share no time span")
    sparse_t, dense_t, dense_x, sparse_x = (tc, t, x, xc) if len(tc) <= len(t) else (t, tc, xc, x)
    keep = (sparse_t >= lo - 1e-12) & (sparse_t <= hi + 1e-12)
    events = sorted({*map(float, events), *event_instants(t), *event_instants(tc)})
    if events:
        keep &= outside_events(sparse_t, events, float(np.max(np.diff(sparse_t))))
        method = f"{method}; {len(events)} events left out (two steps either side)"
    match = EventMatch()
    if len(modes):
        match = match_modes(t, x, tc, xc, names, modes, div, float(np.max(np.diff(sparse_t))))
        for w0, w1 in match.windows:
            keep &= (sparse_t < w0) | (sparse_t > w1)
        if match.matched or match.missing:
            method = f"{method}; {match.matched} mode events matched, values around them left out"
    at = sparse_t[keep]
    if not len(at):
        return ErrorEstimate(None, method=f"{method}: the events leave no recorded instant between them")
    # the dense trace's instants strictly increasing (a stop request may repeat the last instant)
    uniq = np.concatenate([[True], np.diff(dense_t) > 0])
    with np.errstate(all="ignore"):
        dt, dx = dense_t[uniq], dense_x[uniq]
        interp = pchip(dt, dx, at)
        doubt = interpolation_doubt(dt, dx, at, interp)
        diff = np.abs(interp - sparse_x[keep])
        diff = np.where(np.isfinite(diff), np.maximum(diff - doubt, DOUBT_KEEPS * diff), diff)
    if len(held):
        with np.errstate(all="ignore"):
            exact = np.abs(interp - sparse_x[keep])  # a quantum is judged on the values, not less the doubt
        compared, flips = one_count_apart(at, exact, sparse_x[keep], dense_x[uniq], held,
                                          float(np.max(np.diff(sparse_t))))
        if flips:
            diff[np.ix_(~compared, list(held))] = 0.0
            method = (f"{method}; held sampled values compared outside {flips} instants where a quantised one is "
                      f"one quantum apart")
    errors: dict[str, float] = {}
    worst, signal, when = -1.0, "", math.nan
    for j, name in enumerate(names):
        sc = scale(x[:, j])
        col = diff[:, j]
        if not np.isfinite(col).all() or not math.isfinite(sc):
            e, k = math.inf, int(np.argmax(~np.isfinite(col))) if not np.isfinite(col).all() else 0
        else:
            m = float(col.max()) / div
            e = m / sc
            k = int(np.argmax(col))
        errors[name] = e
        if e > worst:
            worst, signal, when = e, name, float(at[k]) if len(at) else math.nan
    if worst < 0:
        return ErrorEstimate(None, method=f"{method}: nothing recorded")
    return ErrorEstimate(worst, signal, when, errors, method, match.time_error, match.signal, match.matched,
                         match.missing)


def judge(status: str, reason: str, est: ErrorEstimate | None, tolerance: float | None) -> tuple[str, str]:
    """The status and reason of a run in the light of its estimate: an "ok" (or "stopped") run
    whose estimate reaches :data:`UNSTABLE` of a signal's range is "unstable", one more than
    :data:`INACCURATE` times over ``tolerance`` "inaccurate", and so is one whose event-time error
    is more than that over :func:`event_time_tolerance`, or whose companion has a different number
    of events (a missing event fails any gate); anything else unchanged."""
    if est is None or est.worst is None or status not in ("ok", "stopped"):
        return status, reason
    w = est.worst
    later = f" ({reason})" if reason else ""
    if tolerance is not None and est.missing:  # first: the values then differ across the jump
        name, (a, b) = next(iter(est.missing.items()))
        return "inaccurate", (f"{name} has {a} events in the run and {b} in its companion run: an event is missing "
                              f"in one of them{later}")
    if not w < UNSTABLE:
        return "unstable", (f"the estimated error of {est.signal} is {w:.3g} of its range (at t = {est.at:.6g} s): "
                            f"the coupling has gone unstable; take a smaller step or master.tolerance{later}")
    if tolerance is not None and w > INACCURATE * tolerance:
        return "inaccurate", (f"the estimated error of {est.signal} is {w:.3g} of its range (at t = {est.at:.6g} s), "
                              f"more than {INACCURATE:g}x the tolerance {tolerance:g}{later}")
    et = event_time_tolerance(tolerance)
    if et is not None and est.event_time is not None and est.event_time > INACCURATE * et:
        return "inaccurate", (f"the estimated event-time error of {est.event_signal} is {est.event_time:.3g} s, more "
                              f"than {INACCURATE:g}x the event time tolerance {et:g} s{later}")
    return status, reason


def event_counts(names: Sequence[str], data: np.ndarray, modes: Sequence[str]) -> dict[str, dict[str, int]]:
    """The events a run counted, per component: each recorded mode that is a counter (whole
    numbers, never decreasing: ``leg[2].impacts``, ``sticks``), its increase over the run, e.g.
    ``{"rig": {"leg[2].impacts": 3}}`` (the sidecar's ``statistics.events.counted``)."""
    out: dict[str, dict[str, int]] = {}
    for j, name in enumerate(names):
        if name not in modes or not len(data):
            continue
        col = data[:, j + 1]
        col = col[np.isfinite(col)]
        if not len(col) or np.any(col != np.round(col)) or np.any(np.diff(col) < 0):
            continue
        comp, var = name.split(".", 1)
        out.setdefault(comp, {})[var] = int(col[-1] - col[0])
    return out


class EstimatingObserver(Observer):
    """An observer of the run loop around the run's own observers: it forwards everything, keeps
    the recorded rows, and when the run finishes estimates its error against ``companion``
    (``(time, values)`` of the companion run, or None with ``why`` there is none), judges the run
    (:func:`judge`) and finishes the inner observers with that status, the estimate in the
    statistics (``estimate``), the counted events (``events.counted``, :func:`event_counts`) and ``extra``
    statistics (e.g. the master's choice).  ``modes``: the recorded columns that are modes of
    components with state events (their changes are the events the estimate matches); ``held``:
    the recorded held values of sampled components (compared to one quantum, :func:`richardson`)."""

    def __init__(self, inner: Sequence, companion: tuple[np.ndarray, np.ndarray] | None, div: float, method: str,
                 tolerance: float | None, extra: dict | None = None, modes: Sequence[str] = (),
                 held: Sequence[str] = ()):
        self.inner, self.companion, self.div, self.method = list(inner), companion, div, method
        self.modes, self.held = list(modes), list(held)
        self.tolerance, self.extra = tolerance, dict(extra or {})
        self.rows: list[np.ndarray] = []
        self.columns: list[str] = []
        self.events: list[float] = []
        self.estimate: ErrorEstimate | None = None

    def start(self, columns, meta) -> None:
        self.columns = list(columns)
        for ob in self.inner:
            ob.start(columns, dict(meta, **self.extra))

    def record(self, rows) -> None:
        self.rows.append(np.array(rows, dtype=float, copy=True))
        for ob in self.inner:
            ob.record(rows)

    def initial(self, info) -> None:
        for ob in self.inner:
            ob.initial(info)

    def record_text(self, t, column, value) -> None:
        for ob in self.inner:
            ob.record_text(t, column, value)

    def record_event(self, t, component, kind) -> None:
        self.events.append(float(t))
        for ob in self.inner:
            ob.record_event(t, component, kind)

    def _estimate(self) -> ErrorEstimate:
        if self.companion is None:
            return ErrorEstimate(None, method=self.method)
        data = np.concatenate(self.rows) if self.rows else np.empty((0, len(self.columns)))
        if len(data) < 2:
            return ErrorEstimate(None, method=f"{self.method}: fewer than two recorded rows")
        tc, xc = self.companion
        names = self.columns[1:]
        modes = [j for j, n in enumerate(names) if n in set(self.modes)]
        held = [j for j, n in enumerate(names) if n in set(self.held)]
        return richardson(data[:, 0], data[:, 1:], tc, xc, names, self.div, self.method, self.events, modes, held)

    def finish(self, status, reason, stats) -> None:
        for figures in ((stats or {}).get("model_exchange") or {}).values():  # events inside ME components' steps
            self.events.extend(float(t) for t, _ in figures.get("events", ()))
        try:
            self.estimate = self._estimate()
        except Exception as exc:  # the estimate must never cost the run its trace
            self.estimate = ErrorEstimate(None, method=f"{self.method}: {type(exc).__name__}: {exc}")
        status, reason = judge(status, reason, self.estimate, self.tolerance)
        stats = dict(stats or {}, status=status, reason=reason, estimate=self.estimate.as_dict(), **self.extra)
        data = np.concatenate(self.rows) if self.rows else np.empty((0, len(self.columns)))
        counts = event_counts(self.columns[1:], data, self.modes)
        if counts:  # beside the master's own event statistics (event mode: "handled", "late")
            stats["events"] = {**(stats.get("events") or {}), "counted": counts}
        self.status, self.reason, self.stats = status, reason, stats
        for ob in self.inner:
            ob.finish(status, reason, stats)

    @property
    def note(self) -> str:
        return "; ".join(ob.note for ob in self.inner if ob.note)
