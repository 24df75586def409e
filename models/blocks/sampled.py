"""The board's sampled I/O as blocks whose samples are time events (issue 30): the potentiometers'
12-bit ADC and the drivers' PWM duty, each quantised and held between samples.

``adc`` (per channel ``u`` -> ``y``, ``raw``)
    The rig's leg sensing (thesis.md §7, :mod:`hardware.convert`): 1.8 V -> 1 kOhm -> a potentiometer
    of ``pot_ohm`` over ``pot_length`` -> ground, read by the BeagleBone's 12-bit ADC over 0..1.8 V.
    A leg of length ``u`` [m] (stroke ``u - s_offset``) gives the level
    ``raw* = 4096 ((u - s_offset) / pot_length) pot_ohm / (pot_ohm + series_ohm)`` counts; the ADC
    reports ``raw = clip(floor(raw* + 1/2), 0, 4095)`` at each sample ``k period`` and the board
    reads the length back as ``y = s_offset + raw pot_length (pot_ohm + series_ohm) / (4096 pot_ohm)``
    (one count is 0.17 mm with the defaults).  ``y`` and ``raw`` hold between samples.
``pwm`` (per channel ``u`` -> ``y``, ``duty``)
    The Cytron drivers on a ``v_supply`` supply: a command of ``u`` volts becomes the duty
    ``duty = floor(clip(|u| / v_supply, 0, 1) counts + 1/2)`` of a PWM period of ``counts``
    clock ticks (50 000 ns at 20 kHz), updated at each sample ``k period`` (the board's loop, 1 ms);
    the driver applies the mean voltage ``y = sign(u) duty / counts v_supply`` until the next.

Both have no continuous state (integrator ``none``); the held values are modes, the samples a
:class:`~models.block.Sample` (time events located exactly, whatever the master's step).
"""
from __future__ import annotations

import casadi as ca

from ..block import Block, Sample, Var
from ._common import ParamSet

FIDELITIES = ("adc", "pwm")
#: ADC codes (12 bit) and the nominal sensing and drive constants of hardware/convert.py.
ADC_FULL = 4096
POT_LENGTH, POT_OHM, SERIES_OHM, S_OFFSET = 0.635, 10e3, 1e3, 0.1
PWM_COUNTS, V_SUPPLY = 50_000, 12.0


def _names(channels: int, base: str) -> list[str]:
    return [base] if channels == 1 else [f"{base}[{i}]" for i in range(1, channels + 1)]


def _round(x):
    return ca.floor(x + 0.5)


def adc(channels: int = 1, period: float = 1e-3) -> Block:
    """The potentiometer and 12-bit ADC of each leg, sampled every ``period`` [s] (module docstring)."""
    ps = ParamSet()
    L = ps.add("pot_length", POT_LENGTH, "m", "potentiometer length", lower=1e-9)
    rp = ps.add("pot_ohm", POT_OHM, "Ohm", "potentiometer resistance", lower=1e-9)
    rs = ps.add("series_ohm", SERIES_OHM, "Ohm", "series resistor from 1.8 V", lower=0.0)
    s_off = ps.add("s_offset", S_OFFSET, "m", "leg length at zero stroke", lower=0.0)
    u = ca.SX.sym("u", channels)
    raw = ca.SX.sym("raw", channels)
    per_count = L * (rp + rs) / (ADC_FULL * rp)  # [m] per ADC count
    level = (u - s_off) / per_count
    sampled = ca.fmin(ca.fmax(_round(level), 0.0), ADC_FULL - 1.0)
    names_u, names_y, names_r = _names(channels, "u"), _names(channels, "y"), _names(channels, "raw")
    return Block.build(
        "sampled", description=f"potentiometer and 12-bit ADC ({channels} channel(s)), sampled as time events",
        params=ps.params, inputs=[Var(n, "m", "leg length") for n in names_u],
        outputs=[Var(n, "m", "leg length as the board reads it (held between samples)") for n in names_y]
        + [Var(n, "1", "ADC code 0..4095 (held)") for n in names_r],
        states=[], p=ps.vector(), u=u, x=ca.SX(0, 1), ode=ca.SX(0, 1), out=ca.vertcat(s_off + raw * per_count, raw),
        start=ca.SX(0, 1), integrator="none", modes=[Var(f"mode.{n}", "1", "held ADC code") for n in names_r],
        m=raw, mode_start=ca.SX.zeros(channels), sample_times=[Sample(float(period), 0.0, sampled, "adc")],
        fidelity="adc")


def pwm(channels: int = 1, period: float = 1e-3) -> Block:
    """The drivers' PWM duty, updated every ``period`` [s] (module docstring)."""
    ps = ParamSet()
    v_supply = ps.add("v_supply", V_SUPPLY, "V", "driver supply: the largest command magnitude", lower=1e-9)
    counts = ps.add("counts", PWM_COUNTS, "1", "clock ticks per PWM period (50 000 ns at 20 kHz)", lower=1.0)
    u = ca.SX.sym("u", channels)
    duty = ca.SX.sym("duty", channels)  # signed: the sign is DIR
    sampled = ca.sign(u) * _round(ca.fmin(ca.fabs(u) / v_supply, 1.0) * counts)
    names_u, names_y, names_d = _names(channels, "u"), _names(channels, "y"), _names(channels, "duty")
    return Block.build(
        "sampled", description=f"PWM duty of the drivers ({channels} channel(s)), sampled as time events",
        params=ps.params, inputs=[Var(n, "V", "voltage command") for n in names_u],
        outputs=[Var(n, "V", "mean voltage the driver applies (held between updates)") for n in names_y]
        + [Var(n, "1", "duty in clock ticks, signed by DIR (held)") for n in names_d],
        states=[], p=ps.vector(), u=u, x=ca.SX(0, 1), ode=ca.SX(0, 1),
        out=ca.vertcat(duty / counts * v_supply, duty), start=ca.SX(0, 1), integrator="none",
        modes=[Var(f"mode.{n}", "1", "held duty") for n in names_d], m=duty, mode_start=ca.SX.zeros(channels),
        sample_times=[Sample(float(period), 0.0, sampled, "pwm")], fidelity="pwm")

