"""Physical guards (cosim.run.row_guards): the findings of issue 7 item 2 that reported "ok" for
physically impossible runs, each reproduced and now stopped or refused with its reason; the
shipped scene still "ok" under the default guards; the ``guards:`` section validated like the
rest of a scene.  Leg lengths and singular poses are checked against SPEC §1's formulas written
out here in plain numpy and a symmetry argument, not against the code under test."""
from __future__ import annotations

import dataclasses
import json
import math
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cosim import cli
from cosim.scenario.guard_settings import DEFAULTS, GuardSettings
from cosim.run.row_guards import Guard, _Limit
from cosim.run.execute import run
from cosim.scenario import SceneError, load

ROOT = Path(__file__).resolve().parents[1]
PID_STEP = ROOT / "scenarios" / "pid_step.yaml"
LMIN, LMAX = 0.10, 0.60  # SPEC §1 stroke
R_MOTOR, U_RATED, I_PEAK = 0.574, 12.0, 30.0  # Table 6.7 resistance; the ratings chosen in models.blocks.motor


def spec_legs(x: float, y: float, phi: float, side: float = 0.3, lmp: float = 0.2) -> np.ndarray:
    """Leg lengths by SPEC §1 (cross pairing), written out independently of models.kinematics."""
    o, r = side / math.sqrt(3), lmp / math.sqrt(3)
    a = [(-o * math.cos(math.pi / 6), o * math.sin(math.pi / 6)), (o * math.cos(math.pi / 6), o * math.sin(math.pi / 6)),
         (0.0, -o)]
    ang = (math.pi / 6, 5 * math.pi / 6, 3 * math.pi / 2)
    return np.array([math.hypot(x - r * math.cos(phi + t) - ax, y - r * math.sin(phi + t) - ay)
                     for (ax, ay), t in zip(a, ang)])


def target(x1: float, y1: float, phi1: float) -> list[str]:
    return [f"components.target.params.x1={x1}", f"components.target.params.y1={y1}",
            f"components.target.params.phi1={phi1}"]


#: the coupling these findings were filed with (the scene itself takes the tolerance default)
GS = "master.algorithm=gauss_seidel"
PID_1E6 = [GS] + [f"components.pid{i}.params.{k}={v}" for i in (1, 2, 3) for k, v in (("Kp", 1e6), ("u_max", 1e9))]


# --- the shipped scene stays "ok" -----------------------------------------------------------------
@pytest.fixture(scope="module")
def pid_step():
    return run(PID_STEP, {"outputs": ["mech.leg[*].s", "motor*.i", "motor*.u"], "master.algorithm": "gauss_seidel",
                          "master.tolerance": "none"})  # the guards, not the accuracy, at the thesis's 1 ms


def test_pid_step_is_ok_under_the_default_guards_and_within_the_ratings(pid_step):
    """The setpoint kick drives the motors to their stall current at the rated voltage, 12 V / 0.574 Ohm
    (20.9 A), for a few milliseconds: inside the 30 A peak rating, and the legs inside the stroke."""
    assert pid_step.ok, pid_step.reason
    tr = pid_step.trace
    i_peak = max(np.abs(tr[f"motor{k}.i"]).max() for k in (1, 2, 3))
    assert U_RATED / R_MOTOR * 0.99 < i_peak <= U_RATED / R_MOTOR < I_PEAK
    assert max(np.abs(tr[f"motor{k}.u"]).max() for k in (1, 2, 3)) == pytest.approx(U_RATED)
    legs = np.vstack([tr[f"mech.leg[{i}].s"] for i in (1, 2, 3)])
    assert LMIN < legs.min() and legs.max() < LMAX
    assert pid_step.stats["guards"]["settings"] == DEFAULTS and pid_step.stats["guards"]["warnings"] == []


# --- the findings, reproduced ---------------------------------------------------------------------
@pytest.mark.parametrize("sets, status, reason", [
    # R = 0: the current runs away at once (legs 14 km without guards)
    (["components.motor1.params.R=0", GS], "out_of_limits",
     r"^beyond rating: motor1\.i = 47\.8\d A at t = 0\.001 s, outside the rated \[-30, 30\] A"),
    (["components.motor1.params.R=0", "guards.rated=off", GS], "out_of_limits",
     r"^out of stroke: mech\.leg\[3\]\.s = 0\.09\d+ m at t = 0\.6\d+ s, outside the stroke \[0\.1, 0\.6\] m"),
    # PID gains 1e6 with a 1e9 output limit: the first voltage is thousands of volts
    (PID_1E6, "out_of_limits", r"^beyond rating: motor1\.u = 3\.129e\+04 V at t = 0 s, outside the rated \[-12, 12\] V"),
    (PID_1E6 + ["guards.rated=off"], "out_of_limits", r"^out of stroke: mech\.leg\[3\]\.s = 0\.08\d+ m at t = 0\.01 s"),
    (PID_1E6 + ["guards.rated=off", "guards.stroke=off", "guards.singularity=off"], "unstable",
     # the value at the offending row depends on the motor's integrator (exact kernel: -3.98e6 N)
     r"^unstable: mech\.leg\[1\]\.f = -\d\.\d+e\+0[67] at t = 0\.013 s \(\|value\| beyond guards\.max_abs = 1e\+06\)"),
], ids=["R0", "R0-stroke", "pid1e6", "pid1e6-stroke", "pid1e6-unstable"])
def test_impossible_runs_are_stopped_with_the_variable_time_and_value(sets, status, reason):
    res = run(PID_STEP, sets)
    assert res.status == status
    assert re.search(reason, res.reason), res.reason
    t_stop = res.trace.time[-1]
    assert f"t = {t_stop:.6g} s" in res.reason  # the trace ends at the offending row
    assert res.stats["steps_done"] == round(t_stop / 1e-3)


def test_without_guards_the_pid_finding_is_caught_by_the_error_estimate():
    """The finding as filed: with every guard off the run went on to legs kilometres long and said
    "ok"; the guards are for that, and without them the run's own error estimate (a companion at
    half the step disagrees by more than the signals' range) ends it "unstable" (issue 19)."""
    res = run(PID_STEP, PID_1E6 + ["guards=off", "stop_time=0.5"])
    assert "guards" not in res.stats
    assert res.trace.final()["mech.leg[1].s"] > 100 * LMAX
    assert res.status == "unstable" and res.stats["estimate"]["signal"] in res.reason, res.reason


def test_a_stopped_run_keeps_its_partial_trace_reason_and_exit_code(tmp_path, capsys):
    rc = cli.main(["run", str(PID_STEP), "--out", str(tmp_path)] + [a for s in PID_1E6 for a in ("--set", s)])
    assert rc == 1
    assert "rpr-cosim run: out_of_limits: beyond rating: motor1.u" in capsys.readouterr().err
    side = json.loads((tmp_path / "pid_step.json").read_text())
    assert side["status"] == "out_of_limits" and side["reason"].startswith("beyond rating: motor1.u = 3.129e+04 V")
    rows = [ln for ln in (tmp_path / "pid_step.csv").read_text().splitlines() if ln and not ln.startswith("#")]
    assert len(rows) == 2  # header and the row at t = 0


def test_warn_lets_the_run_go_on_and_records_the_first_crossing():
    res = run(PID_STEP, ["components.motor1.params.R=0", "guards.rated=warn", "stop_time=0.05", GS,
                         "master.tolerance=none"])  # the guard's warning, not the accuracy of a 0-ohm motor at 1 ms
    assert res.ok, res.reason
    (w,) = res.stats["guards"]["warnings"]
    assert w.startswith("beyond rating: motor1.i = 47.8")


@pytest.mark.parametrize("x1", [1.8, -1.5])
def test_a_target_outside_the_workspace_is_refused_at_check_time(x1, capsys):
    legs = spec_legs(x1, -0.15, 0.2)
    assert legs.min() > 1.4  # the finding: legs of 1.9 m against a 0.6 m stroke
    with pytest.raises(SceneError) as exc:
        load(PID_STEP, target(x1, -0.15, 0.2))
    msgs = [p.message for p in exc.value.problems if "commands leg" in p.message]
    assert len(msgs) == 3
    for i, msg in enumerate(msgs, 1):
        assert (f"component 'target' (pose_setpoint/default) commands leg {i} to {legs[i - 1]:.4g} m at t = 0 s"
                in msg) and "outside the stroke [0.1, 0.6] m" in msg
    sets = [a for s in target(x1, -0.15, 0.2) for a in ("--set", s)]
    assert cli.main(["run", str(PID_STEP), "--check"] + sets) == 2
    err = capsys.readouterr().err
    line = next(i for i, ln in enumerate(PID_STEP.read_text().splitlines(), 1) if ln.startswith("  target:"))
    assert f"pid_step.yaml:{line}: error: component 'target' (pose_setpoint/default) commands leg 1 to {legs[0]:.4g} m" in err


def test_a_target_through_singular_poses_is_refused_and_stopped_at_run_time():
    """Target (0, -0.262, 0): leg 3 is 0.0267 m (SPEC §1) and the pose is singular (x = 0, phi = 0:
    legs 1 and 2 are mirror images about the y axis, so they meet on it, where leg 3 lies: the
    three leg lines are concurrent)."""
    sets = target(0.0, -0.262, 0.0)
    legs = spec_legs(0.0, -0.262, 0.0)
    with pytest.raises(SceneError) as exc:
        load(PID_STEP, sets)
    text = str(exc.value)
    assert f"commands leg 3 to {legs[2]:.4g} m" in text and "outside the stroke [0.1, 0.6] m" in text
    assert "commands a singular pose: |det J| = " in text and "below guards.min_det = 0.01 m" in text
    # accepted with warnings, then run with the stroke guard off: the mechanism crosses a singular pose
    scene = load(PID_STEP, sets + ["guards.stroke=warn", "guards.singularity=warn", GS])
    assert len(scene.warnings) == 2
    forced = dataclasses.replace(scene, guards=dataclasses.replace(scene.guards, stroke="off", singularity="stop"))
    res = run(forced)
    assert res.status == "out_of_limits"
    assert res.reason.startswith("singularity: mech: det J changes sign between t = ")


@pytest.mark.parametrize("pose", [(0.0, -0.15, 0.0), (0.0, -0.05, 0.0)])
def test_a_singular_target_inside_the_stroke_is_refused(pose):
    assert LMIN < spec_legs(*pose).min() and spec_legs(*pose).max() < LMAX
    with pytest.raises(SceneError, match=r"commands a singular pose: \|det J\| = .* m at t = 0 s"):
        load(PID_STEP, target(*pose))


# --- the guards: section ---------------------------------------------------------------------------
def scene_with_guards(tmp_path: Path, guards: str) -> Path:
    path = tmp_path / "g.yaml"
    path.write_text(f"include: {PID_STEP}\nname: g\n" + textwrap.dedent(guards))
    return path


@pytest.mark.parametrize("guards, line, message", [
    ("guards:\n  strok: off\n", 4, "unknown key 'strok' in guards; did you mean 'stroke'?"),
    ("guards:\n  stroke: stop\n  rated: stopp\n", 5, "guards.rated = 'stopp'; did you mean 'stop'?; expected stop, warn or off"),
    ("guards:\n  min_det: -1\n", 4, "guards.min_det = -1 must be a positive number"),
    ("guards: [stroke]\n", 3, "guards must be a mapping"),
    ("guards:\n  max_abs: .nan\n", 4, "guards.max_abs = nan must be a positive number"),
])
def test_guard_settings_mistakes_name_file_and_line(tmp_path, guards, line, message):
    path = scene_with_guards(tmp_path, guards)
    with pytest.raises(SceneError) as exc:
        load(path)
    (p,) = exc.value.problems
    assert (p.file.endswith("g.yaml"), p.line) == (True, line) and message in p.message


@pytest.mark.parametrize("guards, expected", [
    ("", GuardSettings()),
    ("guards: off\n", GuardSettings("off", "off", "off", "off")),
    ("guards: {singularity: warn, min_det: 0.05, unstable: off}\n",
     GuardSettings(singularity="warn", min_det=0.05, unstable="off")),
])
def test_guard_settings_are_read_from_the_scene(tmp_path, guards, expected):
    assert load(scene_with_guards(tmp_path, guards)).guards == expected


def test_run_check_shows_the_guards(tmp_path, capsys):
    path = scene_with_guards(tmp_path, "guards: {singularity: warn, min_det: 0.05}\n")
    assert cli.main(["run", str(path), "--check"]) == 0
    assert "  guards: stroke stop, rated stop, singularity warn (|det J| < 0.05 m), unstable stop (|value| > 1e+06)" \
        in capsys.readouterr().out


# --- the guard on synthetic rows ------------------------------------------------------------------
def make_guard(**settings) -> Guard:
    g = Guard(GuardSettings(**settings), [_Limit("m.u", -12, 12, "rated", "V", "test"),
                                          _Limit("m.s", 0.1, 0.6, "stroke", "m", "test")], [], [])
    g.bind(["m.u", "m.s", "m.other"])
    return g


def rows(n: int = 10) -> np.ndarray:
    t = np.arange(n) * 0.1
    return np.column_stack([t, np.full(n, 12.0), np.full(n, 0.3), np.zeros(n)])


@pytest.mark.parametrize("row, col, value, status, start", [
    (3, 1, 12.5, "out_of_limits", "beyond rating: m.u = 12.5 V at t = 0.3 s"),
    (5, 2, 0.05, "out_of_limits", "out of stroke: m.s = 0.05 m at t = 0.5 s"),
    (2, 3, np.nan, "unstable", "unstable: m.other = nan at t = 0.2 s (not finite)"),
    (7, 3, -2e6, "unstable", "unstable: m.other = -2e+06 at t = 0.7 s (|value| beyond guards.max_abs = 1e+06)"),
])
def test_the_first_offending_row_ends_the_trace(row, col, value, status, start):
    data = rows()
    data[row, col] = value
    data[row + 1:, 1] = 99.0  # later crossings of another guard do not matter
    g = make_guard()
    assert g.check(data) == row + 1
    assert g.status == status and g.reason.startswith(start), g.reason


def test_a_value_exactly_at_its_rating_is_inside_and_off_ignores():
    g = make_guard()
    assert g.check(rows()) is None and not g.tripped
    data = rows()
    data[4, 1] = 13.0
    assert make_guard(rated="off").check(data) is None


@pytest.mark.parametrize("start, later, trips", [
    (2.0 ** 40, 2.0 ** 40, False),          # a large constant (an Int64 input of another tool) is its own scale
    (2.0 ** 40, 2.0 ** 40 * 999, False),
    (2.0 ** 40, 2.0 ** 40 * 1001, True),    # grown a thousandfold
    (0.0, 9.9e5, False),
    (0.0, 1.1e6, True),                     # beyond max_abs from a small start
])
def test_unstable_means_growth_beyond_max_abs_or_a_thousand_times_the_start(start, later, trips):
    data = rows()
    data[:, 3] = start
    data[6, 3] = later
    g = make_guard()
    assert (g.check(data) == 7) is trips
    if trips:
        assert g.reason.startswith(f"unstable: m.other = {later:.6g} at t = 0.6 s (|value| beyond ")
