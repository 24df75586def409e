"""Workspace, singularity and dexterity (DSI) analysis of a 3-RPR design (thesis.md §2, thesis Ch. 4).

Everything here is numpy over grids, evaluating the CasADi expressions of
:mod:`models.kinematics` through :func:`models.kinematics.numpy_map` (``"dexterity"`` gives
``det J``, the DSI ``(mu, mu_x, mu_y, mu_phi)`` and the leg lengths ``L``); no equation of the
manipulator is written again in this module.

Conventions
-----------
- Poses and grid coordinates are in metres; ``phi`` [rad] is held constant (constant-orientation
  workspace).
- ``length_scale`` is the factor applied to the rotational column of ``J`` (thesis.md §2): 100 gives the
  centimetre-unit maps of Chapter 4 (``det J``, ``mu`` and ``mu_phi`` in cm; ``mu_x``, ``mu_y``
  are unitless).  :data:`THESIS_LENGTH_SCALE` is that value.
- A map is a 2-D array indexed ``[row, column] = [y, x]``; points outside the workspace hold NaN.
- The thesis grid is N x N points over ``[-0.6, 0.6)`` m with step ``1.2 / N`` m, and its
  "average" is the mean over x-columns of the per-column mean over workspace points (Matlab
  ``nanmean(nanmean(M))``), see :func:`thesis_average`.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .geometry import GeometryError, Manipulator, custom, preset
from .kinematics import numpy_map

#: Factor on the rotational Jacobian column for the centimetre maps of Chapter 4.
THESIS_LENGTH_SCALE = 100.0
#: Half width [m] of the thesis's square window ``[-0.6, 0.6)``.
THESIS_HALF_WIDTH = 0.6
#: Grid size used by the thesis for Table 4.5, per configuration (thesis.md §2).
THESIS_GRID = {"config1": 500, "config2": 500, "config3": 800, "config4": 500}
#: The four configurations of Table 4.2, in the thesis's order.
CONFIGURATIONS = ("config1", "config2", "config3", "config4")
#: Platform-to-base ratios of Table 4.9.
PLATFORM_RATIOS = tuple(round(0.1 * k, 1) for k in range(1, 13))
#: Base side [m] of the platform-size study (Table 4.9).
PLATFORM_STUDY_SIDE = 0.30
#: Default grid of the platform-size study: the thesis does not state it; on a 1 cm grid
#: (N = 120) the highest x and y DSI of Table 4.9 reproduce to <= 0.28 % (the maxima lie on the
#: workspace boundary, so they move by a few 0.01 % with the grid; finer grids give <= 0.33 %).
PLATFORM_STUDY_GRID = 120
#: Names of the four DSI maps, in the order of ``numpy_map("dexterity")``'s ``dsi`` output.
DSI_NAMES = ("mu", "mu_x", "mu_y", "mu_phi")
#: Largest grid side accepted (8 maps of N x N doubles: about 1 GB at N = 4000).
MAX_GRID = 4000


# --- grids ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Grid:
    """A rectangular grid of sample points: ``x`` [m] along columns, ``y`` [m] along rows.

    Each point stands for one cell of area ``step_x * step_y`` (the thesis's grid samples the
    lower-left corner of each cell of ``[-0.6, 0.6)²``).
    """

    x: np.ndarray
    y: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """``(len(y), len(x))``: the shape of a map on this grid."""
        return len(self.y), len(self.x)

    @property
    def step_x(self) -> float:
        return float(self.x[1] - self.x[0])

    @property
    def step_y(self) -> float:
        return float(self.y[1] - self.y[0])

    @property
    def cell_area(self) -> float:
        """Area [m²] represented by one grid point."""
        return self.step_x * self.step_y

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` [m]: the window covered by the cells."""
        return (float(self.x[0]), float(self.x[-1]) + self.step_x,
                float(self.y[0]), float(self.y[-1]) + self.step_y)


def _check_grid_size(n: int) -> int:
    if isinstance(n, bool) or int(n) != n or not 2 <= int(n) <= MAX_GRID:
        raise GeometryError(f"grid size must be a whole number in 2..{MAX_GRID}, got {n!r}")
    return int(n)


def thesis_grid(n: int, half_width: float = THESIS_HALF_WIDTH) -> Grid:
    """The thesis's N x N grid over ``[-half_width, half_width)`` [m], step ``2 half_width / N``."""
    n = _check_grid_size(n)
    if not (math.isfinite(half_width) and half_width > 0):
        raise GeometryError(f"grid half width must be a positive length in m, got {half_width!r}")
    axis = -half_width + (2.0 * half_width / n) * np.arange(n)
    return Grid(axis, axis.copy())


# --- evaluation of the kinematic maps ----------------------------------------------------------
def _evaluate(m: Manipulator, x, y, phi: float, length_scale: float):
    """``numpy_map("dexterity")`` on broadcastable coordinate arrays: ``det, dsi[4], L[3]``."""
    if not math.isfinite(phi):
        raise GeometryError(f"orientation phi must be a finite angle in rad, got {phi!r}")
    det, dsi, L = numpy_map("dexterity", float(length_scale))([x, y, float(phi)], list(m.geometry_vector()))
    return det[0], dsi, L


def within_stroke(m: Manipulator, L: np.ndarray) -> np.ndarray:
    """True where all three leg lengths ``L`` (leading axis of size 3) lie in ``[Lmin, Lmax]``."""
    return np.all((L >= m.Lmin) & (L <= m.Lmax), axis=0)


def workspace_mask(m: Manipulator, grid: Grid, phi: float = 0.0) -> np.ndarray:
    """Boolean map of the constant-orientation workspace: all legs within the stroke."""
    _, _, L = _evaluate(m, grid.x[None, :], grid.y[:, None], phi, 1.0)
    return within_stroke(m, L)


def workspace_area_grid(m: Manipulator, grid: Grid, phi: float = 0.0) -> float:
    """Workspace area [m²] on a grid: number of workspace points times the cell area."""
    return float(np.count_nonzero(workspace_mask(m, grid, phi))) * grid.cell_area


@dataclass(frozen=True)
class AreaEstimate:
    """A Monte Carlo area [m²] with its standard error [m²], from ``hits`` of ``n`` uniform samples
    in the rectangle ``box = (x0, x1, y0, y1)`` [m]."""

    area: float
    stderr: float
    n: int
    hits: int
    box: tuple[float, float, float, float]


def reach_box(m: Manipulator, phi: float = 0.0) -> tuple[float, float, float, float]:
    """A rectangle ``(x0, x1, y0, y1)`` [m] that contains the whole workspace at orientation phi.

    Leg i ends at ``C = A_i - b_i + d_i`` with ``|d_i| <= Lmax``, so C lies in the disc of radius
    Lmax about ``A_i - b_i`` for every i; the box is the intersection of the three discs' boxes.
    ``A_i - b_i`` is the pose at which leg i has zero length, read off the leg lengths map.
    """
    centres = _zero_length_points(m, phi)
    lo = np.max(centres - m.Lmax, axis=0)
    hi = np.min(centres + m.Lmax, axis=0)
    if np.any(hi <= lo):
        return (0.0, 0.0, 0.0, 0.0)
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _zero_length_points(m: Manipulator, phi: float) -> np.ndarray:
    """Centres ``P_i = A_i - b_i(phi)`` [m], shape (3, 2), from the leg vectors at the origin.

    Leg length is ``|C - P_i|``; with the unit poses ``C = 0, e_x, e_y`` the squared lengths give
    ``P_i`` exactly: ``|P|² = L0²``, ``L_x² = L0² - 2 P_x + 1``, ``L_y² = L0² - 2 P_y + 1``.
    """
    _, _, L = _evaluate(m, np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), phi, 1.0)
    L2 = L ** 2
    px = (L2[:, 0] - L2[:, 1] + 1.0) / 2.0
    py = (L2[:, 0] - L2[:, 2] + 1.0) / 2.0
    return np.stack([px, py], axis=1)


def workspace_area_monte_carlo(m: Manipulator, n: int, phi: float = 0.0,
                               rng: np.random.Generator | int | None = 0,
                               box: tuple[float, float, float, float] | None = None) -> AreaEstimate:
    """Workspace area [m²] by ``n`` uniform random points in ``box`` (default :func:`reach_box`).

    ``area = |box| hits / n`` with standard error ``|box| sqrt(p (1 - p) / n)``, ``p = hits / n``.
    """
    if isinstance(n, bool) or int(n) != n or int(n) < 1:
        raise GeometryError(f"Monte Carlo sample count must be a whole number >= 1, got {n!r}")
    n = int(n)
    box = reach_box(m, phi) if box is None else tuple(float(v) for v in box)
    x0, x1, y0, y1 = box
    size = (x1 - x0) * (y1 - y0)
    if size <= 0:
        return AreaEstimate(0.0, 0.0, n, 0, box)
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    hits = 0
    for start in range(0, n, 1 << 18):  # bounded memory for large n
        k = min(1 << 18, n - start)
        px, py = gen.uniform(x0, x1, k), gen.uniform(y0, y1, k)
        _, _, L = _evaluate(m, px, py, phi, 1.0)
        hits += int(np.count_nonzero(within_stroke(m, L)))
    p = hits / n
    return AreaEstimate(size * p, size * math.sqrt(p * (1.0 - p) / n), n, hits, box)


# --- dexterity maps -----------------------------------------------------------------------------
@dataclass
class DexterityMaps:
    """det J and the four DSI maps of one design on one grid at orientation ``phi`` [rad].

    Every map has ``grid.shape`` and holds NaN outside the workspace.  With
    ``length_scale = 100`` the rotational quantities (``det``, ``mu``, ``mu_phi``) are in
    centimetre units, as in the thesis.
    """

    design: Manipulator
    grid: Grid
    phi: float
    length_scale: float
    inside: np.ndarray
    det: np.ndarray
    mu: np.ndarray
    mu_x: np.ndarray
    mu_y: np.ndarray
    mu_phi: np.ndarray

    @property
    def area(self) -> float:
        """Workspace area [m²] on the grid (points times cell area)."""
        return float(np.count_nonzero(self.inside)) * self.grid.cell_area

    @property
    def clipped(self) -> bool:
        """True when the workspace touches the window's edge (it may extend beyond the grid)."""
        w = self.inside
        return bool(w[0].any() or w[-1].any() or w[:, 0].any() or w[:, -1].any())

    def map(self, name: str) -> np.ndarray:
        """The map called ``"det"`` or one of :data:`DSI_NAMES`."""
        if name not in ("det",) + DSI_NAMES:
            raise KeyError(f"unknown map {name!r}; expected det or one of {', '.join(DSI_NAMES)}")
        return getattr(self, name)


def dexterity_maps(m: Manipulator, grid: Grid, phi: float = 0.0,
                   length_scale: float = THESIS_LENGTH_SCALE) -> DexterityMaps:
    """det J and the DSI ``mu, mu_x, mu_y, mu_phi`` over ``grid`` at orientation ``phi`` [rad]."""
    det, dsi, L = _evaluate(m, grid.x[None, :], grid.y[:, None], phi, length_scale)
    inside = within_stroke(m, L)
    outside = ~inside
    maps = {}
    for name, values in zip(("det",) + DSI_NAMES, (det, *dsi)):
        if values.shape != inside.shape:  # a map constant over the grid comes back unbroadcast
            values = np.array(np.broadcast_to(values, inside.shape), dtype=float)
        values[outside] = np.nan
        maps[name] = values
    return DexterityMaps(m, grid, float(phi), float(length_scale), inside, **maps)


def thesis_average(values: np.ndarray) -> float:
    """Matlab's ``nanmean(nanmean(M))``: the mean over columns of each column's mean over its
    non-NaN entries; columns with no entry are skipped.  NaN when no entry at all."""
    ok = ~np.isnan(values)
    counts = ok.sum(axis=0)
    sums = np.where(ok, values, 0.0).sum(axis=0)
    used = counts > 0
    if not used.any():
        return math.nan
    return float(np.mean(sums[used] / counts[used]))


def highest(values: np.ndarray) -> float:
    """Largest non-NaN entry (NaN when there is none)."""
    ok = ~np.isnan(values)
    return float(np.max(values[ok])) if ok.any() else math.nan


# --- tables -------------------------------------------------------------------------------------
#: Columns of a DSI summary row (Table 4.5 / 4.9 order): highest then average of each index.
SUMMARY_COLUMNS = ("mu_max", "mu_avg", "mu_x_max", "mu_x_avg", "mu_y_max", "mu_y_avg",
                   "mu_phi_max", "mu_phi_avg")


@dataclass(frozen=True)
class DSISummary:
    """Highest and average (thesis rule) of the four DSI over the workspace of one design.

    ``name``: design name; ``grid_n``: grid side; ``phi`` [rad]; ``area`` [m²] (grid);
    ``values``: one number per :data:`SUMMARY_COLUMNS` entry (cm units for ``mu`` and ``mu_phi``
    when ``length_scale = 100``); ``clipped``: the workspace touches the grid window.
    """

    name: str
    grid_n: int
    phi: float
    area: float
    values: dict[str, float] = field(default_factory=dict)
    clipped: bool = False

    def __getitem__(self, column: str) -> float:
        return self.values[column]


def summarize(maps: DexterityMaps, name: str | None = None) -> DSISummary:
    """Table 4.5 numbers of some maps: highest and :func:`thesis_average` of each DSI."""
    values: dict[str, float] = {}
    for index in DSI_NAMES:
        values[f"{index}_max"] = highest(maps.map(index))
        values[f"{index}_avg"] = thesis_average(maps.map(index))
    return DSISummary(name or maps.design.name, maps.grid.shape[1], maps.phi, maps.area, values, maps.clipped)


def table_4_5_row(m: Manipulator, n: int | None = None, phi: float = 0.0,
                  length_scale: float = THESIS_LENGTH_SCALE) -> DSISummary:
    """The Table 4.5 column of one design: highest / average overall, x, y and rotational DSI on
    the thesis grid (``n`` defaults to :data:`THESIS_GRID` for a preset name, else 500)."""
    n = THESIS_GRID.get(m.name, 500) if n is None else n
    return summarize(dexterity_maps(m, thesis_grid(n), phi, length_scale))


def compare_configurations(names: Sequence[str] = CONFIGURATIONS, n: int | None = None, phi: float = 0.0,
                           length_scale: float = THESIS_LENGTH_SCALE) -> list[DSISummary]:
    """Table 4.5 for the named presets (configs 1, 2, 4 on N = 500 and config 3 on N = 800
    unless ``n`` is given)."""
    rows = []
    for name in names:
        m = preset(name)
        rows.append(table_4_5_row(m, THESIS_GRID.get(name, 500) if n is None else n, phi, length_scale))
    return rows


@dataclass(frozen=True)
class PlatformSizeRow:
    """One row of Table 4.9: ``ratio`` = Lmp / base side, ``Lmp`` [m], and the DSI summary."""

    ratio: float
    Lmp: float
    summary: DSISummary


def platform_size_study(ratios: Iterable[float] = PLATFORM_RATIOS, side: float = PLATFORM_STUDY_SIDE,
                        n: int = PLATFORM_STUDY_GRID, phi: float = 0.0, pairing: str = "cross",
                        length_scale: float = THESIS_LENGTH_SCALE) -> list[PlatformSizeRow]:
    """Table 4.9: the DSI summary of a ``side`` [m] equilateral base with platform side
    ``Lmp = ratio * side``, for each ratio (default 0.1 ... 1.2, cross pairing, phi = 0)."""
    grid = thesis_grid(n)
    rows = []
    for ratio in ratios:
        ratio = float(ratio)
        if not (math.isfinite(ratio) and ratio > 0):
            raise GeometryError(f"platform ratio must be positive, got {ratio!r}")
        m = custom(side, Lmp=ratio * side, pairing=pairing, name=f"ratio {ratio:g}")
        rows.append(PlatformSizeRow(ratio, ratio * side, summarize(dexterity_maps(m, grid, phi, length_scale))))
    return rows


# --- singularity curves ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SingularityLocus:
    """The level set ``det J = 0`` on a grid, as straight segments (marching squares).

    ``segments``: shape (k, 2, 2), ``segments[j] = [[x0, y0], [x1, y1]]`` [m].
    ``everywhere``: det J vanishes (to rounding) on the whole workspace, e.g. the homothetic
    configurations at phi = 0; then no curve is drawn (``segments`` is empty).
    """

    segments: np.ndarray
    everywhere: bool

    @property
    def length(self) -> float:
        """Total length [m] of the curves."""
        d = self.segments[:, 1] - self.segments[:, 0]
        return float(np.hypot(d[:, 0], d[:, 1]).sum())


def singularity_locus(maps: DexterityMaps, rtol: float = 1e-9) -> SingularityLocus:
    """``det J = 0`` inside the workspace by marching squares on ``maps.det``.

    Only cells whose four corners are workspace points are contoured (NaN corners skip a cell).
    The design counts as singular everywhere when ``|det J| <= rtol * max(mu_x mu_y mu_phi)`` at
    every workspace point (the product of the column norms bounds ``|det J|``, Hadamard).
    """
    det = maps.det
    inside = maps.inside
    if inside.any():
        bound = (maps.mu_x * maps.mu_y * maps.mu_phi)[inside]
        if np.all(np.abs(det[inside]) <= rtol * np.max(bound)):
            return SingularityLocus(np.zeros((0, 2, 2)), True)
    return SingularityLocus(marching_squares(maps.grid.x, maps.grid.y, det), False)


# Edges of a cell: 0 bottom (v00-v01), 1 right (v01-v11), 2 top (v10-v11), 3 left (v00-v10),
# with v[row][col] the corner values; case index = sum of (corner > 0) << bit,
# bits: v00 -> 1, v01 -> 2, v11 -> 4, v10 -> 8.
_CASES = {
    1: ((3, 0),), 2: ((0, 1),), 3: ((3, 1),), 4: ((1, 2),), 6: ((0, 2),), 7: ((3, 2),),
    8: ((2, 3),), 9: ((2, 0),), 11: ((2, 1),), 12: ((1, 3),), 13: ((1, 0),), 14: ((0, 3),),
}


def marching_squares(x: np.ndarray, y: np.ndarray, values: np.ndarray, level: float = 0.0) -> np.ndarray:
    """Segments (k, 2, 2) [x, y] of the contour ``values == level`` on the grid ``x`` (columns),
    ``y`` (rows), linearly interpolated along cell edges.  Cells with a NaN corner are skipped;
    saddle cells (cases 5, 10) are resolved by the mean of the four corners."""
    v = np.asarray(values, dtype=float) - level
    v00, v01, v10, v11 = v[:-1, :-1], v[:-1, 1:], v[1:, :-1], v[1:, 1:]
    valid = ~(np.isnan(v00) | np.isnan(v01) | np.isnan(v10) | np.isnan(v11))
    case = ((v00 > 0).astype(np.int8) | ((v01 > 0) << 1) | ((v11 > 0) << 2) | ((v10 > 0) << 3))
    case = np.where(valid, case, 0)
    rows, cols = np.nonzero((case != 0) & (case != 15))
    if rows.size == 0:
        return np.zeros((0, 2, 2))
    a, b, c, d = v00[rows, cols], v01[rows, cols], v10[rows, cols], v11[rows, cols]
    x0, x1, y0, y1 = x[cols], x[cols + 1], y[rows], y[rows + 1]

    def frac(p, q):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = p / (p - q)
        return np.clip(np.nan_to_num(t, nan=0.5), 0.0, 1.0)

    t0, t1, t2, t3 = frac(a, b), frac(b, d), frac(c, d), frac(a, c)
    edge_pts = np.stack([
        np.stack([x0 + t0 * (x1 - x0), y0], axis=-1),          # bottom
        np.stack([x1, y0 + t1 * (y1 - y0)], axis=-1),          # right
        np.stack([x0 + t2 * (x1 - x0), y1], axis=-1),          # top
        np.stack([x0, y0 + t3 * (y1 - y0)], axis=-1),          # left
    ])  # (4, k, 2)
    k = np.arange(rows.size)
    cs = case[rows, cols]
    centre_pos = (a + b + c + d) > 0
    segs = []
    for code, pairs in _CASES.items():
        sel = k[cs == code]
        for e0, e1 in pairs:
            segs.append(np.stack([edge_pts[e0, sel], edge_pts[e1, sel]], axis=1))
    # saddles: 5 = v00, v11 positive; 10 = v01, v10 positive
    # (a positive centre joins the positive corners and cuts off the negative ones)
    for code, joined, split in ((5, ((0, 1), (2, 3)), ((3, 0), (1, 2))),
                                (10, ((3, 0), (1, 2)), ((0, 1), (2, 3)))):
        for pairs, mask in ((joined, centre_pos), (split, ~centre_pos)):
            sel = k[(cs == code) & mask]
            for e0, e1 in pairs:
                segs.append(np.stack([edge_pts[e0, sel], edge_pts[e1, sel]], axis=1))
    return np.concatenate(segs, axis=0)
