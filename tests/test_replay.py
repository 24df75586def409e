"""A recording as a component (``{replay: FILE}``, issue 34): the replayed signals against numpy's
interpolation of the same table, the thesis's PID driven by a recorded run (to the bit, and within
the ADC's quantisation once the legs are read through the rig's 12-bit pots), and the refusals."""
from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import UserError
from cosim.run.execute import run
from cosim.scenario import load
from cosim.trace.traces import read_trace
from hardware.convert import quantise
from hardware.virtual import RIG_CALIBRATION

ROOT = Path(__file__).resolve().parent.parent
PID = {"Kp": 30.0, "Ki": 80.0, "Kd": 20.0, "Tf": 1e-3}  # pid_step's gains; Tf the catalog's default
STOP = 1.0


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """pid_step (1 s) under Jacobi with held inputs at 1 ms: each PID's inputs at a step are the
    recorded values at its start, so a replay with ``hold`` feeds them exactly what they saw."""
    out = tmp_path_factory.mktemp("pid")
    res = run(ROOT / "scenarios" / "pid_step.yaml", [f"stop_time={STOP}", "master.algorithm=jacobi",
                                                     "master.inputs=hold", "master.estimate=false"], out_dir=out)
    assert res.ok, res.reason
    return res.trace_path


def _replay_pid_scene(path: Path, recording: str) -> Path:
    pid = "{model: pid, fidelity: continuous, params: {Kp: 30, Ki: 80, Kd: 20, u_max: 12}}"
    path.write_text(textwrap.dedent(f"""\
        name: replay_pid
        stop_time: {STOP}
        components:
          rec: {{replay: {recording}, interpolation: hold}}
          pid1: {pid}
          pid2: {pid}
          pid3: {pid}
        connections:
        """) + "".join(f"  - rec.target.leg[{i}].s -> pid{i}.setpoint\n  - rec.mech.leg[{i}].s -> pid{i}.measurement\n"
                       for i in (1, 2, 3)) +
        "master: {algorithm: jacobi, step: 1e-3, inputs: hold, estimate: false}\noutputs: [pid*.y]\n")
    return path


def test_replayed_run_drives_the_pid_to_the_recorded_voltages(recorded, tmp_path):
    res = run(_replay_pid_scene(tmp_path / "replay.yaml", str(recorded)), out_dir=tmp_path / "out")
    assert res.ok, res.reason
    rec = read_trace(recorded)
    for i in (1, 2, 3):
        assert np.array_equal(res.trace[f"pid{i}.y"], rec[f"pid{i}.y"])  # the same inputs, the same FMU


def test_quantised_legs_reproduce_the_voltages_within_the_quantisation(recorded, tmp_path):
    """The legs as the rig's pots read them (12-bit ADC, 0.17 mm a count): the PID's voltages differ
    from the recorded ones by at most its gain to a bounded input times half a count, the gain
    being Kp + Ki T + 2 Kd / Tf (the L1 norm of the filtered derivative's impulse response is
    2 / Tf); and they do differ (the quantisation is there)."""
    rec = read_trace(recorded)
    cal = RIG_CALIBRATION
    text = recorded.read_text().splitlines()
    header = next(ln for ln in text if not ln.startswith("#"))
    cols = header.split(",")
    data = rec.data.copy()
    for i in (1, 2, 3):
        j = cols.index(f"mech.leg[{i}].s")
        data[:, j] = [cal.leg_length(quantise(cal.counts(s - cal.s_offset))) for s in data[:, j]]
    q = tmp_path / "quantised.csv"
    q.write_text("# units: " + json.dumps(rec.meta["units"]) + "\n" + header + "\n" +
                 "\n".join(",".join(repr(float(v)) for v in row) for row in data) + "\n")
    res = run(_replay_pid_scene(tmp_path / "replay.yaml", str(q)), out_dir=tmp_path / "out")
    assert res.ok, res.reason
    half_count = cal.metres_per_count / 2
    bound = (PID["Kp"] + PID["Ki"] * STOP + 2 * PID["Kd"] / PID["Tf"]) * half_count
    worst = max(np.abs(res.trace[f"pid{i}.y"] - rec[f"pid{i}.y"]).max() for i in (1, 2, 3))
    assert 0 < worst <= bound, (worst, bound)


def _table_scene(tmp_path: Path, interpolation: str, step: float = 1e-3, stop: float = 0.1,
                 units: str = "") -> Path:
    scene = tmp_path / f"table_{interpolation}.yaml"
    scene.write_text(textwrap.dedent(f"""\
        name: table_{interpolation}
        stop_time: {stop}
        components:
          rec: {{replay: table.csv, interpolation: {interpolation}{units}}}
          pid: {{model: pid, fidelity: continuous, params: {{Kp: 1, Ki: 0, Kd: 0}}}}
        connections:
          - rec.x -> pid.setpoint
        master: {{algorithm: jacobi, step: {step}, inputs: hold, estimate: false}}
        outputs: [rec.x, rec.y]
        """))
    return scene


@pytest.mark.parametrize("interpolation", ["linear", "hold"])
def test_replay_between_samples_matches_numpy(tmp_path, interpolation):
    t = np.linspace(0.0, 0.1, 11)  # a sample every 10 ms, stepped every 1 ms
    x, y = np.sin(40 * t), t ** 2
    (tmp_path / "table.csv").write_text("time,x,y\n" + "\n".join(f"{a!r},{b!r},{c!r}" for a, b, c in zip(t.tolist(), x.tolist(), y.tolist())))
    res = run(_table_scene(tmp_path, interpolation, units=", units: {x: m}"), out_dir=tmp_path / "out")
    assert res.ok, res.reason
    tt = res.trace.time
    if interpolation == "linear":
        want = np.interp(tt, t, x), np.interp(tt, t, y)
    else:
        k = np.searchsorted(t, tt + 1e-12, side="right") - 1
        want = x[k], y[k]
    assert np.allclose(res.trace["rec.x"], want[0], rtol=0, atol=1e-14)
    assert np.allclose(res.trace["rec.y"], want[1], rtol=0, atol=1e-14)


def test_parquet_recording_replays_like_its_csv(recorded, tmp_path):
    pytest.importorskip("pyarrow")
    rec = read_trace(recorded)
    rec.to_pandas().reset_index().to_parquet(tmp_path / "rec.parquet")
    # Parquet without metadata carries no units: the scene states them
    scene = _replay_pid_scene(tmp_path / "replay.yaml", "rec.parquet")
    scene.write_text(scene.read_text().replace("interpolation: hold}", "interpolation: hold, units: {"
                     + ", ".join(f"'{k}.leg[{i}].s': m" for k in ("target", "mech") for i in (1, 2, 3)) + "}}"))
    res = run(scene, out_dir=tmp_path / "out")
    assert res.ok, res.reason
    assert np.array_equal(res.trace["pid1.y"], rec["pid1.y"])


def _refusal(tmp_path: Path, table: str, **kw) -> str:
    (tmp_path / "table.csv").write_text(table)
    with pytest.raises(UserError) as exc:
        load(_table_scene(tmp_path, "linear", **kw))
    return str(exc.value)


GOOD = "time,x,y\n0,0,0\n0.05,1,1\n0.1,2,2\n"


@pytest.mark.parametrize("table, kw, expected", [
    ("t,x,y\n0,0,0\n0.1,1,1\n", {"units": ", units: {x: m}"}, "table.csv: not a trace: no 'time' column"),
    ("time,x,y\n0,0,0\n0.05,1,1\n0.05,2,2\n0.1,3,3\n", {"units": ", units: {x: m}"},
     "table.csv: not a trace: time does not increase at row 3"),
    ("time,x,y\n0,0,0\n0.1,abc,1\n", {}, "table.csv:3: expected 3 numbers"),
    (GOOD, {}, "the unit of column 'x' of"),  # the PID's setpoint is in m; the file says nothing
    (GOOD, {"units": ", units: {x: mm}"}, "column 'x' of"),  # mm against m
    (GOOD, {"units": ", units: {z: m}"}, "units names column 'z', which the file does not have"),
    (GOOD, {"units": ", units: {x: m}", "stop": 0.2}, "covers 0..0.1 s, shorter than the scene's 0..0.2 s"),
])
def test_bad_recordings_are_refused_in_one_line_naming_the_file(tmp_path, table, kw, expected):
    msg = _refusal(tmp_path, table, **kw)
    assert expected in msg, msg
    assert "table.csv" in msg
    assert "Traceback" not in msg


def test_misnamed_column_is_named(tmp_path):
    (tmp_path / "table.csv").write_text(GOOD)
    scene = _table_scene(tmp_path, "linear", units=", units: {x: m}")
    scene.write_text(scene.read_text().replace("rec.x -> pid.setpoint", "rec.xx -> pid.setpoint"))
    with pytest.raises(UserError) as exc:
        load(scene)
    assert "xx" in str(exc.value) and "'x'" in str(exc.value), str(exc.value)
