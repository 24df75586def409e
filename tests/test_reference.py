"""The monolithic reference of a scene (cosim.run.reference) and trace comparison (cosim.analysis.trace_diff):
against an analytic path, against the co-simulation converging at first order as the step
shrinks (two independent formulations: FMUs under a master vs one ODE under CVODES), and the
CLI's errors and outputs."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosim import cli
from cosim.analysis.trace_diff import compare, format_table
from cosim.errors import UserError
from cosim.run.reference import composite, reference
from cosim.run.execute import run
from cosim.scenario import from_dict
from cosim.trace.traces import CsvTrace, Trace, read_trace
from models.geometry import preset
from models.kinematics import ik

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
#: the coupling these tests measure (the scene itself takes the tolerance default, cosim.run.choose)
GS = "master.algorithm=gauss_seidel"
NOV = "master.tolerance=none"  # these runs are measured against the reference here, not judged


def sine_scene(**master):
    """The Chapter 7 path (SPEC §5) into the kinematic mechanism."""
    sig = ["x", "y", "phi", "vx", "vy", "omega", "ax", "ay", "alpha"]
    return {
        "name": "sine_kinematic", "stop_time": 2.0,
        "components": {"path": {"model": "pose_setpoint", "options": {"profile": "sine"}},
                       "ref": {"model": "mechanism", "fidelity": "kinematic"}},
        "connections": [f"path.platform.{s} -> ref.platform.{s}" for s in sig],
        "master": {"algorithm": "gauss_seidel", "step": 1e-3, "output_interval": 1e-2, **master},
        "outputs": ["ref.leg[*].s", "path.platform.*"],
    }


def test_reference_of_the_sine_path_equals_inverse_kinematics_of_the_analytic_pose():
    res = reference(from_dict(sine_scene()))
    assert res.ok, res.reason
    t = res.trace.time
    assert np.allclose(t, np.arange(201) * 1e-2, atol=1e-12)
    pose = np.vstack([-0.25 + 0.05 * np.sin(math.pi * t), -0.15 + 0.05 * np.sin(math.pi * t), 0 * t])
    L, _ = ik(preset(), pose)
    for i in (1, 2, 3):
        assert np.abs(res.trace[f"ref.leg[{i}].s"] - L[i - 1]).max() < 1e-9


@pytest.fixture(scope="module")
def pid_reference():
    return reference(SCENES / "pid_step.yaml", ["stop_time=1"])


def pose_error(res, ref) -> float:
    d = {x.name: x.max_abs for x in compare(res.trace, ref.trace, ["mech.platform.*"])}
    return max(d["mech.platform.x"], d["mech.platform.y"])


def test_held_inputs_converge_to_the_reference_at_first_order(pid_reference, cache):
    """Gauss-Seidel with held inputs is first order: halving the step halves the pose error
    against the monolithic solution (measured ratios 2.00, 2.01)."""
    assert pid_reference.ok, pid_reference.reason
    errors = [pose_error(run(SCENES / "pid_step.yaml", ["stop_time=1", f"master.step={h}", "master.inputs=hold", GS, NOV],
                             cache_dir=cache), pid_reference) for h in (5e-4, 2.5e-4, 1.25e-4)]
    r1, r2 = errors[0] / errors[1], errors[1] / errors[2]
    assert 1.8 < r1 < 2.2 and 1.8 < r2 < 2.2, errors
    assert errors[-1] < 2e-3  # 0.125 ms: the position error over the overshoot is below 2 mm


def test_linear_inputs_converge_faster_and_are_far_closer_at_1_ms(pid_reference, cache):
    """The scene's own setting (linear inputs, 1 ms) is within 2e-4 m of the monolithic solution
    (1.25e-4 m measured with the exact PID and motor kernels; 6.5e-5 m with RK4 PIDs, whose own
    error partly cancelled the coupling error), over 100 times closer than holding at the same
    step; halving the step from 0.5 ms divides the error by more than 3 (second order, blunted by
    the voltage limiter's kink)."""
    lin = {h: pose_error(run(SCENES / "pid_step.yaml", ["stop_time=1", f"master.step={h}", GS, NOV], cache_dir=cache),
                         pid_reference) for h in (1e-3, 5e-4, 2.5e-4)}
    held = pose_error(run(SCENES / "pid_step.yaml", ["stop_time=1", "master.inputs=hold", GS, NOV], cache_dir=cache),
                      pid_reference)
    assert lin[1e-3] < 2e-4 and lin[1e-3] < held / 100, (lin, held)
    assert lin[5e-4] / lin[2.5e-4] > 3, lin


def test_reference_writes_a_trace_the_reader_and_compare_accept(tmp_path, pid_reference):
    res = reference(SCENES / "pid_step.yaml", ["stop_time=0.2"], out_dir=tmp_path)
    back = read_trace(tmp_path / "pid_step_reference.csv")
    assert back.columns == res.trace.columns and np.array_equal(back.data, res.trace.data)
    assert back.status == "ok" and back.meta["method"].startswith("monolithic")
    # the first 0.2 s of the 1 s reference: the same solution up to the solver tolerance
    d = compare(back, pid_reference.trace, ["mech.*"])
    assert max(x.max_abs for x in d) < 1e-7


def test_a_reference_is_the_same_to_the_bit_however_slow_the_machine(monkeypatch):
    """The chunks of output instants per CVODES call (each call restarts the integrator, which
    moves the result at 1e-8 of range) follow the solver's step count, not the wall time: a
    clock that says every call took seconds (a loaded machine) gives the same bytes."""
    import cosim.run.reference as ref_module

    args = (SCENES / "pid_step.yaml", ["stop_time=0.3"])
    quick = reference(*args)
    ticks = iter(range(0, 10**9, 7))  # 7 s between any two readings of the clock
    monkeypatch.setattr(ref_module.time, "perf_counter", lambda: float(next(ticks)))
    slow = reference(*args, max_wall_s=1e9)
    assert quick.status == slow.status == "ok"
    assert quick.trace.data.tobytes() == slow.trace.data.tobytes()
    # and a smaller chunk does move it (so the test above can fail)
    monkeypatch.setattr(ref_module, "CHUNK", 25)
    assert not np.array_equal(reference(*args, max_wall_s=1e9).trace.data, quick.trace.data)


def test_an_early_reference_stands_for_the_one_asked_only_on_the_same_scene_and_instants():
    """``same_request``: the reference integrated on a scene's output grid before its run (``run
    --reference``) is the run's reference when the run asks for the same instants (a variable-step
    run landing on the grid, up to rounding) of the same scene; not for a run that stopped early,
    one that records more instants (events, accepted steps), another scene or other overrides."""
    from cosim.scenario import load

    from cosim.run.reference_files import same_request

    pid = SCENES / "pid_step.yaml"
    scene = load(pid, ["stop_time=0.2"])
    grid = np.arange(201) * 1_000_000 / 1e9
    assert same_request(scene, scene) and same_request(scene, scene, grid)
    assert same_request(scene, scene, grid + 1e-16 * (np.arange(201) % 3))
    assert not same_request(scene, scene, grid[:150])
    assert not same_request(scene, scene, np.sort(np.r_[grid, 0.1005]))
    assert not same_request(scene, load(pid, ["stop_time=0.3"]))
    assert not same_request(scene, load(pid, ["stop_time=0.2", "components.pid1.params.Kp=40"]))
    assert not same_request(scene, load(pid, ["stop_time=0.2", "master.output_interval=2e-3"]))


def test_scene_with_a_sampled_or_external_component_has_no_reference(tmp_path):
    data = sine_scene()
    data["components"]["pid"] = {"model": "pid", "fidelity": "discrete"}
    data["connections"] += ["path.leg[1].s -> pid.setpoint", "ref.leg[1].s -> pid.measurement"]
    with pytest.raises(UserError, match=r"no monolithic reference: block pid .* is sampled \(discrete\)"):
        composite(from_dict(data))


def synthetic(name_values: dict, t: np.ndarray) -> Trace:
    return Trace(["time", *name_values], np.column_stack([t, *name_values.values()]))


def test_compare_interpolates_the_reference_and_reports_absolute_and_relative_errors():
    t_ref = np.linspace(0, 2, 2001)
    ref = synthetic({"a.x": np.sin(t_ref), "a.c": 0 * t_ref + 3.0, "only.ref": t_ref}, t_ref)
    t = np.linspace(0, 2.5, 26)  # beyond the reference: compared on [0, 2] only
    test = synthetic({"a.x": np.sin(t) + 1e-3 * t, "a.c": 0 * t + 3.0}, t)
    d = {x.name: x for x in compare(test, ref)}
    assert set(d) == {"a.x", "a.c"}
    assert d["a.x"].max_abs == pytest.approx(2e-3, rel=1e-5) and d["a.x"].at == pytest.approx(2.0)
    # range of the reference at the compared instants 0, 0.1, ..., 2: sin(0) .. sin(1.6)
    assert d["a.x"].scale == pytest.approx(math.sin(1.6), rel=1e-6)
    assert d["a.c"].max_abs == 0 and d["a.c"].scale == 3.0 and d["a.c"].relative == 0
    assert "a.x" in format_table(list(d.values())).splitlines()[1]


def test_an_error_on_a_signal_that_barely_moves_is_relative_to_the_floor_the_tolerance_has():
    """computed_torque's platform angle: the path keeps it at 0, its reference moves 1.8e-18 rad,
    the run is 5e-9 rad off: 5e-5 of the 1e-4 floor (as the tolerance and the estimate measure it),
    not 3e9 of its range."""
    t = np.linspace(0, 1, 11)
    ref = synthetic({"mech.platform.phi": 1.8e-18 * t}, t)
    test = synthetic({"mech.platform.phi": 1.8e-18 * t + 5e-9}, t)
    (d,) = compare(test, ref)
    assert d.scale == pytest.approx(1.8e-18) and d.relative == pytest.approx(5e-5)
    assert "counts as 0.0001" in format_table([d])


def test_compare_mistakes_are_user_errors():
    t = np.linspace(0, 1, 11)
    with pytest.raises(UserError, match="no variable matching mech.* in common"):
        compare(synthetic({"a.x": t}, t), synthetic({"a.x": t}, t), ["mech.*"])
    with pytest.raises(UserError, match="do not overlap in time"):
        compare(synthetic({"a.x": t}, t), synthetic({"a.x": t}, t + 5))


def write(path: Path, trace: Trace) -> Path:
    w = CsvTrace(path)
    w.start(trace.columns, {"scene": path.stem})
    w.record(trace.data)
    w.finish("ok", "", {})
    return path


def test_cli_compare_table_plot_and_tolerance_exit_code(tmp_path, capsys):
    t = np.linspace(0, 1, 101)
    a = write(tmp_path / "a.csv", synthetic({"m.leg[1].s": np.cos(t), "m.v": t}, t))
    b = write(tmp_path / "b.csv", synthetic({"m.leg[1].s": np.cos(t) + 1e-4, "m.v": t}, t))
    assert cli.main(["compare", str(a), str(b), "--only", "m.leg[*].s", "--plot", str(tmp_path / "d.png")]) == 0
    out = capsys.readouterr().out
    assert "m.leg[1].s" in out and "m.v" not in out and (tmp_path / "d.png").stat().st_size > 1000
    assert cli.main(["compare", str(a), str(b), "--tol", "1e-2"]) == 0
    assert cli.main(["compare", str(a), str(b), "--tol", "1e-5"]) == 1
    assert "beyond the relative tolerance 1e-05 (worst: m.leg[1].s)" in capsys.readouterr().err
    assert cli.main(["compare", str(a), str(tmp_path / "missing.csv")]) == 2
    assert "missing.csv: no such trace file" in capsys.readouterr().err


def test_cli_run_with_reference_reports_the_error_table(tmp_path, capsys, cache):
    rc = cli.main(["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=0.3", "--set", "master.step=5e-4", "--set", GS,
                   "--set", NOV,
                   "--reference", "--out", str(tmp_path), "--cache", str(cache)])
    out = capsys.readouterr().out
    assert rc == 0
    assert "monolithic reference" in out and "co-simulation against the reference:" in out
    assert (tmp_path / "pid_step_reference.csv").is_file()
    table = out.split("co-simulation against the reference:")[1]
    rows = [ln.split() for ln in table.splitlines()[2:] if len(ln.split()) == 7 and ln.split()[0].startswith(("mech", "motor", "pid", "target"))]
    assert len(rows) == 12  # the 12 worst of 24 variables, worst first, each with the run's own estimate beside it
    worst = float(rows[0][5])
    assert 0 < worst < 0.05 and all(float(r[5]) <= worst for r in rows)  # relative to range, linear inputs at 0.5 ms
    assert "estimated" in table.splitlines()[1] and all(float(r[6]) > 0 for r in rows)
