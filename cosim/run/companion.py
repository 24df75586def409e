"""The companion of a run, against which its error is estimated (:mod:`cosim.master.estimate`):
the same scene at half the communication step (fixed-step algorithms; recording at the run's own
instants) or a quarter of the tolerance and half the largest step (``adaptive``, ``ecco``), not paced.  A finer companion,
not a coarser one: it stays where the run's error behaves as its order says (a coarser one may
leave that regime, e.g. a slave's own RK4 near its stability limit, and make a good run look
bad). Where half the step would take a sampled block off its samples there is no companion and no
estimate: the only companion left is coarser, and at twice the step a coupling may go unstable and
measure itself (measured on pid_step with discrete PIDs at their 1 ms: 0.94 of range over the first
0.3 s). A scene that needs an estimate gives the sampled block ``timing: events`` (its samples are
time events, any step works). Where only an odd number of nanoseconds forbids halving, the companion
takes twice the step."""
from __future__ import annotations

from dataclasses import dataclass, replace

from ..master import ALGORITHMS
from ..master.estimate import divisor
from ..scenario import Scene

#: The companion's step over the run's (fixed step; COARSE where half cannot be taken) and its
#: tolerance over the run's (variable step).
STEP_RATIO, COARSE, TOLERANCE_RATIO = 0.5, 2.0, 0.25
#: Orders assumed for the divisor: the middle of the range a step's coupling shows, the low end of
#: a tolerance's (0.4 to 0.7 measured: an estimate then errs high), see the estimate's docs.
ORDER_HOLD, ORDER_LINEAR, ORDER_TOLERANCE = 1.0, 1.5, 0.4


@dataclass(frozen=True)
class Companion:
    """The companion ``scene`` (None when there can be none, ``why``), the Richardson divisor
    ``div`` and a one-line ``method``."""

    scene: Scene | None
    div: float = 1.0
    method: str = ""


def companion(scene: Scene, interpolating: bool, rtol: float | None = None) -> Companion:
    """The companion of a run of ``scene`` (module docstring); ``interpolating``: some slave of the
    run follows input slopes (its FMU can interpolate inputs); ``rtol``: a variable-step companion
    at this rtol instead (below the run's: the master's pilots share one, :mod:`cosim.run.choose`)."""
    m = scene.master
    cls = ALGORITHMS[m.algorithm]
    if getattr(cls, "variable_step", False):
        opts = dict(m.options)
        own = opts.get("rtol", next((o.default for o in cls.options if o.name == "rtol"), 1e-3))
        lower = next((o.lower for o in cls.options if o.name == "rtol"), 0.0)
        atol = opts.get("atol", next((o.default for o in cls.options if o.name == "atol"), 0.0))
        given = rtol is not None and lower <= rtol < own
        ratio = rtol / own if given else TOLERANCE_RATIO
        if given or own * TOLERANCE_RATIO >= lower:
            opts["rtol"] = rtol if given else own * TOLERANCE_RATIO
            what = f"rtol {opts['rtol']:.3g}"
        elif atol > 0:  # rtol at its floor (e.g. libcosim's tolerances, cosim.scenario.osp): atol is the tolerance
            opts["atol"], what = atol * TOLERANCE_RATIO, f"atol {atol * TOLERANCE_RATIO:.3g} (rtol at its floor)"
        else:
            return Companion(None, method=f"rtol {own:g} leaves no room for a companion at {TOLERANCE_RATIO:g}x")
        # the largest step halved too: where the step control sees no error (in a chain no input is
        # extrapolated) the steps sit at h_max whatever the tolerance, and a companion at a quarter
        # of it would repeat the run to the bit and estimate 0 (measured on vw_compare: 8e-2 off)
        default = {o.name: o.default for o in cls.options}
        h_max = opts.get("h_max", default.get("h_max"))
        floor = max(opts.get(k, default.get(k)) or 0.0 for k in ("h_min", "h_init"))
        halved = h_max is not None and h_max * STEP_RATIO >= floor
        if halved:
            opts["h_max"] = h_max * STEP_RATIO
        comp = replace(scene, master=replace(m, options=opts, realtime=None))
        if m.step_ns % 2 == 0:  # its steps land on a grid of half the output interval too (the run's points among
            # them): where the grid, not the tolerance, bounds the steps, a companion on the same grid would
            # repeat the run to the bit and estimate 0 (measured on a chain at a 10 ms grid: 4.3e-7 off)
            comp = replace(comp, master=replace(comp.master, step=m.step_ns // 2 / 1e9, step_ns=m.step_ns // 2),
                           n_steps=2 * scene.n_steps)
        return Companion(comp,
                         divisor(ratio, ORDER_TOLERANCE),
                         f"Richardson against a companion run at {what} ({ratio:.3g}x)"
                         + (f", h_max {opts['h_max']:.3g} s" if halved else "")
                         + (f", landing every {comp.master.step_ns * m.record_every / 1e9:g} s"
                            if comp.master.step_ns != m.step_ns else ""))
    order = ORDER_LINEAR if scene.master.inputs == "linear" and interpolating else ORDER_HOLD
    if m.step_ns % 2 == 0 and _on_samples(scene, m.step_ns // 2):
        step_ns = m.step_ns // 2
        master = replace(m, step=step_ns / 1e9, step_ns=step_ns, record_every=2 * m.record_every, realtime=None)
        return Companion(replace(scene, master=master, n_steps=2 * scene.n_steps), divisor(STEP_RATIO, order),
                         f"Richardson against a companion run at step {step_ns / 1e9:g} s ({STEP_RATIO:g}x)")
    sampled = _off_samples(scene, m.step_ns // 2) if m.step_ns % 2 == 0 else []
    if sampled:
        return Companion(None, method=(
            f"{', '.join(sampled)} sample{'s' if len(sampled) == 1 else ''} at {_period(scene, sampled[0]):g} s, so "
            f"no companion at half the step {m.step:g} s; a coarser one would leave the run's regime (Gauss-Seidel "
            f"at twice the step may go unstable) and measure itself, not the run"))
    n = scene.n_steps // 2
    if n < 2:
        return Companion(None, method="too few steps for a companion run at twice the step")
    step_ns = 2 * m.step_ns
    master = replace(m, step=step_ns / 1e9, step_ns=step_ns, record_every=1, realtime=None)
    stop = (scene.start_ns + n * step_ns) / 1e9
    return Companion(replace(scene, master=master, n_steps=n, stop_time=stop), divisor(COARSE, order),
                     f"Richardson against a companion run at step {step_ns / 1e9:g} s ({COARSE:g}x)")


def _off_samples(scene: Scene, step_ns: int) -> list[str]:
    """The sampled blocks a step of ``step_ns`` would take off their samples."""
    out = []
    for c in scene.components.values():
        ts = round((c.description.sample_period or 0) * 1e9)
        if ts and (step_ns % c.rate or (step_ns // c.rate) % ts):
            out.append(c.name)
    return out


def _period(scene: Scene, name: str) -> float:
    return float(scene.components[name].description.sample_period)


def _on_samples(scene: Scene, step_ns: int) -> bool:
    """Does a step of ``step_ns`` keep every sampled block on whole samples (and every rate whole)?"""
    for c in scene.components.values():
        if step_ns % c.rate:
            return False
        ts = round((c.description.sample_period or 0) * 1e9)
        if ts and (step_ns // c.rate) % ts:
            return False
    return True
