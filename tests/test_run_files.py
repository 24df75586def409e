"""A run's files are one set (issue 32, item 2): a rerun into the same directory keeps the earlier
set whole under one name (``<name>.prev.*``) or replaces it whole, never a mix; the sidecar
records every override, from ``--set``, a batch axis or the Python API."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from cosim.cli import main
from cosim.outputs import place, run_set

PID = str(Path(__file__).resolve().parents[1] / "scenarios" / "pid_step.yaml")
SHORT = ["--set", "stop_time=0.05"]


def _names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def test_a_rerun_keeps_the_earlier_good_set_whole_under_prev(tmp_path, cache, capsys):
    """The tutorial's measurement: a run with plot and reference, then a rerun with other gains
    and no plot: no older plot or reference is left beside the new trace."""
    out = tmp_path / "pid_step"
    assert main(["run", PID, *SHORT, "--plot", "--reference", "--out", str(out), "--cache", str(cache)]) == 0
    first = _names(out)
    assert {"pid_step.csv", "pid_step.json", "pid_step.png", "pid_step_reference.csv",
            "pid_step_vs_reference.png"} <= set(first)
    before = (out / "pid_step.csv").read_bytes()
    capsys.readouterr()
    assert main(["run", PID, *SHORT, "--set", "components.pid*.params.Kp=40", "--out", str(out),
                 "--cache", str(cache)]) == 0
    err = capsys.readouterr().err
    now = _names(out)
    assert [n for n in now if ".prev" not in n] == ["pid_step.csv", "pid_step.json"]
    assert sorted(n.replace("pid_step.prev", "pid_step") for n in now if ".prev" in n) == first
    assert (out / "pid_step.prev.csv").read_bytes() == before  # the earlier trace, whole
    assert "kept the earlier good trace as pid_step.prev.csv; its run's" in err and "as pid_step.prev.*" in err
    side = json.loads((out / "pid_step.json").read_text())
    assert side["overrides"] == ["stop_time=0.05", "components.pid*.params.Kp=40"]  # it said [] after --set
    assert json.loads((out / "pid_step.prev.json").read_text())["overrides"] == ["stop_time=0.05"]


def test_the_sidecar_records_the_python_apis_overrides(tmp_path, cache):
    from cosim.run.execute import run

    run(PID, {"stop_time": 0.02, "components.pid1.params.Kd": 15}, out_dir=tmp_path, cache_dir=cache)
    side = json.loads((tmp_path / "pid_step.json").read_text())
    assert side["overrides"] == ["stop_time=0.02", "components.pid1.params.Kd=15"]


def test_a_batch_runs_scene_carries_its_axis_values_as_overrides(tmp_path):
    """What a batch run's sidecar records (the worker runs the scene :func:`resolve` made)."""
    from cosim.batch.axes import points
    from cosim.batch.runner import resolve
    from cosim.batch.spec import load_batch

    spec = tmp_path / "b.yaml"
    spec.write_text(f"name: b\nscene: {PID}\nset: {{stop_time: 0.05}}\n"
                    "grid:\n  Kp: {path: \"components.pid*.params.Kp\", values: [20, 40]}\n")
    batch = load_batch(spec)
    scenes = [resolve(batch, p).scene for p in points(batch)]
    for scene, kp in zip(scenes, (20, 40)):  # the axis's wildcard as the batch expands it, one per PID
        assert scene.overrides == ["stop_time=0.05", *(f"components.pid{i}.params.Kp={kp}" for i in (1, 2, 3))]


def test_a_rerun_replaces_an_earlier_set_that_was_not_ok_whole(tmp_path):
    """The placement itself, on files standing for a run that ended failed: all of them go."""
    for name in ("x.csv", "x.png", "x.gif", "x.html", "x_reference.csv", "x_reference.json", "x_vs_reference.png",
                 "x.prev.csv", "x.prev.json", "x.prev.png", "xy.png"):
        (tmp_path / name).write_text(name)
    (tmp_path / "x.json").write_text(json.dumps({"status": "failed"}))
    part, side_part = tmp_path / ".x.csv.part", tmp_path / ".x.json.part"
    part.write_text("new"), side_part.write_text(json.dumps({"status": "ok"}))
    note = place(part, tmp_path / "x.csv", "ok", part_sidecar=side_part, sidecar=tmp_path / "x.json")
    assert note == "replaced the earlier trace x.csv (its status was failed); its run's 6 other files removed"
    assert _names(tmp_path) == ["x.csv", "x.json", "x.prev.csv", "x.prev.json", "x.prev.png", "xy.png"]
    assert (tmp_path / "x.prev.png").read_text() == "x.prev.png"  # the good set from before stays whole
    assert [p.name for p in run_set(tmp_path, "x")] == ["x.csv", "x.json"]


@pytest.mark.parametrize("name", ["pid_step.png", "pid_step.prev.gif", "pid_step_reference.json"])
def test_a_directory_under_a_name_of_the_set_is_one_line_and_nothing_is_written(tmp_path, cache, capsys, name):
    """A directory where the run keeps one of its files (or moves an earlier one to) could be
    neither replaced nor moved aside: the run is refused before it starts, in one line naming
    it, and leaves nothing behind (no ``.part`` file)."""
    out = tmp_path / "out"
    (out / name).mkdir(parents=True)
    code = main(["run", PID, *SHORT, "--plot", "--animate", "--reference", "--out", str(out), "--cache", str(cache)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert (f"rpr-cosim run: error: {out / name} is a directory, where a run of 'pid_step' keeps a file of its own; "
            f"remove or rename it, or choose another --out") in err.splitlines()
    assert "Traceback" not in err and "pilot" not in err  # refused before the pilot runs
    assert sorted(p.name for p in out.iterdir()) == [name]
