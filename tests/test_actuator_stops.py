"""The linear actuator's clamping end stops as located events (models/blocks/_stops.py
``clamp_stops``), against the closed form of the first-order speed lag: the rod's arrival on a
stop, its rest there while the motor speed runs on, its release where that speed changes sign;
and the clamp beside the impact law with restitution 0, which must agree while the rod rests."""
from __future__ import annotations

import math

import numpy as np
import pytest
from fmpy import extract, read_model_description
from fmpy.fmi2 import FMU2Slave
from scipy.optimize import brentq

from fmus import build_fmu
from models.blocks import make

V_NL, TAU = 0.02032, 0.02  # FA-200-L-12: no-load speed at 12 V [m/s]; the block's speed lag [s]
HI = 0.02  # a short stroke [m], so both stops are reached in a few seconds


def v_at(v0: float, v_free: float, t: float) -> float:
    """Motor speed [m/s] ``t`` seconds after it was ``v0``, the drive's free speed ``v_free``."""
    return v_free + (v0 - v_free) * math.exp(-t / TAU)


def travel(v0: float, v_free: float, t: float) -> float:
    """Stroke gained [m] in ``t`` seconds from the speed ``v0`` (the integral of :func:`v_at`)."""
    return v_free * t + (v0 - v_free) * TAU * (1 - math.exp(-t / TAU))


def release(v0: float, v_free: float) -> float:
    """Time [s] for the speed to fall from ``v0`` to 0 towards ``v_free`` (of the other sign)."""
    return TAU * math.log((v0 - v_free) / -v_free)


def analytic_events(x0: float, t_rev: float, t_back: float) -> dict[str, float]:
    """12 V from rest at the stroke ``x0``, -12 V from ``t_rev``, +12 V from ``t_back``: the
    arrivals at ``HI`` and 0 and the releases from them (the lag's closed form, roots by Brent)."""
    up = brentq(lambda t: x0 + travel(0.0, V_NL, t) - HI, 0.0, 5.0, xtol=1e-15, rtol=1e-15)
    rel_up = t_rev + release(v_at(0.0, V_NL, t_rev), -V_NL)  # the speed wound up from rest since t = 0
    down = rel_up + brentq(lambda t: HI + travel(0.0, -V_NL, t), 0.0, 5.0, xtol=1e-15, rtol=1e-15)
    rel_down = t_back + release(-v_at(0.0, -V_NL, t_back - rel_up), -V_NL)  # mirrored
    return {"up": up, "rel_up": rel_up, "down": down, "rel_down": rel_down}


class Actuator:
    """The ``single`` actuator's FMU (FMPy), stepped at 1 ms, read by variable names."""

    def __init__(self, cache, end_stops: str, integrator: str, x0: float, **params: float) -> None:
        path = build_fmu(make("linear_actuator", "single", end_stops=end_stops, integrator=integrator, substeps=10),
                         cache_dir=cache)
        md = read_model_description(str(path))
        self.vr = {v.name: v.valueReference for v in md.modelVariables}
        self.fmu = FMU2Slave(guid=md.guid, unzipDirectory=extract(str(path)),
                             modelIdentifier=md.coSimulation.modelIdentifier, instanceName="leg")
        self.fmu.instantiate()
        self.set(stroke_max=HI, s0=0.1 + x0, **params)
        self.fmu.setupExperiment(startTime=0.0)
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()
        self.t = 0.0

    def set(self, **values: float) -> None:
        self.fmu.setReal([self.vr[k] for k in values], list(values.values()))

    def get(self, *names: str) -> list[float]:
        return self.fmu.getReal([self.vr[k] for k in names])

    def run_to(self, t_end: float, u: float) -> None:
        self.set(u=u)
        while self.t < t_end - 1e-9:
            self.fmu.doStep(self.t, 1e-3)
            self.t = round(self.t + 1e-3, 9)


@pytest.mark.parametrize("integrator", ["rk4", "radau"])
def test_clamp_arrivals_and_releases_at_the_closed_form_times(integrator, cache):
    """Arrival at the upper stop, rest (stroke exactly on it, rod rate 0, the motor speed winding
    up as the free lag), release when that speed changes sign after the drive reverses, arrival at
    the lower stop and release from it: every time within 1e-10 s of the closed form (measured: 4e-12 s)."""
    x0, t_rev, t_back = 0.01, 0.8, 2.5
    want = analytic_events(x0, t_rev, t_back)
    a = Actuator(cache, "clamp", integrator, x0)
    a.run_to(t_rev, 12.0)
    stroke, rate, v, n, t_in = a.get("stroke", "v", "state.v", "impacts", "mode.t_arrival")
    assert (n, stroke, rate) == (1.0, HI, 0.0)
    assert t_in == pytest.approx(want["up"], abs=1e-10)
    assert v == pytest.approx(v_at(0.0, V_NL, t_rev), rel=1e-9)  # the motor ran on, from rest at t = 0
    a.run_to(1.3, -12.0)
    t_out, stroke = a.get("mode.t_release", "stroke")
    assert t_out == pytest.approx(want["rel_up"], abs=1e-10)
    assert stroke == pytest.approx(HI + travel(0.0, -V_NL, 1.3 - want["rel_up"]), abs=1e-12)
    a.run_to(t_back, -12.0)
    n, t_in, stroke, hold = a.get("impacts", "mode.t_arrival", "stroke", "mode.hold")
    assert (n, stroke, hold) == (2.0, 0.0, -1.0)
    assert t_in == pytest.approx(want["down"], abs=1e-10)
    a.run_to(3.0, 12.0)
    t_out, hold = a.get("mode.t_release", "mode.hold")
    assert hold == 0.0 and t_out == pytest.approx(want["rel_down"], abs=1e-10)


def test_clamp_and_impact_without_restitution_agree_while_the_rod_rests(cache):
    """The same approach, the same arrival and the same stroke and rod rate while resting; they
    part at the release: the impact law zeroed the motor speed, so the rod leaves the moment the
    drive reverses, while the clamp's wound-up speed must first decay (the closed form's delay)."""
    x0, t_rev = 0.01, 0.8
    runs = {k: Actuator(cache, k, "rk4", x0) for k in ("clamp", "impact")}
    rows = {k: [] for k in runs}
    for t in np.arange(0.05, t_rev + 1e-9, 0.05):
        for k, a in runs.items():
            a.run_to(t, 12.0)
            rows[k].append(a.get("stroke", "v", "impacts"))
    assert np.array_equal(rows["clamp"], rows["impact"])
    clamp, impact = runs["clamp"], runs["impact"]
    assert impact.get("state.v") == [0.0] and clamp.get("state.v")[0] > 0.99 * V_NL
    for a in runs.values():
        a.run_to(t_rev + 1e-3, -12.0)
    assert impact.get("mode.hold") == [0.0] and impact.get("stroke")[0] < HI  # left at once
    assert clamp.get("mode.hold") == [1.0] and clamp.get("stroke") == [HI]  # still held
    clamp.run_to(1.3, -12.0)
    assert clamp.get("mode.t_release")[0] == pytest.approx(t_rev + release(v_at(0.0, V_NL, t_rev), -V_NL), abs=1e-10)


@pytest.mark.parametrize("end_stops", ["clamp", "impact"])
def test_a_leg_started_on_a_stop_rests_there_or_leaves_it(end_stops, cache):
    """Started on a stop (its arrival indicator exactly 0, which never fires: without the start
    mode a drive pushing outwards carried the rod through the stop): pushed into it, the rod
    rests there; pulled away, it leaves at once along the free lag from rest."""
    for x0, u, side in ((HI, 12.0, 1.0), (HI, -12.0, 0.0), (0.0, -12.0, -1.0), (0.0, 12.0, 0.0)):
        a = Actuator(cache, end_stops, "rk4", x0)
        assert a.get("mode.hold") == [1.0 if x0 else -1.0]
        a.run_to(0.3, u)
        stroke, hold = a.get("stroke", "mode.hold")
        assert hold == side, (x0, u)
        want = x0 if side else x0 + travel(0.0, V_NL * u / 12, 0.3)
        assert stroke == pytest.approx(want, abs=1e-10), (x0, u)
