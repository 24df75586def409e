"""``rpr-cosim study precision`` with variable-step algorithms, the ecospy peer and the batch runner
(issue 10, item 4): each number checked against a computation that does not go through the study."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from cosim.analysis.trace_diff import compare
from cosim.run.reference import reference
from cosim.run.execute import run
from cosim.study.precision import precision_study
from cosim.trace.traces import read_trace

SCENES = Path(__file__).resolve().parents[1] / "scenarios"
TWO_MASS = SCENES / "two_mass.yaml"
PID_STEP = SCENES / "pid_step.yaml"
RTOLS = [1e-2, 1e-3, 1e-4, 1e-5]
STOP = 1.0


@pytest.fixture(scope="module")
def two_mass_study(tmp_path_factory, cache):
    """two_mass over 1 s: Gauss-Seidel (linear) at 4 and 2 ms, adaptive over four decades of rtol,
    ecco (refused: no power bond)."""
    out = tmp_path_factory.mktemp("precision")
    return precision_study(TWO_MASS, [("gauss_seidel", "linear"), ("adaptive", "linear"), ("ecco", "linear")],
                           [4e-3, 2e-3], rtols=RTOLS, stop_time=STOP, out=out, cache_dir=cache, peer=False)


def _rows(study, alg):
    return [r for r in study.rows if r.algorithm == alg]


def test_adaptive_error_falls_as_its_tolerance_tightens(two_mass_study):
    """Over four decades of rtol the worst error against the monolithic reference falls at every
    decade (measured 9.5e-4, 2.0e-4, 4.2e-5, 8.8e-6), and the tightest run is within 2e-5 of each
    signal's range; each accepted or rejected step is one doStep of each of the two slaves."""
    rows = _rows(two_mass_study, "adaptive")
    assert [r.tolerance for r in rows] == RTOLS
    assert all(r.status == "ok" for r in rows), [r.reason for r in rows]
    worst = [r.worst for r in rows]
    assert all(a > b for a, b in zip(worst, worst[1:])), worst
    assert worst[-1] < 2e-5
    assert all(r.accepted > 0 and r.do_steps == 2 * (r.accepted + r.rejected) for r in rows)
    assert rows[-1].accepted > rows[0].accepted


def test_adaptive_error_equals_interpolating_a_fine_reference(two_mass_study, cache):
    """The adaptive run's trace (from the batch's run directory; its variable steps land on the
    output grid) against the monolithic reference every 10 us, interpolated by hand at the run's
    own instants, relative to the ranges of the
    reference on the study's recording grid: the study's per-signal errors to 1e-3 of themselves
    (two CVODES solutions at rtol 1e-10 on different output grids differ by ~1e-9, the errors are
    ~1e-5 of ranges ~1; the fine reference's interpolation error is ~1e-10)."""
    row = _rows(two_mass_study, "adaptive")[1]
    trace = read_trace(two_mass_study.out / "runs" / row.run_id / "two_mass.npy")
    assert np.allclose(np.diff(trace.time), two_mass_study.record, rtol=0, atol=1e-12)  # the output grid
    fine = reference(TWO_MASS, {"stop_time": STOP, "master.step": 1e-5, "master.output_interval": 1e-5}).trace
    grid = reference(TWO_MASS, {"stop_time": STOP, "master.step": two_mass_study.record,
                                "master.output_interval": two_mass_study.record}).trace
    for name in grid.names:
        hand = np.max(np.abs(trace[name] - np.interp(trace.time, fine.time, fine[name]))) / np.ptp(grid[name])
        assert row.errors[name] == pytest.approx(hand, rel=1e-3), name


def test_fixed_step_rows_equal_a_run_outside_the_batch(two_mass_study, cache):
    """A fixed-step row through the batch (trace written, read back) gives the numbers of the same
    run done in this process and compared with the reference directly, to the last bit."""
    row = _rows(two_mass_study, "gauss_seidel")[1]
    sets = {"stop_time": STOP, "master.algorithm": "gauss_seidel", "master.inputs": "linear", "master.step": 2e-3,
            "master.output_interval": two_mass_study.record}
    res = run(TWO_MASS, sets, cache_dir=cache)
    ref = reference(TWO_MASS, {**sets, "master.step": two_mass_study.record}).trace
    direct = {d.name: d.relative for d in compare(res.trace, ref)}
    assert row.errors == direct
    assert row.do_steps == 2 * round(STOP / 2e-3)


def test_a_variant_the_scene_refuses_is_a_row_with_its_reason(two_mass_study):
    rows = _rows(two_mass_study, "ecco")
    assert len(rows) == len(RTOLS)
    assert all(r.status == "failed" and "power bond" in r.reason and not r.errors for r in rows)


def test_the_table_has_a_tolerance_column(two_mass_study, tmp_path):
    two_mass_study.write_csv(tmp_path / "t.csv")
    import csv

    rows = list(csv.DictReader(open(tmp_path / "t.csv")))
    assert [r["tolerance"] for r in rows if r["algorithm"] == "adaptive"] == [repr(t) for t in RTOLS]
    assert all(r["tolerance"] == "" for r in rows if r["algorithm"] == "gauss_seidel")
    assert {"rejected_steps", "rollbacks", "accepted_steps"} <= set(rows[0])


def test_pid_step_ecospy_point_is_our_jacobi_hold(cache, tmp_path):
    """The ecospy point (its own C++ master on our FMUs) has, on the outputs it can reproduce
    (no direct feedthrough), exactly the errors of our jacobi/hold run at the same step."""
    try:
        import ecospy  # noqa: F401
    except (ImportError, OSError) as exc:
        pytest.skip(f"ecospy (PyPI, with Debian libtbb12) is needed for the peer point: {exc}")
    st = precision_study(PID_STEP, [("jacobi", "hold")], [1e-3], stop_time=0.05, out=tmp_path, cache_dir=cache,
                         peer=True)
    ours, peer = st.rows
    assert peer.algorithm == "ecospy" and peer.status == "inaccurate", peer.reason  # held at 1 ms: 0.4 of range off
    assert len(peer.errors) >= 10 and "motor1.i" in peer.errors and "pid1.y" not in peer.errors  # PID: feedthrough
    assert peer.errors == {n: ours.errors[n] for n in peer.errors}
    assert peer.do_steps == ours.do_steps


def test_cli_study_resumes_in_its_output_directory(tmp_path, capsys):
    argv = ["study", "precision", str(TWO_MASS), "--steps", "4e-3", "--rtols", "1e-2,1e-3", "--variant",
            "adaptive", "--variant", "jacobi/linear", "--stop", "0.5", "--no-peer", "--out", str(tmp_path)]
    assert main(argv) == 0
    first = capsys.readouterr()
    assert "adaptive/linear" in first.out and "rtol 1e-02" in first.out and "slope of error over rtol" in first.out
    assert len((tmp_path / "two_mass_precision.csv").read_text().splitlines()) == 4
    traces = sorted((tmp_path / "runs").glob("*/two_mass.npy"))
    assert len(traces) == 3
    written = [p.stat().st_mtime_ns for p in traces]
    assert main(argv) == 0
    again = capsys.readouterr()
    assert [p.stat().st_mtime_ns for p in traces] == written  # nothing was run again
    assert len((tmp_path / "results.csv").read_text().splitlines()) == 1 + 3
    assert again.out.splitlines()[2:] == first.out.splitlines()[2:]  # the same table, wall times included


@pytest.mark.parametrize("argv, message", [
    (["--rtols", "a,b"], "comma-separated numbers"),
    (["--rtols", "0"], "positive relative tolerances"),
    (["--rtols", "2", "--variant", "adaptive"], "outside [1e-12, 1]"),
    (["--variant", "adaptive/hold"], "choose their own"),
    (["--variant", "newton"], "expected ALG/INPUTS"),
    (["--workers", "0"], "at least 1"),
])
def test_cli_bad_precision_arguments_are_one_line(argv, message, capsys, tmp_path):
    rc = main(["study", "precision", str(TWO_MASS), "--out", str(tmp_path), *argv])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_two_workers_measure_the_same_errors(two_mass_study, tmp_path, cache):
    """The runs on two local worker processes give the same errors as on one (each run is
    deterministic; only the wall times depend on the machine)."""
    st = precision_study(TWO_MASS, [("gauss_seidel", "linear"), ("adaptive", "linear")], [4e-3, 2e-3],
                         rtols=RTOLS, stop_time=STOP, out=tmp_path, cache_dir=cache, workers=2)
    one = [(r.algorithm, r.label, r.errors) for r in two_mass_study.rows if r.algorithm != "ecco"]
    assert [(r.algorithm, r.label, r.errors) for r in st.rows] == one
