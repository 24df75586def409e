"""Results that open everywhere: a trace written plain opens with ``pandas.read_csv(path)`` and no
options and equals its Parquet form and the run's own ``RunResult.trace.to_pandas()``; the
metadata is in the sidecar (CSV) or the Parquet schema; ``compare`` and batches read every format
they write; the commented CSV of earlier versions still reads back.

The scene is the thesis's PID step (eight FMUs) cut to 0.3 s."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from cosim.cli import main
from cosim.run.execute import run
from cosim.trace.traces import read_trace

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenarios" / "pid_step.yaml"
SHORT = ["stop_time=0.3", "master.algorithm=gauss_seidel", "master.tolerance=none"]  # a fixed step: 301 rows


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same run written in each format: {format: RunResult}."""
    base = tmp_path_factory.mktemp("formats")
    return {fmt: run(SCENE, SHORT, out_dir=base / fmt, trace_format=fmt)
            for fmt in ("csv", "parquet", "commented-csv", "npy")}


def test_a_plain_trace_opens_with_pandas_and_no_options_and_equals_the_parquet_form(runs):
    plain, parquet = runs["csv"].trace_path, runs["parquet"].trace_path
    assert plain.suffix == ".csv" and parquet.suffix == ".parquet"
    lines = plain.read_text().splitlines()
    assert lines[0].split(",")[:2] == ["time", "mech.platform.x"] and not any(ln.startswith("#") for ln in lines)
    df = pd.read_csv(plain)
    assert list(df.columns) == runs["csv"].trace.columns and len(df) == 301
    pdf = pd.read_parquet(parquet)
    pd.testing.assert_frame_equal(df, pdf, check_exact=True)
    # the run's own in-memory trace, as pandas users get it
    mem = runs["csv"].trace.to_pandas()
    assert mem.index.name == "time"
    np.testing.assert_array_equal(mem.index.to_numpy(), df["time"].to_numpy())
    np.testing.assert_array_equal(mem.to_numpy(), df.drop(columns="time").to_numpy())


def test_the_metadata_is_in_the_sidecar_and_the_parquet_schema(runs):
    res = runs["parquet"]
    kv = pq.ParquetFile(res.trace_path).metadata.metadata
    meta, outcome = json.loads(kv[b"rpr-cosim"]), json.loads(kv[b"rpr-cosim.outcome"])
    assert meta["scene_hash"] == res.scene.hash and meta["units"]["mech.platform.x"] == "m"
    assert outcome["status"] == "ok" and outcome["rows"] == 301 and outcome["statistics"]["steps_done"] == 300
    side = json.loads(runs["csv"].trace_path.with_suffix(".json").read_text())
    assert side["scene_hash"] == res.scene.hash and side["status"] == "ok" and side["rows"] == 301


def test_read_trace_gives_the_same_trace_from_every_format(runs):
    traces = {fmt: read_trace(r.trace_path) for fmt, r in runs.items()}
    first = traces["csv"]
    assert first.status == "ok" and first.stats["steps_done"] == 300
    assert first.meta["scene_hash"] == runs["csv"].scene.hash
    for fmt, tr in traces.items():
        assert tr.columns == first.columns, fmt
        np.testing.assert_array_equal(tr.data, runs[fmt].trace.data)
        np.testing.assert_array_equal(tr.data, first.data)
        assert (tr.status, tr.meta["units"]) == (first.status, first.meta["units"]), fmt
    assert runs["commented-csv"].trace_path.read_text().startswith("# rpr-cosim trace 1")


def test_an_npy_trace_is_what_numpy_reads_with_the_sidecars_columns_bit_for_bit(runs):
    res, plain = runs["npy"], runs["csv"]
    assert res.trace_path.suffix == ".npy"
    arr = np.load(res.trace_path)  # NumPy's own reader, not ours
    side = json.loads(res.trace_path.with_suffix(".json").read_text())
    assert arr.dtype == np.float64 and arr.shape == (301, len(side["columns"])) and side["rows"] == 301
    df = pd.DataFrame(arr, columns=side["columns"])
    pd.testing.assert_frame_equal(df, pd.read_csv(plain.trace_path), check_exact=True)
    assert arr.view(np.uint64).tobytes() == read_trace(plain.trace_path).data.view(np.uint64).tobytes()


def test_an_npy_trace_cut_by_a_dead_run_keeps_its_whole_rows(tmp_path):
    """A writer that never finished (its process died) with half a row at the end: reading
    settles it as killed, cut to whole rows with their count in the header."""
    from cosim.trace.traces import NpyTrace

    rows = np.arange(40, dtype=float).reshape(10, 4) / 7
    w = NpyTrace(tmp_path / "t.npy")
    w.start(["time", "a", "b", "c"], {})
    w.record(rows)
    with open(w.part, "ab") as fh:
        fh.write(b"\x01" * 12)  # a row cut short
    from cosim.outputs import settle_stale

    assert "10 whole rows kept" in settle_stale(tmp_path)[0]  # what a later run in this directory does
    tr = read_trace(tmp_path / "t.npy")
    assert tr.status == "killed" and tr.columns == ["time", "a", "b", "c"]
    np.testing.assert_array_equal(tr.data, rows)
    np.testing.assert_array_equal(np.load(tmp_path / "t.npy"), rows)


def test_compare_reads_every_format(runs, capsys):
    a, b, c, d = (str(runs[f].trace_path) for f in ("parquet", "csv", "commented-csv", "npy"))
    assert main(["compare", a, b, "--tol", "1e-12"]) == 0
    assert main(["compare", d, b, "--tol", "1e-12"]) == 0
    assert main(["compare", c, a, "--tol", "1e-12"]) == 0
    out = capsys.readouterr().out
    assert "mech.platform.phi" in out


def test_a_broken_parquet_file_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"PAR1 not really")
    other = tmp_path / "x.csv"
    other.write_text("time,a\n0,1\n1,2\n")
    assert main(["compare", str(bad), str(other)]) == 2
    assert "not a readable Parquet trace" in capsys.readouterr().err


def test_a_batch_in_parquet_writes_its_table_and_traces_in_parquet_and_reads_them(tmp_path):
    batch = tmp_path / "b.yaml"
    batch.write_text(f"name: b\nscene: {SCENE}\nset: {{master.algorithm: gauss_seidel, master.tolerance: none, stop_time: 0.2}}\n"
                     "grid:\n  Kp: {path: \"components.pid*.params.Kp\", values: [20, 40]}\n"
                     "metrics:\n  mech.platform.phi: [max]\n")
    out = tmp_path / "out"
    assert main(["batch", str(batch), "--workers", "1", "--out", str(out), "--format", "parquet",
                 "--no-plots"]) == 0
    csv_rows, pq_rows = pd.read_csv(out / "results.csv"), pd.read_parquet(out / "results.parquet")
    assert list(csv_rows.columns) == list(pq_rows.columns) and len(pq_rows) == 2
    np.testing.assert_array_equal(csv_rows["mech.platform.phi:max"], pq_rows["mech.platform.phi:max"])
    meta = json.loads(pq.ParquetFile(out / "results.parquet").metadata.metadata[b"rpr-cosim"])
    assert meta["batch"] == "b" and meta["axes"][0]["values"] == [20, 40]
    for run_id in pq_rows["run_id"]:
        trace = out / "runs" / run_id / "pid_step.parquet"
        tr = read_trace(trace)
        assert tr.status == "ok" and tr["mech.platform.phi"].max() == pytest.approx(
            float(pq_rows.set_index("run_id").loc[run_id, "mech.platform.phi:max"]), rel=0, abs=0)
    # compare OUT/ REF reads the batch's Parquet traces
    ref = out / "runs" / pq_rows["run_id"][0] / "pid_step.parquet"
    assert main(["compare", str(out), str(ref)]) in (0, 1)
