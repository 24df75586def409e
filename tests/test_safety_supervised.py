"""Supervised runs (issue 20, item 1): whatever an FMU does (a NULL write, abort(), exit(0), a call
that never returns, SIGTERM ignored), ``rpr-cosim run`` and each batch run end with a final
status ("crashed", "hung" or "interrupted") naming the component and FMI call, whole rows kept,
the sidecar final and a non-zero exit code.  The FMU is compiled from C at test time
(:mod:`hostile_fmu`)."""
from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cosim.run.execute import run
from cosim.trace.traces import read_trace
from hostile_fmu import build_hostile_fmu, hostile_scene

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hostile")
    return hostile_scene(folder, build_hostile_fmu(folder))


def cli(args, env_extra, timeout=300):
    env = {**os.environ, "PYTHONPATH": str(ROOT), **env_extra}
    return subprocess.run([sys.executable, "-m", "cosim", *map(str, args)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)


def data_rows(path: Path) -> int:
    with open(path) as fh:
        lines = [ln for ln in fh if ln.strip() and not ln.startswith("#")]
    assert all(ln.endswith("\n") for ln in lines)
    return len(lines) - 1


def assert_settled(out: Path, status: str, reason: str) -> dict:
    side = json.loads((out / "hostile.json").read_text())
    assert side["status"] == status and reason in side["reason"], side["reason"]
    path = out / side["trace"]  # hostile.csv of a run, hostile.npy of a batch (its default)
    # the rows kept, counted independently: a CSV's lines, NumPy's reading of the .npy's header
    assert side["rows"] == (data_rows(path) if path.suffix == ".csv" else len(np.load(path)))
    trace = read_trace(path)
    assert trace.status == status and len(trace.data) == side["rows"]
    if len(trace.data):  # every kept row is a whole row of the right width, times on the 1 ms grid
        assert trace.data.shape[1] == 3
        assert abs(trace.time[-1] - (len(trace.data) - 1) * 1e-3) < 1e-12
    assert sorted(p.name for p in out.iterdir()) == sorted([path.name, "hostile.json"])  # no .part, no lock
    return side


@pytest.mark.parametrize("how, reason", [
    ("doStep@100:segv", "the run's process died of SIGSEGV (signal 11) in a.fmi2DoStep at t = 0.099 s"),
    ("doStep@30:abort", "the run's process died of SIGABRT (signal 6) in a.fmi2DoStep at t = 0.029 s"),
    ("instantiate:segv", "the run's process died of SIGSEGV (signal 11) in a.fmi2Instantiate"),
    ("enterInit:abort", "the run's process died of SIGABRT (signal 6) in a.fmi2EnterInitializationMode"),
    ("doStep@50:exit0", "the run's process exited (code 0) without finishing the run in a.fmi2DoStep at t = 0.049 s"),
])
def test_a_crashing_fmu_ends_the_run_crashed_with_the_call_and_whole_rows(tmp_path, hostile, how, reason):
    out = tmp_path / "out"
    res = cli(["run", hostile, "--out", out], {"RPR_HOSTILE": how})
    assert res.returncode == 1, res.stderr
    assert f"rpr-cosim run: crashed: {reason}" in res.stderr
    assert "Traceback" not in res.stderr
    assert_settled(out, "crashed", reason)


def test_a_crash_late_in_the_run_keeps_the_rows_written_before_it(tmp_path, hostile):
    out = tmp_path / "out"
    res = cli(["run", hostile, "--out", out, "--set", "stop_time=2"], {"RPR_HOSTILE": "doStep@1500:segv"})
    assert res.returncode == 1, res.stderr
    side = assert_settled(out, "crashed", "SIGSEGV (signal 11) in a.fmi2DoStep at t = 1.499 s")
    assert 0 < side["rows"] <= 1500
    # the kept rows are the run's: a.y follows y' = (1 - y) / tau (explicit Euler, h = 1 ms)
    trace = read_trace(out / "hostile.csv")
    k = len(trace.data) - 1
    assert trace["a.y"][-1] == pytest.approx(1 - (1 - 1e-3 / 0.1) ** k, rel=1e-9)


@pytest.mark.parametrize("how", ["doStep@100:hang", "doStep@100:sleep", "instantiate:hang_noterm"])
def test_a_call_that_never_returns_ends_the_run_hung_after_the_timeout(tmp_path, hostile, how):
    out = tmp_path / "out"
    t0 = time.monotonic()
    res = cli(["run", hostile, "--out", out, "--call-timeout", "1.5"], {"RPR_HOSTILE": how})
    assert time.monotonic() - t0 < 20
    assert res.returncode == 1, res.stderr
    call = "a.fmi2Instantiate" if how.startswith("instantiate") else "a.fmi2DoStep at t = 0.099 s"
    reason = f"{call} did not return within 1.5 s (the FMI call timeout, $RPR_COSIM_CALL_TIMEOUT)"
    assert f"rpr-cosim run: hung: {reason}" in res.stderr
    assert_settled(out, "hung", reason)


def test_the_call_timeout_comes_from_the_environment_and_is_checked(tmp_path, hostile):
    res = cli(["run", hostile, "--out", tmp_path / "o"], {"RPR_HOSTILE": "doStep@10:sleep", "RPR_COSIM_CALL_TIMEOUT": "1"})
    assert res.returncode == 1 and "did not return within 1 s" in res.stderr
    res = cli(["run", hostile, "--out", tmp_path / "p"], {"RPR_COSIM_CALL_TIMEOUT": "soon"})
    assert res.returncode == 2
    assert ("$RPR_COSIM_CALL_TIMEOUT: expected a positive number of seconds (the longest an FMI call may take), "
            "got 'soon'") in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("how", ["doStep@100:hang_noterm", "doStep@100:sleep"])
def test_sigterm_ends_a_run_within_a_second_even_when_the_fmu_never_returns(tmp_path, hostile, how):
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "RPR_HOSTILE": how}
    proc = subprocess.Popen([sys.executable, "-m", "cosim", "run", str(hostile), "--out", str(out)], cwd=ROOT,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    part = out / ".hostile.csv.part"
    deadline = time.monotonic() + 60
    while not (part.exists() and part.stat().st_size > 2000):  # the first rows are out: it is stuck in doStep 100
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() else "no rows"
        time.sleep(0.05)
    time.sleep(0.3)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    side = out / "hostile.json"
    while not (side.exists() and json.loads(side.read_text()).get("status") == "interrupted"):
        assert time.monotonic() - t0 < 30, "the run never ended"
        time.sleep(0.01)
    took = time.monotonic() - t0  # the run has ended, its status is written: the signal took effect
    _, err = proc.communicate(timeout=30)
    assert took < 1.0, (took, err)
    assert time.monotonic() - t0 < 10  # and the process is gone (the interpreter's own exit on a busy machine)
    assert proc.returncode == 128 + signal.SIGTERM, err
    # sleep() returns early on the forwarded signal, then the second copy sleeps in its doStep 100
    who = "a" if how.endswith("noterm") else "b"
    assert_settled(out, "interrupted", f"interrupted by SIGTERM (signal 15); the run did not end within 0.4 s of the "
                                       f"signal (in {who}.fmi2DoStep at t = 0.099 s) and was killed")


def test_an_in_process_caller_survives_the_crash_and_gets_the_status(tmp_path, hostile, monkeypatch):
    monkeypatch.setenv("RPR_HOSTILE", "doStep@200:segv")
    res = run(hostile, out_dir=tmp_path / "out")
    assert res.status == "crashed" and not res.ok
    assert res.reason == "the run's process died of SIGSEGV (signal 11) in a.fmi2DoStep at t = 0.199 s"
    assert len(res.trace.data) == json.loads((tmp_path / "out" / "hostile.json").read_text())["rows"]
    monkeypatch.delenv("RPR_HOSTILE")
    ok = run(hostile, out_dir=tmp_path / "out")  # the next run is not disturbed by the crashed one
    assert ok.ok and len(ok.trace.data) == 501


def test_a_batch_run_that_crashes_or_hangs_is_its_row_and_the_others_run(tmp_path, hostile):
    spec = tmp_path / "b.yaml"
    spec.write_text(f"name: hb\nscene: {hostile}\n"
                    f"grid:\n  tau: {{path: components.a.params.tau, values: [0.1, 0.2, 0.3, 0.4]}}\n"
                    f"metrics:\n  a.y: [max]\n")
    out = tmp_path / "bout"
    t0 = time.monotonic()
    res = cli(["batch", spec, "--out", out, "--workers", "2"],
              {"RPR_HOSTILE": "doStep@100:segv/0.2", "RPR_COSIM_CALL_TIMEOUT": "1"})
    assert res.returncode == 0, res.stderr
    # an external FMU is loaded anew for each run, so the worker runs it supervised in a child of
    # its own: the run's process dies, the worker lives on
    assert "crashed: " in res.stdout and "(tau=0.2): the run's process died of SIGSEGV (signal 11) in a.fmi2DoStep " \
                                           "at t = 0.099 s" in res.stdout
    with open(out / "results.csv") as fh:
        rows = {r["tau"]: r for r in csv.DictReader(ln for ln in fh if not ln.startswith("#"))}
    assert {t: r["outcome"] for t, r in rows.items()} == {"0.1": "ok", "0.2": "crashed", "0.3": "ok", "0.4": "ok"}
    # the ok rows' metric is the Euler solution's maximum, y(0.5 s) = 1 - (1 - h / tau)^500
    for tau in (0.1, 0.3, 0.4):
        assert float(rows[str(tau)]["a.y:max"]) == pytest.approx(1 - (1 - 1e-3 / tau) ** 500, rel=1e-9)
    crashed = out / "runs" / rows["0.2"]["run_id"]
    side = json.loads((crashed / "hostile.json").read_text())
    assert side["status"] == "crashed" and side["rows"] == len(np.load(crashed / "hostile.npy"))  # the batch default
    assert sorted(p.name for p in crashed.iterdir()) == ["hostile.json", "hostile.npy"]
    res = cli(["batch", spec, "--out", tmp_path / "hung", "--workers", "2"],
              {"RPR_HOSTILE": "doStep@100:hang_noterm/0.3", "RPR_COSIM_CALL_TIMEOUT": "1"})
    assert res.returncode == 0, res.stderr
    assert "hung: " in res.stdout and "(tau=0.3): a.fmi2DoStep at t = 0.099 s did not return within 1 s" in res.stdout
    assert time.monotonic() - t0 < 280


@pytest.mark.parametrize("how, status, reason", [
    ("doStep@100:segv/0.2", "crashed", "the run's process died of SIGSEGV (signal 11) in a.fmi2DoStep at t = 0.099 s"),
    ("doStep@50:exit0/0.2", "crashed",
     "the run's process exited (code 0) without finishing the run in a.fmi2DoStep at t = 0.049 s"),
    ("doStep@100:hang_noterm/0.2", "hung",
     "a.fmi2DoStep at t = 0.099 s did not return within 1 s (the FMI call timeout, $RPR_COSIM_CALL_TIMEOUT); "
     "the run was stopped"),
    # SIGKILL looks like the OOM killer: a second attempt in a new child, killed again
    ("doStep@100:sigkill/0.2", "crashed", "the run's process died of SIGKILL (signal 9) in a.fmi2DoStep at "
                                          "t = 0.099 s (and so did its second attempt, in a new process)"),
])
def test_a_dask_batch_run_that_crashes_or_hangs_is_its_row_and_the_workers_live_on(
        tmp_path, hostile, dask_scheduler, monkeypatch, how, status, reason):
    """On a Dask cluster each run is supervised on its worker: the run whose FMU crashes or hangs
    is its row with the call, its files settled, and the other runs (on the same worker processes,
    which survive) are ok."""
    distributed = pytest.importorskip("distributed")
    from cosim.batch import load_batch, run_batch
    from cosim.batch.executors import DaskExecutor
    from cosim.batch.results import read_rows
    from cosim.batch.worker import end_steppers

    spec = tmp_path / "b.yaml"
    spec.write_text(f"name: hd\nscene: {hostile}\n"
                    f"grid:\n  tau: {{path: components.a.params.tau, values: [0.1, 0.2, 0.3, 0.4]}}\n"
                    f"metrics:\n  a.y: [max]\n")
    monkeypatch.setenv("RPR_COSIM_CALL_TIMEOUT", "1")  # the batch process's timeout goes to the workers
    with distributed.Client(dask_scheduler) as client:
        before = client.run(os.getpid)
        client.run(os.putenv, "RPR_HOSTILE", how)  # the FMU reads it in the process stepping it,
        client.run(end_steppers)  # a child forked after this
        try:
            t0 = time.monotonic()
            res = run_batch(load_batch(spec), out=tmp_path / "out", executor=DaskExecutor(dask_scheduler))
            assert time.monotonic() - t0 < 60
        finally:
            client.run(os.unsetenv, "RPR_HOSTILE")
            client.run(end_steppers)
        assert client.run(os.getpid) == before  # no worker died (nor was restarted by its nanny)
    assert res.ran == 4 and res.failed == 1
    rows = {str(r["tau"]): r for r in read_rows(tmp_path / "out" / "results.csv")[1]}
    assert {t: r["outcome"] for t, r in rows.items()} == {"0.1": "ok", "0.2": status, "0.3": "ok", "0.4": "ok"}
    assert reason in rows["0.2"]["reason"] and rows["0.2"]["attempts"] == 1
    for tau in (0.1, 0.3, 0.4):  # the Euler solution's maximum, y(0.5 s) = 1 - (1 - h / tau)^500
        assert float(rows[str(tau)]["a.y:max"]) == pytest.approx(1 - (1 - 1e-3 / tau) ** 500, rel=1e-9)
    assert_settled(tmp_path / "out" / "runs" / rows["0.2"]["run_id"], status, reason)



def test_a_dask_worker_with_two_threads_supervises_each_threads_runs(tmp_path, hostile):
    """``dask worker --nthreads 2``: each of the worker's threads forks its own stepping child, so
    a run whose FMU crashes in one is its row while the other thread's runs go on, on the same
    worker process (the docs recommend one thread per worker; two must still be right)."""
    dask = pytest.importorskip("dask")
    distributed = pytest.importorskip("distributed")
    from cosim.batch import load_batch, run_batch
    from cosim.batch.executors import DaskExecutor
    from cosim.batch.results import read_rows
    from cosim.batch.worker import end_steppers

    spec = tmp_path / "b.yaml"
    spec.write_text(f"name: hd2\nscene: {hostile}\n"
                    f"grid:\n  tau: {{path: components.a.params.tau, values: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]}}\n"
                    f"metrics:\n  a.y: [max]\n")
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=True,
                                           host="127.0.0.1", dashboard_address="127.0.0.1:0")
    try:
        with distributed.Client(cluster.scheduler_address) as client:
            before = client.run(os.getpid)
            client.run(os.putenv, "RPR_HOSTILE", "doStep@100:segv/0.2")
            client.run(end_steppers)
            res = run_batch(load_batch(spec), out=tmp_path / "out", executor=DaskExecutor(cluster.scheduler_address))
            assert client.run(os.getpid) == before
    finally:
        cluster.close()
    assert res.ran == 6 and res.failed == 1
    rows = {str(r["tau"]): r for r in read_rows(tmp_path / "out" / "results.csv")[1]}
    assert {t for t, r in rows.items() if r["outcome"] != "ok"} == {"0.2"}
    assert "died of SIGSEGV (signal 11) in a.fmi2DoStep" in rows["0.2"]["reason"]
    for tau in (0.1, 0.3, 0.4, 0.5, 0.6):  # the Euler solution's maximum, y(0.5 s) = 1 - (1 - h / tau)^500
        assert float(rows[str(tau)]["a.y:max"]) == pytest.approx(1 - (1 - 1e-3 / tau) ** 500, rel=1e-9)

def _handle(request):
    """A stepping child's work for the Server test: echo, raise, or die."""
    if request == "segv":
        os.kill(os.getpid(), signal.SIGSEGV)
    if request == "raise":
        raise ValueError("no such run")
    return request * 2


def test_a_stepping_child_serves_requests_until_it_dies_and_says_how():
    from cosim.run.supervise import Failed, Server

    server = Server(_handle)
    pid = server.pid
    assert server.call(21) == 42 and server.call("ab") == "abab"
    with pytest.raises(ValueError, match="no such run"):
        server.call("raise")
    assert server.alive and server.call(b"x" * 3_000_000) == b"x" * 6_000_000  # larger than a pipe's buffer
    with pytest.raises(Failed) as failed:
        server.call("segv")
    assert failed.value.status == "crashed" and not server.alive
    assert failed.value.reason == "the run's process died of SIGSEGV (signal 11) before the first FMI call"
    assert failed.value.from_outside  # not inside an FMI call: a second attempt is worth it
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)  # reaped
    other = Server(_handle)
    assert other.call(1) == 2
    other.close()
    assert not other.alive


def test_a_result_written_just_before_the_child_exits_is_not_lost(monkeypatch):
    """The race of a loaded machine: the child writes its result and exits between the parent's
    poll of the pipe (nothing yet) and its check of the child's exit; the parent must still read
    the result (it once reported 'the run's process exited (code 0) without finishing the run')."""
    import select as select_module

    from cosim.run import supervise

    real = select_module.select
    calls = {"n": 0}

    def late_select(r, w, x, timeout=None):
        calls["n"] += 1
        if calls["n"] == 1 and timeout:  # the first poll: the child finishes meanwhile
            time.sleep(1.0)
            return [], [], []
        return real(r, w, x, timeout)

    monkeypatch.setattr(supervise.select, "select", late_select)
    assert supervise.supervised(lambda say: 41 + 1) == 42


def test_a_thread_starting_its_stepping_child_leaves_another_threads_dead_child_to_that_thread(monkeypatch):
    """Two stepping threads in one Dask worker: when thread A's child has just died (A has not yet
    read its end), thread B starting its own child must not reap A's and close A's pipes under it
    (A then read a closed descriptor: 'OSError: [Errno 9] Bad file descriptor' instead of the
    crash's reason)."""
    import threading
    import time as time_module

    from cosim.batch import worker

    monkeypatch.setattr(worker, "_SERVERS", [])
    monkeypatch.setattr(worker, "_LOCAL", worker._Local())
    monkeypatch.setattr(worker, "_serve_runs", lambda: _handle)
    monkeypatch.setattr(worker, "_start_stepping", lambda: None)
    first = worker._server()  # thread A's child
    os.kill(first.pid, signal.SIGKILL)
    time_module.sleep(0.2)  # dead, not yet reaped: A is about to read its end
    started = []
    thread = threading.Thread(target=lambda: started.append(worker._server()))
    thread.start()
    thread.join()
    assert started and started[0] is not first
    assert first.is_open, "thread B reaped thread A's child and closed its pipes"
    assert not first.alive  # A, checking its own child, finds it gone
    worker.end_steppers()
