"""Figures drawn beside the run (issue 32, item 11: the main job's time to answer):
:class:`cosim.analysis.drawing.Drawer` draws in processes of its own what this process would draw,
the same bytes; a failure comes back as one line and leaves the run's files; Ctrl-C and SIGTERM
stop the drawing without a temporary file or a process left behind.  The speed is
benchmarks/bench_main_job.py's."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cosim.analysis import charts
from cosim.analysis.animate import animate
from cosim.analysis.trace_diff import compare
from cosim.analysis.drawing import DrawError, Drawer, Forked, SharedProgress
from cosim.cli import main
from cosim.outputs import staged
from cosim.trace.traces import Trace, read_trace

ROOT = Path(__file__).resolve().parents[1]
PID = ROOT / "scenarios" / "pid_step.yaml"

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="the drawing processes are forked")


def _trace(wobble: float = 0.0) -> Trace:
    t = np.linspace(0.0, 1.0, 401)
    cols = {"mech.platform.x": -0.15 - 0.05 * t, "mech.platform.y": -0.15 + 0.02 * t + wobble * np.sin(9 * t),
            "mech.platform.phi": 0.2 * t, "pid1.y": np.exp(-5 * t), "pid2.y": 0.5 * np.exp(-3 * t)}
    return Trace(["time", *cols], np.column_stack([t, *cols.values()]))


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended (no longer exists, or a zombie that init will reap)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def _where(tag: str) -> tuple[str, int]:
    return tag, os.getpid()


def _fails(message: str) -> None:
    raise ValueError(message)


def _dies() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _writes_slowly(path: Path, pid_file: Path) -> Path:
    pid_file.write_text(str(os.getpid()))
    with staged(path) as part:
        part.write_bytes(b"half a figure")
        time.sleep(60)
    return path


def test_figures_drawn_beside_are_the_bytes_drawn_here(tmp_path):
    """The run chart, the comparison plot and the GIF from the drawing processes are the files
    this process writes with the same calls; each job ran in a process other than this one and
    its warm parent."""
    test, ref = _trace(1e-3), _trace()
    diffs = compare(test, ref)

    def jobs(folder: Path) -> list[tuple]:
        return [(charts.plot_run, (test, folder / "run.png", "t"), {"units": {"pid1.y": "V", "pid2.y": "V"}}),
                (charts.plot_comparison, (test, ref, diffs, folder / "cmp.png"), {"labels": ("adaptive", "reference")}),
                (animate, (test, folder / "anim.gif"), {"title": "t"})]

    with Drawer() as drawer:
        assert drawer.parallel
        asked = [drawer.submit(fn, *args, **kw) for fn, args, kw in jobs(tmp_path / "beside")]
        where = [drawer.submit(_where, k) for k in "ab"]
        written = [drawer.result(j) for j in asked]
        pids = [drawer.result(j)[1] for j in where]
        server = drawer._pid
    assert os.getpid() not in pids and server not in pids and _gone(server)
    for path, (fn, args, kw) in zip(written, jobs(tmp_path / "here")):
        assert path.read_bytes() == fn(*args, **kw).read_bytes(), path.name
    assert written[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and written[2].read_bytes()[:6] == b"GIF89a"


@pytest.mark.parametrize("cut", [1, 2, 4])
def test_a_comparison_drawn_in_parts_is_the_file_drawn_whole(tmp_path, cut):
    """The main job's last figure is drawn in two halves at once and joined: the same PNG, byte
    for byte, as :func:`charts.plot_comparison` writes (five rows, cut after row ``cut``)."""
    t = np.linspace(0.0, 2.0, 801)
    names = [f"m.v{k}" for k in range(5)]
    test = Trace(["time", *names], np.column_stack([t, *[np.sin((k + 1) * t) for k in range(5)]]))
    ref = Trace(["time", *names], np.column_stack([t, *[np.sin((k + 1) * t) + 1e-7 * k * t for k in range(5)]]))
    diffs = compare(test, ref)
    kw = {"labels": ("gauss_seidel", "reference"), "units": {n: "N.m" for n in names}}
    whole = charts.plot_comparison(test, ref, diffs, tmp_path / "whole.png", **kw)
    rows = charts.comparison_rows(diffs)
    with Drawer() as drawer:
        jobs = [drawer.submit(charts.comparison_part, test, ref, diffs, r, **kw) for r in (range(cut), range(cut, rows))]
        joined = charts.join_comparison([drawer.result(j) for j in jobs], tmp_path / "joined.png")
    assert rows == 5 and joined.read_bytes() == whole.read_bytes()


def test_a_failed_figure_is_one_line_and_the_others_are_drawn(tmp_path):
    with Drawer(warm=None) as drawer:
        bad = drawer.submit(_fails, "no canvas\nfor this figure")
        killed = drawer.submit(_dies)
        good = drawer.submit(_where, "ok")
        with pytest.raises(DrawError) as failed:
            drawer.result(bad)
        assert str(failed.value) == "ValueError: no canvas for this figure"
        with pytest.raises(DrawError, match="^the drawing process was killed by SIGKILL$"):
            drawer.result(killed)
        assert drawer.result(good)[0] == "ok"


def test_stop_removes_the_figure_being_written_and_leaves_no_process(tmp_path):
    final, pid_file = tmp_path / "fig.png", tmp_path / "pid"
    drawer = Drawer(warm=None)
    server = drawer._pid
    job = drawer.submit(_writes_slowly, final, pid_file)
    part = final.with_name(".fig.part.png")
    deadline = time.monotonic() + 30
    while not (part.exists() and pid_file.exists()):
        assert time.monotonic() < deadline and not drawer.finished(job)
        time.sleep(0.01)
    child = int(pid_file.read_text())
    os.kill(server, signal.SIGINT)  # Ctrl-C is the command's: the drawing processes ignore it
    os.kill(child, signal.SIGINT)
    time.sleep(0.2)
    assert part.exists() and not _gone(server) and not _gone(child)
    drawer.stop()
    assert not part.exists() and not final.exists()
    assert _gone(server) and _gone(child)
    with pytest.raises(DrawError, match="stopped before the figure was written"):
        drawer.result(job)


def test_the_drawing_process_ends_with_its_parent(tmp_path):
    script = ("import os, sys, time\nfrom cosim.analysis.drawing import Drawer\n"
              "d = Drawer(warm=None)\nprint(d._pid, flush=True)\nos._exit(0)\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=60, check=True)
    server = int(res.stdout.split()[0])
    deadline = time.monotonic() + 10
    while not _gone(server):
        assert time.monotonic() < deadline, f"drawing process {server} outlived its parent"
        time.sleep(0.05)


def _broken_chart(trace, path, title, **kwargs):
    raise RuntimeError(f"the canvas for {Path(path).name} could not be allocated")


def _counts(progress: SharedProgress, n: int) -> int:
    for k in range(1, n + 1):
        progress(k, n)
        time.sleep(0.02)
    return os.getpid()


def test_a_forked_job_runs_beside_and_reports_its_progress():
    """:class:`Forked` runs its call in a child (another pid) at once; ``result`` gives its value,
    calling ``waiting`` meanwhile, where the child's :class:`SharedProgress` is read."""
    progress, seen = SharedProgress(), []
    job = Forked(_counts, progress, 20)
    pid = job._pid
    value = job.result(lambda: seen.append(progress.read()))
    assert value == pid != os.getpid() and _gone(pid)
    assert seen and all(total in (0, 20) and 0 <= done <= 20 for done, total in seen)
    assert progress.read() == (20, 20) and any(0 < done < 20 for done, _ in seen)
    job.stop()  # after the end: nothing to do


def test_a_forked_job_that_fails_is_one_line_and_stop_leaves_no_process(tmp_path):
    with pytest.raises(DrawError, match="^ValueError: no reference for this scene$"):
        Forked(_fails, "no reference\nfor this scene").result()
    with pytest.raises(DrawError, match="^the drawing process was killed by SIGKILL$"):
        Forked(_dies).result()
    slow = Forked(time.sleep, 60)
    pid = slow._pid
    os.kill(pid, signal.SIGINT)  # Ctrl-C is the command's
    time.sleep(0.1)
    assert not _gone(pid)
    t0 = time.monotonic()
    slow.stop()
    assert _gone(pid) and time.monotonic() - t0 < 5


def _reference_where(real, pid_file: Path, fail_beside: bool):
    def reference(scene, *args, **kwargs):
        with open(pid_file, "a") as fh:
            fh.write(f"{os.getpid()}\n")
        if fail_beside and os.getpid() != int(pid_file.with_suffix(".parent").read_text()):
            raise RuntimeError("no memory for the early reference")
        return real(scene, *args, **kwargs)
    return reference


@pytest.mark.parametrize("fail_beside", [False, True])
def test_the_reference_integrates_beside_the_run_and_writes_what_it_would_after(tmp_path, cache, monkeypatch,
                                                                             capsys, fail_beside):
    """``run --reference``: the reference is integrated in a child forked as the run starts, and
    the command writes the files the reference of the run as it ran (the master's choice, its
    instants) writes itself, to the byte; when the child fails the reference is integrated after
    the run, the same files."""
    import cosim.run.reference as ref_module

    pid_file = tmp_path / "pids.txt"
    pid_file.with_suffix(".parent").write_text(str(os.getpid()))
    monkeypatch.setattr(ref_module, "reference", _reference_where(ref_module.reference, pid_file, fail_beside))
    out = tmp_path / "out"
    code = main(["run", str(PID), "--set", "stop_time=0.3", "--reference", "--out", str(out), "--cache", str(cache)])
    assert code == 0, capsys.readouterr().err
    pids = [int(p) for p in pid_file.read_text().split()]
    assert pids[0] != os.getpid() and pids[1:] == ([os.getpid()] if fail_beside else [])
    monkeypatch.undo()
    test = read_trace(out / "pid_step.csv")
    assert test.meta["algorithm"] == "adaptive"  # variable steps landing on the grid: the run's instants
    from cosim.run.execute import run
    from cosim.scenario import load

    ran = run(load(PID, ["stop_time=0.3"]), cache_dir=cache)
    assert np.array_equal(ran.trace.time, test.time)
    here = ref_module.reference(ran.scene, out_dir=tmp_path / "here", times=ran.trace.time)
    assert (out / "pid_step_reference.csv").read_bytes() == here.trace_path.read_bytes()
    sides = [json.loads((d / "pid_step_reference.json").read_text()) for d in (out, tmp_path / "here")]
    for side in sides:
        del side["started"], side["statistics"]["wall_s"], side["statistics"]["real_time_factor"]
    assert sides[0] == sides[1]


def test_a_failed_plot_keeps_the_run_and_says_why(tmp_path, cache, capsys, monkeypatch):
    """The main job with a chart that fails: one line naming the file and the reason, exit code 1,
    the run's trace and sidecar as the run left them, the animation and comparison written."""
    monkeypatch.setattr(charts, "plot_run", _broken_chart)
    code = main(["run", str(PID), "--set", "stop_time=0.05", "--plot", "--animate", "--reference", "--out",
                 str(tmp_path), "--cache", str(cache)])
    err = capsys.readouterr().err
    assert code == 1, err
    assert ("rpr-cosim run: the plot pid_step.png was not written: RuntimeError: the canvas for pid_step.png could "
            "not be allocated; the run's trace pid_step.csv is complete") in err.splitlines()
    assert "Traceback" not in err
    assert json.loads((tmp_path / "pid_step.json").read_text())["status"] == "ok"
    assert len(read_trace(tmp_path / "pid_step.csv").data) == 51
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "pid_step.png" not in names and not [n for n in names if ".part" in n]
    assert {"pid_step.gif", "pid_step_vs_reference.png"} <= set(names)
    # the comparison, drawn beside the run (whole or in halves), is the file drawn here from the two traces
    monkeypatch.undo()
    test, ref = read_trace(tmp_path / "pid_step.csv"), read_trace(tmp_path / "pid_step_reference.csv")
    here = charts.plot_comparison(test, ref, compare(test, ref), tmp_path / "here" / "cmp.png",
                                  labels=(test.meta["algorithm"], "reference"), units=test.meta["units"])
    assert here.read_bytes() == (tmp_path / "pid_step_vs_reference.png").read_bytes()


def test_ctrl_c_while_the_figures_are_drawn_stops_every_process(tmp_path, cache):
    """Ctrl-C (SIGINT to the whole process group) once the figures are being written: exit code
    130, no temporary file, the sidecar says which figures were cut, no process of the group left."""
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "cosim", "run", str(PID), "--set", "stop_time=3", "--plot",
                             "--animate", "--out", str(out), "--cache", str(cache)], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while not list(out.glob(".pid_step.part.*")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.01)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert not list(out.glob(".*part*"))
    side = json.loads((out / "pid_step.json").read_text())
    assert side["status"] == "interrupted" and "while writing the " in side["reason"], side["reason"]
    time.sleep(0.2)
    with pytest.raises(ProcessLookupError):
        os.killpg(proc.pid, 0)


def test_ctrl_c_during_the_run_stops_the_reference_beside_it(tmp_path, cache):
    """Ctrl-C while the run steps and its reference integrates beside it: exit code 130, the
    run's partial trace kept, no reference file, no process of the group left."""
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "cosim", "run", str(PID), "--set", "stop_time=60", "--set",
                             "master.algorithm=gauss_seidel", "--set", "master.step=1e-4", "--reference", "--out",
                             str(out), "--cache", str(cache)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while not (out / ".pid_step.csv.part").exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.01)
    children = subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True, text=True).stdout.split()
    assert len(children) >= 2  # the command and its reference (and the run's supervised process)
    time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert json.loads((out / "pid_step.json").read_text())["status"] == "interrupted"
    assert not list(out.glob("*reference*")) and not list(out.glob(".*part*"))
    time.sleep(0.2)
    with pytest.raises(ProcessLookupError):
        os.killpg(proc.pid, 0)
