"""Presentation of the design analysis (:mod:`models.analysis`): aligned text tables, CSV files
and PNG figures (matplotlib, Agg canvas; no pyplot state).

A :class:`Table` is plain data (title, column headings, rows of cells); :func:`format_table`
prints it and :func:`write_csv` saves it.  Heat maps leave the outside of the workspace blank
(NaN cells are transparent on a white figure) and overlay the singularity curves ``det J = 0``.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models import analysis as A
from .tables import text_table
from ..outputs import staged
from .charts import save_figure

Cell = str | float | int | None


@dataclass
class Table:
    """A titled table: ``columns`` headings and ``rows`` of cells (numbers or text);
    ``keys``: the CSV header (snake_case names), defaults to ``columns``."""

    title: str
    columns: list[str]
    rows: list[list[Cell]]
    keys: list[str] | None = None


def _fmt(value: Cell) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if value != 0 and (abs(value) < 1e-3 or abs(value) >= 1e6):
            return f"{value:.4e}"
        return f"{value:.5g}"
    return str(value)


def format_table(table: Table) -> str:
    """The table as aligned text: text columns left-aligned, numbers right-aligned."""

    cells = [[_fmt(v) for v in row] for row in table.rows]
    numeric = [all(isinstance(row[k], (int, float)) and not isinstance(row[k], bool) for row in table.rows
                   if row[k] is not None) for k in range(len(table.columns))]
    return table.title + "\n" + text_table(table.columns, cells, right=numeric, indent=0, rules=True)


def write_csv(table: Table, path: Path) -> Path:
    """Save the table as CSV with a header row (numbers at full precision), complete or not at
    all and never through a link (:func:`cosim.outputs.staged`)."""

    with staged(path) as part, open(part, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(table.keys or table.columns)
        for row in table.rows:
            w.writerow(["" if v is None else (repr(v) if isinstance(v, float) else v) for v in row])
    return path


# --- tables of the analysis ------------------------------------------------------------------------
_INDEX_LABELS = {"mu": "overall DSI", "mu_x": "DSI in x", "mu_y": "DSI in y", "mu_phi": "rotational DSI"}


def configurations_table(rows: Sequence[A.DSISummary], unit: str = "cm") -> Table:
    """Table 4.5 layout: one column per design, one row per highest/average index."""
    title = (f"Highest and average DSI over the workspace (Table 4.5; overall and rotational DSI in "
             f"{unit}; average = mean over x-columns of the column means)")
    out: list[list[Cell]] = []
    for index in A.DSI_NAMES:
        for kind, word in (("max", "highest"), ("avg", "average")):
            out.append([f"{word} {_INDEX_LABELS[index]}"] + [r[f"{index}_{kind}"] for r in rows])
    out.append(["grid N"] + [r.grid_n for r in rows])
    out.append(["phi (rad)"] + [r.phi for r in rows])
    out.append(["workspace area (m^2)"] + [r.area for r in rows])
    return Table(title, ["index"] + [r.name for r in rows], out)


def configurations_csv_table(rows: Sequence[A.DSISummary]) -> Table:
    """Table 4.5 as one CSV row per design."""
    cols = ["config", "grid_n", "phi_rad", "area_m2", *A.SUMMARY_COLUMNS, "clipped"]
    return Table("DSI by configuration", cols,
                 [[r.name, r.grid_n, r.phi, r.area, *(r[c] for c in A.SUMMARY_COLUMNS), r.clipped] for r in rows])


def platform_size_table(rows: Sequence[A.PlatformSizeRow], side: float, n: int, unit: str = "cm") -> Table:
    """Table 4.9 layout: one row per platform-to-base ratio."""
    cols = ["ratio", f"Lmp ({unit})", "highest mu", "average mu", "highest mu_x", "average mu_x",
            "highest mu_y", "average mu_y", "highest mu_phi", "average mu_phi", "area (m^2)"]
    scale = 100.0 if unit == "cm" else 1.0
    body = [[r.ratio, r.Lmp * scale, *(r.summary[c] for c in A.SUMMARY_COLUMNS), r.summary.area] for r in rows]
    title = (f"Platform size study (Table 4.9): base side {side * scale:g} {unit}, grid {n}x{n}, "
             f"phi = {rows[0].summary.phi:g} rad (mu = |det J| and mu_phi in {unit})" if rows else "Platform size study")
    keys = ["ratio", f"Lmp_{unit}", *A.SUMMARY_COLUMNS, "area_m2"]
    return Table(title, cols, body, keys)


@dataclass
class WorkspaceResult:
    """One mapped design: its maps, singularity locus and optional Monte Carlo area."""

    label: str
    maps: A.DexterityMaps
    locus: A.SingularityLocus
    monte_carlo: A.AreaEstimate | None = None


def workspace_table(results: Sequence[WorkspaceResult]) -> Table:
    """Workspace area (grid and Monte Carlo), det J range and singularity curves per design."""
    cols = ["config", "phi (rad)", "grid N", "area grid (m^2)", "area MC (m^2)", "MC std err (m^2)",
            "MC samples", "det J min", "det J max", "det J = 0", "curve length (m)", "clipped"]
    rows: list[list[Cell]] = []
    for r in results:
        det = r.maps.det[r.maps.inside]
        if r.locus.everywhere:
            sing, length = "everywhere", None
        else:
            sing, length = ("curves" if r.locus.segments.size else "nowhere"), r.locus.length
        mc = r.monte_carlo
        rows.append([r.label, r.maps.phi, r.maps.grid.shape[1], r.maps.area,
                     mc.area if mc else None, mc.stderr if mc else None, mc.n if mc else None,
                     float(det.min()) if det.size else None, float(det.max()) if det.size else None,
                     sing, length, r.maps.clipped])
    keys = ["config", "phi_rad", "grid_n", "area_grid_m2", "area_mc_m2", "area_mc_stderr_m2", "mc_samples",
            "det_min", "det_max", "singular", "singular_curve_length_m", "clipped"]
    return Table("Constant-orientation workspace and singularity (det J in cm units)", cols, rows, keys)


# --- figures -------------------------------------------------------------------------------------------
_MAP_FILES = {"det": "detJ", "mu": "dsi_overall", "mu_x": "dsi_x", "mu_y": "dsi_y", "mu_phi": "dsi_rot"}


def _unit(length_scale: float) -> str:
    return {100.0: "cm", 1.0: "m", 1000.0: "mm"}.get(float(length_scale), f"m/{length_scale:g}")


def _map_label(name: str, unit: str) -> str:
    return {"det": f"det J ({unit})", "mu": f"overall DSI  mu = |det J| ({unit})", "mu_x": "DSI in x  mu_x",
            "mu_y": "DSI in y  mu_y", "mu_phi": f"rotational DSI  mu_phi ({unit})"}[name]


def _figure(width: float = 6.4, height: float = 5.2):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def save_map(result: WorkspaceResult, name: str, path: Path) -> Path:
    """One heat map (``"det"`` or a DSI name) as PNG: blank outside the workspace, singularity
    curves in black, axes in cm."""
    import matplotlib
    from matplotlib.collections import LineCollection

    maps = result.maps
    unit = _unit(maps.length_scale)
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    cmap = matplotlib.colormaps["RdBu_r" if name == "det" else "viridis"].with_extremes(bad=(1.0, 1.0, 1.0, 0.0))
    data = np.ma.masked_invalid(maps.map(name))
    # pixels centred on the grid points, so the image and the singularity curves line up
    hx, hy = maps.grid.step_x / 2, maps.grid.step_y / 2
    x0, x1 = 100.0 * (maps.grid.x[0] - hx), 100.0 * (maps.grid.x[-1] + hx)
    y0, y1 = 100.0 * (maps.grid.y[0] - hy), 100.0 * (maps.grid.y[-1] + hy)
    kw = {}
    if name == "det" and data.count():
        lim = float(np.max(np.abs(data))) or 1.0
        kw = {"vmin": -lim, "vmax": lim}
    im = ax.imshow(data, origin="lower", extent=(x0, x1, y0, y1), cmap=cmap, interpolation="nearest", **kw)
    fig.colorbar(im, ax=ax, label=_map_label(name, unit))
    if result.locus.segments.size:
        ax.add_collection(LineCollection(100.0 * result.locus.segments,
                                         colors="black" if name == "det" else "red", linewidths=1.0,
                                         label="det J = 0"))
        ax.legend(loc="upper right", fontsize=8)
    note = "  [det J = 0 throughout]" if result.locus.everywhere else ""
    ax.set_title(f"{result.label}: {_map_label(name, unit).split('  ')[0]}, phi = {maps.phi:g} rad{note}",
                 fontsize=10)
    ax.set_xlabel("X position (cm)")
    ax.set_ylabel("Y position (cm)")
    ax.set_aspect("equal")

    save_figure(fig, path, dpi="figure")
    return path


def save_maps(result: WorkspaceResult, out: Path, stem: str | None = None) -> list[Path]:
    """det J and the four DSI heat maps of one design: ``<stem>_detJ.png``, ``<stem>_dsi_overall.png``,
    ``<stem>_dsi_x.png``, ``<stem>_dsi_y.png``, ``<stem>_dsi_rot.png``."""
    stem = stem or result.label
    return [save_map(result, name, out / f"{stem}_{suffix}.png") for name, suffix in _MAP_FILES.items()]


def save_platform_figures(rows: Sequence[A.PlatformSizeRow], out: Path) -> list[Path]:
    """Figures 4.10 and 4.11: highest and average DSI in x and y against Lmp / base side."""
    ratios = [r.ratio for r in rows]
    paths = []
    for kind, word, fname in (("max", "Highest", "platform_size_highest.png"),
                              ("avg", "Average", "platform_size_average.png")):
        fig = _figure(6.4, 4.4)
        ax = fig.add_subplot(1, 1, 1)
        for index, marker, label in (("mu_x", "o", "DSI X"), ("mu_y", "s", "DSI Y")):
            ax.plot(ratios, [r.summary[f"{index}_{kind}"] for r in rows], marker=marker, label=f"{word} {label}")
        ax.set_xlabel("Ratio Lmp / base side")
        ax.set_ylabel("DSI")
        ax.set_title(f"{word} values of the x and y DSI vs platform size")
        ax.grid(True, alpha=0.3)
        ax.legend()
        fig.tight_layout()
        paths.append(out / fname)

        save_figure(fig, paths[-1], dpi="figure")
    return paths
