"""Planned tasks (models.trajectory, models.task, models.motion_check) against independent sources:

- limits checked on the result, not on the planner's word: pose rates by central differences of
  the evaluated poses, jerk from the segments' third differences, leg speeds and accelerations by
  finite differences of the inverse kinematics' leg lengths, forces by the virtual-work inverse
  dynamics called point by point, the drive's voltage from SPEC §6's motor constants written here;
- ruckig's own ``at_time`` against the segments rebuilt from its profiles;
- det J's root along a straight path by scipy's brentq on det J alone (and the cross-leg design's
  singular line x = 0 at phi = 0), the assembly modes by ``forward_kinematics``.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from models.geometry import preset
from models.kinematics import det_fn, forward_kinematics, ik, jacobian
from models.motion_check import Margins, check_motion
from models.task import task_from
from models.trajectory import (DRIVES, TrajectoryError, leg_ratios, limits_from, peaks, plan, plan_ruckig)
from models.virtual_work import inverse_dynamics

M = preset("cross_leg")
PICK = [[-0.15, -0.15, 0.0], [-0.20, -0.12, 0.1], [-0.25, -0.15, 0.2], [-0.20, -0.20, 0.0], [-0.15, -0.15, 0.0]]
REL = 1e-9
# SPEC §6 motor (Table 6.7) and rack: kt = 145 rpm/V, R = 0.574 Ohm, b = 86e-6 N m s/rad, 0.05 m/rad
KT, R, B, RACK = 60 / (2 * math.pi * 145), 0.574, 86e-6, 0.05


def spec_voltage(F, v):
    """Quasi-static armature voltage for leg force F at leg speed v (SPEC §6 written out)."""
    w = v / RACK
    return R * (F * RACK + B * w) / KT + KT * w


@pytest.fixture(scope="module")
def toppra_motion():
    lim = limits_from({"leg_speed": 0.3, "leg_accel": 3.0, "u_max": 10.0, "m_act": 0.058})
    return plan(M, PICK, "toppra", lim), lim


def test_ruckig_keeps_its_pose_limits_and_passes_every_waypoint():
    lim = limits_from({"pose_speed": [0.1, 0.08, 0.5], "pose_accel": [1.0, 0.7, 4.0], "pose_jerk": [10, 8, 40]})
    traj = plan_ruckig(PICK, lim)
    q, _, _ = traj.evaluate(np.array(traj.waypoint_times))
    assert np.max(np.abs(q.T - np.array(PICK))) < 1e-12
    h = 1e-5
    t = np.arange(traj.breaks[0] + h, traj.breaks[-1] - h, 1e-4)
    qp, qm, q0 = traj.evaluate(t + h)[0], traj.evaluate(t - h)[0], traj.evaluate(t)[0]
    vel = (qp - qm) / (2 * h)
    acc = (qp - 2 * q0 + qm) / h ** 2
    for d in range(3):
        assert np.max(np.abs(vel[d])) <= lim.pose_speed[d] * (1 + 1e-6)
        assert np.max(np.abs(acc[d])) <= lim.pose_accel[d] * (1 + 1e-3)  # 2nd differences: O(h^2) + round-off
    # jerk: third difference inside each segment (exact for a cubic), every segment
    assert np.min(np.diff(traj.breaks)) > 1e-12
    long = np.diff(traj.breaks) > 1e-3  # a third difference of a shorter segment is round-off
    mid = ((traj.breaks[:-1] + traj.breaks[1:]) / 2)[long]
    w = np.diff(traj.breaks)[long] / 8
    qs = [traj.evaluate(mid + k * w)[0] for k in (-1.5, -0.5, 0.5, 1.5)]
    jerk = (qs[3] - 3 * qs[2] + 3 * qs[1] - qs[0]) / w ** 3
    for d in range(3):
        assert np.max(np.abs(jerk[d])) <= lim.pose_jerk[d] * (1 + 1e-6)
    # exactly, from the segments' own polynomials: the rate is quadratic on a segment (extremes at
    # its ends or at tau = -A/J), the acceleration linear (extremes at its ends)
    seg = np.diff(traj.breaks)[:, None]
    ends = [traj.V, traj.V + traj.A * seg + traj.J * seg ** 2 / 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(traj.J != 0, -traj.A / traj.J, 0.0)
    tau = np.clip(tau, 0.0, seg)
    inner = traj.V + traj.A * tau + traj.J * tau ** 2 / 2
    v_peak = np.max(np.abs(np.stack(ends + [inner])), axis=(0, 1))
    a_peak = np.max(np.abs(np.stack([traj.A, traj.A + traj.J * seg])), axis=(0, 1))
    assert np.all(v_peak <= np.array(lim.pose_speed) * (1 + REL)), v_peak
    assert np.all(a_peak <= np.array(lim.pose_accel) * (1 + REL)), a_peak
    assert np.all(np.max(np.abs(traj.J), axis=0) <= np.array(lim.pose_jerk) * (1 + REL))
    # at least one limit is reached (the move is time-optimal per coordinate)
    assert np.max(np.abs(vel[0])) >= 0.999 * lim.pose_speed[0]


def test_the_segments_are_ruckigs_own_trajectory():
    from ruckig import InputParameter, Ruckig, Trajectory

    lim = limits_from({})
    traj = plan_ruckig(PICK[:2], lim)
    inp = InputParameter(3)
    inp.current_position, inp.target_position = PICK[0], PICK[1]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = list(lim.pose_speed), list(lim.pose_accel), list(lim.pose_jerk)
    ref = Trajectory(3)
    Ruckig(3).calculate(inp, ref)
    for t in np.linspace(0, ref.duration, 97):
        p, v, a = ref.at_time(t)
        q, qd, qdd = traj.evaluate(np.array([t]))
        assert np.allclose(q[:, 0], p, atol=1e-13) and np.allclose(qd[:, 0], v, atol=1e-12)
        assert np.allclose(qdd[:, 0], a, atol=1e-11)


def test_toppra_stays_within_the_leg_limits_and_saturates_one(toppra_motion):
    traj, lim = toppra_motion
    q, _, _ = traj.evaluate(np.array(traj.waypoint_times))
    assert np.max(np.abs(q.T - np.array(PICK))) < 1e-12
    # finite differences of the leg lengths (inverse kinematics only)
    h = 1e-5
    t = np.arange(traj.breaks[0] + h, traj.breaks[-1] - h, 5e-4)
    Lp, Lm, L0 = (ik(M, traj.evaluate(s)[0])[0] for s in (t + h, t - h, t))
    speed = np.max(np.abs((Lp - Lm) / (2 * h)))
    accel = np.max(np.abs((Lp - 2 * L0 + Lm) / h ** 2))
    assert speed <= lim.leg_speed * (1 + 1e-6)
    assert accel <= lim.leg_accel * (1 + 1e-3)
    # forces point by point (virtual work plus the lumped actuator mass) and SPEC's motor voltage
    F_peak = u_peak = 0.0
    for s in t[::8]:
        q, qd, qdd = (a[:, 0] for a in traj.evaluate(np.array([s])))
        Jm = jacobian(M, q)
        Ld = Jm @ qd
        Ldd_fd = (ik(M, traj.evaluate(np.array([s + h]))[0][:, 0])[0] - 2 * ik(M, q)[0]
                  + ik(M, traj.evaluate(np.array([s - h]))[0][:, 0])[0]) / h ** 2
        F = inverse_dynamics(M, q, qd, qdd) + 0.058 * Ldd_fd
        F_peak = max(F_peak, np.max(np.abs(F)))
        u_peak = max(u_peak, np.max(np.abs(spec_voltage(F, Ld))))
    assert F_peak <= DRIVES["table67"].F_max
    assert u_peak <= lim.u_max * (1 + 1e-6)
    # the planner's own dense peaks: within 1e-9 and one constraint at its limit
    ratios = leg_ratios(peaks(M, traj, lim), lim)
    assert max(ratios.values()) <= 1 + REL
    assert max(ratios.values()) >= 1 - 1e-6, ratios


def test_a_straight_path_through_det_j_zero_is_refused_at_the_crossing():
    task = task_from({"waypoints": [[-0.1, -0.15, 0.0], [0.1, -0.15, 0.0]], "margins": {"det": 0, "dsi": 0, "dsi_phi": 0}})
    traj = task.plan()
    res = task.check(traj)
    v = res.refusal
    assert v is not None and v.limit.startswith("det J = 0")
    g = M.geometry_vector()
    root = brentq(lambda s: float(det_fn()(traj.evaluate(np.array([s]))[0][:, 0], g)), traj.breaks[0] + 1e-6,
                  traj.breaks[-1] - 1e-6, xtol=1e-15, rtol=4 * np.finfo(float).eps)
    assert abs(v.t - root) < 1e-9
    q_root = traj.evaluate(np.array([root]))[0][:, 0]
    assert np.max(np.abs(np.array(v.pose) - q_root)) < 1e-9
    assert abs(v.pose[0]) < 1e-9  # the cross-leg design is singular on x = 0 at phi = 0
    line = v.line()
    assert "t = " in line and "pose" in line and "det J = 0" in line and "\n" not in line


def test_a_path_to_another_assembly_mode_is_refused():
    start = np.array([-0.15, -0.15, 0.0])
    L, _ = ik(M, start)
    modes = forward_kinematics(M, L)
    sign0 = np.sign(np.linalg.det(jacobian(M, start)))
    other = next(q for q in modes if np.sign(np.linalg.det(jacobian(M, q))) != sign0)
    assert np.allclose(ik(M, other)[0], L, atol=1e-10)  # same leg lengths: only the mode differs
    task = task_from({"waypoints": [start.tolist(), other.tolist()]})
    res = task.check()
    assert not res.ok
    assert "another assembly mode" in res.refusal.limit


def test_a_path_within_all_limits_passes():
    task = task_from({"waypoints": PICK, "limits": {"m_act": 0.058}})
    res = task.check()
    assert res.ok, [v.line() for v in res.violations]
    assert min(np.min(v) for v in res.margins.values()) >= 0


def test_limits_are_checked_on_the_motion_too():
    """A force limit the motion breaks: refused at the first time |F| reaches it (located by
    root finding, checked here against the point-by-point inverse dynamics)."""
    lim = limits_from({"m_act": 0.058})
    traj = plan(M, PICK, "ruckig", lim)
    F_peak = peaks(M, traj, lim).force
    tight = limits_from({"m_act": 0.058, "drive": "table67"})
    from dataclasses import replace

    tight = replace(tight, drive=replace(tight.drive, F_max=0.5 * F_peak))
    res = check_motion(M, traj.evaluate, 0.0, traj.duration, tight, Margins(0, 0, 0))
    v = res.refusal
    assert v is not None and "force" in v.limit
    q, qd, qdd = (a[:, 0] for a in traj.evaluate(np.array([v.t])))
    Ldd = (ik(M, traj.evaluate(np.array([v.t + 1e-5]))[0][:, 0])[0] - 2 * ik(M, q)[0]
           + ik(M, traj.evaluate(np.array([v.t - 1e-5]))[0][:, 0])[0]) / 1e-10
    F = inverse_dynamics(M, q, qd, qdd) + 0.058 * Ldd
    assert abs(np.max(np.abs(F)) - 0.5 * F_peak) < 1e-4 * F_peak


@pytest.mark.parametrize("spec, words", [
    ({"waypoints": [[0, 0, 0]]}, "at least two"),
    ({"waypoints": [[0, 0], [1, 1]]}, "[x, y, phi]"),
    ({"waypoints": PICK, "method": "fast"}, "method 'fast'"),
    ({"waypoints": PICK, "limits": {"leg_sped": 1}}, "unknown key 'leg_sped'"),
    ({"waypoints": PICK, "limits": {"u_max": 20}}, "exceeds the drive's rated"),
    ({"waypoints": PICK, "times": [0, 1, 2]}, "times"),
    ({"waypoints": PICK, "method": "spline"}, "give one time per waypoint"),
    ({"waypoints": [[-0.1, -0.15, 0.0], [0.1, -0.15, 0.0]], "method": "toppra"}, "crosses det J = 0 at pose (0.0"),
    ({"waypoints": PICK, "limits": {"pose_speed": 1e-300}}, "limits.pose_speed"),
    ({"waypoints": PICK, "times": [0, 1, 2, 3, 1e9]}, "would last"),
])
def test_bad_tasks_say_what_is_wrong(spec, words):
    with pytest.raises(TrajectoryError, match=None) as exc:
        task_from(spec).plan()
    assert words in str(exc.value)


def test_the_drive_line_is_the_motor_blocks():
    """The planner's Table 6.7 drive uses the dc_motor block's own parameter defaults and ratings."""
    from models import blocks
    from models.drives import I_PEAK, TABLE_6_7, U_RATED

    motor = blocks.make("dc_motor", "quasistatic")
    defaults = {p.name: p.default for p in motor.params}
    for key, value in TABLE_6_7.items():
        assert defaults[key] == pytest.approx(value, rel=1e-15), key
    assert motor.ratings["u"].high == U_RATED and motor.ratings["i"].high == I_PEAK
    # the line reproduces the block's steady state: at a given speed and voltage, force = the block's
    d = DRIVES["table67"]
    fn = motor.functions()["out"]
    u, v = 7.0, 0.3
    f_block = float(fn([], [u, v], [defaults[p.name] for p in motor.params])[0])
    assert d.voltage(f_block, v) == pytest.approx(u, rel=1e-12)
