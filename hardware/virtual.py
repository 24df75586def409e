"""The virtual board: the I/O daemon, unchanged, on a fake sysfs tree, and a plant process that
plays the rig behind the tree in real time.

The plant reads each leg's ``duty_cycle`` and DIR ``value`` files, turns them into the driver's
mean voltage (:func:`hardware.convert.drive_to_volts`), advances the catalog's actuator block
(``linear_actuator``/``single``, the same equations and integrator as the co-simulation's ``rig``
block) over the wall-clock time that passed, and writes the potentiometer's ADC counts
(:class:`hardware.convert.Calibration`, 12-bit quantisation) atomically into the tree.

Options reproduce what goes wrong on a rig: ADC noise (counts, standard deviation), sensor
latency, a stuck sensor (the counts freeze), an unplugged sensor (the ADC reads 4095) and a
driver fault (the motor gets no voltage), each per leg.
"""
from __future__ import annotations

import collections
import os
import random
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .convert import ADC_MAX, Calibration, drive_to_volts, quantise
from .pins import RIG_PINS, LegFiles, resolve

#: The rig's sensor calibration as the virtual pots produce it (ideal 10 kOhm pot, 25 inches,
#: leg length 0.1 m at zero stroke): the hardware FMU's default calibration.
RIG_CALIBRATION = Calibration(s_offset=0.1)


@dataclass
class PlantOptions:
    actuator: str = "fa200"
    start: tuple[float, float, float] = (0.31086, 0.35586, 0.20428)  # leg lengths [m] (Table 6.12 start)
    noise: float = 0.0          # ADC noise, standard deviation [counts]
    latency: float = 0.0        # sensor latency [s]
    stuck: tuple[int, ...] = ()     # legs (1..3) whose reading freezes
    unplugged: tuple[int, ...] = ()  # legs whose pot is unplugged (reads 4095)
    driver_fault: tuple[int, ...] = ()  # legs whose driver gives no voltage
    rate: float = 1000.0        # plant updates per second
    seed: int = 0
    calibration: Calibration = field(default_factory=lambda: RIG_CALIBRATION)


class Plant:
    """Three actuators behind the fake tree at ``root`` (see the module docstring)."""

    def __init__(self, root: Path | str, options: PlantOptions | None = None):
        from models.blocks import make
        from models.integrators import Stepper

        self.opt = options or PlantOptions()
        self.legs: list[LegFiles] = resolve(Path(root), RIG_PINS, export=False)
        self.block = make("linear_actuator", "single", actuator=self.opt.actuator)
        self.stepper = Stepper(self.block)
        self.p = [self.block.param_vector(s0=s) for s in self.opt.start]
        self.x = [np.asarray(self.stepper.start(p), dtype=float).reshape(-1) for p in self.p]
        self.rng = random.Random(self.opt.seed)
        self.volts = [0.0, 0.0, 0.0]
        self.history: collections.deque = collections.deque()
        self.frozen: dict[int, int] = {}
        self.steps = 0
        self._write_counts(self._levels(), time.monotonic())

    def stroke(self, i: int) -> float:
        return float(self.x[i][0])

    def _read_drive(self, i: int) -> float:
        leg = self.legs[i]
        try:
            duty = int(leg.duty.read_text().strip())
            dir_high = leg.dir_value.read_text().strip() == "1"
            enabled = leg.enable.read_text().strip() == "1"
            period = int(leg.period.read_text().strip())
        except (OSError, ValueError):
            return self.volts[i]  # mid-write: keep the last reading, as the hardware would
        if not enabled or (i + 1) in self.opt.driver_fault:
            return 0.0
        return drive_to_volts(duty, dir_high, period_ns=period)

    def _levels(self) -> list[float]:
        cal = self.opt.calibration
        return [cal.counts(self.stroke(i)) for i in range(3)]

    def _write_counts(self, levels: list[float], now: float) -> None:
        self.history.append((now, levels))
        while len(self.history) > 1 and self.history[1][0] <= now - self.opt.latency:
            self.history.popleft()
        seen = self.history[0][1]
        for i, leg in enumerate(self.legs):
            if (i + 1) in self.opt.unplugged:
                raw = ADC_MAX
            elif (i + 1) in self.opt.stuck:
                raw = self.frozen.setdefault(i, quantise(seen[i]))
            else:
                raw = quantise(seen[i] + (self.rng.gauss(0.0, self.opt.noise) if self.opt.noise else 0.0))
            tmp = leg.adc.with_name(f".{leg.adc.name}.tmp")
            tmp.write_text(f"{raw}\n")
            os.replace(tmp, leg.adc)

    def advance(self, dt: float, now: float) -> None:
        """Read the drives, integrate ``dt`` seconds, write the counts."""
        if dt > 0:
            for i in range(3):
                self.volts[i] = self._read_drive(i)
                x, ok = self.stepper.step(self.x[i], [self.volts[i], 0.0], self.p[i], dt)
                if ok:
                    self.x[i] = x
            self.steps += 1
        self._write_counts(self._levels(), now)

    def run(self, duration: float | None = None, stop=lambda: False) -> None:
        """Advance in real time at ``options.rate`` until ``duration`` or ``stop()``."""
        period = 1.0 / self.opt.rate
        t0 = last = time.monotonic()
        nxt = t0 + period
        while not stop() and (duration is None or last - t0 < duration):
            now = time.monotonic()
            if now < nxt:
                time.sleep(nxt - now)
                now = time.monotonic()
            self.advance(now - last, now)
            last = now
            nxt += period
            if nxt < now:
                nxt = now + period
