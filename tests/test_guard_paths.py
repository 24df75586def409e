"""The physical guards on every path a run can take (issue 18, item 2): ``run`` with each master
algorithm (fixed-step compiled and Python, adaptive, ecco, iterative), batches on local workers
and on Dask, the precision and stability studies, and an exported SSP archive run as external
FMUs.  Each path runs ``pid_step`` variants that must trip one guard each (the others off):

- rated: the PIDs' output limit raised to 1e6 V, so the first voltage is 614 V (motor1.u rated
  +-12 V, Table 6.7);
- stroke, singularity, unstable: Kp = -30e1 on the three PIDs (positive feedback: the legs run
  out of their 0.10-0.60 m stroke at 0.2 s and the pose passes a singular configuration at
  0.27 s; the unstable variant bounds |values| by guards.max_abs = 30, which they pass as the
  motion runs away at 0.275 s (a motor current under Jacobi at 6 ms), rows before a slave's own
  integrator or the iterative master's coupling iteration gives up at 0.28 s: the guard, not the
  slave's Discard, ends the run).

Every variant asserts the status and the reason in the run's row or sidecar; a sidecar that
claims a guard is on must have looked at every row (``rows_checked``), and one that could not
look (an external FMU without catalog identity) says "not applied" with why."""
from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

import pytest

from cosim.batch import points_batch, run_batch
from cosim.batch.executors import DaskExecutor, LocalExecutor
from cosim.batch.results import read_rows
from cosim.run.execute import run
from cosim.run.ssp_export import export
from cosim.trace.traces import read_trace

ROOT = Path(__file__).resolve().parents[1]
PID_STEP = ROOT / "scenarios" / "pid_step.yaml"
GUARDS = ("stroke", "rated", "singularity", "unstable")
PIDS = (1, 2, 3)


def only(guard: str) -> dict[str, str]:
    """One guard on, the others off, at the fixed step the findings were measured with."""
    return {f"guards.{g}": "stop" if g == guard else "off" for g in GUARDS} | {"master.algorithm": "gauss_seidel"}


#: guard -> (overrides, status, reason pattern at the start of the run's reason)
VARIANTS = {
    "rated": ({**{f"components.pid{i}.params.u_max": 1e6 for i in PIDS}, **only("rated"), "stop_time": 0.05},
              "out_of_limits", r"^beyond rating: motor1\.u = 61\d\.\d V at t = 0 s, outside the rated \[-12, 12\] V"),
    "stroke": ({**{f"components.pid{i}.params.Kp": -300 for i in PIDS}, **only("stroke"), "stop_time": 0.3},
               "out_of_limits", r"^out of stroke: mech\.leg\[3\]\.s = 0\.09\d+ m at t = 0\.(19\d*|2) s, outside the "
                                r"stroke \[0\.1, 0\.6\] m"),
    "singularity": ({**{f"components.pid{i}.params.Kp": -300 for i in PIDS}, **only("singularity"),
                     "stop_time": 0.3},
                    "out_of_limits", r"^singularity: mech(: \|det J\| = [0-9.e-]+ m at t = 0\.27\d* s, below "
                                     r"guards\.min_det|: det J changes sign between t = 0\.27\d* and t = 0\.27\d* s)"),
    "unstable": ({**{f"components.pid{i}.params.Kp": -300 for i in PIDS}, **only("unstable"),
                  "guards.max_abs": 30.0, "stop_time": 0.3},
                 "unstable", r"^unstable: \w+\.[\w\[\]\.]+ = -?[0-9.e+]+ at t = 0\.\d+ s \(\|value\| beyond "
                             r"(guards\.max_abs = 30|[0-9.e+]+, 1000 times its start value)\)"),
}


def check_sidecar(out: Path, guard: str, status: str, pattern: str) -> dict:
    """The sidecar of the run in ``out``: its status and reason, and its guards: the tripped one
    applied (it looked at every recorded row), the others off."""
    meta = json.loads(next(out.glob("*.json")).read_text())
    stats = meta["statistics"]
    assert stats["status"] == status
    assert re.search(pattern, stats["reason"]), stats["reason"]
    g = stats["guards"]
    assert g["applied"] == {x: ("stop" if x == guard else "off") for x in GUARDS}
    trace = next(p for p in out.iterdir() if p.suffix in (".csv", ".npy"))  # a batch writes .npy, a run .csv
    assert g["rows_checked"] == len(read_trace(trace).time)  # every data row
    assert g["tripped"] == stats["reason"].split(" (afterwards:")[0]
    return stats


# --- rpr-cosim run, every algorithm ----------------------------------------------------------------
@pytest.mark.parametrize("guard", GUARDS)
@pytest.mark.parametrize("algorithm, engine", [("gauss_seidel", "compiled"), ("jacobi", "oracle"),
                                               ("adaptive", "compiled"), ("adaptive", "oracle"),
                                               ("ecco", "oracle"), ("iterative", "oracle")])
def test_run_is_guarded_with_every_algorithm(tmp_path, guard, algorithm, engine):
    sets, status, pattern = VARIANTS[guard]
    # a variable-step run records every accepted step here: on its 1 ms output grid a state that diverges
    # within a millisecond meets the step floor ("unstable", said by the controller) before a guard sees a row
    steps = {"master.record": "steps"} if algorithm in ("adaptive", "ecco") else {}
    res = run(PID_STEP, {**sets, **steps, "master.algorithm": algorithm}, out_dir=tmp_path, engine=engine)
    assert res.stats["engine"] == engine
    assert res.status == status, res.reason
    assert re.search(pattern, res.reason), res.reason
    t_stop = res.trace.time[-1]
    assert f"t = {t_stop:.6g} s" in res.reason  # the trace ends at the offending row
    check_sidecar(tmp_path, guard, status, pattern)


def test_a_variable_step_run_cut_by_a_guard_counts_only_the_steps_it_kept(tmp_path):
    sets, _, _ = VARIANTS["stroke"]
    res = run(PID_STEP, {**sets, "master.algorithm": "ecco", "master.record": "steps"})
    assert res.stats["steps_done"] == res.stats["accepted_steps"] == len(res.trace.time) - 1
    assert res.stats["simulated_s"] == res.trace.time[-1]
    grid = run(PID_STEP, {**sets, "master.algorithm": "ecco"})  # on the output grid: the steps up to its last row
    steps = grid.stats["steps_done"]
    assert steps == grid.stats["accepted_steps"] > len(grid.trace.time) - 1
    assert grid.stats["simulated_s"] == grid.trace.time[-1]


# --- batches: local workers and Dask ---------------------------------------------------------------
def guard_batch():
    return points_batch(PID_STEP, [({"variant": g}, VARIANTS[g][0]) for g in GUARDS], name="guarded")


def check_batch_rows(out: Path) -> None:
    rows = {r["variant"]: r for r in read_rows(out / "results.csv")[1]}
    assert set(rows) == set(GUARDS)
    for g, row in rows.items():
        _, status, pattern = VARIANTS[g]
        assert row["outcome"] == status, (g, row["reason"])
        assert re.search(pattern, row["reason"]), row["reason"]
        check_sidecar(out / "runs" / row["run_id"], g, status, pattern)


def test_batch_on_local_workers_is_guarded(tmp_path):
    """The worker gets the scene without its CasADi blocks: the guards' ratings, pose and geometry
    travel with it as plain data."""
    res = run_batch(guard_batch(), out=tmp_path, executor=LocalExecutor(2))
    assert res.failed == len(GUARDS)
    check_batch_rows(tmp_path)


def test_batch_on_dask_is_guarded(tmp_path, dask_scheduler):
    res = run_batch(guard_batch(), out=tmp_path, executor=DaskExecutor(dask_scheduler))
    assert res.failed == len(GUARDS)
    check_batch_rows(tmp_path)


# --- the studies -------------------------------------------------------------------------------
def test_a_guarded_precision_row_is_a_failed_row_not_an_error_figure(tmp_path):
    from cosim.study.precision import precision_study

    sets, status, pattern = VARIANTS["rated"]
    over = [f"{k}={v}" for k, v in sets.items() if k != "stop_time"]
    study = precision_study(PID_STEP, [("gauss_seidel", "linear")], [1e-3], stop_time=0.05, overrides=over,
                            out=tmp_path)
    (row,) = study.rows
    assert row.status == status and re.search(pattern, row.reason), row.reason
    assert row.worst != row.worst and not row.errors  # nan: no error figure for a guarded row
    assert study.cheapest_within(1.0) is None


def test_a_guarded_stability_cell_is_failed_with_the_guard_reason():
    from cosim.study.stability import stability_map

    smap = stability_map(PID_STEP, "components.pid1.params.u_max", (1e6, 1e6), (1e-3, 1e-3), n_values=1,
                         n_steps=1, variants=[("gauss_seidel", "linear")])
    (cell,) = smap.cells
    assert cell.outcome == "failed"
    assert cell.reason.startswith("beyond rating: motor1.u = "), cell.reason


# --- SSP: the exported scene comes back as external FMUs ------------------------------------------------
@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    from cosim.scenario import load

    return export(load(PID_STEP), tmp_path_factory.mktemp("ssp") / "pid_step.ssp")


@pytest.mark.parametrize("guard", GUARDS)
def test_an_exported_ssp_run_is_guarded(tmp_path, archive, guard):
    from cosim.scenario import load

    sets, status, pattern = VARIANTS[guard]
    scene = load(archive, sets)
    assert all(c.kind == "fmu" for c in scene.components.values())
    res = run(scene, out_dir=tmp_path)
    assert res.status == status and re.search(pattern, res.reason), res.reason
    check_sidecar(tmp_path, guard, status, pattern)


def test_external_fmus_without_catalog_identity_are_watched_by_the_unstable_guard_only(tmp_path, archive):
    """The same archive without our component annotations (as from another tool): the unstable
    guard still stops the run, and the sidecar says the other guards were not applied, and why."""
    bare = tmp_path / "bare.ssp"
    with zipfile.ZipFile(archive) as src, zipfile.ZipFile(bare, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "SystemStructure.ssd":
                data = re.sub(rb'\s+guards="[^"]*"', b"", data)
            dst.writestr(item, data)
    sets, status, pattern = VARIANTS["unstable"]
    sets = {**sets, **{f"guards.{g}": "stop" for g in GUARDS}}
    res = run(bare, sets, out_dir=tmp_path / "out")
    assert res.status == status and re.search(pattern, res.reason), res.reason
    applied = res.stats["guards"]["applied"]
    assert applied["unstable"] == "stop"
    for g in ("stroke", "rated", "singularity"):
        assert applied[g].startswith("not applied: ") and "no catalog identity for target, pid1" in applied[g]


def test_rpr_cosim_run_of_the_exported_ssp_stops_with_the_guard(tmp_path, archive, capsys):
    from cosim import cli

    sets, status, pattern = VARIANTS["rated"]
    rc = cli.main(["run", str(archive), "--out", str(tmp_path)] + [a for k, v in sets.items() for a in ("--set", f"{k}={v}")])
    assert rc == 1
    assert f"{status}: beyond rating: motor1.u = " in capsys.readouterr().err
    check_sidecar(tmp_path, "rated", status, pattern)


# --- the monolithic reference: the truth is held to the same limits ---------------------------------
@pytest.mark.parametrize("guard", ["rated", "stroke"])
def test_the_monolithic_reference_is_guarded(tmp_path, guard):
    """The reference integrates the same runaway physics (one ODE, CVODES): it ends with the same
    guard and reason as the co-simulation, its trace cut at the offending row.  (Past the stroke
    the runaway variants stiffen: CVODES gives up at 0.2 s, before the singularity at 0.27 s and
    the unstable bound, and says so: ``failed``, never ``ok``, test below.)"""
    from cosim.run.reference import reference

    sets, status, pattern = VARIANTS[guard]
    ref = reference(PID_STEP, sets, out_dir=tmp_path)
    assert ref.status == status, ref.reason
    assert re.search(pattern, ref.reason), ref.reason
    assert f"t = {ref.trace.time[-1]:.6g} s" in ref.reason
    g = ref.stats["guards"]
    assert g["applied"] == {x: ("stop" if x == guard else "off") for x in GUARDS}
    assert g["rows_checked"] == len(ref.trace.time)


@pytest.mark.parametrize("guard", ["singularity", "unstable"])
def test_a_runaway_reference_never_ends_ok(guard):
    from cosim.run.reference import reference

    sets, status, pattern = VARIANTS[guard]
    ref = reference(PID_STEP, sets)
    assert ref.status in (status, "failed") and ref.reason, ref.reason
    assert ref.trace.time[-1] < 0.3  # it did not reach the stop time
