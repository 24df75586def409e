"""Batches executed: local processes and a Dask LocalCluster give identical rows and
bit-identical traces; an interrupted batch (SIGINT, SIGKILL) resumes with only the missing runs;
a run whose FMU fails is a row with the FMU's message; a worker killed mid-run is replaced and
the run completes; reusing FMU instances (FMI reset) changes no bit of a trace.

The scene is the thesis's PID step (eight FMUs) cut to fractions of a second."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cosim.batch import load_batch, run_batch
from cosim.batch.executors import DaskExecutor, LocalExecutor
from cosim.batch.results import read_rows
from cosim.batch.overview import run_trace_path
from cosim.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenarios" / "pid_step.yaml"
TIMING = {"init_s", "loop_s", "real_time_factor", "run_s", "wall_s", "worker"}

GRID24 = f"""\
name: grid24
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 0.2}}
grid:
  Kp: {{path: "components.pid*.params.Kp", values: [20, 30, 40, 50]}}
  Kd: {{path: "components.pid*.params.Kd", values: [10, 20, 30]}}
  Ki: {{path: "components.pid*.params.Ki", values: [80, 100]}}  # (held inputs at 1 ms are judged unstable)
metrics:
  mech.platform.phi: {{target: 0.2, measure: [max, overshoot, end_error, rms, {{at: [0.1]}}]}}
  mech.platform.x: [min]
"""


def write(tmp_path: Path, text: str, name: str = "b.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def data_lines(path: Path) -> list:
    """The rows of a trace: a CSV's lines (its comment lines carry times and dates), an ``.npy``
    trace's bytes after its header (numpy.load reads its header independently)."""
    if path.suffix == ".npy":
        return [np.load(path).tobytes()]
    return [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]


def stable(rows: list[dict]) -> dict[str, dict]:
    return {r["run_id"]: {k: v for k, v in r.items() if k not in TIMING} for r in rows}


@pytest.fixture(scope="module")
def local_grid(tmp_path_factory):
    """The 24-run grid on two local worker processes: (batch file, output directory, outcome)."""
    tmp = tmp_path_factory.mktemp("grid")
    path = write(tmp, GRID24)
    res = run_batch(load_batch(path), out=tmp / "local", executor=LocalExecutor(2))
    return path, tmp / "local", res


def test_grid_on_local_processes_and_dask_agree(local_grid, tmp_path, dask_scheduler):
    path, out, local = local_grid
    remote = run_batch(load_batch(path), out=tmp_path / "dask", executor=DaskExecutor(dask_scheduler))
    assert local.ran == remote.ran == 24 and local.failed == remote.failed == 0
    a, b = stable(read_rows(out / "results.csv")[1]), stable(read_rows(tmp_path / "dask" / "results.csv")[1])
    assert len(a) == 24 and a == b
    assert {r["Kp"] for r in a.values()} == {20, 30, 40, 50} and all(r["steps"] == 200 for r in a.values())
    for rid in a:
        ta, tb = run_trace_path(out, rid), run_trace_path(tmp_path / "dask", rid)
        assert ta.name == tb.name == "pid_step.npy"  # the batch default
        assert data_lines(ta) == data_lines(tb)
        assert (ta.parent / "pid_step.json").is_file() and (tb.parent / "pid_step.json").is_file()


def test_rerunning_a_finished_batch_runs_nothing_and_prints_the_sorted_table(local_grid, capsys):
    path, out, _ = local_grid
    assert main(["batch", str(path), "--out", str(out), "--sort", "mech.platform.phi:overshoot", "--most", "30"]) == 0
    text = capsys.readouterr().out
    assert "24 runs (24 ok, 0 not ok); this time 0 ran, 24 were in the table already" in text
    lines = text.split("sorted by mech.platform.phi:overshoot:\n")[1].splitlines()
    col = [h.endswith("overshoot") for h in lines[0].split()].index(True)
    values = [float(ln.split()[col]) for ln in lines[1:25]]
    expected = sorted(r["mech.platform.phi:overshoot"] for r in read_rows(out / "results.csv")[1])
    assert values == pytest.approx(expected, rel=1e-3)
    for name in ("heatmap_mech.platform.phi_max.png", "lines_mech.platform.phi_max_vs_Kp.png",
                 "traces_mech.platform.phi.png"):
        assert (out / "plots" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_compare_every_run_against_one_reference(local_grid, capsys):
    """One run's own trace as the reference: that run differs by exactly 0, every other by more."""
    _, out, res = local_grid
    ref_id = res.rows[0]["run_id"]
    assert main(["compare", str(out), str(run_trace_path(out, ref_id)), "--only", "mech.platform.*"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("24 runs of") and len(lines) == 2 + 24
    rel = {ln.split()[0]: float(ln.split()[-1]) for ln in lines[2:]}
    assert rel[ref_id] == 0.0 and all(v > 0 for k, v in rel.items() if k != ref_id)
    assert main(["compare", str(out), str(run_trace_path(out, ref_id)), "--tol", "1e-3"]) == 1


def test_reusing_instances_changes_no_bit(tmp_path):
    text = GRID24.replace("values: [20, 30, 40, 50]", "values: [20, 40]").replace("values: [10, 20, 30]", "values: [10]")
    batch = load_batch(write(tmp_path, text))
    kept = run_batch(batch, out=tmp_path / "reuse", executor=LocalExecutor(1), reuse=True)
    fresh = run_batch(batch, out=tmp_path / "reload", executor=LocalExecutor(1), reuse=False)
    assert kept.ran == fresh.ran == 4
    assert stable(kept.rows) == stable(fresh.rows)
    for rid in stable(kept.rows):
        assert data_lines(run_trace_path(tmp_path / "reuse", rid)) == data_lines(run_trace_path(tmp_path / "reload", rid))


def test_a_failing_fmu_is_a_failed_row_and_the_others_finish(tmp_path):
    """With the PIDs on RK4 (their default, the exact kernel, is stable at any step), at a 10 ms
    step RK4 diverges on the 1 ms derivative filter at t = 1.24 s and the FMU discards (guards off:
    batches are guarded, and the rated guard would stop the diverging PID's voltage first)."""
    text = f"""\
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 1.5, components.pid1.options.integrator: rk4, components.pid2.options.integrator: rk4,
      components.pid3.options.integrator: rk4, guards: "off"}}
zip:
  master.step: [1.0e-3, 1.0e-2, 2.0e-3]
  master.output_interval: [1.0e-3, 1.0e-2, 2.0e-3]
metrics:
  mech.platform.phi: [max]
"""
    res = run_batch(load_batch(write(tmp_path, text)), out=tmp_path / "out", executor=LocalExecutor(2))
    by_step = {r["master.step"]: r for r in res.rows}
    assert res.ran == 3 and res.failed == 2  # the discarded run, and the one judged unstable (below)
    bad = by_step[1e-2]
    assert bad["outcome"] == "failed" and bad["mech.platform.phi:max"] is None
    assert "pid1 returned DISCARD" in bad["reason"] and "the state became non-finite" in bad["reason"]
    assert bad["steps"] == 124  # t = 1.24 s
    partial = np.load(run_trace_path(tmp_path / "out", bad["run_id"]))
    assert len(partial) == 125 and partial[-1, 0] == pytest.approx(1.24)  # t = 0 .. 1.24 s
    assert by_step[1e-3]["outcome"] == "ok" and by_step[1e-3]["steps"] == 1500
    # at 2 ms (twice the derivative filter's 1 ms) RK4 is stable but far off: the run's own error
    # estimate ends it "unstable" after its whole span (against the monolithic reference its
    # platform y is 2.7 of its range off, measured)
    assert by_step[2e-3]["outcome"] == "unstable" and by_step[2e-3]["steps"] == 750
    assert by_step[2e-3]["reason"].startswith("the estimated error of ")


def _tf_samples(first_bad: bool) -> tuple[str, list[float]]:
    """A batch of 4 random derivative-filter constants Tf ~ N(1 ms, 2 ms) (a third fall below the
    parameter's lower bound 1e-9 s) whose seed makes sample 0 invalid or valid, as asked, and at
    least one other sample valid and one invalid; its text and the samples."""
    from cosim.batch.axes import draw

    for seed in range(1, 200):
        text = f"""\
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 0.05}}
random:
  seed: {seed}
  samples: 4
  axes:
    Tf: {{path: components.pid1.params.Tf, dist: normal, mean: 1.0e-3, std: 2.0e-3}}
"""
        ax = load_batch_text(text).random[0]
        tf = [draw(ax, seed, j) for j in range(4)]
        bad = [t < 1e-9 for t in tf]
        if bad[0] == first_bad and any(bad[1:]) and not all(bad[1:]):
            return text, tf
    raise AssertionError("no seed gives the wanted samples")


def load_batch_text(text: str):
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        return load_batch(write(Path(d), text))


def test_a_run_whose_scene_is_invalid_is_a_failed_row_and_the_others_run(tmp_path):
    """Runs are checked as they are handed out: a random sample outside a parameter's bounds is
    a failed row naming the bound; the batch goes on, and a rerun skips it like any finished row."""
    text, tf = _tf_samples(first_bad=False)
    path = write(tmp_path, text)
    res = run_batch(load_batch(path), out=tmp_path / "out", executor=LocalExecutor(1))
    assert res.ran == 4 and len(res.rows) == 4 and res.failed == sum(t < 1e-9 for t in tf)
    for row in res.rows:
        if row["Tf"] < 1e-9:
            assert row["outcome"] == "failed" and row["reason"].startswith(f"invalid scene: run {row['index']} (Tf=")
            assert "parameter Tf" in row["reason"] and "outside [1e-09, inf]" in row["reason"]
            assert not (tmp_path / "out" / "runs" / row["run_id"]).exists()
        else:
            assert row["outcome"] == "ok", row["reason"]
    again = run_batch(load_batch(path), out=tmp_path / "out", executor=LocalExecutor(1))
    assert (again.ran, again.skipped, len(again.rows)) == (0, 4, 4)


def test_an_invalid_first_run_stops_the_batch_before_anything_is_written(tmp_path, capsys):
    text, _ = _tf_samples(first_bad=True)
    out = tmp_path / "out"
    assert main(["batch", str(write(tmp_path, text)), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "b.yaml:1: error: run 0 (Tf=" in err[0] and "outside [1e-09, inf]" in err[0]
    assert "nothing was run" in err[-1] and not out.exists()


def test_a_run_needing_another_fmu_gets_it_with_its_task(tmp_path):
    """The second run's PID is built with RK4 instead of the exact kernel: a different FMU, first
    needed after the workers started, sent with that run; its trace equals a plain run's."""
    from cosim.run.execute import run

    text = f"""\
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 0.05}}
grid:
  kernel: {{path: components.pid1.options.integrator, values: [exact, rk4]}}
"""
    sent = {}
    res = run_batch(load_batch(write(tmp_path, text)), out=tmp_path / "out", executor=LocalExecutor(1),
                    on_start=lambda task, pid: sent.update({task.index: task.blobs}))
    assert res.ran == 2 and res.failed == 0
    assert sent[0] is None and len(sent[1]) == 1  # the workers start with run 0's FMUs; run 1 brings its PID
    by_kernel = {r["kernel"]: r for r in res.rows}
    plain = run(SCENE, ["stop_time=0.05", "components.pid1.options.integrator=rk4", "master.algorithm=gauss_seidel",
                         "master.tolerance=none"],
                out_dir=tmp_path / "plain")
    from cosim.trace.traces import read_trace

    rk4 = read_trace(run_trace_path(tmp_path / "out", by_kernel["rk4"]["run_id"])).data.tobytes()
    exact = read_trace(run_trace_path(tmp_path / "out", by_kernel["exact"]["run_id"])).data.tobytes()
    assert rk4 == read_trace(plain.trace_path).data.tobytes() and rk4 != exact  # .npy against the plain run's CSV


def test_a_worker_killed_mid_run_is_replaced_and_the_run_completes(tmp_path):
    text = f"""\
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, master.tolerance: none}}
zip:
  stop_time: [0.2, 0.3, 3.0, 0.4, 0.5]
metrics:
  mech.platform.phi: [max]
"""
    killed = []

    def kill_long_run(task, pid):
        if task.index == 2 and task.attempt == 1:
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    ex = LocalExecutor(2)
    res = run_batch(load_batch(write(tmp_path, text)), out=tmp_path / "out", executor=ex, on_start=kill_long_run)
    assert len(killed) == 1 and ex.replaced >= 1
    rows = {r["index"]: r for r in res.rows}
    assert len(rows) == 5 and all(r["outcome"] == "ok" for r in rows.values())
    assert rows[2]["attempts"] == 2 and rows[2]["steps"] == 3000
    assert rows[2]["worker"].split(":")[1] != str(killed[0])
    assert all(rows[i]["attempts"] == 1 for i in (0, 1, 3, 4))


RESUME = f"""\
name: resume
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 1.0}}
grid:
  Kp: {{path: "components.pid*.params.Kp", values: [20, 25, 30, 35, 40, 45]}}
  Kd: {{path: "components.pid*.params.Kd", values: [10, 15, 20, 25]}}
metrics:
  mech.platform.phi: {{target: 0.2, measure: [overshoot]}}
"""


def _rows_in(path: Path) -> int:
    try:
        return max(0, path.read_text().count("\n") - 1)
    except FileNotFoundError:
        return 0


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_an_interrupted_batch_resumes_with_only_the_missing_runs(tmp_path, sig):
    path, out = write(tmp_path, RESUME), tmp_path / "out"
    table = out / "results.csv"
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    # as typed at a terminal: Ctrl-C interrupts (a shell starts background jobs with SIGINT ignored, and a child
    # keeps that, so the handler is set explicitly)
    cli = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "from cosim.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.Popen([sys.executable, "-c", cli, "batch", str(path), "--out", str(out), "--workers", "1",
                             "--no-plots"], cwd=tmp_path, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while _rows_in(table) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    seen = _rows_in(table)
    status = Path(f"/proc/{proc.pid}/status").read_text() if proc.poll() is None else "exited"
    os.killpg(proc.pid, sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == (130 if sig == signal.SIGINT else -signal.SIGKILL), (seen, status, err)
    if sig == signal.SIGINT:
        assert "interrupted; the finished runs are in" in err
    for _ in range(100):  # the workers die with the batch: nothing keeps writing into its runs
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        pytest.fail("worker processes outlived the interrupted batch")
    before = table.read_bytes()
    n1 = _rows_in(table)
    assert 3 <= n1 < 24
    res = run_batch(load_batch(path), out=out, executor=LocalExecutor(2))
    assert (res.skipped, res.ran, res.failed) == (n1, 24 - n1, 0)
    assert table.read_bytes().startswith(before)
    header, rows = read_rows(table)
    assert len(rows) == len({r["run_id"] for r in rows}) == 24


def test_random_samples_do_not_depend_on_the_number_of_workers(tmp_path):
    text = f"""\
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 0.1}}
random:
  seed: 11
  samples: 4
  axes:
    m_p: {{path: components.mech.params.m_p, dist: normal, mean: 1.7, std: 0.17}}
    b: {{path: "components.motor*.params.b", dist: log_uniform, low: 4.0e-5, high: 2.0e-4}}
metrics:
  mech.platform.phi: [max]
"""
    batch = load_batch(write(tmp_path, text))
    one = run_batch(batch, out=tmp_path / "one", executor=LocalExecutor(1))
    two = run_batch(batch, out=tmp_path / "two", executor=LocalExecutor(2))
    a = {r["index"]: (r["run_id"], r["m_p"], r["b"], r["mech.platform.phi:max"]) for r in one.rows}
    b = {r["index"]: (r["run_id"], r["m_p"], r["b"], r["mech.platform.phi:max"]) for r in two.rows}
    assert a == b and len(a) == 4 and len({v[1] for v in a.values()}) == 4


def test_a_batchs_npy_traces_read_back_bit_for_bit_equal_to_its_csv_traces(tmp_path):
    """The default (``.npy``) and ``--format csv`` batches of the same grid: every run's trace read
    back the same to the bit (the CSV's shortest round-trip text against float64 bytes), the
    ``.npy`` also as NumPy itself reads it with the column names of the sidecar (the documented
    pandas recipe), and the same results table."""
    import json

    import pandas as pd

    from cosim.trace.traces import read_trace

    text = GRID24.replace("values: [20, 30, 40, 50]", "values: [20, 40]").replace("values: [10, 20, 30]", "values: [10]")
    path = write(tmp_path, text)
    assert main(["batch", str(path), "--workers", "1", "--out", str(tmp_path / "npy"), "--no-plots"]) == 0
    assert main(["batch", str(path), "--workers", "1", "--out", str(tmp_path / "csv"), "--no-plots",
                 "--format", "csv"]) == 0
    a, b = stable(read_rows(tmp_path / "npy" / "results.csv")[1]), stable(read_rows(tmp_path / "csv" / "results.csv")[1])
    assert len(a) == 4 and a == b
    for rid in a:
        pn, pc = run_trace_path(tmp_path / "npy", rid), run_trace_path(tmp_path / "csv", rid)
        assert (pn.name, pc.name) == ("pid_step.npy", "pid_step.csv")
        tn, tc = read_trace(pn), read_trace(pc)
        assert tn.columns == tc.columns and tn.data.shape == tc.data.shape == (201, len(tc.columns))
        assert tn.data.view(np.uint64).tobytes() == tc.data.view(np.uint64).tobytes()
        assert (tn.status, tn.stats["steps_done"], tn.meta["units"]) == (tc.status, tc.stats["steps_done"], tc.meta["units"])
        columns = json.loads(pn.with_suffix(".json").read_text())["columns"]
        df = pd.DataFrame(np.load(pn), columns=columns)
        pd.testing.assert_frame_equal(df, pd.read_csv(pc), check_exact=True)
    # compare OUT/ REF reads the batch's .npy traces against a CSV one
    ref = run_trace_path(tmp_path / "csv", next(iter(a)))
    assert main(["compare", str(tmp_path / "npy"), str(ref), "--only", "mech.platform.*"]) == 0



def _listening() -> set[tuple[str, int]]:
    """The (IP address, port) pairs this process listens on (TCP)."""
    import psutil

    return {(c.laddr.ip, c.laddr.port) for c in psutil.Process().net_connections("tcp") if c.status == "LISTEN"}


def test_the_local_dask_cluster_listens_on_loopback_only():
    """A Dask scheduler runs what it is sent: the cluster a batch starts for itself (no
    --scheduler) must not listen beyond this machine, nor take the dashboard's fixed port 8787
    (it used to listen on every interface, scheduler and dashboard alike)."""
    pytest.importorskip("distributed")
    pytest.importorskip("psutil")
    from cosim.batch.executors import DaskExecutor

    before = _listening()
    client, cluster = DaskExecutor(workers=1)._client()
    try:
        new = _listening() - before
        workers = client.run(_listening)
        assert new and {ip for ip, _ in new} == {"127.0.0.1"}, new
        assert {ip for pairs in workers.values() for ip, _ in pairs} == {"127.0.0.1"}, workers
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:") and 8787 not in {p for _, p in new}
    finally:
        client.close()
        cluster.close()
