"""Pin map and conversions of the rig (SPEC §7; issue 11 acceptance numbers)."""
from __future__ import annotations

import math

import pytest

from hardware import convert, faketree, pins


@pytest.mark.parametrize("volts, duty, dir_high", [(6.0, 25_000, False), (-3.0, 12_500, True),
                                                    (15.0, 50_000, False), (-15.0, 50_000, True),
                                                    (12.0, 50_000, False), (0.0, 0, False)])
def test_volts_to_drive_spec_numbers(volts, duty, dir_high):
    d = convert.volts_to_drive(volts)
    assert (d.duty_ns, d.dir_high, d.fault) == (duty, dir_high, False)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "x", None])
def test_non_finite_command_is_duty_zero_and_fault(bad):
    d = convert.volts_to_drive(bad)
    assert (d.duty_ns, d.dir_high, d.fault) == (0, False, True)


def test_full_stroke_counts_10k_pot():
    # SPEC §7: 4096 * 10k / 11k = 3723.6 at the full 635 mm, ~0.17 mm per count
    assert convert.ideal_counts(0.635) == pytest.approx(4096 * 10 / 11)
    assert round(convert.ideal_counts(0.635)) == 3724
    assert convert.Calibration().metres_per_count * 1e3 == pytest.approx(0.1705, abs=5e-4)


@pytest.mark.parametrize("stroke", [0.0, 0.1, 0.3337, 0.635])
def test_counts_stroke_round_trip(stroke):
    cal = convert.Calibration(raw_zero=37.0, raw_full=3650.0, stroke_full=0.635, s_offset=0.1)
    assert cal.stroke(cal.counts(stroke)) == pytest.approx(stroke, abs=1e-12)
    assert cal.leg_length(cal.counts(stroke)) == pytest.approx(0.1 + stroke, abs=1e-12)


@pytest.mark.parametrize("level, raw", [(-3.0, 0), (1.4, 1), (4095.6, 4095), (9999, 4095)])
def test_quantise_12_bit(level, raw):
    assert convert.quantise(level) == raw


@pytest.mark.parametrize("label, number", [("gpio0_30", 30), ("gpio1_28", 60), ("gpio0_31", 31), ("60", 60), (7, 7)])
def test_gpio_numbers(label, number):
    assert pins.gpio_number(label) == number


@pytest.mark.parametrize("style", ["bone", "mainline"])
def test_resolve_finds_chips_by_address_and_adc_by_name(tmp_path, style):
    faketree.make_fake_tree(tmp_path, style=style, iio_index=2)
    legs = pins.resolve(tmp_path)
    # chip numbers in the fake tree (3 and 6) differ from the usual ones; SPEC §7 addresses decide
    assert "48302200.pwm" in str(legs[0].pwm) and legs[0].pwm.name.endswith("0")
    assert "48302200.pwm" in str(legs[1].pwm) and legs[1].pwm.name.endswith("1")
    assert "48300200.pwm" in str(legs[2].pwm) and legs[2].pwm.name.endswith("1")
    assert [leg.dir.name for leg in legs] == ["gpio30", "gpio60", "gpio31"]
    assert [leg.adc.name for leg in legs] == ["in_voltage4_raw", "in_voltage6_raw", "in_voltage5_raw"]
    assert legs[0].adc.parent.name == "iio:device2"


def test_missing_chip_names_the_address(tmp_path):
    faketree.make_fake_tree(tmp_path)
    with pytest.raises(pins.PinError, match="48399999"):
        pins.find_pwm_chip(tmp_path, "48399999")
