"""Stability maps: where a master algorithm fails, over communication step x one scene parameter.

``stability_map`` runs the scene once per cell of a log-spaced grid (step x parameter) and per
algorithm variant (algorithm, inputs), and classifies each run:

- ``stable``: the run ended ok and its recorded signals did not grow (measured growth factor per
  step ``rho_hat <= 1``, see :func:`growth_per_step`);
- ``unstable``: the signals grew (``rho_hat > 1``), became non-finite, or a slave stopped on a
  non-finite state;
- ``failed``: the run ended for another reason (the slave's message is the cell's reason).

When every component is a catalog block that is linear (``models.coupling.linearize``) and no
connected output has feedthrough, the analytic spectral radius of the macro-step map is computed
for every cell as well (``rho``), and the chart draws the boundary ``rho = 1``.

The run length is ``periods`` times the scene's stop time regardless of the step (a fixed span of
simulated time, so every cell sees the same physics; small steps just take more of them).
"""
from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..run.execute import build_components, run
from ..scenario import Scene, load
from .fidelity import resolve_auto
from ..slaves.fmu_slave import FmuSlave
from fmus.index import real_block
from models.coupling import Link, linearize, macro_map, spectral_radius
from ..master import gauss_seidel_order
from ..analysis.charts import save_figure
from ..outputs import staged

#: Default algorithm variants mapped: every fixed-step algorithm with both input treatments.
DEFAULT_VARIANTS = (("jacobi", "hold"), ("jacobi", "linear"), ("gauss_seidel", "hold"), ("gauss_seidel", "linear"))


@dataclass
class Cell:
    """One run of the map."""

    algorithm: str
    inputs: str
    step: float
    value: float
    outcome: str  # stable | unstable | failed
    reason: str
    rho_hat: float  # measured growth per step
    rho: float = math.nan  # analytic spectral radius of the macro-step map (nan if none)


@dataclass
class StabilityMap:
    """The cells of a map with its axes; ``analytic`` says whether ``rho`` was computed."""

    scene: str
    vary: str
    steps: np.ndarray
    values: np.ndarray
    variants: list[tuple[str, str]]
    cells: list[Cell] = field(default_factory=list)
    analytic: bool = False
    analytic_note: str = ""

    def grid(self, algorithm: str, inputs: str, what: str = "outcome") -> np.ndarray:
        """``what`` of every cell of one variant as an array [value index, step index]."""
        out = np.empty((len(self.values), len(self.steps)), dtype=object if what in ("outcome", "reason") else float)
        for c in self.cells:
            if (c.algorithm, c.inputs) == (algorithm, inputs):
                i = int(np.argmin(np.abs(np.log(self.values / c.value)))) if c.value > 0 else 0
                j = int(np.argmin(np.abs(np.log(self.steps / c.step))))
                out[i, j] = getattr(c, what)
        return out

    def write_csv(self, path: Path) -> None:
        """One row per cell: variant, step [s], parameter value, outcome, reason, growth, rho."""

        with staged(path) as part, open(part, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["algorithm", "inputs", "step", self.vary, "outcome", "rho_measured", "rho_analytic", "reason"])
            for c in self.cells:
                w.writerow([c.algorithm, c.inputs, repr(c.step), repr(c.value), c.outcome, f"{c.rho_hat:.9g}",
                            f"{c.rho:.9g}", c.reason])


def growth_per_step(data: np.ndarray, steps_per_row: float) -> float:
    """Measured growth factor per macro step of the recorded signals ``data`` (rows = time).

    Each column is scaled by its largest magnitude in the first quarter; the amplitude of a window
    is the largest scaled magnitude over columns; the factor compares the last quarter with the
    third: ``(A_4 / A_3) ** (1 / rows between them)``.  Windows span at least one period of the
    slowest mode when the run is long enough (see :func:`stability_map`)."""
    if data.ndim != 2 or len(data) < 8:
        return math.nan
    if not np.all(np.isfinite(data)):
        return math.inf
    q = len(data) // 4
    scale = np.max(np.abs(data[:q]), axis=0)
    keep = scale > 0
    if not np.any(keep):
        return 1.0
    scaled = np.abs(data[:, keep]) / scale[keep]
    a3, a4 = np.max(scaled[2 * q:3 * q]), np.max(scaled[3 * q:])
    if a3 == 0:
        return 1.0 if a4 == 0 else math.inf
    return float((a4 / a3) ** (1.0 / (q * steps_per_row)))


def parse_range(text: str, what: str) -> tuple[float, float]:
    """``"LO:HI"`` with 0 < LO < HI (log axes)."""
    try:
        lo_s, hi_s = text.split(":")
        lo, hi = float(lo_s), float(hi_s)
    except ValueError:
        raise UserError(f"{what}: expected LO:HI with two numbers, got {text!r}") from None
    if not (0 < lo < hi and math.isfinite(hi)):
        raise UserError(f"{what}: expected 0 < LO < HI (the axis is logarithmic), got {text!r}")
    return lo, hi


def _analytic(scene: Scene, vary: str):
    """A function ``(value, step, algorithm, inputs, order) -> rho`` for a linear scene, or a note why not."""

    names = list(scene.components)
    comps = list(scene.components.values())
    if any(c.block is None for c in comps):
        return None, "a component is an external FMU: no analytic map"
    prefix = "components."
    target = None
    if vary.startswith(prefix) and ".params." in vary:
        cname, _, pname = vary[len(prefix):].partition(".params.")
        target = (cname, pname)
    links = []
    for c in scene.connections:
        sb, db = scene.components[c.src].block, scene.components[c.dst].block
        links.append(Link(names.index(c.src), sb.index("outputs", c.src_var), names.index(c.dst),
                          db.index("inputs", c.dst_var)))

    def rho(value: float, h: float, algorithm: str, inputs: str, order) -> float:
        slaves = []
        for cname, comp in scene.components.items():
            params = {k: v for k, v in comp.params.items() if k in {p.name for p in comp.block.params}}
            if target and target[0] == cname:
                params[target[1]] = value
            slaves.append(linearize(real_block(comp.block), params))
        return spectral_radius(macro_map(slaves, links, h, algorithm, inputs, order))

    try:
        rho(scene_value(scene, vary), scene.master.step, "jacobi", "hold", None)
    except ValueError as exc:
        return None, str(exc)
    return rho, ""


def scene_value(scene: Scene, path: str) -> float:
    """The current value at ``path`` (dotted, as ``--set``) in the scene's data."""
    node = scene.data
    parts = path.split(".")
    i = 0
    while i < len(parts):
        key = parts[i]
        if parts[i - 1:i] == ["params"] or parts[i - 1:i] == ["start"]:
            key = ".".join(parts[i:])
            i = len(parts) - 1
        if not isinstance(node, dict) or key not in node:
            raise UserError(f"--vary {path}: the scene has no value at {key!r}")
        node = node[key]
        i += 1
    try:
        return float(node)
    except (TypeError, ValueError):
        raise UserError(f"--vary {path}: the value there is {node!r}, not a number") from None


def stability_map(scene_path: Path | str, vary: str, value_range: tuple[float, float],
                  step_range: tuple[float, float], *, n_values: int = 12, n_steps: int = 12,
                  variants: Sequence[tuple[str, str]] = DEFAULT_VARIANTS, cache_dir: Path | None = None,
                  progress: Callable[[int, int], None] | None = None) -> StabilityMap:
    """Run the map (module docstring).  ``vary`` is a ``--set`` path; ranges are (lo, hi) on log
    axes.  Each run covers the scene's ``stop_time`` of simulated time."""
    base = load(scene_path, auto_fidelity=resolve_auto)
    scene_value(base, vary)  # a clear error before any run
    steps = np.geomspace(*step_range, n_steps)
    values = np.geomspace(*value_range, n_values)
    smap = StabilityMap(base.name, vary, steps, values, [tuple(v) for v in variants])
    rho_fn, note = _analytic(base, vary)
    smap.analytic, smap.analytic_note = rho_fn is not None, note
    paths = build_components(base, cache_dir=cache_dir)
    total, done = len(steps) * len(values) * len(variants), 0
    for alg, inputs in variants:
        for value in values:
            for h in steps:
                h = round(float(h) * 1e9) / 1e9  # whole nanoseconds
                # the map classifies each run by its own growth, not by the run's error estimate
                over = {vary: float(value), "master.step": h, "master.algorithm": alg, "master.inputs": inputs,
                        "master.output_interval": h, "stop_time": max(8, round(base.stop_time / h)) * h,
                        "master.estimate": False}
                scene = load(scene_path, over, auto_fidelity=resolve_auto)
                slaves = [FmuSlave(n, paths[n]) for n in scene.components]
                res = run(scene, slaves=slaves)
                smap.cells.append(_classify(res, alg, inputs, float(h), float(value)))
                if rho_fn is not None:
                    index = {n: i for i, n in enumerate(scene.components)}
                    order = [index[n] for n in scene.master.order] if scene.master.order else None
                    if order is None and alg == "gauss_seidel":

                        order = gauss_seidel_order(len(index), [(index[c.src], index[c.dst])
                                                                for c in scene.connections])
                    try:
                        smap.cells[-1].rho = rho_fn(float(value), float(h), alg, inputs, order)
                    except ValueError:  # no analytic map for this algorithm (e.g. iterative): rho stays nan
                        pass
                done += 1
                if progress:
                    progress(done, total)
    return smap


def _classify(res, alg: str, inputs: str, h: float, value: float) -> Cell:
    data = res.trace.data[:, 1:] if res.trace.data.size else np.zeros((0, 0))
    if res.status != "ok":
        reason = res.reason or res.status
        unstable = "finite" in reason.lower() or "nan" in reason.lower() or "unstable" in res.status
        return Cell(alg, inputs, h, value, "unstable" if unstable else "failed", reason,
                    growth_per_step(data, 1.0) if len(data) else math.nan)
    g = growth_per_step(data, 1.0)
    if not math.isfinite(g) or g > 1.0:
        return Cell(alg, inputs, h, value, "unstable", f"signals grow by {g:.6g} per step" if math.isfinite(g)
                    else "signals became non-finite", g)
    return Cell(alg, inputs, h, value, "stable", "", g)


def analytic_grid(scene_path: Path | str, vary: str, value_range: tuple[float, float],
                  step_range: tuple[float, float], variant: tuple[str, str], n: int = 40) -> tuple | None:
    """``(steps, values, rho)`` of the analytic macro-step map on an ``n x n`` log grid for one
    variant, or None when the scene has no analytic map."""
    scene = load(scene_path, auto_fidelity=resolve_auto)
    rho_fn, _ = _analytic(scene, vary)
    if rho_fn is None:
        return None

    index = {nm: i for i, nm in enumerate(scene.components)}
    order = ([index[nm] for nm in scene.master.order] if scene.master.order else
             gauss_seidel_order(len(index), [(index[c.src], index[c.dst]) for c in scene.connections]))
    steps, values = np.geomspace(*step_range, n), np.geomspace(*value_range, n)
    rho = np.array([[rho_fn(float(v), float(h), variant[0], variant[1], order) for h in steps] for v in values])
    return steps, values, rho


OUTCOME_COLOURS = {"stable": "#4caf50", "unstable": "#e53935", "failed": "#9e9e9e"}


def plot_map(smap: StabilityMap, path: Path, scene_path: Path | str | None = None) -> Path:
    """One panel per variant: cells coloured by outcome, the analytic boundary rho = 1 drawn over
    them when the scene is linear."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    nv = len(smap.variants)
    cols = min(nv, 2)
    rows = math.ceil(nv / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.2 * rows), squeeze=False, layout="constrained")
    codes = {"stable": 0, "unstable": 1, "failed": 2}
    cmap = ListedColormap([OUTCOME_COLOURS[k] for k in codes])
    ls, lv = np.log10(smap.steps), np.log10(smap.values)
    ds = (ls[1] - ls[0]) / 2 if len(ls) > 1 else 0.5
    dv = (lv[1] - lv[0]) / 2 if len(lv) > 1 else 0.5
    for ax, variant in zip(axes.flat, smap.variants):
        grid = smap.grid(*variant)
        z = np.vectorize(lambda o: codes.get(o, 2))(grid).astype(float)
        ax.pcolormesh(10 ** np.append(ls - ds, ls[-1] + ds), 10 ** np.append(lv - dv, lv[-1] + dv), z,
                      cmap=cmap, vmin=0, vmax=2, edgecolors="white", linewidth=0.5)
        if smap.analytic and scene_path is not None:
            fine = analytic_grid(scene_path, smap.vary, (smap.values[0], smap.values[-1]),
                                 (smap.steps[0], smap.steps[-1]), variant)
            if fine is not None:
                ax.contour(fine[0], fine[1], fine[2], levels=[1.0], colors="k", linewidths=1.6)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{variant[0]}, inputs {variant[1]}")
        ax.set_xlabel("communication step [s]")
        ax.set_ylabel(smap.vary.rsplit(".", 1)[-1])
    for ax in list(axes.flat)[nv:]:
        ax.set_visible(False)
    handles = [Patch(color=c, label=k) for k, c in OUTCOME_COLOURS.items()]
    if smap.analytic:
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="k", label="analytic boundary: spectral radius = 1"))
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles))
    fig.suptitle(f"{smap.scene}: stability over step and {smap.vary}")

    return save_figure(fig, Path(path), dpi=110)
