"""Events in blocks and FMUs (docs/explanation/events.md): the Block contract's checks, crossings
located inside doStep against analytic event times, rollback with modes, bounded event iteration
and chattering, time events."""
from __future__ import annotations

import re

from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from fmpy import extract, read_model_description
from fmpy.fmi2 import FMU2Slave
from fmpy.validation import validate_fmu
from scipy.special import ellipk

from fmus import build_fmu
from fmus.errors import BuildError
from models.block import FALLING, RISING, Block, BlockError, Param, Sample, Var
from models.blocks import make

ROOT = Path(__file__).resolve().parents[1]


def analytic_impacts(n: int, L=0.5, g=9.81, theta0=1.0, e=0.7) -> np.ndarray:
    """Impact times of the pendulum on a stop at its lowest point: a quarter period of the
    nonlinear pendulum, then half periods, each amplitude from the previous impact's energy."""
    w0, amp, t, out = np.sqrt(g / L), theta0, 0.0, []
    for k in range(n):
        K = ellipk(np.sin(amp / 2) ** 2)
        t += (K if k == 0 else 2 * K) / w0
        out.append(t)
        amp = np.arccos(1 - e ** 2 * (1 - np.cos(amp)))
    return np.array(out)


class Slave:
    """An FMI 2 slave of FMPy over a built FMU, addressed by variable names."""

    def __init__(self, path: Path, name: str = "s") -> None:
        md = read_model_description(str(path))
        self.vr = {v.name: v.valueReference for v in md.modelVariables}
        self.messages: list[str] = []
        self.fmu = FMU2Slave(guid=md.guid, unzipDirectory=extract(str(path)),
                             modelIdentifier=md.coSimulation.modelIdentifier, instanceName=name)
        self.fmu.instantiate(loggingOn=False)

    def start(self, **inputs: float) -> "Slave":
        self.fmu.setupExperiment(startTime=0.0)
        self.fmu.enterInitializationMode()
        self.set(**inputs)
        self.fmu.exitInitializationMode()
        return self

    def set(self, **values: float) -> None:
        if values:
            self.fmu.setReal([self.vr[k] for k in values], list(values.values()))

    def get(self, *names: str) -> list[float]:
        return self.fmu.getReal([self.vr[k] for k in names])


@pytest.fixture(scope="module")
def pendulum_fmus(cache) -> dict[str, Path]:
    return {integ: build_fmu(make("pendulum", "stop", integrator=integ), cache_dir=cache) for integ in ("rk4", "radau")}


def impact_times(path: Path, h: float, n: int = 5) -> np.ndarray:
    s = Slave(path).start()
    t, seen, times = 0.0, 0, []
    while len(times) < n and t < 10:
        s.fmu.doStep(t, h)
        t += h
        count, when = s.get("mode.impacts", "mode.t_impact")
        if count > seen:
            assert count == seen + 1, "two impacts in one communication step"
            times.append(when)
            seen = int(count)
    return np.array(times)


@pytest.mark.parametrize("integrator", ["rk4", "radau"])
def test_pendulum_impacts_within_1e_9_s_of_the_elliptic_integral(pendulum_fmus, integrator):
    got = impact_times(pendulum_fmus[integrator], 1e-2)
    assert np.max(np.abs(got - analytic_impacts(5))) < 1e-9, got - analytic_impacts(5)


def test_pendulum_fmus_pass_fmpy_validation(pendulum_fmus, cache):
    assert validate_fmu(str(pendulum_fmus["rk4"])) == []
    assert validate_fmu(str(build_fmu(make("pendulum", "stop"), fmi_version="3.0", cache_dir=cache))) == []


def test_pendulum_scene_under_the_master_hits_the_analytic_times(cache):
    from cosim.run.execute import run

    res = run(ROOT / "scenarios" / "pendulum_stop.yaml", cache_dir=cache)
    assert res.ok, res.reason
    tr = res.trace
    times = np.unique(tr["pend.t_impact"])[1:]
    assert len(times) == 5
    assert np.max(np.abs(times - analytic_impacts(5))) < 1e-9
    # between impacts the angle never goes below the stop (the crossing's far side is within 1e-12 rad)
    assert tr["pend.theta"].min() > -1e-9


@pytest.mark.parametrize("integrator", ["rk4", "radau"])
def test_rollback_restores_modes_and_finds_the_same_events(pendulum_fmus, integrator):
    s = Slave(pendulum_fmus[integrator]).start()
    s.fmu.doStep(0.0, 0.3)
    state = s.fmu.getFMUstate()
    blob = s.fmu.serializeFMUstate(state)
    names = ("state.theta", "state.omega", "mode.impacts", "mode.t_impact")
    s.fmu.doStep(0.3, 0.2)  # the first impact, at 0.378 s, is inside
    first = s.get(*names)
    assert first[2] == 1.0
    s.fmu.setFMUstate(state)
    assert s.get("mode.impacts")[0] == 0.0
    s.fmu.doStep(0.3, 0.2)
    assert s.get(*names) == first
    s.fmu.setFMUstate(s.fmu.deSerializeFMUstate(blob))
    s.fmu.doStep(0.3, 0.2)
    assert s.get(*names) == first


def test_modes_cannot_be_set(pendulum_fmus):
    s = Slave(pendulum_fmus["rk4"]).start()
    with pytest.raises(Exception):
        s.set(**{"mode.impacts": 3.0})


def _ball(e: float, **kw) -> Block:
    """A ball under gravity on the floor (h = 0), restitution ``e``: Zeno for e < 1."""
    h, v, g = ca.SX.sym("h"), ca.SX.sym("v"), ca.SX.sym("g")
    return Block.build("ball", params=[Param("g", 9.81, "m/s2")], inputs=[], outputs=[Var("h", "m")],
                       states=[Var("state.h", "m"), Var("state.v", "m/s")], p=g, u=ca.SX(0, 1),
                       x=ca.vertcat(h, v), ode=ca.vertcat(v, -g), out=h, start=[1.0, 0.0],
                       indicators=h, directions=[FALLING], updates=[ca.vertcat(h, -e * v)], event_names=["floor"], **kw)


def test_zeno_ball_fails_the_step_naming_the_chattering(cache):
    path = build_fmu(_ball(0.5), cache_dir=cache)
    s = Slave(path).start()
    logs: list[str] = []
    # t_inf = sqrt(2/g) (1 + e) / (1 - e) = 1.355 s; the step that contains it fails
    t, status = 0.0, None
    for _ in range(300):
        try:
            s.fmu.doStep(t, 0.01)
        except Exception as exc:  # FMPy raises on fmi2Error
            status = str(exc)
            break
        t += 0.01
    assert status is not None and 1.3 < t < 1.36, (t, status)


def test_event_iteration_is_bounded():
    """An update that flips a mode which flips its own indicator never settles."""
    x, m = ca.SX.sym("x"), ca.SX.sym("m")
    blk = Block.build("flip", params=[], inputs=[], outputs=[Var("y")], states=[Var("state.x")], p=ca.SX(0, 1),
                      u=ca.SX(0, 1), x=x, ode=ca.SX(1.0), out=m, start=[0.0], modes=[Var("mode.m")], m=m,
                      mode_start=[0.0], indicators=ca.vertcat(x - 0.5, m - 0.5), directions=[RISING, 0],
                      updates=[ca.vertcat(x, 1 - m), ca.vertcat(x, 1 - m)], event_names=["go", "flip"])
    s = Slave(build_fmu(blk)).start()
    with pytest.raises(Exception):
        s.fmu.doStep(0.0, 1.0)


def test_time_events_sample_the_input_at_their_instants(cache):
    """A sample-and-hold (no states, one mode) at 0.3 s inside 1 s steps, the input a ramp
    given by its slope: the held values are the ramp at the sample instants."""
    u, m, t = ca.SX.sym("u"), ca.SX.sym("held"), ca.SX.sym("t")
    blk = Block.build("hold", params=[], inputs=[Var("u")], outputs=[Var("y")], states=[], p=ca.SX(0, 1), u=u,
                      x=ca.SX(0, 1), ode=ca.SX(0, 1), out=m, start=ca.SX(0, 1), modes=[Var("mode.held")], m=m,
                      mode_start=[-1.0], t=t, integrator="none",
                      sample_times=[Sample(0.3, 0.1, ca.vertcat(u), "adc")])
    s = Slave(build_fmu(blk, cache_dir=cache)).start(u=5.0)
    assert s.get("y") == [-1.0]  # the first sample is at 0.1 s
    held = []
    for k in range(3):
        s.set(u=5.0 + 2.0 * k)
        s.fmu.setRealInputDerivatives([s.vr["u"]], [1], [2.0])  # u(t) = 5 + 2 t
        s.fmu.doStep(float(k), 1.0)
        held.append(s.get("y")[0])
    # samples at 0.1, 0.4, 0.7 | 1.0, 1.3, 1.6, 1.9 | 2.2, 2.5, 2.8: the last of each step
    assert held == pytest.approx([5 + 2 * 0.7, 5 + 2 * 1.9, 5 + 2 * 2.8], abs=1e-12)


@pytest.mark.parametrize("change, message", [
    (dict(directions=[2]), "direction of indicator"),
    (dict(updates=[ca.SX.sym("q")]), r"update of .z\[0\]. uses symbol .q."),
    (dict(updates=[ca.SX.ones(2)]), r"update of .z\[0\]. has shape"),
    (dict(directions=[1, 1]), "2 directions for 1 indicators"),
    (dict(integrator="discrete", sample_period=0.1), "events need one of the integrators"),
    (dict(sample_times=[Sample(0.0)]), "finite period > 0"),
])
def test_block_event_declarations_are_checked(change, message):
    x = ca.SX.sym("x")
    kw = dict(params=[], inputs=[], outputs=[Var("y")], states=[Var("state.x")], p=ca.SX(0, 1), u=ca.SX(0, 1), x=x,
              ode=-x, out=x, start=[1.0], indicators=x - 0.5, directions=[FALLING])
    kw.update(change)
    with pytest.raises(BlockError, match=message):
        Block.build("b", **kw)


def test_time_in_the_ode_is_refused_with_a_hint():
    x, t = ca.SX.sym("x"), ca.SX.sym("t")
    with pytest.raises(BlockError, match="time appears in indicators and updates only"):
        Block.build("b", params=[], inputs=[], outputs=[Var("y")], states=[Var("state.x")], p=ca.SX(0, 1),
                    u=ca.SX(0, 1), x=x, ode=-x + t, out=x, start=[1.0], t=t, indicators=x, directions=[FALLING])


def test_fmi3_event_mode_returns_early_at_each_impact(cache):
    """FMI 3 with eventModeUsed and earlyReturnAllowed: doStep stops at the impact with the state
    at its left limit (rate still negative); the update comes in event mode."""
    from fmpy.fmi3 import FMU3Slave

    path = build_fmu(make("pendulum", "stop"), fmi_version="3.0", cache_dir=cache)
    md = read_model_description(str(path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    fmu = FMU3Slave(guid=md.guid, unzipDirectory=extract(str(path)), modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="p")
    fmu.instantiate(eventModeUsed=True, earlyReturnAllowed=True)
    fmu.enterInitializationMode(startTime=0.0)
    fmu.exitInitializationMode()
    fmu.updateDiscreteStates()
    fmu.enterStepMode()
    t, times = 0.0, []
    while len(times) < 5:
        need, _, early, reached = fmu.doStep(t, 0.01)
        if need:
            assert early or reached == pytest.approx(t + 0.01)
            theta, omega = fmu.getFloat64([vr["state.theta"], vr["state.omega"]])
            assert omega < 0 and abs(theta) < 1e-9  # the left limit: not yet bounced
            fmu.enterEventMode()
            fmu.updateDiscreteStates()
            assert fmu.getFloat64([vr["state.omega"]])[0] == pytest.approx(-0.7 * omega, rel=1e-15)
            fmu.enterStepMode()
            times.append(reached)
        t = reached
    assert np.max(np.abs(np.array(times) - analytic_impacts(5))) < 1e-9
    fmu.terminate()
    fmu.freeInstance()


@pytest.fixture(scope="module")
def stop_mass(cache) -> Path:
    return build_fmu(make("oscillator", "linear", stop="impact", k=0.0, d=0.0, m=1.0, x_max=0.5, e=0.6,
                          v_rest=1e-3), cache_dir=cache)


def test_a_mass_driven_into_a_stop_leaves_at_minus_e_times_the_impact_velocity(stop_mass):
    """2 N on 1 kg from rest 0.5 m before the stop: impact at sqrt(0.5) s with sqrt(2) m/s; it
    leaves at -0.6 sqrt(2) and comes back after 2 * 0.6 sqrt(2) / 2 s at 0.6 sqrt(2) m/s."""
    s = Slave(stop_mass).start(f=2.0)
    a, v1, e = 2.0, np.sqrt(2.0), 0.6
    t1 = np.sqrt(0.5)
    t, h = 0.0, 1e-3
    while t + h < t1:
        s.fmu.doStep(t, h)
        t += h
    s.fmu.doStep(t, h)  # the impact is inside this step
    t += h
    v_imp, v_now, x_now = s.get("v_impact", "v", "x")
    assert v_imp == pytest.approx(v1, rel=1e-9)
    assert v_now == pytest.approx(-e * v1 + a * (t - t1), rel=1e-9)
    assert x_now == pytest.approx(0.5 - e * v1 * (t - t1) + a / 2 * (t - t1) ** 2, rel=1e-9)
    t2 = t1 + 2 * e * v1 / a
    while t < t2 + 0.01:
        s.fmu.doStep(t, h)
        t += h
    assert s.get("impacts", "v_impact") == pytest.approx([2.0, e * v1], rel=1e-9)


def test_a_mass_pushed_into_a_stop_comes_to_rest_and_leaves_when_pulled(stop_mass):
    """The bounces shrink by 0.6 each until the rebound is below v_rest: the mass rests on the
    stop (no chattering), then a pull releases it."""
    s = Slave(stop_mass).start(f=2.0)
    t, h = 0.0, 1e-2
    for _ in range(400):
        s.fmu.doStep(t, h)
        t += h
    x, v, n = s.get("x", "v", "impacts")
    assert (x, v) == (0.5, 0.0)
    # rebounds 0.6^k sqrt(2) down to v_rest = 1e-3: k = 14 bounces, the 15th impact rests
    assert n == 1 + np.ceil(np.log(1e-3 / np.sqrt(2)) / np.log(0.6)) - 1
    s.set(f=-1.0)
    s.fmu.doStep(t, h)
    x, v = s.get("x", "v")
    assert v == pytest.approx(-1.0 * h, rel=1e-12) and x == pytest.approx(0.5 - h ** 2 / 2, rel=1e-12)


def test_stiction_breaks_away_where_a_ramp_force_passes_fs_and_slides_by_coulomb(cache):
    """f = 2 t N on 1 kg with Fs = 3 N, Fc = 2 N, no viscous friction: stuck until 1.5 s, then
    dv/dt = 2 t - 2, v(t) = t^2 - 2.25 - 2 (t - 1.5)."""
    path = build_fmu(make("sliding_mass", "stiction", m=1.0, Fc=2.0, Fs=3.0, b=0.0), cache_dir=cache)
    s = Slave(path).start(f=0.0)
    t, h = 0.0, 0.01
    while t < 2.0 - 1e-12:
        s.set(f=2.0 * t)
        s.fmu.setRealInputDerivatives([s.vr["f"]], [1], [2.0])
        s.fmu.doStep(t, h)
        t += h
        x, v, stuck = s.get("x", "v", "stuck")
        if t < 1.5 - 1e-9:
            assert (x, v, stuck) == (0.0, 0.0, 1.0)
    assert stuck == 0.0
    assert v == pytest.approx(t ** 2 - 2.25 - 2 * (t - 1.5), rel=1e-9)
    assert x == pytest.approx((t ** 3 - 1.5 ** 3) / 3 - 2.25 * (t - 1.5) - (t - 1.5) ** 2, rel=1e-9)


def test_the_smooth_friction_law_creeps_at_its_analytic_velocity(cache):
    """stick_slip_smooth's friction (sliding_mass, smooth) against the law solved by hand: with
    Fc = Fs (no Stribeck dip) and no viscous term, a constant 1.5 N against Fs = 3 N is balanced at
    Fs tanh(v / v_eps) = f, v = v_eps artanh(1/2) (a creep, not a stick); the friction force is -f."""
    path = build_fmu(make("sliding_mass", "smooth", m=1.0, Fc=3.0, Fs=3.0, b=0.0), cache_dir=cache)
    s = Slave(path).start(f=1.5)
    t, h = 0.0, 1e-3
    while t < 0.05 - 1e-12:
        s.fmu.doStep(t, h)
        t += h
    v, friction = s.get("v", "friction")
    assert v == pytest.approx(1e-3 * np.arctanh(0.5), rel=1e-6) and friction == pytest.approx(-1.5, rel=1e-6)


def test_a_sliding_mass_sticks_where_its_velocity_reaches_zero(cache):
    """Sliding at 1 m/s against Fc = 2 N with f = 1 N (< Fs): it decelerates at 1 m/s2 and sticks
    at t = 1 s, 0.5 m on, and stays (the surface then holds the 1 N)."""
    path = build_fmu(make("sliding_mass", "stiction", m=1.0, Fc=2.0, Fs=3.0, b=0.0), cache_dir=cache)
    s = Slave(path).start(f=3.5)
    s.fmu.doStep(0.0, 1.0)  # breaks away at once (3.5 N > Fs), accelerates at 1.5 m/s2
    x1, v1 = s.get("x", "v")
    assert (x1, v1) == pytest.approx((0.75, 1.5), rel=1e-12)
    s.set(f=1.0)  # now it decelerates at 1 m/s2: stops 1.5 s later, 1.125 m on
    s.fmu.doStep(1.0, 1.0)
    assert s.get("stuck")[0] == 0.0
    s.fmu.doStep(2.0, 1.0)
    x, v, stuck, friction = s.get("x", "v", "stuck", "friction")
    assert (v, stuck, friction) == (0.0, 1.0, -1.0)
    assert x == pytest.approx(0.75 + 1.125, rel=1e-12)


def test_discrete_pid_with_time_events_equals_the_periodic_one_and_takes_any_step(cache):
    """The samples as time events give the periodic block's values at a step equal to the
    period, and the same samples when the master's step is 2.5 periods."""
    kw = dict(sample_period=0.01, Kp=3.0, Ki=2.0, Kd=0.5, Tf=0.02)
    periodic = Slave(build_fmu(make("pid", "discrete", **kw), cache_dir=cache), "a").start(setpoint=1.0)
    events = Slave(build_fmu(make("pid", "discrete", timing="events", **kw), cache_dir=cache), "b").start(setpoint=1.0)
    coarse = Slave(build_fmu(make("pid", "discrete", timing="events", **kw), cache_dir=cache), "c").start(setpoint=1.0)
    meas = lambda t: 0.3 * np.floor(t / 0.05 + 1e-9)  # changes at multiples of 0.05 s only  # noqa: E731
    for k in range(20):
        t = 0.01 * k
        for s in (periodic, events):
            s.set(measurement=meas(t))
            s.fmu.doStep(t, 0.01)
        assert events.get("y", "state.I", "state.w") == pytest.approx(periodic.get("y", "state.I", "state.w"),
                                                                       rel=1e-14, abs=1e-15)
    for k in range(8):  # steps of 0.025 s: samples fall inside the steps
        t = 0.025 * k
        coarse.set(measurement=meas(t))
        coarse.fmu.doStep(t, 0.025)
        if k % 2 == 1:  # t + 0.025 is a multiple of 0.05: the same samples taken
            events_at = (k + 1) * 0.025
            assert coarse.get("state.I")[0] == pytest.approx(_pid_integral(events_at, meas), rel=1e-12)


def _pid_integral(t_end: float, meas) -> float:
    """The discrete integral after the samples k T < t_end (Ki = 2, setpoint 1, T = 0.01)."""
    return sum(0.01 * 2.0 * (1.0 - meas(0.01 * k)) for k in range(int(round(t_end / 0.01))))


def test_adc_codes_and_held_lengths_match_the_board_conversion(cache):
    """The sampled ADC against hardware.convert (the board's own conversion, written apart):
    a leg moving at 0.1 m/s sampled every ms inside 10 ms steps."""
    from hardware.convert import Calibration, ideal_counts, quantise

    s = Slave(build_fmu(make("sampled", "adc", period=1e-3), cache_dir=cache)).start(u=0.3)
    cal = Calibration(s_offset=0.1)
    for k in range(5):
        t = 0.01 * k
        s.set(u=0.3 + 0.1 * t)
        s.fmu.setRealInputDerivatives([s.vr["u"]], [1], [0.1])
        s.fmu.doStep(t, 0.01)
        last = t + 0.009  # the last sample inside the step
        raw = quantise(ideal_counts(0.3 + 0.1 * last - 0.1))
        assert s.get("raw", "y") == pytest.approx([raw, cal.leg_length(raw)], rel=1e-12)


def test_pwm_duty_matches_the_board_drive(cache):
    """The sampled duty against hardware.convert: a command set at a communication point is
    sampled at the step's start (the sample at the end belongs to the next step): the voltage
    after step k is the one of command k - 1's successor, i.e. of the command set for step k
    once its start sample (at k ms) is taken."""
    from hardware.convert import drive_to_volts, volts_to_drive

    s = Slave(build_fmu(make("sampled", "pwm"), cache_dir=cache)).start(u=0.0)
    for k, volts in enumerate((3.14159, -7.2000003, 12.5, -0.00011)):
        s.set(u=volts)
        s.fmu.doStep(1e-3 * k, 1e-3)  # its start sample (at k ms, k >= 1) takes this command
        drive = volts_to_drive(volts)
        if k:
            assert s.get("y")[0] == pytest.approx(drive_to_volts(drive.duty_ns, drive.dir_high), rel=1e-12,
                                                  abs=1e-12)
            assert abs(s.get("duty")[0]) == drive.duty_ns


# --- event scenes against their monolithic references (events design page: two measures) -------
@pytest.fixture(scope="module")
def stick_slip_runs(cache):
    from cosim.run.execute import run
    from cosim.run.reference import reference

    scene = ROOT / "scenarios" / "stick_slip.yaml"
    return run(scene, cache_dir=cache), reference(scene)


def test_stick_slip_sticks_start_and_end_within_1e_4_s_of_the_reference(stick_slip_runs):
    from cosim.analysis.trace_diff import match_events, times_from_clock

    cosim, ref = stick_slip_runs
    assert cosim.ok and ref.status == "ok", (cosim.reason, ref.reason)
    for kind in ("t_stick", "t_slip"):
        timing = match_events(kind, times_from_clock(cosim.trace, f"mass.{kind}"), times_from_clock(ref.trace, f"mass.{kind}"))
        assert timing.missing == () and timing.matched >= 8, timing
        assert timing.max_error < 1e-4, timing


def test_stick_slip_values_between_events_within_1e_3_of_range(stick_slip_runs):
    from cosim.analysis.trace_diff import compare, compare_between_events, times_from_clock, windows

    cosim, ref = stick_slip_runs
    pairs = [(times_from_clock(cosim.trace, n), times_from_clock(ref.trace, n)) for n in ("mass.t_stick", "mass.t_slip")]
    names = ["mass.x", "mass.v", "mass.friction", "pid.y"]
    between = compare_between_events(cosim.trace, ref.trace, windows(pairs, 1e-3), names)
    assert max(d.relative for d in between) < 1e-3, [(d.name, d.relative) for d in between]
    # the plain max-norm reads a switch a hair apart as an error of the jump's size
    assert max(d.relative for d in compare(cosim.trace, ref.trace, ["mass.friction"])) > 10 * max(
        d.relative for d in between if d.name == "mass.friction")


def test_the_reference_finds_the_pendulum_impacts_itself():
    """The event reference against the elliptic-integral times: an independent check of the
    reference (its own solver, LSODA, and its own event location)."""
    from cosim.run.reference import reference

    res = reference(ROOT / "scenarios" / "pendulum_stop.yaml")
    assert res.status == "ok"
    times = [e["time"] for e in res.stats["events"]["list"]]
    assert np.max(np.abs(np.array(times) - analytic_impacts(5))) < 1e-8
    t = res.trace.time
    pairs = np.nonzero(np.diff(t) == 0)[0]  # two rows per event: the left then the right limit
    assert len(pairs) == 5
    assert all(res.trace["pend.omega"][k] < 0 < res.trace["pend.omega"][k + 1] for k in pairs)


def test_end_stop_scene_against_its_reference_between_events(cache):
    from cosim.analysis.trace_diff import compare_between_events, match_events, times_from_counter, windows
    from cosim.run.execute import run
    from cosim.run.reference import reference

    scene = ROOT / "scenarios" / "rig_end_stop.yaml"
    cosim, ref = run(scene, cache_dir=cache), reference(scene)
    assert cosim.ok and ref.status == "ok"
    assert cosim.trace["rig.leg[2].s"].max() == pytest.approx(0.36, abs=1e-12)  # on the stop, never past it
    pairs = [(times_from_counter(cosim.trace, f"rig.leg[{i}].impacts"),
              times_from_counter(ref.trace, f"rig.leg[{i}].impacts")) for i in (1, 2, 3)]
    timing = match_events("leg 2 impacts", *pairs[1])
    assert timing.matched == 1 and timing.missing == () and timing.max_error < 1e-3
    between = compare_between_events(cosim.trace, ref.trace, windows(pairs, 1e-3), ["rig.leg*.s", "pid*.y"])
    assert max(d.relative for d in between) < 1e-3, [(d.name, d.relative) for d in between]


def test_compare_cli_measures_event_times_and_values_between_events(tmp_path, cache, capsys):
    """`rpr-cosim run --reference` then `compare --events`: the switch times and the values
    between them pass a 1e-3 gate that the plain max-norm (across the jumps) fails."""
    from cosim.cli import main

    out = tmp_path / "out"
    assert main(["run", str(ROOT / "scenarios" / "stick_slip.yaml"), "--reference", "--out", str(out),
                 "--cache", str(cache)]) == 0
    test, ref = str(out / "stick_slip.csv"), str(out / "stick_slip_reference.csv")
    said = capsys.readouterr().out  # run --reference gives the two numbers itself (the modes' changes matched)
    assert re.search(r"events: \d\d mode changes matched, largest time error [0-9.e-]+ s \(mass\.t_s", said), said
    assert "co-simulation against the reference (values between events):" in said
    assert main(["compare", test, ref, "--only", "mass.x", "--only", "mass.friction", "--tol", "1e-3"]) == 1
    assert main(["compare", test, ref, "--only", "mass.x", "--only", "mass.friction", "--tol", "1e-3",
                 "--events", "mass.t_stick", "--events", "mass.t_slip", "--event-tol", "1e-4"]) == 0
    text = capsys.readouterr().out
    assert "events mass.t_stick: 9 matched" in text and "(values between events)" in text
    assert main(["compare", test, ref, "--tol", "1e-3", "--events", "mass.t_slip", "--event-tol", "1e-6"]) == 1
    # without --event-tol the runs' own event time tolerance, tol x 0.1 s (not tol x the span, 3 s)
    gate = ["compare", test, ref, "--only", "mass.x", "--events", "mass.t_stick", "--events", "mass.t_slip", "--tol"]
    assert main(gate + ["1e-3"]) == 0  # switches within 1e-4 s
    capsys.readouterr()
    assert main(gate + ["4e-4"]) == 1  # values within 4e-4, switches (5.7e-5 s) beyond 4e-5 s
    assert "beyond the event time tolerance 4e-05 s" in capsys.readouterr().err


def test_the_estimate_leaves_out_the_instants_around_events():
    """A switch placed one step apart in a run and its companion: across it the max-norm reads the
    jump (0.5 of range: 'unstable'); with the event marked (two rows at one time, or reported by
    the master), the estimate measures the smooth error between events."""
    from cosim.master.estimate import richardson

    t = np.linspace(0.0, 1.0, 101)
    tc = np.linspace(0.0, 1.0, 201)
    smooth = lambda s, e: np.sin(3 * s) + e * s  # noqa: E731  (a small coupling error e)
    x = (smooth(t, 1e-4) + (t >= 0.50)).reshape(-1, 1)
    xc = (smooth(tc, 0.0) + (tc >= 0.505)).reshape(-1, 1)
    plain = richardson(t, x, tc, xc, ["y"], 1.0, "test")
    marked = richardson(t, x, tc, xc, ["y"], 1.0, "test", events=[0.5])
    assert plain.worst > 0.3
    assert marked.worst == pytest.approx(1e-4 / (np.ptp(x)), rel=0.2)
    # the two-row convention marks the event by itself
    t2 = np.insert(t, 50, 0.5)
    x2 = np.insert(x, 50, smooth(0.5, 1e-4), axis=0)
    assert richardson(t2, x2, tc, xc, ["y"], 1.0, "test").worst < 2e-4


def test_block_builder_events_give_the_catalog_pendulum(cache):
    """The pendulum written with BlockBuilder's mode/when (the how-to's example) hits the same
    analytic impact times as the catalog block."""
    from models.user import BlockBuilder

    b = BlockBuilder("bouncer", "pendulum against a stop, written with BlockBuilder")
    L = b.param("L", 0.5, "m", "rod length", lower=1e-9)
    e = b.param("e", 0.7, "1", "restitution", lower=0.0, upper=1.0)
    th = b.state("theta", 1.0, "rad", "angle from the downward vertical")
    w = b.state("omega", 0.0, "rad/s", "angular rate")
    hits = b.mode("hits", 0.0, "1", "impacts so far")
    last = b.mode("t_hit", 0.0, "s", "time of the last impact")
    b.der(th, w)
    b.der(w, -9.81 / L * ca.sin(th))
    b.output("angle", th, "rad", "angle")
    b.when(th, {w: -e * w, hits: hits + 1, last: b.time()}, direction=-1, name="stop")
    blk = b.build(substeps=10)
    s = Slave(build_fmu(blk, cache_dir=cache)).start()
    t, times = 0.0, []
    while len(times) < 5:
        s.fmu.doStep(t, 0.01)
        t += 0.01
        n, when = s.get("hits", "t_hit")
        if n > len(times):
            times.append(when)
    assert np.max(np.abs(np.array(times) - analytic_impacts(5))) < 1e-9


def test_rig_step_with_sampled_adc_and_pwm_settles_within_one_count(cache):
    """The ADC's and PWM's samples as time events in the loop: the run is ok, the ADC reports
    whole codes, and each leg ends within one count (0.171 mm) of its target."""
    from cosim.run.execute import run

    res = run(ROOT / "scenarios" / "rig_step_sampled.yaml", cache_dir=cache)
    assert res.ok, res.reason
    tr = res.trace
    count = 0.635 * 11e3 / (4096 * 10e3)
    for i in (1, 2, 3):
        raw = tr[f"adc.raw[{i}]"]
        assert np.all(raw == np.rint(raw)) and raw.min() >= 0 and raw.max() <= 4095
        assert abs(tr[f"rig.leg[{i}].s"][-1] - tr[f"target.leg[{i}].s"][-1]) < count
        steps = np.diff(tr[f"adc.y[{i}]"]) / count  # the read-back length moves in whole counts
        assert np.allclose(steps, np.rint(steps), atol=1e-6)


def test_the_precision_study_of_an_event_scene_measures_between_events(stick_slip_runs, cache, tmp_path):
    """`study precision` on stick_slip: each row's errors are the two numbers (the value error
    between events, the event-time error), not the max-norm across the switches that called every
    run "inaccurate, 1.0 of range on mass.stuck".  The scene's own run (Gauss-Seidel, 0.5 ms,
    linear) against the same measure taken apart: `compare --events` on the clocks."""
    from cosim.analysis.trace_diff import compare_events
    from cosim.study.precision import precision_study

    st = precision_study(ROOT / "scenarios" / "stick_slip.yaml", [("gauss_seidel", "linear"), ("gauss_seidel", "hold")],
                         [1e-3, 5e-4], out=tmp_path / "study", cache_dir=cache, peer=False)
    rows = {(r.inputs, r.step): r for r in st.rows}
    scene_row = rows[("linear", 5e-4)]
    assert scene_row.status == "ok" and scene_row.missing_events == "", scene_row.reason
    cosim, ref = stick_slip_runs
    timings, diffs = compare_events(cosim.trace, ref.trace, ["mass.t_stick", "mass.t_slip"])
    assert scene_row.event_time == pytest.approx(max(t.max_error for t in timings), rel=1e-6)
    assert scene_row.event_time < 1e-4 and scene_row.worst < 1e-3
    assert scene_row.worst == pytest.approx(max(d.relative for d in diffs), rel=0.05)  # windows of the modes, not the clocks
    assert st.cheapest_within(1e-3) is scene_row
    assert rows[("hold", 1e-3)].status == "inaccurate" and rows[("hold", 1e-3)].event_time > 1e-2  # the drifting cycle
