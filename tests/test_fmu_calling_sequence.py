"""Our FMUs check the calling sequence as the FMI standard requires (the Modelica Reference FMUs
behave the same way): a doStep past the stop time given at initialisation, a communication point
that does not follow the previous one, and fmi2GetReal before initialisation mode return Error
with a log message.  Driven through FMPy's FMU2Slave / FMU3Slave."""
from __future__ import annotations

import pytest
from fmpy.fmi1 import FMICallException

import fmus
from test_fmu_integrators import msd_block
from test_fmus import Slave

VERSIONS = ["2.0", "3.0"]
ERROR = 3  # fmi2Error == fmi3Error


@pytest.fixture(scope="module")
def msd_fmus(tmp_path_factory):
    cache = tmp_path_factory.getbasetemp() / "fmu-cache"
    return {v: fmus.build_fmu(msd_block(), fmi_version=v, cache_dir=cache) for v in VERSIONS}


def _setup(path, version, stop_time):
    """An initialised instance whose stop time is ``stop_time`` (None: undefined)."""
    logs: list = []
    sl = Slave(path, logs=logs, init=False)
    if sl.fmi3:
        sl.fmu.enterInitializationMode(startTime=0.0, stopTime=stop_time)
    else:
        # Slave already called fmi2SetupExperiment(startTime=0) without a stop time: reset and redo
        sl.fmu.reset()
        sl.fmu.setupExperiment(startTime=0.0, stopTime=stop_time)
        sl.fmu.enterInitializationMode()
    sl.fmu.exitInitializationMode()
    return sl, logs


def _error_of(call) -> int:
    with pytest.raises(FMICallException) as info:
        call()
    return info.value.status


@pytest.mark.parametrize("version", VERSIONS)
def test_step_past_the_stop_time_is_an_error(msd_fmus, version):
    sl, logs = _setup(msd_fmus[version], version, stop_time=0.01)
    for _ in range(9):
        sl.step(1e-3)
    sl.step(1e-3)  # ends exactly at the stop time: allowed
    assert _error_of(lambda: sl.fmu.doStep(sl.t, 1e-3)) == ERROR
    assert any(st == ERROR and "past the stop time 0.01" in msg for st, msg in logs), logs


@pytest.mark.parametrize("version", VERSIONS)
def test_a_step_ending_at_the_stop_time_up_to_round_off_is_allowed(msd_fmus, version):
    sl, logs = _setup(msd_fmus[version], version, stop_time=0.3)
    for _ in range(3):
        sl.step(0.1)  # 0.1 + 0.1 + 0.1 = 0.30000000000000004 > 0.3
    assert not [m for st, m in logs if st == ERROR]


@pytest.mark.parametrize("offset", [-1e-3, 5e-4, 1e-6])
@pytest.mark.parametrize("version", VERSIONS)
def test_a_communication_point_that_does_not_follow_the_previous_one_is_an_error(msd_fmus, version, offset):
    sl, logs = _setup(msd_fmus[version], version, stop_time=None)
    sl.step(1e-3)
    sl.step(1e-3)
    assert _error_of(lambda: sl.fmu.doStep(sl.t + offset, 1e-3)) == ERROR
    assert any(st == ERROR and "does not follow the previous one" in msg and "expected 0.002" in msg
               for st, msg in logs), logs
    sl.step(1e-3)  # the right point still works: the error changed nothing
    assert sl.get("body.s")[0] > 0


@pytest.mark.parametrize("version", VERSIONS)
def test_a_step_after_restoring_a_state_starts_at_the_restored_time(msd_fmus, version):
    sl, logs = _setup(msd_fmus[version], version, stop_time=None)
    sl.step(1e-3)
    saved = sl.get_state()
    sl.step(1e-3)
    sl.set_state(saved)
    assert _error_of(lambda: sl.fmu.doStep(sl.t, 1e-3)) == ERROR  # the FMU is back at 1 ms
    sl.fmu.doStep(1e-3, 1e-3)
    assert not [m for st, m in logs[1:] if st == ERROR and "expected 0.002" in m]


def test_fmi2_get_real_before_initialization_mode_is_an_error(msd_fmus):
    logs: list = []
    sl = Slave(msd_fmus["2.0"], logs=logs, init=False)
    assert _error_of(lambda: sl.fmu.getReal([sl.vr["body.s"]])) == ERROR
    assert any(st == ERROR and "fmi2GetReal is not allowed in instantiated" in msg for st, msg in logs), logs
    sl.fmu.enterInitializationMode()
    assert sl.fmu.getReal([sl.vr["body.s"]]) == [pytest.approx(0.01)]  # allowed from initialisation on


def test_fmi3_get_float64_when_instantiated_is_allowed(msd_fmus):
    """FMI 3.0 allows getters in the Instantiated state (the Reference FMUs do too)."""
    sl = Slave(msd_fmus["3.0"], init=False)
    assert sl.fmu.getFloat64([sl.vr["k"]]) == [100.0]


@pytest.mark.parametrize("version", VERSIONS)
def test_do_step_before_initialization_is_an_error(msd_fmus, version):
    logs: list = []
    sl = Slave(msd_fmus[version], logs=logs, init=False)
    assert _error_of(lambda: sl.fmu.doStep(0.0, 1e-3)) == ERROR
    assert any("doStep is not allowed in instantiated" in msg for _, msg in logs), logs
