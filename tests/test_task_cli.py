"""``rpr-cosim task check|plan``: exit status, one-line refusals and errors, CSV waypoints, the plot;
the thesis's motions as tasks (Chapter 7's sine path against its formula, SPEC §5)."""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from models.task import task_from

TASKS = Path(__file__).resolve().parents[1] / "scenarios" / "tasks"


def test_check_passes_the_pick_and_place_and_plots(tmp_path, capsys):
    assert main(["task", "check", str(TASKS / "pick_and_place.yaml"), "--plot", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "passes every check" in out and "leg speed" in out
    assert (tmp_path / "pick_and_place_check.png").stat().st_size > 10_000


def test_check_refuses_the_singular_path_in_one_line(tmp_path, capsys):
    assert main(["task", "check", str(TASKS / "through_singularity.yaml"), "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "refused at t = 1.100000000 s" in err[0] and "det J = 0" in err[0]


def test_plan_writes_the_samples_from_csv_waypoints(tmp_path, capsys):
    (tmp_path / "w.csv").write_text("x,y,phi,t\n-0.15,-0.15,0,0\n-0.2,-0.15,0.2,1.5\n-0.15,-0.15,0,3\n")
    (tmp_path / "t.yaml").write_text("waypoints: w.csv\n")
    assert main(["task", "plan", str(tmp_path / "t.yaml"), "--out", str(tmp_path / "o")]) == 0
    rows = list(csv.DictReader(open(tmp_path / "o" / "t.csv")))
    assert len(rows) == 3001
    at = {round(float(r["time"]), 9): r for r in rows}
    assert float(at[1.5]["x"]) == pytest.approx(-0.2, abs=1e-15) and float(at[1.5]["phi"]) == pytest.approx(0.2, abs=1e-15)


@pytest.mark.parametrize("text, words", [
    ("waypoints: [[0, 0, 0]]\n", "at least two"),
    ("waypoints: [[-0.15, -0.15, 0], [-0.2, -0.15, 0.2]]\nlimits: {leg_speed: -1}\n", "limits.leg_speed"),
    ("waypoints: [[-0.15, -0.15, 0], [-0.2, -0.15, 0.2]]\nspeed: 1\n", "unknown key 'speed'"),
    ("waypoints: [[-0.15, -0.15, 0]\n", "YAML syntax"),
    ("waypoints: missing.csv\n", "missing.csv"),
])
def test_bad_task_files_are_one_line(tmp_path, capsys, text, words):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    assert main(["task", "check", str(path), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and str(path) in err[0], err


def test_the_chapter_7_sine_path_is_a_task():
    """SPEC §5: x = -0.25 + 0.05 sin(pi t), y = -0.15 + 0.05 sin(pi t); as a spline task through its
    samples every 50 ms (rest at both ends: from its extremes t = 0.5 s to 2.5 s), within 2e-6 m."""
    t = np.arange(0.5, 2.5 + 1e-12, 0.05)
    w = np.column_stack([-0.25 + 0.05 * np.sin(math.pi * t), -0.15 + 0.05 * np.sin(math.pi * t), 0 * t])
    traj = task_from({"waypoints": w.tolist(), "times": t.tolist()}).plan()
    s = np.linspace(0.5, 2.5, 2001)
    q, qd, _ = traj.evaluate(s)
    assert np.max(np.abs(q[0] - (-0.25 + 0.05 * np.sin(math.pi * s)))) < 2e-6
    assert np.max(np.abs(qd[1] - 0.05 * math.pi * np.cos(math.pi * s))) < 1e-4


def test_a_check_too_long_to_sample_is_one_line(tmp_path, capsys):
    path = tmp_path / "slow.yaml"
    path.write_text("waypoints: [[-0.15, -0.15, 0], [-0.2, -0.15, 0.2]]\ntimes: [0, 5000]\n")
    assert main(["task", "check", str(path), "--dt", "1e-3", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "at most 1000000" in err[0]


@pytest.mark.parametrize("make, words", [
    (lambda d: Path("/dev/zero"), "character device, not a regular file"),
    (lambda d: (os.mkfifo(d / "w.csv"), (d / "t.yaml").write_text("waypoints: w.csv\n"), d / "t.yaml")[-1],
     "FIFO"),
    (lambda d: ((d / "t.yaml").write_text("a: " + "[" * 200 + "]" * 200 + "\n"), d / "t.yaml")[-1],
     "nested more than"),
    (lambda d: d, "directory, not a regular file"),
])
def test_task_files_are_read_only_when_regular_and_bounded(tmp_path, capsys, make, words):
    """A task file or its waypoints CSV that is a device, a FIFO (which would hang a plain open),
    a directory or YAML nested without end is one line and exit 2, as a scene is."""
    path = make(tmp_path)
    assert main(["task", "check", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err
