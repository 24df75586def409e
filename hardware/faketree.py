"""A fake sysfs tree of the rig's BeagleBone (the files :mod:`hardware.pins` uses), for tests
and the virtual board.  Chip and device numbers are deliberately not the usual ones, so code
that finds them by number instead of by address or name fails here.
"""
from __future__ import annotations

import os
from pathlib import Path

from .convert import PERIOD_NS
from .pins import RIG_PINS, gpio_number

#: (address, epwmss, chip number) -- numbers as a 4.19 BeagleBoard kernel might give them.
_CHIPS = {"48300200": ("48300000", 6), "48302200": ("48302000", 3), "48304200": ("48304000", 0)}


def make_fake_tree(root: Path | str, *, style: str = "bone", adc_counts: tuple[int, ...] = (2000, 2000, 2000),
                   iio_index: int = 1) -> Path:
    """Create the sysfs files of the rig under ``root`` (PWM channels and GPIO lines already
    exported, duty 0, DIR low, PWM disabled; ADC channels at ``adc_counts``).  ``style`` is
    ``"bone"`` (channel dirs ``pwm-N:M``) or ``"mainline"`` (``pwmM``).  Returns ``root``."""
    root = Path(root)
    ocp = root / "sys/devices/platform/ocp"
    cls = root / "sys/class/pwm"
    cls.mkdir(parents=True, exist_ok=True)
    for addr, (ss, n) in _CHIPS.items():
        chip = ocp / f"{ss}.epwmss" / f"{addr}.pwm" / "pwm" / f"pwmchip{n}"
        chip.mkdir(parents=True, exist_ok=True)
        for name, text in (("export", ""), ("unexport", ""), ("npwm", "2")):
            (chip / name).write_text(text)
        for ch in (0, 1):
            d = chip / (f"pwm-{n}:{ch}" if style == "bone" else f"pwm{ch}")
            d.mkdir(exist_ok=True)
            for name, text in (("period", str(PERIOD_NS)), ("duty_cycle", "0"), ("enable", "0"),
                               ("polarity", "normal")):
                (d / name).write_text(text)
        link = cls / f"pwmchip{n}"
        if not link.exists():
            os.symlink(os.path.relpath(chip, cls), link)
    gpio = root / "sys/class/gpio"
    gpio.mkdir(parents=True, exist_ok=True)
    (gpio / "export").write_text("")
    (gpio / "unexport").write_text("")
    for k in sorted({gpio_number(p.dir_gpio) for p in RIG_PINS} | {48, 49}):
        d = gpio / f"gpio{k}"
        d.mkdir(exist_ok=True)
        (d / "direction").write_text("in")
        (d / "value").write_text("0")
    iio = root / "sys/bus/iio/devices"
    devices = [(iio_index, "TI-am335x-adc.0.auto")] + ([(0, "44e0d000.tscadc-other")] if iio_index != 0 else [])
    for idx, name in devices:
        d = iio / f"iio:device{idx}"
        d.mkdir(parents=True, exist_ok=True)
        (d / "name").write_text(name + "\n")
        if name.startswith("TI"):
            for ch in range(8):
                (d / f"in_voltage{ch}_raw").write_text("0\n")
            for p, c in zip(RIG_PINS, adc_counts):
                (d / f"in_voltage{p.adc_channel}_raw").write_text(f"{c}\n")
    return root


def snapshot(root: Path | str) -> dict[str, str]:
    """Every regular file under ``root`` (relative path -> content), symlinks not followed."""
    root = Path(root)
    out = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            p = Path(dirpath) / f
            if p.is_symlink():
                continue
            out[str(p.relative_to(root))] = p.read_text()
    return out
