"""The DC motor's Coulomb friction with stiction (dc_motor, friction="stiction", issue 30): stick,
breakaway and stick again located inside the FMU's step, against the motor's equations solved
apart (closed forms of the electrical and mechanical ODEs, SciPy's solve_ivp), for each of the
block's integrators (the rotor unloaded: bond stiffness and damping 0, leg speed 0); the
motor_stiction scene against its monolithic event reference and the closed form of its first
breakaway."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fmus import build_fmu
from models.block import BlockError
from models.blocks import make
from test_events import Slave

R, KT, L, J, B = 0.574, 60.0 / (2 * np.pi * 145.0), 0.251e-3, 1.45e-4, 86e-6  # Table 6.7
TC, TS = 0.02, 0.03  # the block's assumed defaults
FREE = {"k_bond": 0.0, "c_bond": 0.0}  # unloaded rotor
INTEGRATORS = {"exact": 1, "rk4": 20, "radau": 4}  # integrator -> substeps per 1 ms


def motor(cache, fidelity: str, integrator: str):
    extra = {"solver.rtol": 1e-10, "solver.atol": 1e-12} if integrator == "radau" else {}
    return build_fmu(make("dc_motor", fidelity, rotor="state", friction="stiction", integrator=integrator,
                          substeps=INTEGRATORS[integrator], **FREE, **extra), cache_dir=cache)


def run(s: Slave, t0: float, t1: float, h: float = 1e-3) -> float:
    t = t0
    while t < t1 - 1e-12:
        s.fmu.doStep(t, h)
        t += h
    return t


def test_defaults_keep_the_viscous_law_and_stiction_needs_a_rotor_state():
    plain = make("dc_motor", "full")
    assert "Ts" not in {p.name for p in plain.params} and plain.indicators.numel() == 0
    blk = make("dc_motor", "full", rotor="state", friction="stiction")
    assert {"Tc", "Ts"} <= {p.name for p in blk.params} and blk.indicators.numel() == 3
    with pytest.raises(BlockError, match="friction 'stiction' needs rotor 'state'"):
        make("dc_motor", "full", friction="stiction")


@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_a_voltage_below_breakaway_leaves_the_rotor_stuck(cache, integrator):
    """0.2 V < Ts R / kt = 0.261 V: the current settles at u/R, its torque 0.023 N m < Ts holds."""
    s = Slave(motor(cache, "full", integrator)).start(u=0.2)
    run(s, 0.0, 0.1)
    w, stuck, i, friction = s.get("w", "stuck", "i", "friction")
    assert (w, stuck) == (0.0, 1.0)
    assert i == pytest.approx(0.2 / R, rel=1e-9) and friction == pytest.approx(-KT * 0.2 / R, rel=1e-9)


@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_breakaway_at_the_analytic_time_then_slip_as_solve_ivp(cache, integrator):
    """1 V from rest: stuck, i = u/R (1 - exp(-R t / L)) until kt i = Ts, at
    t_b = -(L/R) ln(1 - Ts R / (kt u)); then L di/dt = u - R i - kt w, J dw/dt = kt i - Tc - b w."""
    u = 1.0
    s = Slave(motor(cache, "full", integrator)).start(u=u)
    t = run(s, 0.0, 0.05)
    t_b = -(L / R) * np.log(1 - TS * R / (KT * u))
    t_slip, stuck, sticks = s.get("t_slip", "stuck", "sticks")
    assert (stuck, sticks) == (0.0, 0.0)
    assert t_slip == pytest.approx(t_b, abs=1e-9)

    def slip(_, y):
        i, w = y
        return [(u - R * i - KT * w) / L, (KT * i - TC - B * w) / J]

    sol = solve_ivp(slip, (t_b, t), [TS / KT, 0.0], method="Radau", rtol=1e-12, atol=1e-12)
    i_ref, w_ref = sol.y[:, -1]
    i, w = s.get("i", "w")
    tol = 1e-6 if integrator == "rk4" else 1e-8
    assert w == pytest.approx(w_ref, rel=tol) and i == pytest.approx(i_ref, rel=tol, abs=1e-9)


@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_the_rotor_sticks_where_coulomb_torque_stops_it(cache, integrator):
    """Quasistatic motor (i = (u - kt w)/R), a = kt^2/R + b: 1 V slips at once,
    w = w_inf (1 - exp(-a t / J)) with w_inf = (kt u / R - Tc) / a; with the drive removed at t1 it
    decelerates, w = (w1 + Tc/a) exp(-a (t - t1) / J) - Tc/a, and sticks at
    t1 + (J/a) ln(1 + a w1 / Tc), then stays (no torque)."""
    u, t1, a = 1.0, 0.02, KT ** 2 / R + B
    s = Slave(motor(cache, "quasistatic", integrator)).start(u=u)
    run(s, 0.0, t1)
    w_inf = (KT * u / R - TC) / a
    w1 = w_inf * (1 - np.exp(-a * t1 / J))
    tol = 1e-7 if integrator == "rk4" else 1e-9
    assert s.get("w")[0] == pytest.approx(w1, rel=tol)
    assert s.get("t_slip")[0] == 0.0  # broke away at the start
    s.set(u=0.0)
    t_stop = t1 + (J / a) * np.log(1 + a * w1 / TC)
    t = run(s, t1, t_stop + 0.01)
    w, stuck, sticks, t_stick, friction = s.get("w", "stuck", "sticks", "t_stick", "friction")
    assert (stuck, sticks) == (1.0, 1.0)
    assert abs(w) < 1e-15 and abs(friction) < 1e-15  # 0; the exact integrator's matrix exponential: round-off
    assert t_stick == pytest.approx(t_stop, abs=1e-9 if integrator != "rk4" else 1e-7)
    assert t > t_stop


@pytest.mark.parametrize("integrator", ["rk4", "radau"])
def test_a_reversed_drive_reverses_the_slip_without_sticking(cache, integrator):
    """Slipping forward, the voltage reversed to -1 V: at w = 0 the net torque -kt/R is past -Ts,
    so the rotor slips on backwards (no stick), t_slip the reversal's time."""
    u, t1, a = 1.0, 0.02, KT ** 2 / R + B
    s = Slave(motor(cache, "quasistatic", integrator)).start(u=u)
    run(s, 0.0, t1)
    w1 = (KT * u / R - TC) / a * (1 - np.exp(-a * t1 / J))
    s.set(u=-u)
    # J dw/dt = -kt u/R - Tc - a w: w = (w1 + c) exp(-a t / J) - c, c = (kt u / R + Tc) / a
    c = (KT * u / R + TC) / a
    t_rev = t1 + (J / a) * np.log((w1 + c) / c)
    run(s, t1, t_rev + 0.01)
    stuck, sticks, t_slip, w = s.get("stuck", "sticks", "t_slip", "w")
    assert (stuck, sticks) == (0.0, 0.0) and w < 0
    assert t_slip == pytest.approx(t_rev, abs=1e-7)


# --- the scene against its monolithic event reference and the first breakaway's closed form ----
@pytest.fixture(scope="module")
def motor_stiction_runs(cache):
    from cosim.run.execute import run
    from cosim.run.reference import reference

    scene = Path(__file__).resolve().parents[1] / "scenarios" / "motor_stiction.yaml"
    return run(scene, cache_dir=cache), reference(scene)


def test_motor_stiction_scene_sticks_and_slips_at_the_reference_times(motor_stiction_runs):
    from cosim.analysis.trace_diff import match_events, times_from_clock

    cosim, ref = motor_stiction_runs
    assert cosim.ok and ref.status == "ok", (cosim.reason, ref.reason)
    assert cosim.trace["motor.sticks"][-1] == ref.trace["motor.sticks"][-1] == 3  # it hunts
    for kind in ("t_stick", "t_slip"):
        timing = match_events(kind, times_from_clock(cosim.trace, f"motor.{kind}"),
                              times_from_clock(ref.trace, f"motor.{kind}"))
        assert timing.missing == () and timing.matched >= 3, timing
        assert timing.max_error < 1e-4, timing


def test_motor_stiction_scene_values_between_events_within_1e_3_of_range(motor_stiction_runs):
    from cosim.analysis.trace_diff import compare_between_events, times_from_clock, windows

    cosim, ref = motor_stiction_runs
    pairs = [(times_from_clock(cosim.trace, n), times_from_clock(ref.trace, n)) for n in ("motor.t_stick", "motor.t_slip")]
    names = ["load.x", "load.v", "motor.w", "motor.i", "motor.friction", "pid.y"]
    between = compare_between_events(cosim.trace, ref.trace, windows(pairs, 1e-3), names)
    assert max(d.relative for d in between) < 1e-3, [(d.name, d.relative) for d in between]


def test_motor_stiction_scene_breaks_away_where_the_current_ramp_reaches_ts(motor_stiction_runs):
    """While stuck the carriage rests (no bond force), so the PID gives y = Kp e0 + Ki e0 t with
    e0 = 10 mm, and L di/dt = y - R i: i = (a0/R)(1 - E) + (a1/R)(t - tau (1 - E)),
    E = exp(-t/tau), tau = L/R; the rotor breaks away where kt i = Ts."""
    from scipy.optimize import brentq

    a0, a1, tau = 100 * 0.01, 1000 * 0.01, L / R

    def current(t):
        e = np.exp(-t / tau)
        return a0 / R * (1 - e) + a1 / R * (t - tau * (1 - e))

    t_b = brentq(lambda t: KT * current(t) - TS, 0.0, 1e-2, xtol=1e-15)
    for res in motor_stiction_runs:
        first = res.trace["motor.t_slip"][res.trace["motor.t_slip"] > 0][0]
        assert first == pytest.approx(t_b, abs=1e-9)
