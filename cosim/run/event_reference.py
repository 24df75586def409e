"""The monolithic reference of a scene with events (docs/explanation/events.md): the composite
ODE of :func:`models.compose.compose` with its blocks' own indicators, updates and samples,
integrated by SciPy's ``solve_ivp`` (LSODA with the CasADi Jacobian) from event to event.

Why not CasADi's integrators: CasADi 3.8's zero-crossing support (DAE output ``zero`` with the
``transition`` option) is experimental and fell short here: it fires only where an indicator
falls through zero (no directions), missed the second of two crossings of ``sin t - 1/2`` in a
test and ended with ``CV_ILL_INPUT`` when a crossing lay in the last internal step before an
output time.  ``solve_ivp`` takes directions and terminal events, locates a crossing on the
solver's dense output (Brent's method to machine precision), and the loop here applies the
update, iterates (an update may fire another indicator, at most 100 rounds) and restarts.

Samples (time events) end the integration segments exactly at their instants.  The trace has
the scene's output grid plus two rows at each event time, the left limit then the right one.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp

from models.compose import Composite

#: Rounds of one event iteration, and events in one run, before the reference gives up.
MAX_ROUNDS, MAX_EVENTS = 100, 200_000
#: How far past zero [the indicator's unit] a directed indicator is watched: a crossing is found
#: where it reaches +-EPS_Z (a time error of EPS_Z / |dz/dt|, 1e-12 s at 0.1 unit/s).
EPS_Z = 1e-13
#: The look-ahead [s] that gives an undirected indicator its side at a segment's start (the FMU
#: core's rule: the sign of ``z + dz/dt * LOOK_AHEAD``, so one at zero, or a rounding error off it,
#: takes the side it is moving to).
LOOK_AHEAD = 1e-9
#: The SciPy solver (stiff and non-stiff alike, with the CasADi Jacobian).
SOLVER = "LSODA"


@dataclass
class EventLog:
    """The events of a reference run: ``(time, name)`` in order, capped with a count."""

    items: list[tuple[float, str]] = field(default_factory=list)
    total: int = 0

    def add(self, t: float, name: str) -> None:
        self.total += 1
        if len(self.items) < 10_000:
            self.items.append((t, name))


@dataclass(frozen=True)
class Tolerances:
    """The solver's relative and absolute tolerances (``rtol``, ``atol`` [state units])."""

    rtol: float
    atol: float


class EventReferenceError(RuntimeError):
    """The reference could not go on (chattering, an event iteration that does not end)."""


def _fires(direction: int, before: float, z: float) -> bool:
    return (direction >= 0 and before < 0 <= z) or (direction <= 0 and before > 0 >= z)


class _Model:
    """The composite's CasADi functions, evaluated numerically."""

    def __init__(self, comp: Composite, signals: ca.Function) -> None:
        t, x, m = comp.t, comp.x, comp.m
        self.ode = ca.Function("ode", [t, x, m], [comp.ode])
        self.jac = ca.Function("ode_jac", [t, x, m], [ca.densify(ca.jacobian(comp.ode, x))])
        ind = [e for e in comp.events if e.indicator is not None]
        self.indicators = ind
        self.samples = [e for e in comp.events if e.indicator is None]
        self.z = ca.Function("z", [t, x, m], [ca.vertcat(*[e.indicator for e in ind]) if ind else ca.SX(0, 1)])
        self.updates = {id(e): ca.Function("g", [t, x, m], [e.new_x, e.new_m]) for e in comp.events}
        self.signals = signals

    def zval(self, t, x, m) -> np.ndarray:
        return np.array(self.z(t, x, m)).ravel()

    def watches(self, t, x, m, kept: dict[int, float] | None = None) -> list[tuple[float, int, bool]]:
        """How each indicator is watched from ``(t, x, m)``: ``(shift, direction, rearm)``, the
        function ``z - shift`` crossing zero in ``direction``.  Each takes its side by look-ahead
        (the FMU core's rule).  An undirected one is watched EPS_Z beyond zero from its side, so one
        that starts at zero (``time - startTime`` at the start time, one that has just fired) does
        not fire again at once; a directed one EPS_Z on its far side, unless it is there already and
        moving on across (``when x > 0.5`` just fired, x still rising): that one is only watched
        for its return EPS_Z on the near side (``rearm``: no event, the segment restarts with it
        armed), where watching it on the far side fired it again and again.  One across that
        moves back (a bounce's reset) stays armed: SciPy fires a watch starting at zero only if
        it moves in the watch's direction, and a rebound too small to leave the watch level is
        a Zeno sequence that must fail, not fall through the floor.  ``kept``: the sides undirected
        indicators were watched from in the segment before, kept by those within EPS_Z of zero that
        did not fire where it ended (x - 1 = -2e-16 at a sample instant, rising: its look-ahead side
        took it as crossed already, and its crossing was lost)."""
        ahead = self.zval(t + LOOK_AHEAD, x + LOOK_AHEAD * np.array(self.ode(t, x, m)).ravel(), m)
        z = self.zval(t, x, m)
        side = np.where(ahead != 0, np.sign(ahead), np.sign(z))
        for i, s in (kept or {}).items():
            if abs(z[i]) <= EPS_Z:
                side[i] = s
        out = []
        for i, e in enumerate(self.indicators):
            if not e.direction:
                out.append((-EPS_Z * float(side[i] or 1.0), 0, False))
            elif z[i] * e.direction > 0 and (ahead[i] - z[i]) * e.direction > 0:  # across and moving on across
                out.append((-EPS_Z * e.direction, -e.direction, True))
            else:
                out.append((EPS_Z * e.direction, e.direction, False))
        return out

    def update(self, e, t, x, m) -> tuple[np.ndarray, np.ndarray]:
        xn, mn = self.updates[id(e)](t, x, m)
        return np.array(xn).ravel(), np.array(mn).ravel()


def _iterate(model: _Model, fired: list, t: float, x, m, log: EventLog):
    """Apply ``fired`` (events) at ``t``; repeat with the indicators the updates make fire."""
    for _ in range(MAX_ROUNDS):
        if not fired:
            return x, m
        z_before = np.sign(model.zval(t, x, m))
        for e in fired:
            x, m = model.update(e, t, x, m)
            log.add(t, e.name)
            if e in model.indicators:  # it has just crossed: at zero, it cannot fire again in this iteration
                z_before[model.indicators.index(e)] = 0.0
        z = model.zval(t, x, m)
        fired = [e for i, e in enumerate(model.indicators) if _fires(e.direction, z_before[i], z[i])]
    raise EventReferenceError(f"the event iteration at t = {t:.17g} s did not end after {MAX_ROUNDS} rounds "
                              f"({', '.join(e.name for e in fired)} keep firing)")


def integrate(comp: Composite, signals: ca.Function, grid: np.ndarray, tol: Tolerances,
              record: Callable[[np.ndarray], bool], deadline: float = math.inf) -> tuple[EventLog, float]:
    """Integrate ``comp`` over ``grid`` (output instants from 0) at the tolerances ``tol``, calling
    ``record(rows)`` with rows ``[t, signals...]`` (the grid's rows and two per event) until it
    returns False; returns the event log and the time reached (``deadline``: a
    :func:`time.perf_counter` value past which it raises :class:`TimeoutError`)."""
    rtol, atol = tol.rtol, tol.atol
    model = _Model(comp, signals)
    log = EventLog()
    x, m = np.array(comp.x0, dtype=float).ravel(), np.array(comp.m0, dtype=float).ravel()
    t_end = float(grid[-1])

    def rows(ts, xs, mm) -> np.ndarray:
        vals = np.array(signals.map(len(ts))(xs, np.tile(mm.reshape(-1, 1), (1, len(ts))))).reshape(-1, len(ts))
        return np.column_stack([ts, vals.T])

    def jump_rows(t, x_left, m_left, x_right, m_right) -> bool:
        return record(np.vstack([rows(np.array([t]), x_left.reshape(-1, 1), m_left),
                                 rows(np.array([t]), x_right.reshape(-1, 1), m_right)]))

    # the start: indicators already across their direction fire at t0, then the samples due
    z0 = model.zval(0.0, x, m)
    fired = [e for i, e in enumerate(model.indicators) if e.direction * z0[i] > 0]  # strictly across at the start
    next_k = {id(e): 0 for e in model.samples}
    fired += [e for e in model.samples if e.offset <= 0.0]
    for e in model.samples:
        if e.offset <= 0.0:
            next_k[id(e)] = 1
    x, m = _iterate(model, fired, 0.0, x, m, log)
    if not record(rows(np.zeros(1), x.reshape(-1, 1), m)):
        return log, 0.0
    t, done, kept = 0.0, 1, {}
    while t < t_end:
        if time.perf_counter() > deadline:
            raise TimeoutError(f"t = {t:g} s")
        t_sample = min((e.offset + next_k[id(e)] * e.period for e in model.samples), default=math.inf)
        seg_end = min(t_end, t_sample)
        # the grid's instants in the segment; one a rounding past its end (3 x 0.1 against a sample
        # at 0.3) is taken at the end, which solve_ivp's t_eval must not pass
        outs = np.minimum(grid[done:][grid[done:] <= seg_end + 1e-15], seg_end)

        def rhs(tt, y, m=m):
            return np.array(model.ode(tt, y, m)).ravel()

        def jac(tt, y, m=m):
            return np.array(model.jac(tt, y, m))

        funcs, armed, last = [], [], {}
        watches = model.watches(t, x, m, kept)
        kept = {i: -math.copysign(1.0, w[0]) for i, w in enumerate(watches) if not model.indicators[i].direction}

        def zs(tt, y, m=m) -> np.ndarray:
            """The indicators at ``(tt, y)``, evaluated once for all (SciPy asks each in turn)."""
            key = (tt, y.tobytes())
            if last.get("key") != key:
                last["key"], last["z"] = key, model.zval(tt, y, m)
            return last["z"]

        for i, e in enumerate(model.indicators):
            # SciPy counts an indicator resting at zero (an end stop held, a stuck mass's idle
            # indicator, time - startTime at the start) as a crossing: each is watched EPS_Z past it
            def g(tt, y, i=i, shift=watches[i][0]):
                return float(zs(tt, y)[i]) - shift
            g.terminal, g.direction = True, float(watches[i][1])
            funcs.append(g)
            armed.append(i)
        if seg_end <= t:
            t = seg_end
        else:
            t_eval = np.unique(np.append(outs, seg_end))
            try:
                sol = solve_ivp(rhs, (t, seg_end), x, method=SOLVER, t_eval=t_eval, events=funcs or None,
                                rtol=rtol, atol=atol, jac=jac if SOLVER in ("LSODA", "Radau", "BDF") else None)
            except ValueError as exc:  # SciPy's root bracket lost (brentq): an indicator hovering at its watch
                if "different signs" not in str(exc):
                    raise
                raise EventReferenceError(
                    f"the event location failed after t = {t:.17g} s ({exc}; {log.total} events so far): events at "
                    f"ever shorter intervals (a Zeno sequence) or an indicator hovering at zero") from None
            if sol.status < 0:
                raise EventReferenceError(f"{SOLVER} failed after t = {t:g} s: {sol.message}")
            sol_t = np.asarray(sol.t, dtype=float).ravel()
            sol_y = np.asarray(sol.y, dtype=float).reshape(len(x), len(sol_t)) if len(sol_t) else np.zeros((len(x), 0))
            on_grid = np.isin(sol_t, outs)
            if sol.status == 1:  # a crossing: the earliest, and those at the same instant
                hits = [(float(te[0]), armed[j]) for j, te in enumerate(sol.t_events) if len(te)]
                te = min(h[0] for h in hits)
                keep = on_grid & (sol_t < te)
                if keep.any() and not record(rows(sol_t[keep], sol_y[:, keep], m)):
                    return log, float(sol_t[keep][-1])
                j0 = armed.index(min(hits)[1])
                x_left = np.array(sol.y_events[j0][0], dtype=float)
                fired = [model.indicators[i] for tt, i in hits if tt <= te + 1e-14 * max(1.0, abs(te))
                         and not watches[i][2]]
                if not fired:  # only indicators back on their near side: re-armed, no event
                    while done < len(grid) and grid[done] < te:
                        done += 1
                    t, x = te, x_left
                    continue
                for e in fired:  # these have crossed: their side is the one they move to
                    kept.pop(model.indicators.index(e), None)
                x_new, m_new = _iterate(model, fired, te, x_left, m, log)
                if log.total > MAX_EVENTS:
                    raise EventReferenceError(f"chattering: more than {MAX_EVENTS:,} events by t = {te:g} s")
                if not jump_rows(te, x_left, m, x_new, m_new):
                    return log, te
                while done < len(grid) and grid[done] <= te:  # grid instants up to the event are written
                    done += 1
                t, x, m = te, x_new, m_new
                continue
            if on_grid.any() and not record(rows(sol_t[on_grid], sol_y[:, on_grid], m)):
                return log, float(sol_t[on_grid][-1])
            done += int(on_grid.sum())
            x, t = sol_y[:, -1], seg_end
        if t_sample <= t + 1e-15 and t < t_end:
            due = [e for e in model.samples if e.offset + next_k[id(e)] * e.period <= t + 1e-12]
            for e in due:
                next_k[id(e)] += 1
            x_new, m_new = _iterate(model, due, t, x, m, log)
            if not jump_rows(t, x, m, x_new, m_new):
                return log, t
            x, m = x_new, m_new
    return log, t

