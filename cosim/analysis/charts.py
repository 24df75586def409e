"""Charts of runs: units on every axis (from the FMUs' unit declarations), each setpoint on the
axes of the signal it commands, a co-simulation overlaid on its reference with the error axis in
the variable's unit.  matplotlib is imported inside the plotting functions only."""
from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..trace.traces import Trace
from .trace_diff import aligned
from ..outputs import staged


def setpoint_pairs(scene) -> dict[str, str]:
    """Setpoint signal -> the signal it commands: for every component with inputs ``setpoint``
    and ``measurement`` (a controller), the sources feeding them."""
    src = {(c.dst, c.dst_var): f"{c.src}.{c.src_var}" for c in scene.connections}
    pairs = {}
    for name in scene.components:
        sp, meas = src.get((name, "setpoint")), src.get((name, "measurement"))
        if sp and meas:
            pairs[sp] = meas
    return pairs


@dataclass
class Panel:
    """One axes: a title, the y label (with unit) and the lines (name, dashed?)."""

    title: str
    ylabel: str
    lines: list[tuple[str, bool]] = field(default_factory=list)


def _group_key(name: str) -> str:
    return re.sub(r"\[\d+\]", "[*]", re.sub(r"^([A-Za-z_]+?)\d+\.", r"\1*.", name))


def _ylabel(names: Sequence[str], units: Mapping[str, str]) -> str:
    found = sorted({units.get(n, "") for n in names})
    if len(found) == 1:
        return f"[{found[0] or '1'}]"
    return "[" + ", ".join(u or "1" for u in found) + "]"


def run_panels(names: Sequence[str], units: Mapping[str, str], pairs: Mapping[str, str] | None = None,
               most: int | None = None) -> list[Panel]:
    """Axes of a run chart: like variables together (``pid1.y``, ``pid2.y``; ``leg[1..3].s``), a
    setpoint dashed on the axes of the signal it commands (``pairs``), the unit on each y axis;
    every variable of ``names`` on one (``most``: at most that many axes, for a preview)."""
    pairs = {s: m for s, m in (pairs or {}).items() if s in names and m in names}
    groups: dict[str, list[str]] = {}
    for name in names:
        if name not in pairs:
            groups.setdefault(_group_key(name), []).append(name)
    panels = []
    for key, members in list(groups.items())[:most]:  # most None: all of them
        lines = [(n, False) for n in members]
        lines += [(s, True) for s, m in pairs.items() if m in members]
        panels.append(Panel(key, _ylabel([n for n, _ in lines], units), lines))
    return panels


#: Beyond this many axes a run chart takes three columns instead of two (a tall page, never fewer axes).
WIDE = 24


def plot_run(trace: Trace, path: Path, title: str, *, units: Mapping[str, str] | None = None,
             pairs: Mapping[str, str] | None = None) -> Path:
    """PNG of a run: one axes per :class:`Panel` of :func:`run_panels`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = run_panels(trace.names, units or {}, pairs)  # every recorded variable: a taller page, none dropped
    ncol = 1 if len(panels) == 1 else 2 if len(panels) <= WIDE else 3
    nrow = -(-len(panels) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(6 * ncol, 2.2 * nrow), sharex=True, squeeze=False)
    for ax, panel in zip(axes.flat, panels):
        colour: dict[str, str] = {}
        for i, (name, dashed) in enumerate(panel.lines):
            c = colour.get((pairs or {}).get(name, ""), f"C{i}") if dashed else f"C{i}"
            colour[name] = c  # a setpoint takes the colour of the signal it commands
            ax.plot(trace.time, trace[name], lw=1, ls="--" if dashed else "-", color=c,
                    label=f"{name} (setpoint)" if dashed else name)
        # y given: matplotlib does not measure the tick labels once more to place a title this short
        ax.set_title(panel.title, fontsize=9, y=1.0)
        ax.set_ylabel(panel.ylabel, fontsize=8)
        ax.grid(alpha=0.3)
        if len(panel.lines) > 1:
            ax.legend(fontsize=7, loc="best")
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    # fixed margins in inches instead of tight_layout, which renders every tick label once more
    # to measure it (a third of pid_step's 2.3 s plot); the title 0.1 in below the top, at any height
    w, h = fig.get_size_inches()
    fig.suptitle(title, y=1 - 0.1 / h, va="top")
    fig.subplots_adjust(left=0.95 / w, right=1 - 0.15 / w, bottom=0.5 / h, top=1 - 0.55 / h, hspace=0.45,
                        wspace=0.2 * ncol)
    return _save(fig, path)


def comparison_figure(test: Trace, ref: Trace, diffs, *, labels: tuple[str, str] = ("test", "reference"),
                      most: int = 8, units: Mapping[str, str] | None = None, rows: range | None = None):
    """The figure of :func:`plot_comparison` (for the ``most`` worst variables: both traces
    overlaid on the left, their difference on the right, each y axis in the variable's unit);
    ``rows``: only these rows' axes, where the whole figure has them (:func:`comparison_part`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    units = units or {}
    worst = sorted(diffs, key=lambda d: -d.relative)[:most]
    names = [d.name for d in worst]
    t, a, b = aligned(test, ref, names)
    rows = range(len(names)) if rows is None else rows
    fig = plt.figure(figsize=(11, 1.9 * len(names) + 1.1))
    # fixed margins in inches: constrained layout measured every tick label again (2/3 of pid_step's plot)
    w, h = fig.get_size_inches()
    fig.suptitle((f"the {len(names)} worst of {len(diffs)} variables by largest difference relative to range "
                  f"(every one in the printed table)") if len(names) < len(diffs) else
                 f"all {len(diffs)} variables, by largest difference relative to range", y=1 - 0.1 / h, va="top",
                 fontsize=10)
    grid = fig.add_gridspec(len(names), 2, left=0.95 / w, right=1 - 0.15 / w, bottom=0.5 / h, top=1 - 0.65 / h,
                            hspace=0.5, wspace=0.22)
    first = None
    for j in rows:
        n, d = names[j], worst[j]
        ax = fig.add_subplot(grid[j, 0], sharex=first)
        first = first or ax
        ad = fig.add_subplot(grid[j, 1], sharex=first)
        unit = units.get(n, "") or "1"
        ax.plot(ref.time, ref[n], color="0.6", lw=2.5, label=labels[1])
        ax.plot(t, a[:, j], color="C0", lw=1.0, label=labels[0])
        ax.set_title(n, fontsize=9, y=1.0)  # short: placed without measuring the tick labels (as above)
        ax.set_ylabel(f"[{unit}]", fontsize=8)
        ad.plot(t, a[:, j] - b[:, j], color="C3", lw=1.0)
        # a long title: matplotlib lifts it above the y axis's offset text (1e-7) where they would overlap
        ad.set_title(f"{labels[0]} - {labels[1]}: max {d.max_abs:.2e} {unit} ({d.relative:.1e} of range)", fontsize=9)
        ad.set_ylabel(f"error [{unit}]", fontsize=8)
        for x in (ax, ad):
            x.grid(alpha=0.3)
            if j == len(names) - 1:
                x.set_xlabel("time [s]")
            else:  # one time axis for the column: its tick labels under the last row only
                x.xaxis.set_tick_params(which="both", labelbottom=False)
                x.xaxis.offsetText.set_visible(False)
        if j == 0:
            ax.legend(fontsize=8)
    return fig


def plot_comparison(test: Trace, ref: Trace, diffs, path: Path, *, labels: tuple[str, str] = ("test", "reference"),
                    most: int = 8, units: Mapping[str, str] | None = None) -> Path:
    """PNG of :func:`comparison_figure`."""
    return _save(comparison_figure(test, ref, diffs, labels=labels, most=most, units=units), path)


def comparison_rows(diffs, most: int = 8) -> int:
    """How many rows :func:`comparison_figure` has."""
    return min(most, len(diffs))


def comparison_part(test: Trace, ref: Trace, diffs, rows: range, *, labels: tuple[str, str] = ("test", "reference"),
                    most: int = 8, units: Mapping[str, str] | None = None) -> tuple[np.ndarray, int, str]:
    """Rows ``rows`` of :func:`plot_comparison`'s figure rendered at its size and resolution, for
    :func:`join_comparison`: (RGBA pixels, the pixel row 10 px below the axes of the row above
    ``rows`` (0 for the first), the PNG's Software text).  Two parts drawn in two processes
    halve the time of the last figure of the main job."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = comparison_figure(test, ref, diffs, labels=labels, most=most, units=units, rows=rows)
    fig.set_dpi(DPI)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    split = 0
    if rows.start:
        above = fig.axes[0].get_subplotspec().get_gridspec()[rows.start - 1, 0].get_position(fig)
        split = round((1 - above.y0) * fig.bbox.height) + 10  # below the x ticks (no labels), above the titles
    return np.asarray(canvas.buffer_rgba()).copy(), split, f"Matplotlib version{matplotlib.__version__}, https://matplotlib.org/"


def join_comparison(parts: Sequence[tuple[np.ndarray, int, str]], path: Path) -> Path:
    """The PNG of :func:`plot_comparison` from its :func:`comparison_part` (in row order): each
    part's pixels from its split row to the next part's; the file is the one ``plot_comparison``
    writes (same pixels, same PNG text and resolution)."""
    from PIL import Image, PngImagePlugin


    bounds = [p[1] for p in parts[1:]]
    rgba = np.concatenate([p[0][lo:hi] for p, lo, hi in zip(parts, [0, *bounds], [*bounds, None])])
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", parts[0][2])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with staged(path) as part:
        Image.fromarray(rgba).save(part, format="png", pnginfo=info, dpi=(DPI, DPI))
    return path


#: Resolution of the PNGs [dots per inch].
DPI = 90


def _save(fig, path: Path) -> Path:
    return save_figure(fig, path, dpi=DPI)


def save_figure(fig, path: Path, *, dpi: int | str = 90) -> Path:
    """Write ``fig`` to ``path`` complete or not at all (a temporary name moved into place,
    :func:`cosim.outputs.staged`, never through a link planted under that name) and close it."""
    import matplotlib.pyplot as plt


    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with staged(path) as part:  # complete or not at all, never through a link
            fig.savefig(part, dpi=dpi)
    finally:
        plt.close(fig)
    return path
