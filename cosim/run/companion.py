"""The companion of a run, against which its error is estimated (:mod:`cosim.master.estimate`):
the same scene at twice the communication step (fixed-step algorithms) or four times the
tolerance (``adaptive``, ``ecco``), not paced, recording every step."""
from __future__ import annotations

from dataclasses import dataclass, replace

from ..master import ALGORITHMS
from ..master.estimate import divisor
from ..scenario import Scene

#: Coarsening of the companion: step ratio (fixed step) and tolerance ratio (variable step).
STEP_RATIO, TOLERANCE_RATIO = 2.0, 4.0
#: Orders assumed for the divisor (the middle of the range each coupling shows, see the estimate's docs).
ORDER_HOLD, ORDER_LINEAR, ORDER_TOLERANCE = 1.0, 1.5, 0.75


@dataclass(frozen=True)
class Companion:
    """The companion ``scene`` (None when there can be none, ``why``), the Richardson divisor
    ``div`` and a one-line ``method``."""

    scene: Scene | None
    div: float = 1.0
    method: str = ""


def companion(scene: Scene, interpolating: bool) -> Companion:
    """The companion of a run of ``scene`` (module docstring); ``interpolating``: some slave of the
    run follows input slopes (its FMU can interpolate inputs)."""
    m = scene.master
    cls = ALGORITHMS[m.algorithm]
    if getattr(cls, "variable_step", False):
        opts = dict(m.options)
        bound = next((o.upper for o in getattr(cls, "options", ()) if o.name == "rtol"), 1.0)
        rtol = opts.get("rtol", next((o.default for o in cls.options if o.name == "rtol"), 1e-3))
        if rtol * TOLERANCE_RATIO > bound:
            return Companion(None, method=f"rtol {rtol:g} leaves no room for a companion at {TOLERANCE_RATIO:g}x")
        opts["rtol"] = rtol * TOLERANCE_RATIO
        return Companion(replace(scene, master=replace(m, options=opts, realtime=None)),
                         divisor(TOLERANCE_RATIO, ORDER_TOLERANCE),
                         f"Richardson against a companion run at rtol {opts['rtol']:.3g} ({TOLERANCE_RATIO:g}x)")
    n = scene.n_steps // 2
    if n < 2:
        return Companion(None, method="too few steps for a companion run at twice the step")
    step_ns = 2 * m.step_ns
    master = replace(m, step=step_ns / 1e9, step_ns=step_ns, record_every=1, realtime=None)
    stop = (scene.start_ns + n * step_ns) / 1e9
    order = ORDER_LINEAR if scene.master.inputs == "linear" and interpolating else ORDER_HOLD
    return Companion(replace(scene, master=master, n_steps=n, stop_time=stop), divisor(STEP_RATIO, order),
                     f"Richardson against a companion run at step {step_ns / 1e9:g} s ({STEP_RATIO:g}x)")
