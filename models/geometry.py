"""Manipulator description of the 3-RPR planar parallel manipulator (thesis.md §1, §4).

Conventions (SI units):
- Pose of the platform centre C is ``q = (x, y, phi)`` [m, m, rad].
- Fixed joint ``A_i`` is a point in the base frame.
- Platform joint ``B_i = C - r (cos(phi + a_i), sin(phi + a_i))`` with ``r = Lmp / sqrt(3)``.
  The cross pairing uses ``a_i = pi/6, 5pi/6, 3pi/2``; the homothetic pairing
  ``a_i = -pi/6, 7pi/6, pi/2`` puts B_i at the polar angle of A_i.
- Leg i joins ``A_i`` to ``B_i``; its stroke is limited to ``[Lmin, Lmax]``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

CROSS_ANGLES = (math.pi / 6, 5 * math.pi / 6, 3 * math.pi / 2)
#: Homothetic pairing: B_i at the same polar angle about C as A_i about the base centre, so at
#: phi = 0 the platform is a scaled copy of the base and the legs meet in the homothety centre
#: (singular everywhere at phi = 0, thesis.md §1-2).
HOMOTHETIC_ANGLES = (-math.pi / 6, 7 * math.pi / 6, math.pi / 2)

#: Names and order of the flat geometry vector used by the symbolic models.
GEOMETRY_FIELDS = ("A1x", "A1y", "A2x", "A2y", "A3x", "A3y", "r", "a1", "a2", "a3")
#: Names and order of the flat inertia vector used by the symbolic models.
INERTIA_FIELDS = ("e1", "e2", "m_cyl", "I_cyl", "m_rod", "I_rod", "m_p", "I_p")


class GeometryError(ValueError):
    """A manipulator description that cannot be built (message names the field)."""


def base_joints(side: float) -> np.ndarray:
    """Fixed joints A1..A3 [m] of an equilateral base of the given side (thesis.md §1), shape (3, 2)."""
    o = side / math.sqrt(3.0)
    c30, s30 = math.cos(math.pi / 6), math.sin(math.pi / 6)
    return np.array([[-o * c30, o * s30], [o * c30, o * s30], [0.0, -o]])


@dataclass(frozen=True)
class Inertia:
    """Mass properties of the legs and platform (thesis.md §4, Table 7.1).

    ``e1``: distance [m] from ``A_i`` back to the cylinder's mass centre (at ``A_i - e1 s_i``).
    ``e2``: distance [m] from ``B_i`` back to the rod's mass centre (at ``A_i + (L_i - e2) s_i``).
    Masses in kg, moments of inertia in kg m² about each body's own mass centre.
    """

    e1: float = 0.3
    e2: float = 0.3
    m_cyl: float = 1.0
    I_cyl: float = 0.03003800838
    m_rod: float = 1.0
    I_rod: float = 0.03003800838
    m_p: float = 1.69935
    I_p: float = 0.01145826355

    def vector(self) -> np.ndarray:
        """Flat vector in the order of :data:`INERTIA_FIELDS`."""
        return np.array([getattr(self, f) for f in INERTIA_FIELDS], dtype=float)


@dataclass(frozen=True)
class Manipulator:
    """A 3-RPR design: joints, pairing, stroke limits and mass properties.

    ``base``: fixed joints A1..A3 [m], shape (3, 2).  ``Lmp``: platform side [m].
    ``angles``: the platform joint angles ``a_i`` [rad] (pairing).  ``Lmin``/``Lmax``: stroke [m].
    """

    name: str
    base: tuple[tuple[float, float], ...]
    Lmp: float = 0.2
    angles: tuple[float, float, float] = CROSS_ANGLES
    Lmin: float = 0.10
    Lmax: float = 0.60
    inertia: Inertia = field(default_factory=Inertia)

    def __post_init__(self) -> None:
        self.validate()

    # -- validation ---------------------------------------------------------------------------
    def validate(self) -> None:
        """Refuse a geometry that cannot describe a manipulator; the message names the field."""
        a = np.asarray(self.base, dtype=float)
        if a.shape != (3, 2) or not np.all(np.isfinite(a)):
            raise GeometryError(f"{self.name}: base must be three finite (x, y) points, got {self.base!r}")
        for i in range(3):
            for j in range(i + 1, 3):
                if np.hypot(*(a[i] - a[j])) < 1e-9:
                    raise GeometryError(f"{self.name}: fixed joints A{i + 1} and A{j + 1} coincide")
        if abs((a[1, 0] - a[0, 0]) * (a[2, 1] - a[0, 1]) - (a[1, 1] - a[0, 1]) * (a[2, 0] - a[0, 0])) < 1e-12:
            raise GeometryError(f"{self.name}: fixed joints A1, A2, A3 are collinear")
        if not (math.isfinite(self.Lmp) and self.Lmp > 0):
            raise GeometryError(f"{self.name}: Lmp must be a positive length in m, got {self.Lmp!r}")
        if len(self.angles) != 3:
            raise GeometryError(f"{self.name}: angles must hold three values, got {self.angles!r}")
        ang = [float(t) % (2 * math.pi) for t in self.angles]
        for i in range(3):
            for j in range(i + 1, 3):
                d = abs(ang[i] - ang[j])
                if min(d, 2 * math.pi - d) < 1e-9:
                    raise GeometryError(f"{self.name}: platform joints B{i + 1} and B{j + 1} coincide")
        if not (0 <= self.Lmin < self.Lmax):
            raise GeometryError(
                f"{self.name}: stroke limits need 0 <= Lmin < Lmax, got Lmin={self.Lmin}, Lmax={self.Lmax}")
        for f in INERTIA_FIELDS:
            v = getattr(self.inertia, f)
            if not (math.isfinite(v) and v > 0):
                raise GeometryError(f"{self.name}: inertia.{f} must be positive, got {v!r}")

    # -- derived quantities ---------------------------------------------------------------------
    @property
    def r(self) -> float:
        """Radius [m] of the platform joint circle, ``Lmp / sqrt(3)``."""
        return self.Lmp / math.sqrt(3.0)

    def geometry_vector(self) -> np.ndarray:
        """Flat vector in the order of :data:`GEOMETRY_FIELDS` (input of the symbolic models)."""
        a = np.asarray(self.base, dtype=float)
        return np.concatenate([a.ravel(), [self.r], np.asarray(self.angles, dtype=float)])

    def with_(self, **changes) -> "Manipulator":
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)


def _preset(name: str, side: float, pairing: str) -> Manipulator:
    angles = CROSS_ANGLES if pairing == "cross" else HOMOTHETIC_ANGLES
    base = tuple(tuple(float(v) for v in row) for row in base_joints(side))
    return Manipulator(name=name, base=base, Lmp=0.2, angles=angles)


#: The four configurations of Chapter 4 (Table 4.2); ``cross_leg`` (config 4) is the default.
PRESETS: dict[str, Manipulator] = {
    "config1": _preset("config1", 0.90, "homothetic"),
    "config2": _preset("config2", 0.60, "cross"),
    "config3": _preset("config3", 0.30, "homothetic"),
    "config4": _preset("config4", 0.30, "cross"),
}
PRESETS["classic"] = PRESETS["config1"]
PRESETS["cross_leg"] = PRESETS["config4"]
DEFAULT = "cross_leg"


def preset(name: str = DEFAULT) -> Manipulator:
    """The named configuration; raises :class:`GeometryError` listing the known names."""
    try:
        return PRESETS[name]
    except KeyError:
        raise GeometryError(f"unknown configuration {name!r}; expected one of {', '.join(PRESETS)}") from None


def custom(side: float, Lmp: float = 0.2, pairing: str = "cross", name: str = "custom", **kw) -> Manipulator:
    """An equilateral design of base ``side`` [m] and platform side ``Lmp`` [m]."""
    if pairing not in ("cross", "homothetic"):
        raise GeometryError(f"{name}: pairing must be 'cross' or 'homothetic', got {pairing!r}")
    if not (math.isfinite(side) and side > 0):
        raise GeometryError(f"{name}: base side must be a positive length in m, got {side!r}")
    angles = CROSS_ANGLES if pairing == "cross" else HOMOTHETIC_ANGLES
    base = tuple(tuple(float(v) for v in row) for row in base_joints(side))
    return Manipulator(name=name, base=base, Lmp=Lmp, angles=angles, **kw)
