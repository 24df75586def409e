"""Work-precision study: error against cost of master algorithm variants on one scene.

``precision_study`` integrates the scene's monolithic reference once (:mod:`cosim.reference`,
CVODES at tight tolerances), then runs the co-simulation for every variant (algorithm, inputs)
and communication step and measures, per recorded signal, the largest error relative to the
reference's range (``compare``), at instants both traces share exactly (everything is recorded
every ``record`` seconds, a multiple of every step, so no interpolation enters the error).  The
cost is the wall time of the stepping loop (FMU builds excluded, as the reference's excludes
building its integrator) and the number of doStep calls.

The observed order of each variant is the slope of log(error) against log(step) over the runs
that ended ok.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..compare import compare
from ..errors import UserError
from ..run import build_components, run
from ..scenario import load
from ..slaves import FmuSlave


@dataclass
class PrecisionRow:
    """One co-simulation: variant, step [s], outcome, worst relative error and the signal it is on,
    RMS of the relative errors, wall time [s] and doStep calls; ``errors`` per signal."""

    algorithm: str
    inputs: str
    step: float
    status: str
    reason: str
    worst: float = math.nan
    worst_signal: str = ""
    rms: float = math.nan
    wall_s: float = math.nan
    do_steps: int = 0
    errors: dict[str, float] = field(default_factory=dict)


@dataclass
class PrecisionStudy:
    scene: str
    stop_time: float
    record: float
    reference_wall_s: float
    rows: list[PrecisionRow] = field(default_factory=list)

    def variants(self) -> list[tuple[str, str]]:
        return list(dict.fromkeys((r.algorithm, r.inputs) for r in self.rows))

    def order(self, variant: tuple[str, str]) -> float:
        """Observed order of convergence of ``variant`` (nan with fewer than two ok runs)."""
        pts = [(r.step, r.worst) for r in self.rows
               if (r.algorithm, r.inputs) == variant and r.status == "ok" and 0 < r.worst < math.inf]
        if len(pts) < 2:
            return math.nan
        h, e = np.log(np.array(pts)).T
        return float(np.polyfit(h, e, 1)[0])

    def cheapest_within(self, tol: float) -> PrecisionRow | None:
        """The fastest ok run whose worst relative error is at most ``tol``."""
        ok = [r for r in self.rows if r.status == "ok" and r.worst <= tol]
        return min(ok, key=lambda r: r.wall_s) if ok else None

    def write_csv(self, path: Path) -> None:
        signals = list(dict.fromkeys(s for r in self.rows for s in r.errors))
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["algorithm", "inputs", "step", "status", "worst_relative", "worst_signal", "rms_relative",
                        "wall_s", "do_steps", "reason", *(f"rel:{s}" for s in signals)])
            for r in self.rows:
                w.writerow([r.algorithm, r.inputs, repr(r.step), r.status, f"{r.worst:.6g}", r.worst_signal,
                            f"{r.rms:.6g}", f"{r.wall_s:.6g}", r.do_steps, r.reason,
                            *(f"{r.errors[s]:.6g}" if s in r.errors else "" for s in signals)])


def default_steps(step: float) -> list[float]:
    """Four times the scene's step down to an eighth of it, by halves."""
    return [step * f for f in (4, 2, 1, 0.5, 0.25, 0.125)]


def _record_interval(steps: Sequence[float], scene_interval: float) -> float:
    big = max(steps)
    k = scene_interval / big
    return scene_interval if k >= 1 and abs(k - round(k)) < 1e-9 else big


def precision_study(scene_path: Path | str, variants: Sequence[tuple[str, str]], steps: Sequence[float] | None = None,
                    *, stop_time: float | None = None, only: Sequence[str] | None = None,
                    cache_dir: Path | None = None, progress: Callable[[str], None] | None = None,
                    overrides: Sequence[str] | None = None) -> PrecisionStudy:
    """Run the study (module docstring).  ``steps`` default to :func:`default_steps` of the
    scene's step; ``stop_time`` overrides the scene's (rounded to a whole number of recording
    intervals); ``only`` restricts the signals compared (globs); ``overrides`` (``--set`` items)
    apply to every run and to the reference (e.g. ``components.mech.rate=4``)."""
    from ..reference import reference
    from ..scenario import parse_set

    sets = dict(parse_set(s) for s in overrides or ())
    base = load(scene_path, sets)
    steps = sorted({round(float(h) * 1e9) / 1e9 for h in (steps or default_steps(base.master.step))}, reverse=True)
    if any(h <= 0 for h in steps):
        raise UserError(f"steps must be positive, got {steps}")
    for h in steps:
        k = steps[0] / h
        if abs(k - round(k)) > 1e-9:
            raise UserError(f"step {h:g} s does not divide the largest step {steps[0]:g} s: choose steps that halve")
    record = _record_interval(steps, base.master.record_every * base.master.step)
    stop = stop_time if stop_time is not None else base.stop_time
    stop = max(1, round(stop / record)) * record
    common = {**sets, "stop_time": stop}
    ref = reference(scene_path, {**common, "master.step": record, "master.output_interval": record})
    if not ref.ok:
        raise UserError(f"{base.name}: the monolithic reference failed ({ref.reason}); no study without it")
    study = PrecisionStudy(base.name, stop, record, float(ref.stats.get("wall_s", math.nan)))
    paths = build_components(base, cache_dir=cache_dir)
    for alg, inputs in variants:
        for h in steps:
            scene = load(scene_path, {**common, "master.algorithm": alg, "master.inputs": inputs, "master.step": h,
                                      "master.output_interval": record})
            res = run(scene, slaves=[FmuSlave(n, paths[n]) for n in scene.components])
            row = PrecisionRow(alg, inputs, h, res.status, res.reason, wall_s=float(res.stats.get("wall_s", math.nan)),
                               do_steps=int(sum(s.get("do_step_calls", 0) for s in (res.stats.get("slaves") or {}).values())))
            if res.ok:
                diffs = compare(res.trace, ref.trace, only)
                row.errors = {d.name: d.relative for d in diffs}
                worst = max(diffs, key=lambda d: d.relative)
                row.worst, row.worst_signal = worst.relative, worst.name
                row.rms = float(np.sqrt(np.mean([d.relative ** 2 for d in diffs])))
            study.rows.append(row)
            if progress:
                progress(f"{alg:<13} {inputs:<7} step {h:<10.4g} {res.status:<8} worst {row.worst:10.3e} "
                         f"({row.worst_signal or res.reason[:40]})  {row.wall_s:7.3f} s")
    return study


def plot_study(study: PrecisionStudy, path: Path) -> Path:
    """Work-precision chart: worst relative error against wall time, one curve per variant, each
    point labelled with its step; the monolithic reference's wall time as a vertical line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5), layout="constrained")
    for variant in study.variants():
        pts = [r for r in study.rows if (r.algorithm, r.inputs) == variant and r.status == "ok" and r.worst > 0]
        if not pts:
            continue
        p = study.order(variant)
        line, = ax.loglog([r.wall_s for r in pts], [r.worst for r in pts], marker="o",
                          label=f"{variant[0]}, {variant[1]} (order {p:.2f})" if math.isfinite(p) else
                          f"{variant[0]}, {variant[1]}")
        for r in pts:
            ax.annotate(f"{r.step * 1e3:g} ms", (r.wall_s, r.worst), fontsize=7, textcoords="offset points",
                        xytext=(4, 3), color=line.get_color())
    if math.isfinite(study.reference_wall_s):
        ax.axvline(study.reference_wall_s, color="k", ls=":", lw=1, label="monolithic reference (CVODES)")
    ax.set_xlabel("wall time of the stepping loop [s]")
    ax.set_ylabel("worst error relative to the signal's range [1]")
    ax.set_title(f"{study.scene}: work-precision over {study.stop_time:g} s")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
