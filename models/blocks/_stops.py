"""End stops with located impacts: the event part shared by the catalog's bodies on a stroke.

A body at position ``x`` [m] with velocity ``v`` [m/s] and free acceleration ``a(x, v, u, p)``
moves between stops at ``lo`` and ``hi``.  Modes per stop pair: ``hold`` (0 free, +1 resting on
the upper stop, -1 on the lower), ``impacts`` (count) and ``v_impact`` (the last impact velocity).

- free (``hold = 0``): ``dx/dt = v``, ``dv/dt = a``;
- impact, located where ``x`` reaches ``hi`` rising (or ``lo`` falling): Newton's law of
  restitution ``v+ = -e v-``; when the rebound ``e |v-|`` is below ``v_rest`` the body comes to
  rest on the stop instead (``x+ = hi``, ``v+ = 0``, ``hold = +1``), which ends the Zeno sequence
  of ever smaller bounces that a force pushing into the stop would make;
- resting (``hold = +-1``): ``dx/dt = dv/dt = 0`` while the push into the stop ``a(x, 0)`` (its
  sign towards the stop) stays positive; it leaves (``hold = 0``) where the push falls to zero.

Indicators: ``x - hi`` and ``lo - x`` (rising; exactly 0 while resting on that stop, which never
fires), and the push (falling, watched ``R_EPS`` past zero: a body resting from the start under
no push has a side to leave from) while resting, the constant 1 while free: switching it on fires
it only if the push is already gone, switching it off (its own event) takes it upwards, which
a falling indicator ignores.

:func:`clamp_stops` is the other law, for a body whose rate ``r`` is a drive's (a lead screw's
rod, moved at the rate its motor turns): the stop holds the body, not the drive, so nothing is
reset.  Modes ``hold``, ``impacts`` (arrivals), ``t_arrival`` and ``t_release`` (clocks: the time
of the last arrival and the last release):

- free (``hold = 0``): ``dx/dt = r``;
- arrival, located where ``x`` reaches ``hi`` rising (or ``lo`` falling): ``x+ = hi``,
  ``hold = +1``; the drive's own states run on;
- resting (``hold = +-1``): ``dx/dt = 0``; it leaves (``hold = 0``) where the drive's rate ``r``
  turns away from the stop (falls through 0 on the upper stop, rises through 0 on the lower).

The same indicators as above, with ``r`` (towards the stop) in place of the push, also watched
``R_EPS`` past zero (a body resting from the start with its drive at rest, ``r = 0``).

A body that starts on a stop (its start ``x0`` given: ``x0 >= hi`` or ``x0 <= lo``) starts resting
there (``hold = +-1``), under either law: its arrival indicator is 0 and would never fire, so
without the mode a drive pushing outwards would carry it through the stop.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca

from ..block import FALLING, RISING, Var


#: How far past zero a release indicator (the push, or a clamped body's drive rate) is watched, in
#: its own units: an indicator at exactly 0 never fires.
R_EPS = 1e-12


def _start_hold(x0, lo, hi) -> ca.SX:
    """The ``hold`` mode at the start: +1 on the upper stop, -1 on the lower, else 0."""
    if x0 is None:
        return ca.SX(0.0)
    return ca.if_else(x0 >= hi, 1.0, ca.if_else(x0 <= lo, -1.0, 0.0))


@dataclass
class StopEvents:
    """The event declarations of one or more stop pairs, to pass to :meth:`Block.build`."""

    modes: list[Var] = field(default_factory=list)
    m: list[ca.SX] = field(default_factory=list)
    mode_start: list[float | ca.SX] = field(default_factory=list)
    indicators: list[ca.SX] = field(default_factory=list)
    directions: list[int] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    changes: list[dict] = field(default_factory=list)  # per indicator: symbol name -> new value
    t: ca.SX | None = None  # the time symbol, where an update reads the time (a clock)

    def block_kw(self, x: ca.SX, m_extra: list[ca.SX] | None = None) -> dict:
        """``Block.build`` keywords: modes, indicators, directions, names and full updates of
        ``(x, m)`` (every symbol not changed keeps its value)."""
        ms = self.m + list(m_extra or [])
        syms = [x[i] for i in range(x.numel())] + ms
        updates = [ca.vertcat(*[ch.get(s.name(), s) for s in syms]) for ch in self.changes]
        return dict(modes=self.modes, m=ca.vertcat(*ms), mode_start=self.mode_start,
                    indicators=ca.vertcat(*self.indicators), directions=self.directions, event_names=self.names,
                    updates=updates, **({"t": self.t} if self.t is not None else {}))


def end_stops(ev: StopEvents, prefix: str, x: ca.SX, v: ca.SX, accel: ca.SX, lo, hi, e, v_rest,
              unit: str = "m", x0=None) -> tuple[ca.SX, ca.SX, dict[str, ca.SX]]:
    """Add a stop pair at ``lo``/``hi`` on the body ``(x, v)`` with free acceleration ``accel`` to
    ``ev``; returns ``(dx/dt, dv/dt, modes)`` with the modes by short name (``hold``,
    ``impacts``, ``v_impact``).  ``x`` and ``v`` must be pure symbols (state entries); ``x0``, the
    start of ``x`` (of the parameters), makes a body that starts on a stop rest there."""
    hold = ca.SX.sym(f"{prefix}hold")
    impacts = ca.SX.sym(f"{prefix}impacts")
    v_imp = ca.SX.sym(f"{prefix}v_impact")
    ev.modes += [Var(f"mode.{prefix}hold", "1", "0 free, +1 resting on the upper stop, -1 on the lower"),
                 Var(f"mode.{prefix}impacts", "1", "impacts on the stops so far"),
                 Var(f"mode.{prefix}v_impact", f"{unit}/s", "velocity of the last impact")]
    ev.m += [hold, impacts, v_imp]
    ev.mode_start += [_start_hold(x0, lo, hi), 0.0, 0.0]
    free = hold == 0
    push = ca.substitute(accel, v, ca.SX(0))  # the acceleration at rest on the stop
    ev.indicators += [x - hi, lo - x, ca.if_else(hold == 1, push + R_EPS, ca.if_else(hold == -1, R_EPS - push, 1.0))]
    ev.directions += [RISING, RISING, FALLING]
    ev.names += [f"{prefix}upper_stop", f"{prefix}lower_stop", f"{prefix}leaves_stop"]
    for side, stop in ((1, hi), (-1, lo)):
        bounce = e * side * v > v_rest
        ev.changes.append({x.name(): ca.if_else(bounce, x, stop), v.name(): ca.if_else(bounce, -e * v, 0.0),
                           hold.name(): ca.if_else(bounce, 0.0, float(side)), impacts.name(): impacts + 1,
                           v_imp.name(): v})
    ev.changes.append({hold.name(): ca.SX(0.0)})
    dx = ca.if_else(free, v, 0.0)
    dv = ca.if_else(free, accel, 0.0)
    return dx, dv, {"hold": hold, "impacts": impacts, "v_impact": v_imp}


def clamp_stops(ev: StopEvents, prefix: str, x: ca.SX, rate: ca.SX, lo, hi, t: ca.SX,
                x0=None) -> tuple[ca.SX, dict[str, ca.SX]]:
    """Add a clamping stop pair at ``lo``/``hi`` on the body ``x`` moved at the drive's rate
    ``rate`` to ``ev`` (module docstring); returns ``(dx/dt, modes)`` with the modes by short
    name (``hold``, ``impacts``, ``t_arrival``, ``t_release``).  ``x`` must be a state entry,
    ``t`` the block's time symbol, ``x0`` the start of ``x`` (as in :func:`end_stops`)."""
    hold, impacts = ca.SX.sym(f"{prefix}hold"), ca.SX.sym(f"{prefix}impacts")
    t_in, t_out = ca.SX.sym(f"{prefix}t_arrival"), ca.SX.sym(f"{prefix}t_release")
    ev.modes += [Var(f"mode.{prefix}hold", "1", "0 free, +1 resting on the upper stop, -1 on the lower"),
                 Var(f"mode.{prefix}impacts", "1", "arrivals at the stops so far"),
                 Var(f"mode.{prefix}t_arrival", "s", "time of the last arrival at a stop"),
                 Var(f"mode.{prefix}t_release", "s", "time of the last release from a stop")]
    ev.m += [hold, impacts, t_in, t_out]
    ev.mode_start += [_start_hold(x0, lo, hi), 0.0, 0.0, 0.0]
    ev.t = t
    ev.indicators += [x - hi, lo - x,
                      ca.if_else(hold == 1, rate + R_EPS, ca.if_else(hold == -1, R_EPS - rate, 1.0))]
    ev.directions += [RISING, RISING, FALLING]
    ev.names += [f"{prefix}upper_stop", f"{prefix}lower_stop", f"{prefix}leaves_stop"]
    for side, stop in ((1, hi), (-1, lo)):
        ev.changes.append({x.name(): ca.SX(stop), hold.name(): float(side), impacts.name(): impacts + 1, t_in.name(): t})
    ev.changes.append({hold.name(): ca.SX(0.0), t_out.name(): t})
    return ca.if_else(hold == 0, rate, 0.0), {"hold": hold, "impacts": impacts, "t_arrival": t_in, "t_release": t_out}
