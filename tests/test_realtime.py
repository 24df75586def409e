"""Real-time pacing of the run loop (cosim.master.realtime) and its place in scenes and runs."""
from __future__ import annotations

import gc

import json
from pathlib import Path

import pytest

from cosim import master as M
from cosim.master import realtime
from cosim.errors import UserError
from cosim.run.execute import run
from cosim.scenario import SceneError, load
from cosim.slaves.fmu_slave import FmuSlave

SCENES = Path(__file__).resolve().parent.parent / "scenarios"
H = 1_000_000  # 1 ms step [ns]


class FakeClock:
    """Monotonic nanoseconds that advance 1 us per reading (a spin makes progress) and by the
    requested time plus ``oversleep`` per sleep."""

    def __init__(self, oversleep_ns: int = 0):
        self.t, self.oversleep = 10**12, oversleep_ns

    def now(self) -> int:
        self.t += 1000
        return self.t

    def sleep(self, s: float) -> None:
        self.t += int(s * 1e9) + self.oversleep


@pytest.fixture(autouse=True)
def _thawed_heap():
    yield
    gc.unfreeze()  # a Pacer not finished by its test freezes the heap


def test_the_pacer_quiets_the_heap_before_the_run_and_gives_it_back():
    gc.unfreeze()
    p = realtime.Pacer(H, 10)
    assert gc.get_freeze_count() > 0  # what existed is kept out of collections while paced
    p.finish()
    assert gc.get_freeze_count() == 0


@pytest.fixture
def clock(monkeypatch):
    c = FakeClock(oversleep_ns=200_000)
    monkeypatch.setattr(realtime, "_now", c.now)
    monkeypatch.setattr(realtime.time, "sleep", c.sleep)
    return c


def test_schedule_is_absolute_and_never_early(clock):
    p = realtime.Pacer(H, 1000)
    starts = []
    for k in range(1000):
        assert p.wait(k)
        starts.append(clock.t)
        clock.t += 400_000  # the step's work
    # each step starts at its own deadline t0 + k h (within the spin's clock granularity): no drift
    assert all(0 <= s - (p.t0 + k * H) <= 2000 for k, s in enumerate(starts))
    st = p.stats()
    assert st["missed_deadlines"] == 0 and st["lateness_max_s"] <= 2e-6 and st["paced_steps"] == 1000


def test_overrun_catches_up_and_counts(clock):
    p = realtime.Pacer(H, 100)
    late = []
    for k in range(20):
        assert p.wait(k)
        late.append(clock.t - (p.t0 + k * H))
        clock.t += 4_500_000 if k == 5 else 100_000  # step 5 takes 4.5 steps
    # step 6 starts when step 5 ends, 3.5 ms late; each catch-up step gains 0.9 ms, then on time
    assert [round(x / 1e5) for x in late[6:11]] == [35, 26, 17, 8, 0]
    assert p.missed == 3  # more than one step late: steps 6, 7, 8


def test_consecutive_misses_fail_the_run(clock):
    p = realtime.Pacer(H, 100, realtime.RealtimeSettings(max_misses=5))
    results = []
    for k in range(10):
        results.append(p.wait(k))
        if not results[-1]:
            break
        clock.t += 2_000_000  # every step costs two
    assert results == [True] * 5 + [False]  # steps 1..5 start (k + a little) ms late: five misses
    assert "5 deadlines in a row" in p.reason


def test_real_clock_never_starts_a_step_early():
    p = realtime.Pacer(H, 50)
    for k in range(50):
        assert p.wait(k)
    assert (p.late[:50] >= 0).all()


@pytest.mark.parametrize("value, message", [("5", "expected true, false"), ("{priority: 200}", "priority"),
                                            ("{max_misses: 0}", "max_misses"), ("{spin: -1}", "spin"),
                                            ("{max_mises: 3}", "max_misses")])
def test_scene_validates_master_realtime(value, message):
    with pytest.raises(SceneError, match=message) as exc:
        load(SCENES / "rig_step.yaml", [f"master.realtime={value}"])
    assert "master.realtime" in str(exc.value)


def test_paced_run_reports_lateness_and_rtf(tmp_path):
    res = run(SCENES / "rig_step.yaml", ["stop_time=0.2", "master.realtime={max_misses: 100000}"], out_dir=tmp_path)
    assert res.ok
    rt = res.stats["realtime"]
    assert rt["paced_steps"] == 200 and rt["lateness_p50_s"] <= rt["lateness_p99_s"] <= rt["lateness_max_s"]
    assert res.stats["real_time_factor"] <= 1.0 + 1e-2  # paced: a 0.2 s scene takes 0.2 s of wall time
    side = json.loads((tmp_path / "rig_step.json").read_text())
    assert side["statistics"]["realtime"]["paced_steps"] == 200


def test_rollback_algorithms_are_refused_with_a_slave_that_cannot_roll_back(tmp_path):
    from hardware.hil_fmu import build_hil_fmu

    fmu = build_hil_fmu()

    @M.register
    class NeedsRollback(M.GaussSeidel):
        name = "test_needs_rollback"
        needs_rollback = True
    try:
        system = M.CoupledSystem([FmuSlave("rig", fmu)], [])
        with pytest.raises(UserError, match="rig cannot roll back"):
            M.simulate(system, "test_needs_rollback", step_ns=H, n_steps=10)
    finally:
        M.ALGORITHMS.pop("test_needs_rollback")


def test_a_paced_runs_summary_labels_its_priority_and_the_glossary_has_each_term(tmp_path, capsys):
    """The summary's real-time line said "122 missed deadlines of 4000 paced steps (not requested)",
    as if the misses were not requested: the scheduling priority is named, and each label of the
    line is a glossary entry (issue 32, item 8)."""
    import re

    from cosim.cli import main

    assert main(["run", str(SCENES / "rig_step.yaml"), "--set", "stop_time=0.2", "--set",
                 "master.realtime={max_misses: 100000}", "--out", str(tmp_path)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("  real time: "))
    assert re.search(r"missed deadlines of 200 paced steps; scheduling priority: not requested$", line), line
    glossary = (SCENES.parent / "docs" / "reference" / "glossary.md").read_text()
    entries = re.findall(r"\*\*(.+?)\*\*", glossary)
    assert {"lateness", "missed deadlines", "scheduling priority"} <= set(entries)
