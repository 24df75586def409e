"""The virtual board: the I/O daemon (the same C binary as on the board) on a fake sysfs tree,
and a plant process that plays the rig behind the tree in real time.

The plant reads each leg's ``duty_cycle`` and DIR ``value`` files, turns them into the driver's
mean voltage (:func:`hardware.convert.drive_to_volts`), advances the catalog's actuator block
(``linear_actuator``/``rig``: the very FMU that ``rig_step`` co-simulates, built and cached by
:mod:`fmus`, stepped through FMPy) over the wall-clock time that passed, and writes the
potentiometer's ADC counts (:class:`hardware.convert.Calibration`, 12-bit quantisation) into the
tree, as fixed-width text in one write (a reader never sees a torn or empty value).

Options reproduce what goes wrong on a rig: ADC noise (counts, standard deviation), sensor
latency, a stuck sensor (the counts freeze), an unplugged sensor (the ADC reads 4095) and a
driver fault (the motor gets no voltage), each per leg.

The plant is any fidelity of the actuator block (``fidelity``: ``rig``, the FA-200's first-order
speed lag, or ``motor``, a DC motor per leg) with its parameters overridden (``params``: the names
``--set components.rig.params.NAME=VALUE`` takes), and each leg's pot has its own calibration
(``calibration``: one for all legs or one per leg), so recordings with known true values can be
made (:mod:`hardware.record`).
"""
from __future__ import annotations

import collections
import os
import random
import time
from dataclasses import dataclass, field
from pathlib import Path

from .convert import ADC_MAX, PERIOD_NS, Calibration, drive_to_volts, quantise
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
    calibration: Calibration | tuple[Calibration, Calibration, Calibration] = field(
        default_factory=lambda: RIG_CALIBRATION)
    fidelity: str = "rig"       # the actuator block's fidelity (rig: first-order lag; motor: a DC motor per leg)
    params: dict[str, float] = field(default_factory=dict)  # the block's parameters by name (true values)

    def calibrations(self) -> tuple[Calibration, Calibration, Calibration]:
        """Each leg's pot calibration."""
        cal = self.calibration
        return (cal, cal, cal) if isinstance(cal, Calibration) else tuple(cal)


def plant_block(options: PlantOptions, *, nominal: bool = False):
    """The actuator block the plant integrates, its parameters overridden (``nominal``: at their
    defaults, the FMU the plant loads and sets them on); a ValueError names an unknown parameter
    or fidelity, or a value outside the parameter's bounds."""
    from models.block import BlockError
    from models.blocks import make

    kw = {"actuator": options.actuator} if options.fidelity != "motor" else {}
    try:
        return make("linear_actuator", options.fidelity, **kw,
                    **({} if nominal else {k: float(v) for k, v in options.params.items()}))
    except BlockError as exc:
        raise ValueError(f"virtual board plant: {exc}") from None


class Plant:
    """Three actuators behind the fake tree at ``root`` (see the module docstring)."""

    def __init__(self, root: Path | str, options: PlantOptions | None = None):
        from fmpy import read_model_description
        from fmpy.fmi2 import FMU2Slave

        import fmus

        self.opt = options or PlantOptions()
        self.cal = self.opt.calibrations()
        if len(self.cal) != 3:
            raise ValueError(f"virtual board plant: {len(self.cal)} calibrations; expected one or one per leg (3)")
        self.legs: list[LegFiles] = resolve(Path(root), RIG_PINS, export=False)
        self.block = plant_block(self.opt)  # checks the overrides
        path = fmus.build_fmu(plant_block(self.opt, nominal=True))  # one build; the values set on it
        md = read_model_description(str(path))
        vr = {v.name: v.valueReference for v in md.modelVariables}
        self.fmu = FMU2Slave(guid=md.guid, unzipDirectory=_unzip(path), modelIdentifier=md.coSimulation.modelIdentifier,
                             instanceName="virtual_rig")
        self.fmu.instantiate()
        self.fmu.setReal([vr[f"leg[{i}].s0"] for i in (1, 2, 3)], list(self.opt.start))
        given = {k: float(v) for k, v in self.opt.params.items() if not k.endswith(".s0")}
        self.fmu.setReal([vr[k] for k in given], list(given.values()))
        self.fmu.setupExperiment(startTime=0.0)
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()
        self.vr_u = [vr[f"leg[{i}].u"] for i in (1, 2, 3)]
        self.vr_stroke = [vr[f"leg[{i}].stroke"] for i in (1, 2, 3)]
        self.vr_current = [vr[f"leg[{i}].i"] for i in (1, 2, 3)] if "leg[1].i" in vr else None
        self.t = 0.0
        self.strokes = self.fmu.getReal(self.vr_stroke)
        self.rng = random.Random(self.opt.seed)
        self.volts = [0.0, 0.0, 0.0]
        self.history: collections.deque = collections.deque()
        self.frozen: dict[int, int] = {}
        self.steps = 0
        self._fd_duty = [os.open(leg.duty, os.O_RDONLY) for leg in self.legs]
        self._fd_dir = [os.open(leg.dir_value, os.O_RDONLY) for leg in self.legs]
        self._fd_adc = [os.open(leg.adc, os.O_WRONLY) for leg in self.legs]
        self._period = [PERIOD_NS] * 3
        self._enabled = [False] * 3
        self._write_counts(self._levels(), time.monotonic())

    def close(self) -> None:
        for fd in self._fd_duty + self._fd_dir + self._fd_adc:
            os.close(fd)
        self.fmu.terminate()
        self.fmu.freeInstance()

    def stroke(self, i: int) -> float:
        return float(self.strokes[i])

    def _slow_reads(self) -> None:
        """``enable`` and ``period`` change rarely: read every so often."""
        for i, leg in enumerate(self.legs):
            try:
                self._enabled[i] = leg.enable.read_text().strip() == "1"
                self._period[i] = int(leg.period.read_text().strip())
            except (OSError, ValueError):
                pass

    def _read_drive(self, i: int) -> float:
        try:
            duty = int(os.pread(self._fd_duty[i], 32, 0).strip())
            dir_high = os.pread(self._fd_dir[i], 8, 0).strip() == b"1"
        except (OSError, ValueError):
            return self.volts[i]  # mid-write: keep the last reading, as the hardware would
        if not self._enabled[i] or (i + 1) in self.opt.driver_fault:
            return 0.0
        return drive_to_volts(duty, dir_high, period_ns=self._period[i])

    def currents(self, volts: list[float]) -> list[float]:
        """The motor currents [A] with ``volts`` applied now (the ``motor`` fidelity; the driver's
        current sense of a virtual rig)."""
        if self.vr_current is None:
            raise ValueError(f"the {self.opt.fidelity!r} plant has no motor current (fidelity motor has)")
        self.fmu.setReal(self.vr_u, list(volts))
        return list(self.fmu.getReal(self.vr_current))

    def _levels(self) -> list[float]:
        return [self.cal[i].counts(self.stroke(i)) for i in range(3)]

    def _write_counts(self, levels: list[float], now: float) -> None:
        self.history.append((now, levels))
        while len(self.history) > 1 and self.history[1][0] <= now - self.opt.latency:
            self.history.popleft()
        seen = self.history[0][1]
        for i in range(3):
            if (i + 1) in self.opt.unplugged:
                raw = ADC_MAX
            elif (i + 1) in self.opt.stuck:
                raw = self.frozen.setdefault(i, quantise(seen[i]))
            else:
                raw = quantise(seen[i] + (self.rng.gauss(0.0, self.opt.noise) if self.opt.noise else 0.0))
            os.pwrite(self._fd_adc[i], b"%04d\n" % raw, 0)

    def advance(self, dt: float, now: float) -> None:
        """Read the drives, integrate ``dt`` seconds, write the counts."""
        if self.steps % 100 == 0:
            self._slow_reads()
        if dt > 0:
            self.volts = [self._read_drive(i) for i in range(3)]
            self.fmu.setReal(self.vr_u, self.volts)
            self.fmu.doStep(self.t, dt)
            self.t += dt
            self.strokes = self.fmu.getReal(self.vr_stroke)
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


def _unzip(path: Path) -> str:
    import atexit
    import shutil
    import tempfile
    import zipfile

    d = tempfile.mkdtemp(prefix="rpr-plant-")
    atexit.register(shutil.rmtree, d, True)
    with zipfile.ZipFile(path) as z:
        z.extractall(d)
    return d
