"""The BeagleBone Black pin map of the rig (docs/explanation/thesis.md §7, thesis Table 8.2) as data, and the sysfs
files behind it, resolved under a configurable ``root`` ("/" on the board, a temporary fake
tree in tests).  The daemon is compiled with this map (``board_config.h``) and resolves it the
same way in C (``hardware/c/board_io.c``); :func:`resolve` here is how the virtual board's plant
and the tests find the files the daemon drives.

- PWM: chips are found by their hardware address (``48302200`` ...), never by ``pwmchipN``,
  whose number changes between kernels: each ``<root>/sys/class/pwm/pwmchipN`` is a symlink into
  ``.../<addr>.pwm/pwm/pwmchipN`` (or ``<addr>.ehrpwm``).  The channel directory is ``pwmM``
  (mainline) or ``pwm-N:M`` (BeagleBoard 4.14+ kernels); it is exported when absent.
- GPIO: a line is named by its number ``30`` or its SoC label ``gpio0_30`` (bank * 32 + line).
  The board daemon uses the GPIO character device when the board has one (``<root>/dev/gpiochipN``,
  the chip labelled with the bank's address :data:`GPIO_BANKS` or ``gpio-<first>-<last>``), and
  sysfs ``<root>/sys/class/gpio/gpioK/{direction,value}`` otherwise.  In a fake tree the
  character device's line K of chip N is the directory ``dev/gpiochipN.lines/K`` (what the
  fake kernel, ``hardware/c/fake_gpiochip.c``, writes), so this module finds DIR in both.
- ADC: the IIO device whose ``name`` starts with ``TI-am335x-adc``, channel files
  ``in_voltage<ch>_raw``.
"""
from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

ADC_NAME_PREFIX = "TI-am335x-adc"
#: AM335x GPIO banks 0..3 by their controller's address.
GPIO_BANKS = ("44e07000", "4804c000", "481ac000", "481ae000")


class PinError(OSError):
    """A pin's sysfs file cannot be found or used; the message names the file."""


@dataclass(frozen=True)
class LegPins:
    """The three signals of one leg: PWM (chip address, channel), DIR GPIO line, ADC channel."""

    pwm_chip: str
    pwm_channel: int
    dir_gpio: str
    adc_channel: int
    header: str = ""  # the P9 pins, for people wiring the rig


#: docs/explanation/thesis.md §7: legs 1..3.
RIG_PINS: tuple[LegPins, ...] = (
    LegPins("48302200", 0, "gpio0_30", 4, "PWM P9-14 (EHRPWM1A), DIR P9-11, pot P9-33 (AIN4)"),
    LegPins("48302200", 1, "gpio1_28", 6, "PWM P9-16 (EHRPWM1B), DIR P9-12, pot P9-35 (AIN6)"),
    LegPins("48300200", 1, "gpio0_31", 5, "PWM P9-21 (EHRPWM0B), DIR P9-13, pot P9-36 (AIN5)"),
)


def gpio_number(line: str | int) -> int:
    """Linux GPIO number of ``line``: an integer, ``"60"`` or a SoC label ``"gpio1_28"`` (= 60)."""
    if isinstance(line, int):
        return line
    text = str(line).strip()
    m = re.fullmatch(r"gpio(\d+)_(\d+)", text)
    if m:
        bank, idx = int(m.group(1)), int(m.group(2))
        if idx >= 32:
            raise PinError(f"GPIO label {text!r}: a bank has lines 0..31")
        return bank * 32 + idx
    if text.isdigit():
        return int(text)
    raise PinError(f"GPIO line {text!r}: expected a number (60) or a label (gpio1_28)")


def find_pwm_chip(root: Path, address: str) -> Path:
    """The ``pwmchipN`` directory of the PWM controller at ``address`` (hex, e.g. 48302200)."""
    cls = Path(root) / "sys/class/pwm"
    if not cls.is_dir():
        raise PinError(f"no PWM class directory {cls} (is the PWM overlay loaded?)")
    found = []
    for entry in sorted(cls.glob("pwmchip*")):
        target = os.path.realpath(entry)
        if re.search(rf"/{re.escape(address)}\.(e?hr)?pwm/", target + "/") or f"/{address}.pwm/" in target:
            found.append(Path(target))
    if not found:
        raise PinError(f"no PWM chip at address {address} under {cls} (chips: "
                       f"{', '.join(p.name for p in cls.glob('pwmchip*')) or 'none'})")
    return found[0]


def pwm_channel_dir(chip: Path, channel: int, *, export: bool = True, wait_s: float = 1.0) -> Path:
    """The channel directory (``pwmM`` or ``pwm-N:M``), exported through ``export`` if absent."""
    n = chip.name.removeprefix("pwmchip")
    cands = [chip / f"pwm{channel}", chip / f"pwm-{n}:{channel}"]
    for c in cands:
        if c.is_dir():
            return c
    if not export:
        raise PinError(f"PWM channel {channel} of {chip} is not exported")
    _write(chip / "export", str(channel))
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        for c in cands:
            if c.is_dir():
                return c
        time.sleep(0.01)
    raise PinError(f"exporting PWM channel {channel} of {chip} made no {cands[0].name} or {cands[1].name}")


def chardev_line_dir(root: Path, k: int) -> Path | None:
    """A fake tree's character-device line ``k`` (``dev/gpiochipN.lines/<offset>``, the chip
    found by its label as the daemon finds it), or None when the tree has no such chip."""
    bank, offset = divmod(k, 32)
    if bank >= len(GPIO_BANKS):
        return None
    for chip in sorted(Path(root).glob("dev/gpiochip*")):
        if not chip.is_file():
            continue
        label = chip.read_text().splitlines()[0].strip() if chip.stat().st_size else ""
        if label == f"gpio-{bank * 32}-{bank * 32 + 31}" or GPIO_BANKS[bank] in label:
            d = chip.with_name(chip.name + ".lines") / str(offset)
            return d if d.is_dir() else None
    return None


def gpio_dir(root: Path, line: str | int, *, export: bool = True, wait_s: float = 1.0) -> Path:
    """``<root>/sys/class/gpio/gpioK`` (exported through ``export`` if absent), or a fake tree's
    character-device line directory when the tree has the chip and no sysfs GPIO class."""
    k = gpio_number(line)
    base = Path(root) / "sys/class/gpio"
    d = base / f"gpio{k}"
    if d.is_dir():
        return d
    cd = chardev_line_dir(Path(root), k)
    if cd is not None and not base.is_dir():
        return cd
    if not export:
        raise PinError(f"GPIO {k} is not exported ({d})")
    _write(base / "export", str(k))
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if d.is_dir():
            return d
        time.sleep(0.01)
    raise PinError(f"exporting GPIO {k} made no {d}")


def find_adc(root: Path) -> Path:
    """The IIO device directory of the AM335x ADC (found by its ``name``)."""
    base = Path(root) / "sys/bus/iio/devices"
    for dev in sorted(base.glob("iio:device*")):
        try:
            if (dev / "name").read_text().strip().startswith(ADC_NAME_PREFIX):
                return dev
        except OSError:
            continue
    raise PinError(f"no IIO device named {ADC_NAME_PREFIX}* under {base} (is the ADC overlay loaded?)")


@dataclass(frozen=True)
class LegFiles:
    """The resolved files of one leg."""

    pwm: Path  # the channel directory
    dir: Path  # the gpio directory
    adc: Path  # in_voltageN_raw

    @property
    def duty(self) -> Path:
        return self.pwm / "duty_cycle"

    @property
    def period(self) -> Path:
        return self.pwm / "period"

    @property
    def enable(self) -> Path:
        return self.pwm / "enable"

    @property
    def dir_value(self) -> Path:
        return self.dir / "value"

    @property
    def dir_direction(self) -> Path:
        return self.dir / "direction"

    def written(self) -> list[Path]:
        """Every file the daemon may write for this leg."""
        return [self.duty, self.period, self.enable, self.pwm / "polarity", self.dir_value, self.dir_direction]


def resolve(root: Path | str = "/", pins: tuple[LegPins, ...] = RIG_PINS, *, export: bool = True) -> list[LegFiles]:
    """The files of every leg under ``root`` (exporting channels and lines when needed)."""
    root = Path(root)
    adc = find_adc(root)
    legs = []
    for i, p in enumerate(pins, start=1):
        chip = find_pwm_chip(root, p.pwm_chip)
        raw = adc / f"in_voltage{p.adc_channel}_raw"
        if not raw.exists():
            raise PinError(f"leg {i}: ADC channel file {raw} is missing")
        legs.append(LegFiles(pwm_channel_dir(chip, p.pwm_channel, export=export), gpio_dir(root, p.dir_gpio, export=export), raw))
    return legs


def _write(path: Path, text: str) -> None:
    try:
        with open(path, "w") as fh:
            fh.write(text)
    except OSError as exc:
        raise PinError(f"cannot write {text!r} to {path}: {exc.strerror or exc}") from None
