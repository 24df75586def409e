"""Recordings from the virtual board: its plant (:mod:`hardware.virtual`, with its ADC noise,
12-bit quantisation, sensor latency, per-leg pot calibration and overridden parameters) driven
open-loop by a voltage profile on synthetic time (no wall clock: the same file every time), written
as a trace that a scene replays and ``rpr-cosim fit`` fits.

At each sample ``t_k`` the recorder reads the three ADC files and the motor currents (the
``motor`` fidelity; the current sense of a virtual rig, with ``current_noise``), both as the plant
is at the end of the interval before (under ``u_{k-1}``; at ``t_0`` under ``u_0``), then sets the
drive (PWM duty and DIR, as the daemon's output stage would) for the command ``u_k``, records the
row, and lets the plant run to ``t_{k+1}``.  So ``u`` is held from its sample to the next (replay
it with ``interpolation: hold``), and a sample reads the plant under the voltage held before it:
what a co-simulation records at a communication point (the outputs after the step, before the
inputs change), under Jacobi's exchange.

Columns (the names a run of the hardware scene records): ``time``; ``rig.leg[i].u`` [V], the
voltage the driver applied; ``rig.leg[i].raw`` [counts]; ``rig.leg[i].s`` [m], the leg length by
the *nominal* calibration, as the hardware FMU reports it; ``rig.leg[i].i`` [A] when the plant has
currents.  The true values the plant ran with are kept in the file's ``# truth:`` line.
"""
from __future__ import annotations

import json
import math
import os
import random
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

from .convert import drive_to_volts, volts_to_drive
from .faketree import make_fake_tree
from .virtual import RIG_CALIBRATION, Plant, PlantOptions

LEGS = (1, 2, 3)


def excitation(t: float) -> tuple[float, float, float]:
    """A default test signal [V] per leg: a slow sine (the legs travel about +-12 mm) plus a
    faster square wave (the 20 ms speed lag shows), different for each leg."""
    out = []
    for j, (f, g, phase) in enumerate(((0.4, 2.3, 0.0), (0.55, 3.1, 1.0), (0.7, 3.7, 2.0))):
        square = 1.0 if math.sin(2 * math.pi * g * t + phase) >= 0 else -1.0
        out.append(8.0 * math.sin(2 * math.pi * f * t + phase) + 3.0 * square)
    return tuple(out)


def _open(path: Path, flags: int, fds: list[int]) -> int:
    fds.append(os.open(path, flags))
    return fds[-1]


def _put(fd: int, text: bytes) -> None:
    """Replace a sysfs-like file's text in one write (the plant reads it with pread)."""
    os.ftruncate(fd, 0)
    os.pwrite(fd, text, 0)


def record(path: Path | str, options: PlantOptions, *, seconds: float = 5.0, rate: float = 1000.0,
           volts: Callable[[float], Sequence[float]] = excitation, current_noise: float = 0.0) -> Path:
    """Record ``seconds`` of the virtual board's plant at ``rate`` samples per second into the CSV
    ``path`` (module docstring); returns the path."""
    path = Path(path)
    n = int(round(seconds * rate))
    if n < 2 or not math.isfinite(seconds) or rate <= 0:
        raise ValueError(f"recording: {seconds} s at {rate} /s is not at least two samples")
    dt = 1.0 / rate
    rng = random.Random(options.seed + 7919)
    with tempfile.TemporaryDirectory(prefix="rpr-record-") as tmp:
        tree = make_fake_tree(Path(tmp) / "tree")
        plant = Plant(tree, options)
        fds: list[int] = []
        try:
            for leg in plant.legs:
                leg.enable.write_text("1")
            adc = [_open(leg.adc, os.O_RDONLY, fds) for leg in plant.legs]
            duty = [_open(leg.duty, os.O_WRONLY, fds) for leg in plant.legs]
            direction = [_open(leg.dir_value, os.O_WRONLY, fds) for leg in plant.legs]
            rows = []
            for k in range(n + 1):
                t = k * dt
                raw = [int(os.pread(fd, 16, 0)) for fd in adc]
                before = list(plant.volts)  # in force over the interval that ends now
                applied = []
                for j, v in enumerate(volts(t)):
                    d = volts_to_drive(v)
                    _put(duty[j], b"%d" % d.duty_ns)
                    _put(direction[j], b"1" if d.dir_high else b"0")
                    applied.append(drive_to_volts(d.duty_ns, d.dir_high))
                amps = ([a + (rng.gauss(0.0, current_noise) if current_noise else 0.0)
                         for a in plant.currents(before if k else applied)] if plant.vr_current is not None else [])
                lengths = [RIG_CALIBRATION.leg_length(r) for r in raw]
                rows.append([t, *applied, *raw, *lengths, *amps])
                if k < n:
                    plant.advance(dt, t + dt)
        finally:
            for fd in fds:
                os.close(fd)
            plant.close()
    names = ([f"rig.leg[{i}].u" for i in LEGS] + [f"rig.leg[{i}].raw" for i in LEGS] +
             [f"rig.leg[{i}].s" for i in LEGS] + ([f"rig.leg[{i}].i" for i in LEGS] if rows and len(rows[0]) > 10
                                                   else []))
    units = {n_: {"u": "V", "raw": "1", "s": "m", "i": "A"}[n_.rsplit(".", 1)[1]] for n_ in names}
    truth = {"fidelity": options.fidelity, "params": dict(options.params), "start": list(options.start),
             "noise": options.noise, "latency": options.latency, "current_noise": current_noise,
             "calibration": [{"raw_zero": c.raw_zero, "raw_full": c.raw_full, "stroke_full": c.stroke_full}
                             for c in options.calibrations()], "seed": options.seed}
    lines = [f"# units: {json.dumps(units)}", f"# truth: {json.dumps(truth)}", ",".join(["time", *names])]
    lines += [",".join(repr(float(v)) for v in row) for row in rows]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


__all__ = ["excitation", "record"]
