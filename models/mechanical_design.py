"""The static design checks of the thesis's Chapter 8 (thesis.md §8): fixed-joint shaft, bearings,
clamp and actuator, as plain functions of the loads.

Conventions (SI units throughout: N, m, N m, Pa; lengths of the shaft sketch in m):

- The shaft of a fixed joint is loaded at one point by a horizontal force ``F_h`` [N] (the leg's
  axial force, reacted by the joint) and by the bending moment ``M_w`` [N m] of the weights hung
  on the joint (actuator and platform share, out of the plane of motion).  The point lies ``a``
  above the top of the shaft (63 mm) and ``a + b`` above the first bearing (b = 92.5 mm); the two
  bearings are ``s`` apart (65 mm).
- Eq. 8.1 (moments about bearing 2): ``F_h (a + b) + M_w = F1 s``;
  Eq. 8.2 (moments about bearing 1): ``F_h (a + b - s) + M_w = F2 s``.  The largest bending
  moment, at bearing 1 (Figure 8.5), is ``M_max = F_h (a + b - s) + M_w = F2 s``.
- Eq. 8.3: ``M_e = (M + sqrt(M^2 + T^2)) / 2``; Eq. 8.4: ``[sigma] = min(0.6 sigma_el,
  0.36 sigma_ult)``; Eq. 8.5: ``d >= (32 M_e / (pi [sigma]))^(1/3)``.
- Clamp (Section 8.1.5): the clamp holds the actuator by friction, so an axial force ``F``
  needs a compression ``F / mu`` (steel on aluminium, mu = 0.6).
- The weight moment at a pose is the thesis's: Table 8.1 prints 17.27 N m with the platform
  closest to the joint and 5.24 N m furthest; its lever arms survive only in the lost figure, so
  the moment is taken as affine in the leg length between those two printed values at the
  stroke's ends (every mass that moves with the leg moves along it, so the true moment is affine
  in L; the two printed points fix the line).  See docs/explanation/design-checks.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

#: Inputs of Chapter 8 as printed (Section 8.1.2 and Table 8.1; thesis.md §8).
PLATFORM_MASS = 3.0          # kg
ACTUATOR_MASS = 4.0          # kg: motor 2, rod 1, cylinder 1 (Table 8.1)
HORIZONTAL_FORCE = 100.0     # N, at the load point
LEVER_TOP = 0.063            # m, load point above the top of the shaft
LEVER_BEARING = 0.0925       # m, from there down to the first bearing
BEARING_SPACING = 0.065      # m
SHAFT_TORQUE = 2.0           # N m, the largest torque on the shaft
WEIGHT_MOMENT_CLOSEST = 17.27  # N m, Table 8.1 (the text's "17.37" is an OCR/typing slip)
WEIGHT_MOMENT_FURTHEST = 5.24  # N m, Table 8.1 (the clamp section uses 5.25)
#: Eq. 8.4's result: the steel's elastic and ultimate limits are not printed, so the printed
#: permissible stress is the input.
PERMISSIBLE_STRESS = 210e6   # Pa
SHAFT_DIAMETER = 0.015       # m, the chosen shaft
FRICTION_STEEL_ALUMINIUM = 0.6


@dataclass(frozen=True)
class ShaftLoads:
    """What loads one fixed joint: horizontal force ``F_h`` [N], weight moment ``M_w`` [N m] and
    shaft torque ``T`` [N m]."""

    F_h: float = HORIZONTAL_FORCE
    M_w: float = WEIGHT_MOMENT_CLOSEST
    T: float = SHAFT_TORQUE


@dataclass(frozen=True)
class ShaftGeometry:
    """The sketch of Figure 8.4 [m] and the chosen diameter [m]."""

    a: float = LEVER_TOP
    b: float = LEVER_BEARING
    s: float = BEARING_SPACING
    d: float = SHAFT_DIAMETER


def bearing_forces(loads: ShaftLoads, geo: ShaftGeometry = ShaftGeometry()) -> tuple[float, float]:
    """``(F1, F2)`` [N] of Eq. 8.1-8.2."""
    f1 = (loads.F_h * (geo.a + geo.b) + loads.M_w) / geo.s
    f2 = (loads.F_h * (geo.a + geo.b - geo.s) + loads.M_w) / geo.s
    return f1, f2


def largest_bending_moment(loads: ShaftLoads, geo: ShaftGeometry = ShaftGeometry()) -> float:
    """Bending moment [N m] at bearing 1, the shaft's most loaded section (Figure 8.5)."""
    return loads.F_h * (geo.a + geo.b - geo.s) + loads.M_w


def equivalent_moment(M: float, T: float) -> float:
    """Eq. 8.3: ``M_e = (M + sqrt(M^2 + T^2)) / 2`` [N m]."""
    return 0.5 * (M + math.hypot(M, T))


def permissible_stress(sigma_elastic: float, sigma_ultimate: float) -> float:
    """Eq. 8.4: ``min(0.6 sigma_el, 0.36 sigma_ult)`` [Pa]."""
    return min(0.6 * sigma_elastic, 0.36 * sigma_ultimate)


def minimum_diameter(M_e: float, sigma: float) -> float:
    """Eq. 8.5: the smallest solid shaft diameter [m] for the equivalent moment ``M_e`` [N m]."""
    return (32.0 * M_e / (math.pi * sigma)) ** (1.0 / 3.0)


def bending_stress(M_e: float, d: float) -> float:
    """Bending stress [Pa] of a solid shaft of diameter ``d`` [m] under ``M_e`` [N m]."""
    return 32.0 * M_e / (math.pi * d ** 3)


def clamp_compression(F_axial: float, mu: float = FRICTION_STEEL_ALUMINIUM) -> float:
    """Compression [N] the clamp needs to hold the axial force ``F_axial`` [N] by friction."""
    return abs(F_axial) / mu


def weight_moment(L, Lmin: float, Lmax: float, closest: float = WEIGHT_MOMENT_CLOSEST,
                  furthest: float = WEIGHT_MOMENT_FURTHEST):
    """Weight moment [N m] on a fixed joint with its leg at length ``L`` [m] (scalar or array):
    affine in L through Table 8.1's values at ``Lmin`` (closest) and ``Lmax`` (furthest)."""
    return closest + (furthest - closest) * (L - Lmin) / (Lmax - Lmin)


@dataclass(frozen=True)
class ShaftCheck:
    """Every Chapter 8 number for one set of loads (units as in the module docstring)."""

    loads: ShaftLoads
    F1: float
    F2: float
    M_max: float
    M_e: float
    sigma_allowed: float
    d_min: float
    d: float
    stress: float
    clamp: float

    @property
    def diameter_margin(self) -> float:
        """``d / d_min - 1``: negative when the chosen shaft is too thin."""
        return self.d / self.d_min - 1.0

    @property
    def stress_margin(self) -> float:
        """``[sigma] / sigma - 1`` at the chosen diameter."""
        return self.sigma_allowed / self.stress - 1.0


def check_shaft(loads: ShaftLoads = ShaftLoads(), geo: ShaftGeometry = ShaftGeometry(),
                sigma_allowed: float = PERMISSIBLE_STRESS) -> ShaftCheck:
    """Eq. 8.1-8.5 and the clamp force for ``loads`` (defaults: the thesis's own inputs)."""
    f1, f2 = bearing_forces(loads, geo)
    m = largest_bending_moment(loads, geo)
    me = equivalent_moment(m, loads.T)
    return ShaftCheck(loads, f1, f2, m, me, sigma_allowed, minimum_diameter(me, sigma_allowed), geo.d,
                      bending_stress(me, geo.d), clamp_compression(loads.F_h))
