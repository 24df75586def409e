"""The virtual board's plant and the actuator block, stepped together with the C daemon on
synthetic time (its ``--step`` harness, no wall clock): the plant's motion against the actuator's analytic step response, and each
failure option against the daemon's documented fault."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

from hardware import daemon, faketree, protocol as P, virtual
from hardware.convert import Calibration
from models.blocks import make

MS = 1_000_000
V_NL, TAU = 0.02032, 0.02  # FA-200-L-12 (SPEC §7) and the block's assumed time constant


def step_response(u: float, t: float) -> float:
    """Stroke gained [m] from rest after a voltage step ``u`` held for ``t`` seconds:
    ``x = v_nl (u/12) (t - tau (1 - exp(-t/tau)))`` (first-order speed lag)."""
    return V_NL * u / 12 * (t - TAU * (1 - math.exp(-t / TAU)))


def _fmu_states(blk, u: list[float], steps: int, cache, states: list[str], **params: float) -> list[float]:
    """The states ``states`` of the block's FMU (its end stops located inside doStep) after
    ``steps`` steps of 1 ms with the inputs ``u`` held."""
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave

    from fmus import build_fmu

    path = build_fmu(blk, cache_dir=cache)
    md = read_model_description(str(path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=extract(str(path)), modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="actuator")
    fmu.instantiate()
    fmu.setReal([vr[k] for k in params], list(params.values()))
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.setReal([v.valueReference for v in md.modelVariables if v.causality == "input"], u)
    fmu.exitInitializationMode()
    for k in range(steps):
        fmu.doStep(k * 1e-3, 1e-3)  # raises on an error
    out = fmu.getReal([vr[n] for n in states])
    fmu.terminate()
    fmu.freeInstance()
    return out


@pytest.mark.parametrize("fidelity, u", [("single", 12.0), ("single", -6.0), ("rig", 3.0)])
def test_actuator_block_step_response(fidelity, u, cache):
    blk = make("linear_actuator", fidelity)
    names = ["state.stroke", "state.v"] if fidelity == "single" else ["state.leg[1].stroke", "state.leg[1].v"]
    uu = [u, 0.0] if fidelity == "single" else [u, u, u]
    x0 = _fmu_states(blk, uu, 0, cache, names)[0]
    x = _fmu_states(blk, uu, 700, cache, names)
    assert x[0] - x0 == pytest.approx(step_response(u, 0.7), rel=1e-6)
    assert x[1] == pytest.approx(V_NL * u / 12 * (1 - math.exp(-0.7 / TAU)), rel=1e-6)


@pytest.mark.parametrize("preset, accel", [("fa200", 0.02032 / 0.02), ("x", 147.15)])
def test_actuator_presets_initial_acceleration(preset, accel):
    # the X actuator's one published figure: 15 g from rest at the rated voltage (thesis 8.1.7)
    blk = make("linear_actuator", "single", actuator=preset)
    xdot = blk.functions()["ode"]([0.1, 0.0], [12.0, 0.0], blk.param_defaults, [0.0] * blk.m.numel())
    assert float(xdot[1]) == pytest.approx(accel, rel=1e-9)


def test_end_stop_holds_the_stroke(cache):
    blk = make("linear_actuator", "single")  # s0 = 0.59 m: 9 mm from the end of the 0.5 m stroke
    x = _fmu_states(blk, [12.0, 0.0], 2000, cache, ["state.stroke"], s0=0.59)
    assert x[0] == pytest.approx(0.5, abs=V_NL * 1e-3)


_OPEN: list = []


@pytest.fixture(autouse=True)
def _close_daemons():
    yield
    while _OPEN:
        _OPEN.pop().close()


def rig(tmp_path, **opts):
    tree = faketree.make_fake_tree(tmp_path / "tree")
    plant = virtual.Plant(tree, virtual.PlantOptions(**opts))
    key = os.urandom(32)
    d = daemon.Stepped(key, root=tree)
    _OPEN.append(d)
    nonce = P.new_nonce()
    t = 1000 * MS
    dg = P.parse(d.handle(P.pack(key, P.HELLO, 0, 0, t, nonce), None, t))
    skey = P.session_key(key, nonce, dg.fields[1])
    seq = [0]

    def send(flags, volts, now):
        seq[0] += 1
        d.handle(P.pack(skey, P.COMMAND, dg.session, seq[0], now, flags, *volts), None, now)
    send(P.ARM, (0, 0, 0), t)
    return d, plant, send, t


def drive(d, plant, send, t0, volts, seconds):
    """Command ``volts`` every millisecond for ``seconds``; the plant follows in the same time."""
    for k in range(1, int(seconds * 1000) + 1):
        now = t0 + k * MS
        if d.state != P.FAULT:
            send(P.RUN, volts, now)
        d.tick(now)
        plant.advance(1e-3, now / 1e9)
    return t0 + int(seconds * 1000) * MS


def test_plant_follows_the_daemons_outputs(tmp_path):
    d, plant, send, t0 = rig(tmp_path)
    s0 = [plant.stroke(i) for i in range(3)]
    drive(d, plant, send, t0, (6.0, -12.0, 0.0), 0.5)
    cal = Calibration(s_offset=0.1)
    for i, u in enumerate((6.0, -12.0, 0.0)):
        # the voltage reaches the motor between 1 ms (the first command's update) and 1 ms plus the
        # daemon's slew ramp (|u| / 2400 V/s) after the step: the motion lies between both responses
        late = 1e-3 + abs(u) / d.safety.slew
        lo, hi = sorted((step_response(u, 0.5 - late), step_response(u, 0.5)))
        assert lo - 1e-12 <= plant.stroke(i) - s0[i] <= hi + 1e-12
        raw = int(d.files[i].adc.read_text())
        assert abs(cal.stroke(raw) - plant.stroke(i)) <= cal.metres_per_count / 2 + 1e-12  # 12-bit quantisation
    assert d.state == P.RUNNING and d.faults == 0


@pytest.mark.parametrize("option, fault", [({"stuck": (2,)}, P.F_ADC_STUCK), ({"driver_fault": (1,)}, P.F_ADC_STUCK),
                                           ({"unplugged": (3,)}, P.F_ADC_RANGE)])
def test_plant_failures_give_the_documented_fault_and_safe_outputs(tmp_path, option, fault):
    d, plant, send, t0 = rig(tmp_path, **option)
    drive(d, plant, send, t0, (12.0, 12.0, -12.0), 0.6)
    assert d.state == P.FAULT and d.faults == fault
    assert [(f.duty.read_text(), f.dir_value.read_text()) for f in d.files] == [("0", "0")] * 3
    still = [plant.stroke(i) for i in range(3)]
    drive(d, plant, send, t0 + 600 * MS, (12.0, 12.0, -12.0), 0.2)  # latched: nothing moves any more
    assert [plant.stroke(i) for i in range(3)] == pytest.approx(still, abs=V_NL * TAU * 1.01)


def test_noise_option_spreads_the_counts(tmp_path):
    tree = faketree.make_fake_tree(tmp_path / "tree")
    plant = virtual.Plant(tree, virtual.PlantOptions(noise=3.0, seed=4))
    adc = plant.legs[0].adc
    raws = []
    for k in range(400):
        plant.advance(1e-3, k * 1e-3)
        raws.append(int(adc.read_text()))
    assert np.std(raws) == pytest.approx(3.0, rel=0.15)


def test_latency_option_delays_the_counts(tmp_path):
    tree = faketree.make_fake_tree(tmp_path / "tree")
    plant = virtual.Plant(tree, virtual.PlantOptions(latency=0.05))
    adc = plant.legs[0].adc
    first = int(adc.read_text())
    plant.fmu.setReal(plant.vr_u[:1], [12.0])
    seen = []
    for k in range(1, 200):
        plant.volts = [12.0, 0.0, 0.0]
        plant.fmu.setReal(plant.vr_u, plant.volts)
        plant.fmu.doStep(plant.t, 1e-3)
        plant.t += 1e-3
        plant.strokes = plant.fmu.getReal(plant.vr_stroke)
        plant._write_counts(plant._levels(), k * 1e-3)
        seen.append(int(adc.read_text()))
    moved = next(i for i, r in enumerate(seen) if r != first) + 1  # ms until the reading changes
    undelayed = next(k for k in range(1, 200) if round(Calibration(s_offset=0.1).counts(
        0.21086 + step_response(12.0, k * 1e-3))) != first)
    assert moved - undelayed == pytest.approx(50, abs=1)
