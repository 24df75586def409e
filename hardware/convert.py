"""Calibrated conversions between the master's quantities and the board's (docs/explanation/thesis.md §7).

Drive: a Cytron driver on a 12 V supply takes PWM + DIR.  A command of ``v`` volts becomes a duty
``|v| / v_supply`` of the PWM period (20 kHz: 50 000 ns) and DIR low for ``v >= 0`` (extend),
DIR high for ``v < 0`` (Cytron: DIR high = reverse).  Commands beyond the supply are clamped;
a non-finite command gives duty 0 and a fault.

Sense: 1.8 V -> 1 kOhm -> potentiometer (``Rp``, wiper at ``x / L_pot`` of it) -> ground, read by
the 12-bit ADC over 0..1.8 V: ``raw = 4096 (x / L_pot) Rp / (Rp + 1 kOhm)``; 10 kOhm and a 25-inch
(0.635 m) pot give about 3723 counts at full stroke, 0.17 mm per count.  On the rig each
actuator is calibrated at both ends (:class:`Calibration`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

#: PWM period [ns] of the drivers' 20 kHz carrier.
PERIOD_NS = 50_000
#: Driver supply [V]: the largest command magnitude.
V_SUPPLY = 12.0
ADC_FULL_SCALE = 4096  # 12 bit: raw 0..4095
ADC_MAX = ADC_FULL_SCALE - 1
POT_LENGTH = 0.635  # [m] Firgelli 25-inch linear potentiometer
POT_OHM = 10e3
SERIES_OHM = 1e3


@dataclass(frozen=True)
class Drive:
    """One leg's drive outputs: ``duty_ns`` of ``period_ns``, ``dir_high`` (reverse), ``fault``
    (the command was not a finite number, so the outputs are safe zeros)."""

    duty_ns: int
    dir_high: bool
    fault: bool = False


def volts_to_drive(volts: float, *, v_supply: float = V_SUPPLY, period_ns: int = PERIOD_NS) -> Drive:
    """PWM duty [ns] and DIR for a command of ``volts`` [V], clamped to ``+-v_supply``."""
    try:
        v = float(volts)
    except (TypeError, ValueError):
        return Drive(0, False, True)
    if not math.isfinite(v):
        return Drive(0, False, True)
    v = max(-v_supply, min(v_supply, v))
    duty = int(round(abs(v) / v_supply * period_ns))
    return Drive(min(duty, period_ns), v < 0 and duty > 0, False)


def drive_to_volts(duty_ns: int, dir_high: bool, *, v_supply: float = V_SUPPLY, period_ns: int = PERIOD_NS) -> float:
    """The mean voltage [V] a driver applies for ``duty_ns`` of ``period_ns`` and DIR."""
    frac = max(0.0, min(1.0, duty_ns / period_ns)) if period_ns > 0 else 0.0
    return -frac * v_supply if dir_high else frac * v_supply


def ideal_counts(stroke: float, *, pot_length: float = POT_LENGTH, pot_ohm: float = POT_OHM,
                 series_ohm: float = SERIES_OHM) -> float:
    """ADC counts (unrounded) of the divider for a wiper at ``stroke`` [m] along the pot."""
    return ADC_FULL_SCALE * (stroke / pot_length) * pot_ohm / (pot_ohm + series_ohm)


@dataclass(frozen=True)
class Calibration:
    """Two-point calibration of one leg: ``raw_zero`` counts at zero stroke, ``raw_full`` at
    ``stroke_full`` [m]; ``s_offset`` [m] is the leg length (joint to joint) at zero stroke."""

    raw_zero: float = 0.0
    raw_full: float = ideal_counts(POT_LENGTH)
    stroke_full: float = POT_LENGTH
    s_offset: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.raw_zero) and math.isfinite(self.raw_full) and self.raw_full != self.raw_zero):
            raise ValueError(f"calibration needs two different finite counts, got {self.raw_zero}, {self.raw_full}")
        if not (self.stroke_full > 0):
            raise ValueError(f"calibration stroke_full must be positive [m], got {self.stroke_full}")

    @property
    def metres_per_count(self) -> float:
        return self.stroke_full / (self.raw_full - self.raw_zero)

    def stroke(self, raw: float) -> float:
        """Stroke [m] for ``raw`` counts."""
        return (raw - self.raw_zero) * self.metres_per_count

    def counts(self, stroke: float) -> float:
        """Counts (unrounded) for ``stroke`` [m]."""
        return self.raw_zero + stroke / self.metres_per_count

    def leg_length(self, raw: float) -> float:
        """Leg length [m] (joint to joint) for ``raw`` counts."""
        return self.s_offset + self.stroke(raw)


def quantise(counts: float) -> int:
    """What the 12-bit ADC reports for an analogue level of ``counts``: rounded, within 0..4095."""
    if not math.isfinite(counts):
        return ADC_MAX
    return int(max(0, min(ADC_MAX, round(counts))))
