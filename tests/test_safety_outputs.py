"""Outputs that cannot be redirected (issue 20, items 2 and 5): links planted in --out are never
followed, one lock for runs, batches and studies, a run never replaces a batch's files, backup
names cannot collide with scene names, plots and animations are moved into place complete, an
interrupted animation is not "ok", an early refusal leaves no part file."""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cosim import outputs
from cosim.errors import UserError
from cosim.run.execute import run
from cosim.scenario import SceneError, load
from cosim.trace import traces as trace_module
from cosim.trace.traces import read_trace
from test_robustness_outputs import PID, SHORT, whole_rows

ROOT = Path(__file__).resolve().parents[1]
VICTIM = "precious data\n"


def cli(args, cache, timeout=300):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "cosim", *map(str, args), "--cache", str(cache)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def victim(tmp_path: Path) -> Path:
    v = tmp_path / "victim.txt"
    v.write_text(VICTIM)
    return v


@pytest.mark.parametrize("planted", [".pid_step.csv.part", ".pid_step.json.part", ".rpr-cosim.lock",
                                     "..pid_step.json.part.{pid}.tmp"])
def test_a_link_planted_under_a_temporary_name_is_replaced_never_written_through(tmp_path, cache, planted):
    out = tmp_path / "out"
    out.mkdir()
    v = victim(out)  # inside --out, so that only the link (not confinement) is in question
    (out / planted.format(pid=os.getpid())).symlink_to(v)
    res = run(PID, [*SHORT, "master.algorithm=gauss_seidel", "master.tolerance=none"], out_dir=out,
              cache_dir=cache)  # 1 ms rows
    assert res.ok
    assert v.read_text() == VICTIM  # neither truncated nor written
    for name in ("pid_step.csv", "pid_step.json"):
        assert (out / name).is_file() and not (out / name).is_symlink()
    assert whole_rows(out / "pid_step.csv") == len(res.trace.data) == 51


@pytest.mark.parametrize("planted", ["pid_step.csv", "pid_step.json"])
def test_a_link_under_the_traces_own_name_is_refused_in_one_line(tmp_path, cache, planted):
    out = tmp_path / "out"
    out.mkdir()
    v = victim(out)
    (out / planted).symlink_to(v)
    with pytest.raises(UserError, match=rf"refusing to replace .*{planted}: it is not an rpr-cosim trace"):
        run(PID, SHORT, out_dir=out, cache_dir=cache)
    assert v.read_text() == VICTIM


def test_a_link_to_a_file_outside_out_is_refused_or_replaced(tmp_path, cache):
    out = tmp_path / "out"
    out.mkdir()
    v = victim(tmp_path)
    (out / ".pid_step.csv.part").symlink_to(v)
    (out / ".rpr-cosim.lock").symlink_to(v)
    assert run(PID, SHORT, out_dir=out, cache_dir=cache).ok
    assert v.read_text() == VICTIM
    (out / "pid_step.csv").unlink()
    (out / "pid_step.csv").symlink_to(v)  # the trace's own name pointing outside: one line, nothing written
    with pytest.raises(UserError, match=r"refusing to write 'pid_step.csv': it resolves to .*victim.txt, outside "
                                        r"the output directory"):
        run(PID, SHORT, out_dir=out, cache_dir=cache)
    assert v.read_text() == VICTIM


def test_the_reference_part_file_is_not_followed(tmp_path, cache):
    out = tmp_path / "out"
    out.mkdir()
    v = victim(tmp_path)
    (out / ".pid_step_reference.csv.part").symlink_to(v)
    res = cli(["run", PID, "--set", "stop_time=0.05", "--reference", "--out", out], cache)
    assert res.returncode == 0, res.stderr
    assert v.read_text() == VICTIM
    assert read_trace(out / "pid_step_reference.csv").status == "ok"
    assert not (out / "pid_step_reference.csv").is_symlink()


@pytest.mark.parametrize("name", ["pid_step.prev", "pid_step.PREV", "x.part", "x.tmp", "pid_step_reference",
                                  "a.lock"])
def test_a_scene_name_ending_like_our_own_files_is_refused(tmp_path, name):
    with pytest.raises(SceneError, match=rf"name '{name}' ends with '\.?[a-z_]+', which rpr-cosim uses for files "
                                         rf"of its own next to a scene's .*choose another name"):
        load(PID, [f"name={name}"])


def test_a_good_trace_kept_as_prev_cannot_be_another_scenes(tmp_path, cache):
    res = cli(["run", PID, "--set", "name=pid_step.prev", "--set", "stop_time=0.05", "--out", tmp_path], cache)
    assert res.returncode == 2 and "ends with '.prev'" in res.stderr and "Traceback" not in res.stderr
    assert not list(tmp_path.iterdir())


BATCH = f"""\
name: small
scene: {PID}
set: {{stop_time: 0.05}}
grid:
  Kp: {{path: "components.pid*.params.Kp", values: [20, 30]}}
metrics:
  mech.platform.phi: [max]
"""


def test_a_run_never_replaces_a_batchs_files(tmp_path, cache):
    spec = tmp_path / "b.yaml"
    spec.write_text(BATCH)
    out = tmp_path / "bout"
    res = cli(["batch", spec, "--out", out, "--workers", "1"], cache)
    assert res.returncode == 0, res.stderr
    before = {p: (out / p).read_bytes() for p in ("results.csv", "batch.json")}
    for scene_name, clash in (("results", "results.csv"), ("batch", "batch.json")):
        res = cli(["run", PID, "--set", f"name={scene_name}", "--set", "stop_time=0.05", "--out", out], cache)
        assert res.returncode == 2, res.stderr
        assert f"refusing to replace {out / clash}: it is not an rpr-cosim trace" in res.stderr
        assert "Traceback" not in res.stderr
    assert {p: (out / p).read_bytes() for p in before} == before
    again = cli(["batch", spec, "--out", out, "--workers", "1"], cache)  # the batch still resumes
    assert again.returncode == 0 and "0 ran, 2 were in the table already" in again.stdout, again.stdout


def test_runs_batches_and_studies_share_one_lock(tmp_path, cache):
    out = tmp_path / "out"
    out.mkdir()
    with outputs.OutputLock(out):  # as a running batch holds it
        assert (out / outputs.LOCK_NAME).is_file()
        proc = subprocess.run([sys.executable, "-c", "import sys; from cosim.outputs import OutputLock\n"
                               f"OutputLock({str(out)!r}).__enter__()"], cwd=ROOT, capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert f"output directory {out} is in use by another run (pid {os.getpid()}" in proc.stderr
        spec = tmp_path / "b.yaml"
        spec.write_text(BATCH)
        res = cli(["batch", spec, "--out", out, "--workers", "1"], cache)
        assert res.returncode == 2 and f"is in use by another run (pid {os.getpid()}" in res.stderr, res.stderr
    assert not list(out.glob("results.csv"))


def test_an_early_trace_write_refusal_leaves_no_part_file(tmp_path, cache, monkeypatch):
    real = os.write

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(trace_module.os, "write", full)
    with pytest.raises(UserError, match="cannot write the trace .*pid_step.csv: No space left on device"):
        run(PID, SHORT, out_dir=tmp_path / "out", cache_dir=cache)
    monkeypatch.setattr(trace_module.os, "write", real)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == []


def test_a_plot_is_moved_into_place_and_not_written_through_a_link(tmp_path, cache):
    out = tmp_path / "out"
    out.mkdir()
    v = victim(tmp_path)
    (out / ".pid_step.part.png").symlink_to(v)
    res = cli(["run", PID, "--set", "stop_time=0.05", "--plot", "--out", out], cache)
    assert res.returncode == 0, res.stderr
    assert v.read_text() == VICTIM
    assert (out / "pid_step.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in out.iterdir()) == ["pid_step.csv", "pid_step.json", "pid_step.png"]


def test_sigterm_during_the_animation_keeps_the_complete_gif_and_the_sidecar_says_so(tmp_path, cache):
    out = tmp_path / "out"
    res = cli(["run", PID, "--set", "stop_time=0.2", "--animate", "--out", out], cache)
    assert res.returncode == 0, res.stderr
    good = (out / "pid_step.gif").read_bytes()
    assert good[:6] == b"GIF89a"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "cosim", "run", str(PID), "--set", "stop_time=3", "--animate",
                             "--out", str(out), "--cache", str(cache)], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    part = out / ".pid_step.part.gif"
    deadline = time.monotonic() + 120
    while not part.exists():  # the run is done and the animation has begun
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "interrupted by SIGTERM (signal 15) while writing the animation pid_step.gif" in err
    # the earlier run's set, its complete animation with it, kept whole as pid_step.prev.* (issue 32)
    assert (out / "pid_step.prev.gif").read_bytes() == good and not (out / "pid_step.gif").exists()
    side = json.loads((out / "pid_step.json").read_text())
    assert side["status"] == "interrupted"
    assert side["reason"].startswith("interrupted by SIGTERM (signal 15) while writing the animation pid_step.gif "
                                     "(the run itself ended ok")
    assert read_trace(out / "pid_step.csv").status == "interrupted"
    assert not part.exists()
