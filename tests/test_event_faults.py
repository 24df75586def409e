"""Misbehaving event FMUs end honestly (issue 35, item 5): tests/data/me_lag's ``fault`` parameter,
as an FMI 3.0 co-simulation FMU in event mode (chattering, an event iteration that does not
settle, a NaN state) and as a model-exchange or event-mode FMU that crashes or hangs inside the
new calls (CVODES's right-hand side, the event update): each run ends with a status naming the
FMU, the time and what happened, the supervised ones with the call the breadcrumb names.  (The
model-exchange faults 1-4 are in tests/test_model_exchange.py.)"""
from __future__ import annotations

import json
import re

import pytest

from cosim.run.execute import run
from cosim.scenario import from_dict
from cosim.slaves.model_exchange import available
from test_safety_supervised import cli


def _scene(fmu, fault: int, step: float = 0.01) -> dict:
    return {"name": "hostile", "components": {"a": {"fmu": str(fmu), "params": {"fault": fault}, "start": {"x": 1.0}}},
            "master": {"algorithm": "jacobi", "step": step, "estimate": False}, "stop_time": 1.0, "outputs": ["a.x"]}


@pytest.mark.parametrize("fault,step,status,says,last", [
    (2, 0.05, "failed", r"^a: more than 1000 events in the step from t = 0.5 s \(chattering\); the last at t = 0.51\d* s$",
     0.51),
    (3, 0.01, "event_iteration_failed", r"^the event iteration at t = 0.5 s did not settle in 100 rounds: a kept asking "
                                        r"for new discrete states$", 0.5),
    (1, 0.01, "unstable", r"a\.x = nan at t = 0.51 s", 0.51),
])
def test_a_misbehaving_event_mode_fmu_ends_the_run_naming_it(lag_fmus, fault, step, status, says, last):
    res = run(from_dict(_scene(lag_fmus["3cs"], fault, step)))
    assert res.status == status and re.search(says, res.reason), (res.status, res.reason)
    assert res.trace.time[-1] == pytest.approx(last)


def test_an_event_every_solver_step_below_the_bound_runs_and_is_counted(lag_fmus):
    """Fault 2 at a 0.01 s step: an event at each of the FMU's 1e-5 s solver steps from 0.5 s, 999 per
    communication step (below the stated bound of 1000): the run goes on, two rows per event."""
    scene = _scene(lag_fmus["3cs"], 2) | {"stop_time": 0.52}
    res = run(from_dict(scene))
    assert res.status == "ok", res.reason
    t = res.trace.time
    events = int((t[1:] == t[:-1]).sum())
    assert res.stats["events"]["handled"] == events and 1990 <= events <= 2010


@pytest.mark.parametrize("fmu,fault,call", [
    ("3", 5, "a.fmi2DoStep at t = 0.5 s"),  # CVODES's right-hand side (getDerivatives) inside the ME slave's step
    ("2", 7, "a.fmi2DoStep at t = 0.49 s"),  # the ME slave's event update (a time event at 0.5 s) inside its step
    ("3cs", 7, "a.fmi3UpdateDiscreteStates at t = 0.5 s"),  # the master's event iteration
])
def test_a_crash_in_an_event_or_model_exchange_call_is_named(lag_fmus, tmp_path, fmu, fault, call):
    if fmu != "3cs" and available():
        pytest.skip(available())
    scene = tmp_path / "hostile.json"
    scene.write_text(json.dumps(_scene(lag_fmus[fmu], fault)))
    res = cli(["run", scene, "--out", tmp_path / "out"], {})
    reason = f"the run's process died of SIGSEGV (signal 11) in {call}"
    assert res.returncode == 1 and f"rpr-cosim run: crashed: {reason}" in res.stderr, res.stderr
    side = json.loads((tmp_path / "out" / "hostile.json").read_text())
    assert side["status"] == "crashed" and side["reason"] == reason


@pytest.mark.parametrize("fmu,fault,call", [
    ("3", 6, "a.fmi2DoStep at t = 0.5 s"),
    ("3cs", 8, "a.fmi3UpdateDiscreteStates at t = 0.5 s"),
])
def test_a_hang_in_an_event_or_model_exchange_call_is_named(lag_fmus, tmp_path, fmu, fault, call):
    if fmu != "3cs" and available():
        pytest.skip(available())
    scene = tmp_path / "hostile.json"
    scene.write_text(json.dumps(_scene(lag_fmus[fmu], fault)))
    res = cli(["run", scene, "--out", tmp_path / "out", "--call-timeout", "1.5"], {})
    reason = f"{call} did not return within 1.5 s (the FMI call timeout, $RPR_COSIM_CALL_TIMEOUT)"
    assert res.returncode == 1 and f"rpr-cosim run: hung: {reason}" in res.stderr, res.stderr
