"""Shared pieces of the catalog's block builders: a parameter collector, the geometry/inertia
parameters of a 3-RPR preset, construction options and "did you mean" suggestions."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import casadi as ca

from ..block import BlockError, Param, Rating
from ..interface import suggest  # noqa: F401  (re-exported for the catalog)
from ..geometry import GEOMETRY_FIELDS, INERTIA_FIELDS, PRESETS, preset

INF = math.inf


class ParamSet:
    """Collects :class:`~models.block.Param` declarations and their SX symbols in order."""

    def __init__(self) -> None:
        self.params: list[Param] = []
        self._syms: list[ca.SX] = []

    def add(self, name: str, default: float, unit: str = "", description: str = "", *,
            lower: float = -INF, upper: float = INF) -> ca.SX:
        """Declare a parameter; returns its scalar symbol."""
        self.params.append(Param(name=name, default=float(default), unit=unit, lower=lower, upper=upper,
                                 description=description))
        sym = ca.SX.sym(name)
        self._syms.append(sym)
        return sym

    def vector(self) -> ca.SX:
        """The parameter vector (column) in declaration order."""
        return ca.vertcat(*self._syms) if self._syms else ca.SX(0, 1)


def geometry_params(ps: ParamSet, config: str) -> ca.SX:
    """Geometry parameters with defaults from the preset ``config``; returns the symbolic geometry
    vector ``g`` in the order of :data:`~models.geometry.GEOMETRY_FIELDS`.

    Parameters are the fixed joints ``A1x .. A3y`` [m], the platform side ``Lmp`` [m] (the vector's
    ``r`` entry is ``Lmp / sqrt(3)``) and the platform joint angles ``a1 .. a3`` [rad]."""
    m = preset(config)
    values = dict(zip(GEOMETRY_FIELDS, m.geometry_vector()))
    g = []
    for f in GEOMETRY_FIELDS:
        if f == "r":
            lmp = ps.add("Lmp", m.Lmp, "m", "platform side (B_i on a circle of radius Lmp/sqrt(3))", lower=0.0)
            g.append(lmp / math.sqrt(3.0))
        elif f.startswith("A"):
            g.append(ps.add(f, values[f], "m", f"fixed joint A{f[1]}, {f[2]} coordinate"))
        else:
            g.append(ps.add(f, values[f], "rad", f"platform joint angle a{f[1]}: B_{f[1]} = C - r (cos(phi + a), "
                                                 f"sin(phi + a))"))
    return ca.vertcat(*g)


_INERTIA_TEXT = {
    "e1": ("m", "cylinder mass centre behind A_i: A_i - e1 s_i"),
    "e2": ("m", "rod mass centre behind B_i: A_i + (L_i - e2) s_i"),
    "m_cyl": ("kg", "cylinder mass"),
    "I_cyl": ("kg.m2", "cylinder moment of inertia about its mass centre"),
    "m_rod": ("kg", "rod mass"),
    "I_rod": ("kg.m2", "rod moment of inertia about its mass centre"),
    "m_p": ("kg", "platform mass"),
    "I_p": ("kg.m2", "platform moment of inertia about C"),
}


def inertia_params(ps: ParamSet, config: str) -> ca.SX:
    """Mass parameters (thesis.md §4, Table 7.1) with the preset's defaults; returns the symbolic
    inertia vector ``m`` in the order of :data:`~models.geometry.INERTIA_FIELDS`."""
    inertia = preset(config).inertia
    syms = []
    for f in INERTIA_FIELDS:
        unit, text = _INERTIA_TEXT[f]
        syms.append(ps.add(f, getattr(inertia, f), unit, text, lower=-INF if f in ("e1", "e2") else 0.0))
    return ca.vertcat(*syms)


def stroke_ratings(config: str, legs: Sequence[int] = (1, 2, 3)) -> dict[str, Rating]:
    """``leg[i].s`` must stay inside the stroke ``[Lmin, Lmax]`` of the preset ``config``
    (thesis.md §1: 0.10-0.60 m)."""
    m = preset(config)
    return {f"leg[{i}].s": Rating(m.Lmin, m.Lmax, "stroke", f"actuator stroke of the {config} preset (thesis.md §1)")
            for i in legs}


@dataclass(frozen=True)
class Option:
    """A construction option of a block: ``choices`` (strings) or a ``check`` on the value."""

    name: str
    default: Any
    description: str
    choices: tuple[str, ...] | None = None
    check: Callable[[Any], str | None] | None = None  # returns an error text or None

    def validate(self, where: str, value: Any) -> Any:
        if self.choices is not None:
            if not isinstance(value, str) or value not in self.choices:
                hint = suggest(value, self.choices) if isinstance(value, str) else ""
                raise BlockError(f"{where}: option {self.name}={value!r} is not valid{hint} "
                                 f"(expected one of {', '.join(self.choices)})")
            return value
        if self.check is not None:
            msg = self.check(value)
            if msg:
                raise BlockError(f"{where}: option {self.name}={value!r} {msg}")
        return value


def positive_int(v: Any) -> str | None:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        return "must be a whole number >= 1"
    return None


def unit_text(v: Any) -> str | None:
    """A unit as written in FMI: symbols, exponents, '.', '/' and parentheses (e.g. ``N.m/rad``)."""
    import re

    if not isinstance(v, str) or not re.fullmatch(r"[A-Za-z0-9.*/()\-]+", v):
        return "must be a unit such as m, V, rad or N.m/rad"
    return None


def positive_float(v: Any) -> str | None:
    if isinstance(v, bool):
        return "must be a positive number"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return "must be a positive number"
    if not (math.isfinite(f) and f > 0):
        return "must be a positive number"
    return None


CONFIG = Option("config", "cross_leg", "geometry preset giving the parameter defaults (models.geometry.PRESETS)",
                choices=tuple(PRESETS))
SUBSTEPS = Option("substeps", 1, "integrator substeps per communication step", check=positive_int)


def solver_params(ps: ParamSet, integrator: str) -> None:
    """Declare the implicit solver's tolerances as tunable parameters ``solver.rtol`` and
    ``solver.atol`` when ``integrator`` is ``radau`` (its Newton acceptance test,
    :func:`models.integrators.radau_accepts`); other integrators have none."""
    from ..integrators import RADAU_ATOL, RADAU_RTOL, SOLVER_ATOL, SOLVER_RTOL
    if integrator == "radau":
        ps.add(SOLVER_RTOL, RADAU_RTOL, "1", "relative tolerance of the Radau Newton iteration", lower=1e-15, upper=1e-2)
        ps.add(SOLVER_ATOL, RADAU_ATOL, "1", "absolute tolerance of the Radau Newton iteration (applied to "
               "each state in its own unit)", lower=1e-20, upper=1.0)


def integrator_option(default: str, choices: tuple[str, ...] = ("rk4", "radau")) -> Option:
    return Option("integrator", default, "embedded integrator of the continuous states", choices=choices)
