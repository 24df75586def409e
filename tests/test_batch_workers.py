"""Local batch workers started both ways give the same rows and bit-identical traces: forked
from the warmed-up batch process (single-threaded) and from a forkserver (when the batch
process runs another thread); either way the workers leave no FMU folder behind."""
from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest

from cosim.batch import load_batch, run_batch
from cosim.batch.executors import LocalExecutor
from cosim.batch.overview import run_trace_path
from cosim.trace.traces import read_trace

ROOT = Path(__file__).resolve().parents[1]
BATCH = f"""\
name: starts
scene: {ROOT / "scenarios" / "pid_step.yaml"}
set: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 0.1}}
grid:
  Kp: {{path: "components.pid*.params.Kp", values: [20, 60]}}
  Kd: {{path: "components.pid*.params.Kd", values: [10, 30]}}
metrics:
  mech.platform.phi: {{target: 0.2, measure: [max, end_error]}}
"""
TIMING = {"init_s", "loop_s", "real_time_factor", "run_s", "wall_s", "worker"}


def _batch(tmp: Path, how: str):
    path = tmp / "b.yaml"
    path.write_text(BATCH)
    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)
    if how == "forkserver":  # another thread in the batch process: no plain fork
        other.start()
    try:
        res = run_batch(load_batch(path), out=tmp / how, executor=LocalExecutor(2))
    finally:
        stop.set()
    return res


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("starts")
    return tmp, {how: _batch(tmp, how) for how in ("fork", "forkserver")}


def test_both_starts_give_the_same_rows_and_traces(both):
    tmp, res = both
    rows = {how: {r["run_id"]: {k: v for k, v in r.items() if k not in TIMING} for r in out.rows}
            for how, out in res.items()}
    assert len(rows["fork"]) == 4 and rows["fork"] == rows["forkserver"]
    assert all(r["outcome"] == "ok" for r in rows["fork"].values())
    for rid in rows["fork"]:
        a, b = (read_trace(run_trace_path(tmp / how, rid)) for how in ("fork", "forkserver"))
        assert a.columns == b.columns and np.array_equal(a.data, b.data)  # bit for bit


@pytest.mark.parametrize("how", ["fork", "forkserver"])
def test_workers_leave_no_fmu_folders(both, how):
    _, res = both
    pids = {r["worker"].rsplit(":", 1)[1] for r in res[how].rows}
    assert len(pids) >= 1 and str(os.getpid()) not in pids
    tmp = Path(tempfile.gettempdir())
    left = [p for pid in pids for p in tmp.glob(f"rpr-batch-{pid}-*")] + [p for pid in pids for p in tmp.glob(f"rpr-fmu-{pid}-*")]
    left += list(tmp.glob(f"rpr-batch-{os.getpid()}-*"))  # what this process prepared for forked workers
    assert left == []
