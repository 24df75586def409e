"""A fake sysfs tree of the rig's BeagleBone (the files :mod:`hardware.pins` uses), for tests
and the virtual board.  Chip and device numbers are deliberately not the usual ones, so code
that finds them by number instead of by address or name fails here.
"""
from __future__ import annotations

import os
from pathlib import Path

from .convert import PERIOD_NS
from .pins import GPIO_BANKS, RIG_PINS, gpio_number

#: (address, epwmss, chip number) -- numbers as a 4.19 BeagleBoard kernel might give them.
_CHIPS = {"48300200": ("48300000", 6), "48302200": ("48302000", 3), "48304200": ("48304000", 0)}
#: GPIO character devices: bank -> (chip number, label); numbers not the banks', labels in both
#: kernels' styles (5.10+: the controller's address; 4.19 BeagleBoard: ``gpio-<first>-<last>``).
_GPIOCHIPS = {0: (2, f"{GPIO_BANKS[0]}.gpio"), 1: (0, "gpio-32-63"), 2: (3, f"{GPIO_BANKS[2]}.gpio"),
              3: (1, "gpio-96-127")}


def make_fake_tree(root: Path | str, *, style: str = "bone", adc_counts: tuple[int, ...] = (2000, 2000, 2000),
                   iio_index: int = 1, gpio: str = "sysfs") -> Path:
    """Create the sysfs files of the rig under ``root`` (PWM channels and GPIO lines already
    exported, duty 0, DIR low, PWM disabled; ADC channels at ``adc_counts``).  ``style`` is
    ``"bone"`` (channel dirs ``pwm-N:M``) or ``"mainline"`` (``pwmM``).  ``gpio`` is
    ``"sysfs"`` (``sys/class/gpio``), ``"chardev"`` (``dev/gpiochipN``, served to the daemon by
    the fake kernel ``hardware/c/fake_gpiochip.c`` preloaded, :func:`fake_gpiochip_library`) or
    ``"both"``.  Returns ``root``."""
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
    lines = sorted({gpio_number(p.dir_gpio) for p in RIG_PINS} | {48, 49})
    if gpio not in ("sysfs", "chardev", "both"):
        raise ValueError(f"gpio={gpio!r}: expected sysfs, chardev or both")
    if gpio in ("sysfs", "both"):
        base = root / "sys/class/gpio"
        base.mkdir(parents=True, exist_ok=True)
        (base / "export").write_text("")
        (base / "unexport").write_text("")
        for k in lines:
            d = base / f"gpio{k}"
            d.mkdir(exist_ok=True)
            (d / "direction").write_text("in")
            (d / "value").write_text("0")
    if gpio in ("chardev", "both"):
        dev = root / "dev"
        dev.mkdir(parents=True, exist_ok=True)
        for bank, (n, label) in _GPIOCHIPS.items():
            (dev / f"gpiochip{n}").write_text(f"{label}\n32\n")
            (dev / f"gpiochip{n}.lines").mkdir(exist_ok=True)
        for k in lines:
            n = _GPIOCHIPS[k // 32][0]
            d = dev / f"gpiochip{n}.lines" / str(k % 32)
            d.mkdir(exist_ok=True)
            (d / "direction").write_text("in")
            (d / "value").write_text("0")
            (d / "consumer").write_text("")
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


def fake_gpiochip_library(target: str = "host") -> Path:
    """The fake kernel of a tree's GPIO character devices for ``target``, a library to preload
    into the daemon (``LD_PRELOAD``; a dynamically linked daemon): it answers the uAPI ioctls
    (chip info, line request, set/get values) on ``dev/gpiochipN`` files of a fake tree and keeps
    each line's ``value``, ``direction`` and ``consumer`` in ``dev/gpiochipN.lines/<offset>/``."""
    from .build import build_program

    src = Path(__file__).with_name("c") / "fake_gpiochip.c"
    return build_program("fake_gpiochip.so", {src.name: src.read_text()}, [src.name], target=target, library=True)


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
