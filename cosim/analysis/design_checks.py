"""Chapter 8's design checks as a report (``rpr-cosim design``): the thesis's own numbers, then the
same checks under the loads a task or a recorded run produces.

Loads of a motion (:class:`Loads`): per leg the axial force ``F`` [N], length ``L`` [m] and speed
``v`` [m/s] over time.  From a task they come from the virtual-work inverse dynamics along the
planned motion (plus the lumped actuator mass); from a trace, from the recorded
``<mech>.leg[i].f`` / ``.s`` / ``.v`` columns, end-stop impacts included where the scene has them.
The fixed joint's horizontal force is the largest leg force and its weight moment the thesis's
(:func:`models.mechanical_design.weight_moment`) at the closest pose along the motion; the
largest bending moment is also computed at every instant (for the plot), and the load over time
is drawn against the moment the chosen shaft may carry.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models import mechanical_design as D
from models.geometry import Manipulator
from models.trajectory import Drive

from .design_views import Table
from models.trajectory import TrajectoryError, leg_profile, sample_times
from ..errors import UserError
from .charts import save_figure
from .design_views import _figure

#: The printed values of Chapter 8 (docs/explanation/design-checks.md) and the digits they are printed to.
PRINTED = {
    "F1": (504.92, 2), "F2": (404.92, 2), "M_max": (26.32, 2), "M_e": (26.36, 2),
    "sigma_allowed": (210.0, 0), "d_min": (10.9, 1), "clamp": (166.67, 2),
}


@dataclass
class Loads:
    """A motion's loads: ``t`` [s] (n,), and per leg (3, n) force ``F`` [N], length ``L`` [m],
    speed ``v`` [m/s]; ``label`` names the task or trace."""

    label: str
    t: np.ndarray
    F: np.ndarray
    L: np.ndarray
    v: np.ndarray


def loads_from_task(task, label: str, dt: float = 1e-3) -> Loads:
    """Loads along a planned task (:class:`models.task.Task`), sampled every ``dt`` [s]."""


    try:
        traj = task.plan()
    except TrajectoryError as exc:
        raise UserError(f"{label}: {exc}") from None
    t = sample_times(traj, dt=dt)
    prof = leg_profile(task.manipulator, traj, t, task.limits)
    return Loads(label, t, prof["F"], prof["L"], prof["Ld"])


def loads_from_trace(trace, label: str) -> Loads:
    """Loads from a recorded run: the first component with ``leg[1..3].f`` and ``.s`` columns."""

    for col in trace.columns:
        mt = re.fullmatch(r"(.+)\.leg\[1\]\.f", col)
        if mt and all(f"{mt[1]}.leg[{i}].{k}" in trace for i in (1, 2, 3) for k in ("f", "s")):
            p = mt[1]
            F = np.array([trace[f"{p}.leg[{i}].f"] for i in (1, 2, 3)])
            L = np.array([trace[f"{p}.leg[{i}].s"] for i in (1, 2, 3)])
            if all(f"{p}.leg[{i}].v" in trace for i in (1, 2, 3)):
                v = np.array([trace[f"{p}.leg[{i}].v"] for i in (1, 2, 3)])
            else:
                v = np.gradient(L, trace.time, axis=1)
            return Loads(label, trace.time, F, L, v)
    raise UserError(f"{label}: the trace records no leg forces and lengths (<component>.leg[1..3].f and .s); "
                    "add mech.leg[*].f and mech.leg[*].s to the scene's outputs")


@dataclass
class DesignCase:
    """One column of the report: its label, the shaft check and the actuator's peaks."""

    label: str
    shaft: D.ShaftCheck
    M_w_furthest: float
    force: float | None = None
    speed: float | None = None
    power: float | None = None


def thesis_case() -> DesignCase:
    """The thesis's own inputs (Section 8.1.2, Table 8.1)."""
    return DesignCase("thesis inputs", D.check_shaft(), D.WEIGHT_MOMENT_FURTHEST)


def task_case(loads: Loads, m: Manipulator) -> DesignCase:
    """Chapter 8's checks under a motion's loads (module docstring)."""
    F_h = float(np.max(np.abs(loads.F)))
    M_close = float(np.max(D.weight_moment(loads.L, m.Lmin, m.Lmax)))
    M_far = float(np.min(D.weight_moment(loads.L, m.Lmin, m.Lmax)))
    shaft = D.check_shaft(D.ShaftLoads(F_h=F_h, M_w=M_close))
    return DesignCase(loads.label, shaft, M_far, F_h, float(np.max(np.abs(loads.v))),
                      float(np.max(np.abs(loads.F * loads.v))))


def _margin(limit: float, value: float | None) -> float | None:
    if value is None:
        return None
    return math.inf if value == 0 else limit / value - 1.0


def design_table(cases: list[DesignCase], drive: Drive) -> Table:
    """Every quantity of Chapter 8 (rows) for each case (columns), with the margins."""
    rows: list[list] = []

    def row(name: str, unit: str, values, printed=None):
        rows.append([name, unit, printed] + list(values))

    P = PRINTED
    row("horizontal force F_h", "N", [c.shaft.loads.F_h for c in cases], 100.0)
    row("weight moment, closest pose", "N m", [c.shaft.loads.M_w for c in cases], D.WEIGHT_MOMENT_CLOSEST)
    row("weight moment, furthest pose", "N m", [c.M_w_furthest for c in cases], D.WEIGHT_MOMENT_FURTHEST)
    row("bearing force F1 (Eq. 8.1)", "N", [c.shaft.F1 for c in cases], P["F1"][0])
    row("bearing force F2 (Eq. 8.2)", "N", [c.shaft.F2 for c in cases], P["F2"][0])
    row("largest bending moment", "N m", [c.shaft.M_max for c in cases], P["M_max"][0])
    row("equivalent moment M_e (Eq. 8.3)", "N m", [c.shaft.M_e for c in cases], P["M_e"][0])
    row("permissible stress (Eq. 8.4)", "MPa", [c.shaft.sigma_allowed / 1e6 for c in cases], P["sigma_allowed"][0])
    row("minimum diameter d (Eq. 8.5)", "mm", [c.shaft.d_min * 1e3 for c in cases], P["d_min"][0])
    row("chosen shaft diameter", "mm", [c.shaft.d * 1e3 for c in cases], 15.0)
    row("margin: diameter d / d_min - 1", "-", [c.shaft.diameter_margin for c in cases], None)
    row("stress at 15 mm", "MPa", [c.shaft.stress / 1e6 for c in cases], None)
    row("margin: stress [sigma] / sigma - 1", "-", [c.shaft.stress_margin for c in cases], None)
    row("clamp compression (Section 8.1.5)", "N", [c.shaft.clamp for c in cases], P["clamp"][0])
    row("margin: clamp 166.67 N / needed - 1", "-", [_margin(D.clamp_compression(D.HORIZONTAL_FORCE), c.shaft.clamp)
                                                   for c in cases], None)
    row(f"actuator force (rated {drive.F_max:.4g} N, {drive.name})", "N", [c.force for c in cases], None)
    row("margin: actuator force", "-", [_margin(drive.F_max, c.force) for c in cases], None)
    row(f"actuator speed (no-load {drive.v_nl:.4g} m/s)", "m/s", [c.speed for c in cases], None)
    row("margin: actuator speed", "-", [_margin(drive.v_nl, c.speed) for c in cases], None)
    row(f"actuator power (line's {drive.power:.4g} W)", "W", [c.power for c in cases], None)
    row("margin: actuator power", "-", [_margin(drive.power, c.power) for c in cases], None)
    cols = ["quantity", "unit", "printed"] + [c.label for c in cases]
    keys = ["quantity", "unit", "printed"] + [re.sub(r"\W+", "_", c.label).strip("_") for c in cases]
    return Table("Chapter 8 design checks (fixed-joint shaft, bearings, clamp, actuator)", cols, rows, keys)


def negative_margins(table: Table) -> list[str]:
    """``"<case>: <margin row>"`` for every negative margin in the table."""
    out = []
    for r in table.rows:
        if str(r[0]).startswith("margin"):
            for label, v in zip(table.columns[3:], r[3:]):
                if isinstance(v, float) and v < 0:
                    out.append(f"{label}: {r[0]} = {v:.3g}")
    return out


def shaft_moment_limit(T: float = D.SHAFT_TORQUE, d: float = D.SHAFT_DIAMETER,
                       sigma: float = D.PERMISSIBLE_STRESS) -> float:
    """The largest bending moment [N m] the shaft of diameter ``d`` carries with torque ``T``:
    Eq. 8.5 solved for ``M_e``, then Eq. 8.3 for ``M``: ``M = M_e - T^2 / (4 M_e)``."""
    me = sigma * math.pi * d ** 3 / 32.0
    return me - T ** 2 / (4.0 * me)


def save_load_plot(loads: Loads, m: Manipulator, drive: Drive, path: Path) -> Path:
    """The shaft's largest bending moment and the leg forces over the motion, against their limits."""

    geo = D.ShaftGeometry()
    M = np.abs(loads.F) * (geo.a + geo.b - geo.s) + D.weight_moment(loads.L, m.Lmin, m.Lmax)
    fig = _figure(7.0, 6.4)
    ax1, ax2 = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2, sharex=None)
    for i in range(3):
        ax1.plot(loads.t, M[i], label=f"leg {i + 1}")
        ax2.plot(loads.t, np.abs(loads.F[i]), label=f"leg {i + 1}")
    ax1.axhline(shaft_moment_limit(), color="red", ls="--", label="15 mm shaft's limit")
    ax1.axhline(D.largest_bending_moment(D.ShaftLoads()), color="grey", ls=":", label="thesis design load")
    ax1.set_ylabel("bending moment at bearing 1 [N m]")
    ax1.set_title(f"{loads.label}: fixed-joint shaft and actuator loads", fontsize=10)
    ax1.legend(fontsize=7)
    ax2.axhline(drive.F_max, color="red", ls="--", label=f"{drive.name} force rating")
    ax2.set_ylabel("|leg force| [N]")
    ax2.set_xlabel("time [s]")
    ax2.set_yscale("symlog", linthresh=1.0)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi="figure")
