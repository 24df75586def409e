"""Honest end states of a real ``rpr-cosim run`` process (issue #7, finding 3): SIGTERM, SIGINT
and SIGHUP end it with the status and reason in the sidecar, whole CSV rows and no temporary FMU
folders left; after SIGKILL the sidecar says "running" only until the next command finds the
stale lock and marks the run "killed"."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from cosim.run.execute import run
from cosim.trace.traces import read_trace
from test_robustness_outputs import PID, SHORT, whole_rows

ROOT = Path(__file__).resolve().parents[1]
#: a run of minutes if nobody stops it; rows every 10 ms of simulated time keep the trace small
LONG = ["--set", "stop_time=3000", "--set", "master.output_interval=0.01"]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    path = tmp_path_factory.getbasetemp() / "fmu-cache"
    run(PID, SHORT, cache_dir=path)
    return path


def start_long_run(out: Path, cache: Path) -> subprocess.Popen:
    """A long run in its own process, returned once it is streaming rows."""
    proc = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "cosim", "run", str(PID), *LONG, "--out", str(out),
                             "--cache", str(cache)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    part = out / ".pid_step.csv.part"
    deadline = time.monotonic() + 120
    while not (part.exists() and part.stat().st_size > 20_000):
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "the run did not start streaming"
        time.sleep(0.05)
    return proc


def unzip_dirs(pid: int) -> list[Path]:
    return list(Path(tempfile.gettempdir()).glob(f"rpr-fmu-{pid}-*"))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP], ids=lambda s: s.name)
def test_a_signal_ends_the_run_with_status_reason_and_whole_rows(tmp_path, cache, sig):
    out = tmp_path / "out"
    proc = start_long_run(out, cache)
    assert unzip_dirs(proc.pid)
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:  # show where it hangs (faulthandler dumps every thread)
        proc.send_signal(signal.SIGABRT)
        raise AssertionError(f"{sig.name} did not end the run:\n{proc.communicate()[1][-5000:]}") from None
    assert proc.returncode == 128 + sig, err
    assert f"interrupted by {sig.name} (signal {int(sig)})" in err
    side = json.loads((out / "pid_step.json").read_text())
    assert side["status"] == "interrupted" and side["reason"].startswith(f"interrupted by {sig.name}")
    rows = whole_rows(out / "pid_step.csv")
    assert side["rows"] == rows > 10
    assert read_trace(out / "pid_step.csv").status == "interrupted"
    assert sorted(p.name for p in out.iterdir()) == ["pid_step.csv", "pid_step.json"]  # no lock, no .part
    assert not unzip_dirs(proc.pid)  # temporary FMU folders removed at exit


def test_after_sigkill_the_next_command_marks_the_run_killed_and_keeps_the_good_trace(tmp_path, cache):
    out = tmp_path / "out"
    good = run(PID, ["stop_time=0.2"], out_dir=out, cache_dir=cache)
    proc = start_long_run(out, cache)
    proc.kill()
    proc.communicate(timeout=60)
    part_side = out / ".pid_step.json.part"
    assert json.loads(part_side.read_text())["status"] == "running"  # nobody could write anything
    assert read_trace(out / "pid_step.csv").status == "killed"  # reading the trace settles the dead run
    side = json.loads((out / "pid_step.json").read_text())
    assert side["status"] == "killed" and f"pid {proc.pid}" in side["reason"]
    rows = whole_rows(out / "pid_step.csv")
    assert side["rows"] == rows > 10
    prev = read_trace(out / "pid_step.prev.csv")
    assert prev.status == "ok" and len(prev.data) == len(good.trace.data)
    assert sorted(p.name for p in out.iterdir()) == ["pid_step.csv", "pid_step.json", "pid_step.prev.csv",
                                                     "pid_step.prev.json"]
    # the killed process's FMU folders go with the next command that unpacks FMUs
    assert unzip_dirs(proc.pid)
    subprocess.run([sys.executable, "-m", "cosim", "run", str(PID), "--set", SHORT[0], "--out", str(tmp_path / "next"),
                    "--cache", str(cache)], cwd=ROOT, capture_output=True, check=True, timeout=120)
    assert not unzip_dirs(proc.pid)


def test_after_sigkill_a_new_run_into_the_directory_settles_it_first(tmp_path, cache):
    out = tmp_path / "out"
    proc = start_long_run(out, cache)
    proc.kill()
    proc.communicate(timeout=60)
    notes: list[str] = []
    res = run(PID, SHORT, out_dir=out, cache_dir=cache, log=notes.append)
    assert res.ok
    assert any('an earlier run was killed; marked "killed"' in n for n in notes), notes
    assert any("replaced the earlier trace pid_step.csv (its status was killed)" in n for n in notes), notes
    assert json.loads((out / "pid_step.json").read_text())["status"] == "ok"
