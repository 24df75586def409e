"""The master's choice for a scene that names no algorithm: algorithm and settings from
``master.tolerance`` (default 1e-3 of each recorded signal's range) and what the scene allows.

* an algebraic loop: ``iterative`` (it solves the loop within each step), at a fixed step;
* real-time pacing, a sampled block (a discrete PID), or slaves at several rates: ``gauss_seidel``
  at a fixed step (on whole samples);
* a single component: ``gauss_seidel`` at a fixed step (nothing to couple);
* no feedback between the components (a chain): ``gauss_seidel`` at a fixed step (adaptive's
  error control measures extrapolated inputs, and in a chain no input is extrapolated);
* every slave can roll back: ``adaptive``, at an ``rtol`` that meets the tolerance;
* power bonds, and a slave that cannot roll back: ``ecco``, at an ``rtol`` that meets it;
* otherwise (a slave that cannot roll back, no bonds): ``gauss_seidel`` at a fixed step;
* and whatever the above says, FMI 3.0 event-mode components (but no algebraic loop): an algorithm
  that ends its steps at their events (the one above where it does, else ``gauss_seidel``), with
  held inputs, so an event is not smeared over a step in the pilots' estimates either.

Inputs are linear (slaves that cannot interpolate hold theirs) unless the scene sets ``master.inputs``.
The setting (step or rtol) comes from pilot runs, each with its error estimate
(:mod:`cosim.master.estimate`).  A fixed step: first over the first quarter of the run, from the
scene's step, then ``h * (tolerance / 2 / estimate)^(1/p)`` snapped to a step that divides the
output interval, checked over the whole run and refined while the estimate misses.  A tolerance:
every pilot over the whole run, the first at a tenth of the tolerance with a companion at a tenth
of that, against which a later pilot is measured too while it is at least twice as loose as that
companion (a pilot that misses costs one run, not two); the next rtol from the estimate and the
order the divisor assumes, and a smaller ``h_max`` too once a tighter rtol stops moving the
estimate (:func:`_tolerance_search`).  The first whole-run pilot that meets the tolerance ends the search: it
is the run itself (:mod:`cosim.run.execute` writes it out rather than running it again).  Where
runs cannot be repeated (hardware, real-time pacing) there are no pilots: the scene's step is
kept and the choice says so.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from ..errors import UserError
from ..master import ALGORITHMS, find_algebraic_loop
from ..master.algorithm import option_values
from ..scenario import Scene
from ..scenario.check_connections import algebraic_loop
from .companion import ORDER_HOLD, ORDER_LINEAR, ORDER_TOLERANCE
from .companion import TOLERANCE_RATIO as RATIO

#: The most fixed steps a chosen step may take over the run.
MAX_STEPS = 10 ** 7
#: Pilot runs at most (each with its companion).
MAX_PILOTS = 5
#: The first whole-run pilot within the tolerance is kept: it is the run (written out, not run
#: again), and a looser try would cost a run and its companion to save a fraction of one.
#: The estimate a new setting aims at, as a fraction of the tolerance.
TARGET = 0.6
#: The first fixed-step pilot runs over this share of the run (the next ones over the whole run).
WINDOW = 0.25
#: First rtol of adaptive and ecco, as a fraction of the tolerance (a start, refined by the pilots).
FIRST_RTOL = {"adaptive": 1 / 10, "ecco": 1.0}
#: The first variable-step pilot's companion, as a fraction of its rtol: tighter than a run's own
#: (:data:`cosim.run.companion.TOLERANCE_RATIO`), so that it measures a later, tighter pilot too.
FIRST_COMPANION = 0.1
#: A later pilot is measured against the first one's companion while that companion's rtol is at
#: most this fraction of the pilot's (a closer pair leaves their difference to the step histories).
REUSE = 0.5
#: The estimate a new setting may aim at instead of TARGET when that spares a companion run.
LOOSER = 0.8


@dataclass
class Choice:
    """What the master chose: ``algorithm``, ``settings`` (step [s], inputs, rtol), ``why`` (one
    line) and the ``pilots`` that led there (setting, estimate)."""

    algorithm: str
    settings: dict
    why: str
    tolerance: float
    pilots: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"algorithm": self.algorithm, "settings": self.settings, "why": self.why, "tolerance": self.tolerance,
                "pilots": self.pilots}

    def __str__(self) -> str:
        s = ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}" for k, v in self.settings.items())
        tried = f"; {len(self.pilots)} pilot run{'s' if len(self.pilots) != 1 else ''}" if self.pilots else ""
        return f"master chose {self.algorithm} ({s}) for tolerance {self.tolerance:g}: {self.why}{tried}"


def kind(scene: Scene) -> tuple[str, str]:
    """(algorithm, why) for ``scene`` from what it allows (module docstring); a scene with FMI 3.0
    event-mode components gets an algorithm that ends its steps at their events (the one chosen
    above where it does, else gauss_seidel; held inputs: :func:`event_inputs`) unless it needs
    ``iterative`` for an algebraic loop."""
    alg, why = _kind(scene)
    events = event_components(scene)
    if events and alg != "iterative" and not ALGORITHMS[alg].ends_steps_at_events:
        return "gauss_seidel", (f"{', '.join(events)} report{'s' if len(events) == 1 else ''} events (FMI 3.0 event "
                                f"mode): gauss_seidel ends its steps at them for the whole coupling ({alg} would leave "
                                f"them inside the components' steps); held inputs, a fixed step")
    return alg, why


def event_components(scene: Scene) -> list[str]:
    """The components of ``scene`` that can report events through FMI 3.0 event mode."""
    return [c.name for c in scene.components.values() if c.description.has_event_mode]


def event_inputs(scene: Scene, alg: str) -> bool:
    """Must ``alg`` hold the inputs so that event mode is used (it ends steps at events only then)?"""
    return bool(event_components(scene)) and ALGORITHMS[alg].ends_steps_at_events


def _kind(scene: Scene) -> tuple[str, str]:
    """(algorithm, why) from what the scene allows, events aside (module docstring)."""
    comps = scene.components.values()
    fixed = [c.name for c in comps if not (c.rollback and c.description.can_get_set_state)]
    loop = algebraic_loop(scene.components, scene.connections)
    if loop:
        text = " -> ".join(f"{c}.{v}" for c, v in loop)
        if fixed:
            raise UserError(f"scene {scene.name}: an algebraic loop ({text}) needs master algorithm iterative, which "
                            f"rolls back every step, but {', '.join(fixed)} cannot roll back; break the loop with a "
                            f"state on its path")
        return "iterative", f"an algebraic loop ({text}): iterative solves it within each step"
    if scene.master.realtime is not None:
        return "gauss_seidel", "real-time pacing needs a fixed step"
    sampled = [c.name for c in comps if c.description.sample_period]
    if sampled:  # a variable step would cut a sample period (doStep refuses a step off its samples)
        return "gauss_seidel", (f"{', '.join(sampled)} sample{'s' if len(sampled) == 1 else ''} at a fixed period: "
                                f"a fixed step on whole samples")
    rates = [c.name for c in comps if c.rate > 1]
    if rates:
        return "gauss_seidel", f"{', '.join(rates)} step{'s' if len(rates) == 1 else ''} at several rates per step"
    if len(scene.components) == 1:
        return "gauss_seidel", "a single component: no coupling for a step to control; a fixed step"
    if not fixed and find_algebraic_loop((c.src, c.dst) for c in scene.connections) is None:
        return "gauss_seidel", ("no feedback between the components: in Gauss-Seidel order every input comes from a "
                                "source that has stepped, a coupling error adaptive's control does not measure; a "
                                "fixed step")
    if not fixed:
        return "adaptive", "every slave can roll back: error-controlled steps"
    if scene.bonds:
        return "ecco", f"{', '.join(fixed)} cannot roll back; the power bonds control the step"
    return "gauss_seidel", f"{', '.join(fixed)} cannot roll back and there are no power bonds: a fixed step"


def steps_for(scene: Scene) -> Callable[[float], int | None]:
    """A function from a wished step [s] to the largest step [ns] at most that long which divides
    the output interval and the run and keeps every sampled block on whole samples (None: none)."""
    m = scene.master
    interval_ns, span_ns = m.record_every * m.step_ns, scene.n_steps * m.step_ns
    periods = [(round(c.description.sample_period * 1e9), c.rate) for c in scene.components.values()
               if c.description.sample_period]

    def fits(h_ns: int) -> bool:
        return span_ns % h_ns == 0 and all(h_ns % r == 0 and (h_ns // r) % ts == 0 for ts, r in periods if ts)

    def step(h: float) -> int | None:
        n = max(1, math.ceil(interval_ns / max(h * 1e9, 1.0)))
        while n <= interval_ns:
            if interval_ns % n == 0 and fits(interval_ns // n):
                return interval_ns // n
            n += 1
        return None
    return step


def windowed(scene: Scene, window: float) -> Scene:
    """``scene`` over the first ``window`` of its span (whole output intervals, at least one)."""
    if window >= 1.0:
        return scene
    per = scene.master.record_every
    n = max(per, int(scene.n_steps * window) // per * per)
    return replace(scene, n_steps=n, stop_time=(scene.start_ns + n * scene.master.step_ns) / 1e9)


def with_step(scene: Scene, algorithm: str, inputs: str, step_ns: int, window: float = 1.0) -> Scene:
    """``scene`` at a fixed ``step_ns`` (same output interval), over the first ``window`` of its span."""
    m = scene.master
    interval_ns = m.record_every * m.step_ns
    n = scene.n_steps * m.step_ns // step_ns
    master = replace(m, algorithm=algorithm, step=step_ns / 1e9, step_ns=step_ns, record_every=interval_ns // step_ns,
                     inputs=inputs, options={})
    return windowed(replace(scene, master=master, n_steps=n, stop_time=(scene.start_ns + n * step_ns) / 1e9), window)


def with_rtol(scene: Scene, algorithm: str, inputs: str, rtol: float, h_max: float | None = None) -> Scene:
    """``scene`` with a variable-step ``algorithm`` at ``rtol`` (and ``h_max`` [s] when given)."""
    opts = option_values({"rtol": rtol} | ({"h_max": h_max} if h_max else {}), ALGORITHMS[algorithm].options)
    return replace(scene, master=replace(scene.master, algorithm=algorithm, inputs=inputs, options=opts))


def choose(scene: Scene, pilot: Callable[[Scene, float | None], object] | None, log: Callable[[str], None] = lambda m: None,
           why_not: str | None = None) -> tuple[Scene, Choice]:
    """The scene as the master will run it, and the :class:`Choice`; ``pilot(scene, companion_rtol)``
    runs a scene into memory, its companion at ``companion_rtol`` when that is not None, and returns
    its :class:`cosim.run.execute.RunResult` (None: runs cannot be repeated, ``why_not``)."""
    m, tol = scene.master, scene.master.tolerance
    alg, why = kind(scene)
    # slaves that cannot interpolate hold their inputs; event mode needs held inputs
    inputs = m.inputs if m.inputs_given else ("hold" if event_inputs(scene, alg) else "linear")
    cls = ALGORITHMS[alg]
    choice = Choice(alg, {"inputs": inputs}, why, tol)

    def trial(sc: Scene, setting: dict, what: str, companion_rtol: float | None = None) -> float | None:
        """A pilot run of ``sc`` (its companion at ``companion_rtol`` when given): its estimate (inf
        for a failed or unstable run), recorded in the choice and logged."""
        res = pilot(sc, companion_rtol)
        e = (res.stats.get("estimate") or {}).get("worst")
        if res.status not in ("ok", "stopped", "inaccurate", "unstable") or e is None:
            e = math.inf if res.status in ("failed", "unstable") else e
        window = sc.stop_time - sc.start_time
        choice.pilots.append({**setting, "window_s": window, "estimate": e})
        log(f"{scene.name}: pilot {alg} at {what} over {window:g} s: "
            + (f"estimated worst error {e:.3g}" if e is not None else "no estimate"))
        return e

    def factor(e: float, order: float) -> float:
        """How far to change the setting for the estimate to reach TARGET of the tolerance: an
        estimate of 0 (nothing the coupling changes, a lone FMU) asks for no finer setting, the
        most a step may grow (:func:`choose` caps it at 10x); a failed pilot (inf) a tenth."""
        if e == 0:
            return math.inf
        return (TARGET * tol / e) ** (1 / order) if e > 0 and math.isfinite(e) else 0.1

    # the first whole-run pilot within the tolerance ends the search: it is the run itself
    # (cosim.run.execute keeps it), and a looser try would only add its cost
    met = False
    p = ORDER_LINEAR if inputs == "linear" else ORDER_HOLD
    if getattr(cls, "variable_step", False):
        rtol, h_max, met, last = _tolerance_search(scene, choice, trial, factor, p, bool(pilot))
        choice.settings["rtol"] = rtol
        if h_max is not None:
            choice.settings["h_max"] = h_max
        if not pilot:
            choice.why += f"; rtol {rtol:g} without pilot runs ({why_not})"
        elif not met:
            choice.why += (f"; no pilot met the tolerance (the closest estimated {last:.3g}, the run)"
                           if last is not None else "; the pilots gave no estimate")
        return with_rtol(scene, alg, inputs, rtol, h_max), choice

    snap = steps_for(scene)
    h_ns = snap(m.step) or m.step_ns
    for k in range(MAX_PILOTS if pilot else 0):
        window = WINDOW if k == 0 else 1.0
        e = trial(with_step(scene, alg, inputs, h_ns, window), {"step": h_ns / 1e9}, f"step {h_ns / 1e9:g} s")
        if e is None:
            break
        if met := e <= tol and window == 1.0:
            break
        nxt = snap(h_ns / 1e9 * min(10.0, max(0.05, factor(e, p))))
        if e > tol and (nxt is None or nxt >= h_ns):
            nxt = snap(h_ns / 2e9)
            if nxt is None or nxt >= h_ns:
                raise UserError(f"scene {scene.name}: no fixed step that divides the output interval "
                                f"{m.record_every * m.step:g} s meets master.tolerance {tol:g} (estimated {e:.3g} at "
                                f"step {h_ns / 1e9:g} s); record more often or relax the tolerance")
        if scene.n_steps * m.step_ns // nxt > MAX_STEPS:
            raise UserError(f"scene {scene.name}: meeting master.tolerance {tol:g} needs a step of about "
                            f"{nxt / 1e9:.3g} s or less (estimated {e:.3g} at step {h_ns / 1e9:g} s), more than "
                            f"{MAX_STEPS:.0e} steps; relax the tolerance or name an algorithm")
        h_ns = nxt
    choice.settings["step"] = h_ns / 1e9
    if not pilot:
        choice.why += f"; the scene's step, without pilot runs ({why_not})"
    elif not met:
        last = choice.pilots[-1]["estimate"] if choice.pilots else None
        choice.why += (f"; no pilot met the tolerance (last estimate {last:.3g})" if last is not None else
                       "; the pilots gave no estimate")
    return with_step(scene, alg, inputs, h_ns), choice


def _tolerance_search(scene: Scene, choice: Choice, trial, factor, p: float,
                      piloted: bool) -> tuple[float, float | None, bool, float | None]:
    """(rtol, h_max or None for the algorithm's, met, the estimate of the pilot that is the run)
    for a variable-step ``alg`` (module docstring): pilots over the whole run, the first one's
    companion shared while it can measure; when a pilot at a 3x tighter rtol is estimated no
    better than 1/1.5 of the last, the largest step limits the error as well (ecco's steps at
    ``h_max`` in a quiet stretch), and from then on each pilot also shrinks ``h_max`` by the order
    ``p`` of the step's coupling.  When none meets the tolerance, the closest pilot is the run.
    The algorithm, its inputs and the tolerance are the ``choice``'s."""
    alg, inputs, tol = choice.algorithm, choice.settings["inputs"], choice.tolerance
    floor = _lower(alg, "rtol")  # a tolerance far below the rtol's range: the pilots meet it by h_max
    rtol, h_max = max(tol * FIRST_RTOL.get(alg, 1.0), floor), None
    shared = max(rtol * FIRST_COMPANION, floor)  # the first pilot's companion, also every later pilot's it can measure
    tried: list[tuple[float, float, float | None]] = []  # (estimate, rtol, h_max)
    for _ in range(MAX_PILOTS if piloted else 0):
        crtol = shared if shared <= REUSE * rtol else None
        setting = {"rtol": rtol, "companion_rtol": crtol or rtol * RATIO} | ({"h_max": h_max} if h_max else {})
        what = f"rtol {rtol:.3g}" + (f", h_max {h_max:.3g} s" if h_max else "")
        e = trial(with_rtol(scene, alg, inputs, rtol, h_max), setting, what, crtol)
        if e is None:
            return rtol, h_max, False, None
        if e <= tol:
            return rtol, h_max, True, e
        tried.append((e, rtol, h_max))
        last = tried[-2] if len(tried) > 1 else None
        if h_max is not None or rtol <= floor or (last is not None and last[1] >= 3 * rtol and last[0] < 1.5 * e):
            h_max = (h_max or _default(alg, "h_max")) * min(0.9, max(0.1, factor(e, p)))
        nxt = rtol * min(30.0, max(1 / 30, factor(e, ORDER_TOLERANCE)))
        if nxt < shared / REUSE <= rtol and e * (shared / REUSE / rtol) ** ORDER_TOLERANCE <= LOOSER * tol:
            nxt = shared / REUSE  # aiming a little higher spares a companion run
        rtol = max(nxt, floor)
    if not tried:
        return rtol, h_max, False, None
    e, rtol, h_max = min(tried, key=lambda x: x[0])
    return rtol, h_max, False, e


def _default(alg: str, option: str) -> float:
    return next(o.default for o in ALGORITHMS[alg].options if o.name == option)


def _lower(alg: str, option: str) -> float:
    return next(o.lower for o in ALGORITHMS[alg].options if o.name == option)


def applied(scene: Scene, choice: dict) -> Scene:
    """``scene`` as the :class:`Choice` ``choice`` (its :meth:`Choice.as_dict`) runs it."""
    sets, alg = choice["settings"], choice["algorithm"]
    if "rtol" in sets:
        return with_rtol(scene, alg, sets["inputs"], sets["rtol"], sets.get("h_max"))
    return with_step(scene, alg, sets["inputs"], round(sets["step"] * 1e9))
