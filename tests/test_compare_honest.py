"""``compare`` never passes a comparison it cannot stand behind (issue 7 item 2): a trace whose run
did not end "ok", an overlap shorter than the reference's span, and the variables it could not
match are all reported; ``--allow-failed`` / ``--allow-partial`` say so explicitly."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cosim import cli
from cosim.analysis.trace_diff import comparability, run_status
from cosim.trace.traces import CsvTrace, Trace, read_trace


def trace(t: np.ndarray, **cols: np.ndarray) -> Trace:
    return Trace(["time", *cols], np.column_stack([t, *cols.values()]))


def write(path: Path, tr: Trace, status: str = "ok", reason: str = "", commented: bool = False) -> Path:
    w = CsvTrace(path, commented=commented)
    w.start(tr.columns, {"scene": path.stem})
    w.record(tr.data)
    w.finish(status, reason, {})
    return path


T = np.linspace(0.0, 2.0, 201)


@pytest.fixture
def good(tmp_path) -> Path:
    return write(tmp_path / "good.csv", trace(T, **{"m.x": np.sin(T), "m.y": np.cos(T)}))


def test_a_one_row_failed_trace_fails_the_tolerance_gate(tmp_path, good, capsys):
    """The finding: a failed run with one row passed ``--tol`` (it matched the reference at t = 0)."""
    bad = write(tmp_path / "bad.csv", trace(T[:1], **{"m.x": np.sin(T[:1]), "m.y": np.cos(T[:1])}),
                "failed", "motor1 returned DISCARD in the step from t = 0 s")
    assert cli.main(["compare", str(bad), str(good), "--tol", "1e-3"]) == 1
    err = capsys.readouterr().err
    assert f"fails: {bad}: the run's status is 'failed', not 'ok' (motor1 returned DISCARD" in err
    assert "fails: the traces overlap over 0..0 s, 0 % of the reference's span 0..2 s" in err
    assert cli.main(["compare", str(bad), str(good)]) == 2
    assert "rpr-cosim compare: error: refused: " in capsys.readouterr().err
    assert cli.main(["compare", str(bad), str(good), "--tol", "1e-3", "--allow-failed", "--allow-partial"]) == 0


@pytest.mark.parametrize("status", ["out_of_limits", "unstable", "interrupted", "running", "failed"])
def test_a_reference_that_did_not_end_ok_is_refused_too(tmp_path, good, status, capsys):
    ref = write(tmp_path / "ref.csv", read_trace(good), status, "because")
    assert cli.main(["compare", str(good), str(ref)]) == 2
    assert f"{ref}: the run's status is {status!r}, not 'ok' (because); use --allow-failed" in capsys.readouterr().err
    assert cli.main(["compare", str(good), str(ref), "--allow-failed", "--tol", "1e-9"]) == 0


def test_a_run_a_component_stopped_is_a_result_when_it_covers_the_span(tmp_path, good, capsys):
    """FMI terminateSimulation ends a run "stopped" at the component's request: a normal end."""
    ended = write(tmp_path / "ended.csv", read_trace(good), "stopped", "stopped by ball at t = 2 s")
    assert cli.main(["compare", str(ended), str(good), "--tol", "1e-9"]) == 0
    assert f"note: {ended}: the run ended at a component's request (stopped by ball at t = 2 s)" in capsys.readouterr().out
    early = write(tmp_path / "early.csv", Trace(read_trace(good).columns, read_trace(good).data[:101]), "stopped", "x")
    assert cli.main(["compare", str(early), str(good), "--tol", "1e-9"]) == 1


def test_the_sidecar_of_a_killed_run_is_read(tmp_path, good, capsys):
    """A run killed while writing leaves a CSV without its final status and a sidecar saying
    "running": not a result."""
    killed = tmp_path / "killed.csv"
    old = write(tmp_path / "old.csv", read_trace(good), commented=True)  # the commented form of earlier versions
    text = old.read_text()
    killed.write_text(text[:text.index("# status:")])
    (tmp_path / "killed.json").write_text(json.dumps({"status": "running", "reason": ""}))
    assert run_status(read_trace(killed), killed) == ("running", "")
    assert cli.main(["compare", str(killed), str(good)]) == 2
    assert "the run's status is 'running', not 'ok'" in capsys.readouterr().err
    (tmp_path / "killed.json").unlink()
    assert run_status(read_trace(killed), killed)[0] == "unfinished"


def test_a_plain_trace_takes_its_status_from_the_sidecar(tmp_path, good, capsys):
    """A plain CSV has no comment lines: the sidecar says how its run ended, also for a run
    killed while writing (sidecar still "running")."""
    assert not good.read_text().startswith("#") and good.read_text().splitlines()[0] == "time,m.x,m.y"
    assert run_status(read_trace(good), good) == ("ok", "")
    killed = tmp_path / "killed.csv"
    killed.write_text("".join(good.read_text().splitlines(keepends=True)[:50]))
    side = json.loads(good.with_suffix(".json").read_text())
    (tmp_path / "killed.json").write_text(json.dumps({**side, "status": "running", "trace": "killed.csv"}))
    assert run_status(read_trace(killed), killed) == ("running", "")
    assert cli.main(["compare", str(killed), str(good)]) == 2
    assert "the run's status is 'running', not 'ok'" in capsys.readouterr().err


def test_a_trace_from_another_tool_has_an_unknown_status_and_is_compared_with_a_note(tmp_path, good, capsys):
    foreign = tmp_path / "foreign.csv"
    foreign.write_text("time,m.x\n" + "\n".join(f"{float(t)!r},{float(np.sin(t))!r}" for t in T) + "\n")
    assert run_status(read_trace(foreign), foreign) == ("unknown", "")
    assert cli.main(["compare", str(foreign), str(good), "--tol", "1e-9"]) == 0
    out = capsys.readouterr().out
    assert f"note: {foreign}: no run status recorded" in out


@pytest.mark.parametrize("t_test, partial", [
    (np.linspace(0.0, 1.0, 101), "the reference"),   # stops half way
    (np.linspace(0.5, 2.0, 151), "the reference"),   # starts late
    (np.linspace(0.0, 2.0, 21), ""),                 # coarser, whole span
    (np.linspace(0.0, 1.995, 400), ""),              # ends within half a sample of the span
    (np.linspace(0.0, 3.0, 301), "the test"),        # longer than the reference: its last third unchecked
    (np.linspace(-1.0, 2.0, 301), "the test"),       # starts before the reference
    (np.linspace(0.0, 20.0, 2001), "the test"),      # issue 33: ten times the reference's span
])
def test_the_overlap_must_cover_both_spans(tmp_path, good, t_test, partial, capsys):
    """The overlap must cover the reference's span and the test's (issue 33: a 0-2 s test
    against a 0-0.2 s reference passed with error 0)."""
    test = write(tmp_path / "test.csv", trace(t_test, **{"m.x": np.sin(t_test), "m.y": np.cos(t_test)}))
    rc = cli.main(["compare", str(test), str(good)])
    assert rc == (2 if partial else 0)
    if partial:
        a, b = max(t_test[0], 0.0), min(t_test[-1], 2.0)
        s0, s1 = (0.0, 2.0) if partial == "the reference" else (t_test[0], t_test[-1])
        assert (f"the traces overlap over {a:g}..{b:g} s, {100 * (b - a) / (s1 - s0):.3g} % of {partial}'s span "
                f"{s0:g}..{s1:g} s" in capsys.readouterr().err)
        assert cli.main(["compare", str(test), str(good), "--allow-partial"]) == 0
        assert cli.main(["compare", str(good), str(test)]) == 2  # and the other way round
        assert cli.main(["compare", str(good), str(test), "--tol", "1"]) == 1


def test_columns_that_could_not_be_matched_are_reported(tmp_path, good, capsys):
    test = write(tmp_path / "test.csv", trace(T, **{"m.x": np.sin(T), "m.extra": T, "n.z": T}))
    assert cli.main(["compare", str(test), str(good)]) == 0
    out = capsys.readouterr().out
    assert f"note: not compared (only in {test}): m.extra, n.z" in out
    assert f"note: not compared (only in {good}): m.y" in out
    assert cli.main(["compare", str(test), str(good), "--only", "m.*"]) == 0
    out = capsys.readouterr().out
    assert "m.extra" in out and "n.z" not in out


def test_comparability_is_a_function_other_verbs_can_call(good):
    """The checks live in cosim.analysis.trace_diff, not in the CLI handler (a many-against-one compare calls them)."""
    ok = read_trace(good)
    short = Trace(ok.columns, ok.data[:50], status="out_of_limits", reason="guard")
    c = comparability(short, ok, labels=("short", "ref"))
    assert c.partial and c.only_test == [] and c.only_ref == []
    first, second = c.problems()
    assert first == ("short: the run's status is 'out_of_limits', not 'ok' (guard); use --allow-failed to compare "
                     "it anyway")
    assert second.startswith("the traces overlap over 0..0.49 s, 24.5 % of the reference's span 0..2 s")
    assert c.problems(allow_failed=True, allow_partial=True) == []


def test_a_batch_is_not_compared_against_a_failed_reference(tmp_path, good, capsys):
    ref = write(tmp_path / "ref.csv", read_trace(good), "unstable", "unstable: m.x = nan at t = 1 s")
    batch = tmp_path / "batch"
    batch.mkdir()
    assert cli.main(["compare", str(batch), str(ref)]) == 2
    assert f"refused: {ref}: the run's status is 'unstable', not 'ok'" in capsys.readouterr().err
