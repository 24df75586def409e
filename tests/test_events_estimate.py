"""The run's own error estimate across events (cosim.master.estimate: the modes' events of a run
and its companion matched, the event-time error, the value error outside a window around each)
and the verdict it gives, checked against the event reference (SciPy LSODA, an independent
integration of the same scene); the sidecar's count of events."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.master.estimate import INACCURATE, event_time_tolerance, judge, richardson

ROOT = Path(__file__).resolve().parents[1]
STICK_SLIP = ROOT / "scenarios" / "stick_slip.yaml"


def _clocked(t: np.ndarray, switch: float) -> np.ndarray:
    """Columns: a signal that jumps from 0 to 1 at ``switch``, and a clock mode (``time`` of the
    last switch, 0 before it)."""
    y = np.where(t < switch, 0.0, 1.0)
    return np.column_stack([y, np.where(t < switch, 0.0, switch)])


def test_matched_events_give_the_event_time_error_and_the_value_error_between_them():
    t = np.linspace(0, 1, 1001)
    run, comp = _clocked(t, 0.5012), _clocked(t, 0.5004)  # the switch 0.8 ms apart, in different rows
    names = ["y", "clock"]
    plain = richardson(t, run, t, comp, names, 0.5, "test")  # no modes: the jump reads as an error
    est = richardson(t, run, t, comp, names, 0.5, "test", modes=[1])
    assert plain.worst > 0.3
    assert est.events == 1 and est.event_time == pytest.approx(8e-4 / 0.5, rel=1e-6)  # the clock: exact
    assert est.errors["y"] < 1e-12  # equal outside the window
    status, reason = judge("ok", "", est, 1e-3)  # 1.6e-3 s: over 10x the 1e-4 s event time tolerance
    assert status == "inaccurate" and "event-time error of clock" in reason
    near = richardson(t, _clocked(t, 0.50041), t, comp, names, 0.5, "test", modes=[1])
    assert near.event_time == pytest.approx(2e-5, rel=1e-6) and event_time_tolerance(1e-3) == pytest.approx(1e-4)
    assert judge("ok", "", near, 1e-3)[0] == "ok"


def test_a_missing_event_fails_the_verdict():
    t = np.linspace(0, 1, 1001)
    run = _clocked(t, 0.5)
    comp = np.column_stack([np.zeros_like(t), np.zeros_like(t)])  # the companion never switched
    est = richardson(t, run, t, comp, ["y", "clock"], 0.5, "test", modes=[1])
    assert est.missing == {"clock": (1, 0)}
    status, reason = judge("ok", "", est, 1e-3)
    assert status == "inaccurate" and "clock has 1 events in the run and 0 in its companion" in reason


@pytest.fixture(scope="module")
def stick_slip_reference():
    from cosim.run.reference import reference

    ref = reference(STICK_SLIP)
    assert ref.status == "ok", ref.reason
    return ref


def _against_reference(res, ref) -> tuple[float, float]:
    """(largest switch time error [s], value error between switches [of range]) of a run."""
    from cosim.analysis.compare import compare_between_events, match_events, times_from_clock, windows

    pairs = [(times_from_clock(res.trace, n), times_from_clock(ref.trace, n)) for n in ("mass.t_stick", "mass.t_slip")]
    timing = [match_events(n, a, b) for n, (a, b) in zip(("stick", "slip"), pairs)]
    dt = max(tm.max_error if not tm.missing else np.inf for tm in timing)
    between = compare_between_events(res.trace, ref.trace, windows(pairs, 1e-3), ["mass.x", "mass.v", "pid.y"])
    return dt, max(d.relative for d in between)


@pytest.mark.parametrize("loose", [False, True], ids=["scene", "held inputs at 1 ms"])
def test_the_stick_slip_verdict_agrees_with_the_event_reference(loose, stick_slip_reference, cache, tmp_path):
    """At the scene's setting (0.5 ms, linear inputs) the run is "ok" by its own estimate and
    within its tolerances of the reference (switches within 1e-4 s, values within 1e-3 of range);
    at 1 ms with held inputs its estimate judges it "inaccurate", and the reference agrees: its
    switches are off by more than ten times the event time tolerance."""
    from cosim.run.execute import run

    sets = ["master.step=1e-3", "master.inputs=hold"] if loose else []
    res = run(STICK_SLIP, sets, cache_dir=cache, out_dir=tmp_path)
    dt, value = _against_reference(res, stick_slip_reference)
    est = res.stats["estimate"]
    assert est["events"]["matched"] >= 8 or est["events"]["missing"]
    if loose:
        assert res.status == "inaccurate", res.reason
        assert dt > INACCURATE * 1e-4 or value > INACCURATE * 1e-3, (dt, value)
    else:
        assert res.status == "ok", res.reason
        assert est["events"]["time_error"] <= 1e-4 and est["worst"] <= 1e-3
        assert dt < 1e-4 and value < 1e-3, (dt, value)


def test_a_leg_run_into_its_end_stop_goes_on_and_the_sidecar_counts_the_impacts(cache, tmp_path):
    """rig_end_stop: leg 2 reaches its 0.36 m stop and rests on it; the run goes on to its stop
    time ("ok", its own estimate matching the impact) and the sidecar's statistics count one
    impact of leg 2, as many as the event reference locates."""
    import json

    from cosim.run.execute import run
    from cosim.run.reference import reference

    scene = ROOT / "scenarios" / "rig_end_stop.yaml"
    res = run(scene, cache_dir=cache, out_dir=tmp_path)
    assert res.status == "ok", res.reason
    assert res.trace.time[-1] == pytest.approx(2.0)
    ref = reference(scene)
    located = [e for e in ref.stats["events"]["list"] if "2" in str(e)]
    counts = res.stats["events"]["counted"]["rig"]
    assert counts == {"leg[1].impacts": 0, "leg[2].impacts": 1, "leg[3].impacts": 0}
    assert counts["leg[2].impacts"] == len(located) == 1, ref.stats["events"]["list"]
    sidecar = json.loads((tmp_path / "rig_end_stop.json").read_text())
    assert sidecar["statistics"]["events"]["counted"] == {"rig": counts}
