"""Exported FMUs: validation, simulation in FMPy, agreement with the CasADi step map, analytic
solutions, rollback, parallel instances, directional derivatives, parameter rules, the cache and
build-time refusal of malformed blocks.

FMUs are built once per session into a shared temporary cache (content-hashed, so tests that ask
for the same block reuse the file)."""
from __future__ import annotations

import math
import shutil
import sys
import threading
import types
import xml.etree.ElementTree as ET
import zipfile
from ctypes import byref
from pathlib import Path

import casadi as ca
import fmpy
import numpy as np
import pytest
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import FMU2Slave, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE, defaultCallbacks
from fmpy.fmi3 import FMU3Slave, fmi3LogMessageCallback
from fmpy.validation import validate_fmu

import fmus
import fmus.build
from fmus import BuildError
from fmus.compile import exported_symbols
from models import integrators as I
from models.block import Block, Param, Var
from test_fmu_integrators import gain_block, lag_block, msd_block, msd_exact, rk4_amplification, stiff_block

VERSIONS = ["2.0", "3.0"]


_UNZIPPED: dict[Path, str] = {}


class Slave:
    """A thin adapter over FMPy's FMU2Slave / FMU3Slave addressing variables by name."""

    def __init__(self, path: Path, name: str = "inst", *, logs: list | None = None, init: bool = True,
                 start: dict[str, float] | None = None):
        self.md = fmpy.read_model_description(str(path))
        if path not in _UNZIPPED:
            _UNZIPPED[path] = fmpy.extract(str(path))
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.fmi3 = self.md.fmiVersion.startswith("3")
        ident = self.md.coSimulation.modelIdentifier
        self.logs = logs if logs is not None else []
        if self.fmi3:
            self._log3 = fmi3LogMessageCallback(lambda env, status, cat, msg: self.logs.append((status, msg.decode())))
            self.fmu = FMU3Slave(guid=self.md.guid, unzipDirectory=_UNZIPPED[path], modelIdentifier=ident,
                                 instanceName=name)
            self.fmu.instantiate(logMessage=self._log3)
        else:
            self._cb = fmi2CallbackFunctions()
            self._cb.logger = fmi2CallbackLoggerTYPE(
                lambda env, inst, status, cat, msg: self.logs.append((status, msg.decode())))
            self._cb.allocateMemory = defaultCallbacks.allocateMemory
            self._cb.freeMemory = defaultCallbacks.freeMemory
            self.fmu = FMU2Slave(guid=self.md.guid, unzipDirectory=_UNZIPPED[path], modelIdentifier=ident,
                                 instanceName=name)
            self.fmu.instantiate(callbacks=self._cb)
            self.fmu.setupExperiment(startTime=0.0)
        self.t = 0.0
        if init:
            self.initialize(start or {})

    def initialize(self, start: dict[str, float]) -> None:
        if self.fmi3:
            self.fmu.enterInitializationMode(startTime=0.0)
        else:
            self.fmu.enterInitializationMode()
        if start:
            self.set(**start)
        self.fmu.exitInitializationMode()

    def set(self, **values: float) -> None:
        vrs = [self.vr[k.replace("__", ".")] for k in values]
        (self.fmu.setFloat64 if self.fmi3 else self.fmu.setReal)(vrs, [float(v) for v in values.values()])

    def setn(self, values: dict[str, float]) -> None:
        vrs = [self.vr[k] for k in values]
        (self.fmu.setFloat64 if self.fmi3 else self.fmu.setReal)(vrs, [float(v) for v in values.values()])

    def get(self, *names: str) -> np.ndarray:
        vals = (self.fmu.getFloat64 if self.fmi3 else self.fmu.getReal)([self.vr[n] for n in names])
        return np.array(vals, dtype=float)

    def step(self, h: float) -> None:
        self.fmu.doStep(self.t, h)
        self.t += h

    def get_state(self):
        return self.fmu.getFMUState() if self.fmi3 else self.fmu.getFMUstate()

    def set_state(self, s) -> None:
        (self.fmu.setFMUState if self.fmi3 else self.fmu.setFMUstate)(s)

    def serialize(self, s) -> bytes:
        return bytes((self.fmu.serializeFMUState if self.fmi3 else self.fmu.serializeFMUstate)(s))

    def deserialize(self, b: bytes):
        return (self.fmu.deserializeFMUState if self.fmi3 else self.fmu.deSerializeFMUstate)(b)

    def derivative(self, unknowns: list[str], knowns: list[str], seed: list[float]) -> np.ndarray:
        return np.array(self.fmu.getDirectionalDerivative([self.vr[n] for n in unknowns],
                                                          [self.vr[n] for n in knowns], seed))

    def free(self) -> None:
        self.fmu.terminate()
        self.fmu.freeInstance()


CASES = {
    "msd_radau": lambda: msd_block(integrator="radau"),
    "msd_rk4": lambda: msd_block(integrator="rk4", substeps=4),
    "stiff_radau": lambda: stiff_block(),
    "lag_discrete": lambda: lag_block(),
    "gain_none": lambda: gain_block(),
}


# --- validation and FMPy -------------------------------------------------------------------------
@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("case", list(CASES))
def test_fmu_validates_and_runs_in_fmpy(case, version, cache):
    blk = CASES[case]()
    path = fmus.build_fmu(blk, fmi_version=version, cache_dir=cache)
    assert validate_fmu(str(path)) == []
    h = blk.sample_period or 1e-3
    res = fmpy.simulate_fmu(str(path), stop_time=0.1, step_size=h, output_interval=h,
                            start_values={"f": 3.0} if "msd" in case or "stiff" in case else {"u": 1.0})
    assert res["time"][-1] == pytest.approx(0.1)
    if case.startswith("msd"):
        exact = msd_exact(0.1, m=1, k=100, c=2, s0=0.01, f=3.0)
        np.testing.assert_allclose([res["body.s"][-1], res["body.v"][-1]], exact, rtol=1e-7, atol=1e-10)
    elif case == "lag_discrete":
        assert res["y"][-1] == pytest.approx(1 - math.exp(-0.1 / 0.05), rel=1e-12)
    elif case == "gain_none":
        assert res["y"][-1] == 2.5


@pytest.mark.parametrize("version", VERSIONS)
def test_only_fmi_functions_are_exported(version, cache):
    path = fmus.build_fmu(msd_block(), fmi_version=version, cache_dir=cache)
    unz = fmpy.extract(str(path))
    lib = next(Path(unz, "binaries").rglob("*.so"))
    names = exported_symbols(lib)
    prefix = "fmi2" if version == "2.0" else "fmi3"
    assert names and all(n.startswith(prefix) for n in names), names
    assert f"{prefix}DoStep" in names and f"{prefix}GetDirectionalDerivative" in names
    shutil.rmtree(unz)


# --- exact agreement with the CasADi step map ------------------------------------------------
@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("case", ["msd_radau", "msd_rk4", "stiff_radau", "lag_discrete", "gain_none"])
def test_fmu_equals_the_casadi_step_map(case, version, cache):
    blk = CASES[case]()
    path = fmus.build_fmu(blk, fmi_version=version, cache_dir=cache)
    sl = Slave(path)
    st = I.Stepper(blk)
    p = blk.param_defaults
    x = np.asarray(st.start(p), dtype=float).ravel()
    h = 2 * blk.sample_period if blk.integrator == "discrete" else 2e-3
    uname = blk.inputs[0].name
    ynames = [v.name for v in blk.outputs]
    rng = np.random.default_rng(3)
    for k in range(40):
        u = float(rng.normal())
        sl.setn({uname: u})
        y_fmu = sl.get(*ynames)
        y_ref = np.asarray(st.out(x, [u], p), dtype=float).ravel()
        np.testing.assert_allclose(y_fmu, y_ref, rtol=1e-12, atol=1e-15)
        sl.step(h)
        x, ok = st.step(x, [u], p, h)
        assert ok
    sl.free()


# --- analytic solutions and stiffness ----------------------------------------------------------
@pytest.mark.parametrize("version", VERSIONS)
def test_radau_fmu_matches_the_analytic_solution(version, cache):
    path = fmus.build_fmu(msd_block(integrator="radau"), fmi_version=version, cache_dir=cache)
    sl = Slave(path)
    sl.set(f=3.0)
    for _ in range(100):
        sl.step(0.01)
    exact = msd_exact(1.0, m=1, k=100, c=2, s0=0.01, f=3.0)
    np.testing.assert_allclose(sl.get("body.s", "body.v"), exact, atol=2e-9)
    sl.free()


def _outcome(sl: Slave, steps: int, h: float, limit: float = 1.0) -> str:
    """'stable', 'discard' (the FMU refused a step) or 'diverged' (|s| grew past ``limit`` m)."""
    for _ in range(steps):
        before = sl.get("body.s", "body.v")
        try:
            sl.step(h)
        except FMICallException as exc:
            assert exc.status == 2  # fmi2Discard / fmi3Discard
            # (Slave.step did not advance sl.t: the FMU is still at sl.t, and says so if asked
            # to step from anywhere else)
            np.testing.assert_array_equal(sl.get("body.s", "body.v"), before)  # state left untouched
            return "discard"
        if abs(sl.get("body.s")[0]) > limit:
            return "diverged"
    return "stable"


@pytest.mark.parametrize("version", VERSIONS)
def test_stiff_joint_radau_stable_at_1ms(version, cache):
    sl = Slave(fmus.build_fmu(stiff_block(), fmi_version=version, cache_dir=cache))
    assert _outcome(sl, 200, 1e-3) == "stable"
    assert abs(sl.get("body.s")[0]) < 1e-12  # decays like exp(-1000 t)
    sl.free()


@pytest.mark.parametrize("substeps", [1, 5])
def test_stiff_joint_rk4_fails_exactly_where_spec_says(substeps, cache):
    """SPEC §6: RK4 at a 1 ms step diverges, 0.2 ms substeps are stable; cross-checked with the
    RK4 stability function at the joint's eigenvalues."""
    sl = Slave(fmus.build_fmu(stiff_block(integrator="rk4", substeps=substeps), cache_dir=cache))
    outcome = _outcome(sl, 300, 1e-3, limit=math.inf)  # run until the FMU itself notices
    assert (outcome != "stable") == (rk4_amplification(1e-3 / substeps) > 1)
    assert outcome == ("stable" if substeps == 5 else "discard")
    sl.free()


def test_discard_is_logged_with_the_block_name(cache):
    logs: list = []
    sl = Slave(fmus.build_fmu(stiff_block(integrator="rk4"), cache_dir=cache), logs=logs)
    assert _outcome(sl, 300, 1e-3, limit=math.inf) == "discard"
    assert any(status == 2 and "stiff" in msg and "discarded" in msg for status, msg in logs), logs
    # the FMU keeps working after a discard: a smaller step from the kept state succeeds
    sl.step(1e-9)
    sl.free()


@pytest.mark.parametrize("version", VERSIONS)
def test_debug_logging_categories(version, cache):
    logs: list = []
    sl = Slave(fmus.build_fmu(stiff_block(), fmi_version=version, cache_dir=cache), logs=logs)
    sl.step(1e-3)
    assert not any("residual/tolerance" in m for _, m in logs)  # off by default
    sl.fmu.setDebugLogging(True, ["logNonlinearSystems"])
    sl.step(1e-3)
    assert any(status == 0 and "Radau IIA residual/tolerance" in m for status, m in logs)
    with pytest.raises(FMICallException):
        sl.fmu.setDebugLogging(True, ["logNoSuchThing"])
    assert any("unknown log category 'logNoSuchThing'" in m for _, m in logs)
    sl.free()


# --- instances, rollback, serialisation -----------------------------------------------------------
@pytest.mark.parametrize("version", VERSIONS)
def test_two_instances_with_different_parameters_in_one_process(version, cache):
    path = fmus.build_fmu(msd_block(integrator="radau", substeps=2), fmi_version=version, cache_dir=cache)
    a = Slave(path, "a", init=False)
    b = Slave(path, "b", init=False)
    a.initialize({"k": 100.0, "f": 3.0})
    b.initialize({"k": 400.0, "c": 1.0, "f": -1.0})
    for _ in range(50):
        a.step(0.02)
        b.step(0.02)
    np.testing.assert_allclose(a.get("body.s", "body.v"), msd_exact(1.0, m=1, k=100, c=2, s0=0.01, f=3.0),
                               atol=1e-8)
    # Radau at h w = 0.2 per substep: error ~1e-7; the two solutions differ by ~0.1
    np.testing.assert_allclose(b.get("body.s", "body.v"), msd_exact(1.0, m=1, k=400, c=1, s0=0.01, f=-1.0),
                               atol=5e-7)
    assert np.max(np.abs(a.get("body.s", "body.v") - b.get("body.s", "body.v"))) > 0.05
    a.free()
    b.free()


def test_two_fmus_with_the_same_model_identifier_in_one_process(cache):
    """Builds of one block with different defaults share the identifier 'msd' (and the library
    name); loaded together, each runs its own code and defaults."""
    soft = Slave(fmus.build_fmu(msd_block(), cache_dir=cache, params={"k": 100.0}), "soft")
    hard = Slave(fmus.build_fmu(msd_block(), cache_dir=cache, params={"k": 250.0}), "hard")
    for _ in range(50):
        soft.step(0.02)
        hard.step(0.02)
    # Radau at h w = 0.2 and 0.32: errors ~1e-8 and ~1e-7; the two solutions differ by ~1e-2
    np.testing.assert_allclose(soft.get("body.s", "body.v"), msd_exact(1.0, m=1, k=100, c=2, s0=0.01), atol=1e-7)
    np.testing.assert_allclose(hard.get("body.s", "body.v"), msd_exact(1.0, m=1, k=250, c=2, s0=0.01), atol=1e-6)
    assert np.max(np.abs(soft.get("body.s", "body.v") - hard.get("body.s", "body.v"))) > 5e-3
    soft.free()
    hard.free()


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("case", ["stiff_radau", "msd_rk4", "lag_discrete"])
def test_rollback_is_bit_exact(case, version, cache):
    blk = CASES[case]()
    path = fmus.build_fmu(blk, fmi_version=version, cache_dir=cache)
    h = blk.sample_period or 1e-3
    names = [v.name for v in blk.outputs]
    uname = blk.inputs[0].name
    sl = Slave(path)
    sl.setn({uname: 0.7})
    for _ in range(10):
        sl.step(h)
    saved, t_saved = sl.get_state(), sl.t

    def continuation(s: Slave) -> np.ndarray:
        out = []
        for k in range(5):
            s.setn({uname: 0.1 * k})
            s.step(h)
            out.append(s.get(*names))
        return np.array(out)

    first = continuation(sl)
    sl.set_state(saved)
    sl.t = t_saved
    second = continuation(sl)
    assert np.array_equal(first, second)
    # a serialised state restored into another instance continues identically too
    blob = sl.serialize(saved)
    other = Slave(path, "other")
    other.set_state(other.deserialize(blob))
    other.t = t_saved
    assert np.array_equal(continuation(other), first)
    sl.free()
    other.free()


def test_state_from_another_fmu_is_refused(cache):
    a = Slave(fmus.build_fmu(msd_block(), cache_dir=cache))
    b = Slave(fmus.build_fmu(lag_block(), cache_dir=cache))
    blob = a.serialize(a.get_state())
    with pytest.raises(FMICallException):
        b.deserialize(blob)
    a.free()
    b.free()


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("how", ["set", "deserialize"])
def test_state_from_another_fmu_of_the_same_size_is_refused(cache, version, how):
    """The same mass-spring-damper built with RK4 in one and in two substeps: same variables, same
    state size, different GUID.  Only the GUID can tell their states apart, and it must.  (Not
    RK4 against Radau: a Radau FMU's state also holds its kept Newton factors, so its size differs.)"""
    a = Slave(fmus.build_fmu(msd_block(integrator="rk4"), fmi_version=version, cache_dir=cache), "a")
    logs: list = []
    b = Slave(fmus.build_fmu(msd_block(integrator="rk4", substeps=2), fmi_version=version, cache_dir=cache), "b",
              logs=logs)
    assert a.md.guid != b.md.guid
    state = a.get_state()
    blob = a.serialize(state)
    assert len(blob) == len(b.serialize(b.get_state()))  # the same size: no other check can refuse it
    with pytest.raises(FMICallException):
        b.set_state(state) if how == "set" else b.deserialize(blob)
    assert any("the FMU state was not made by this FMU" in m for _, m in logs), logs
    a.free()
    b.free()


# --- directional derivatives --------------------------------------------------------------------
@pytest.mark.parametrize("version", VERSIONS)
def test_directional_derivatives_are_the_analytic_partials(version, cache):
    sl = Slave(fmus.build_fmu(msd_block(m=2.0, k=50.0, c=3.0), fmi_version=version, cache_dir=cache))
    # a = (f - k s - c v) / m
    np.testing.assert_allclose(sl.derivative(["body.a"], ["f"], [1.0]), [0.5], rtol=1e-15)
    np.testing.assert_allclose(sl.derivative(["body.a", "body.s"], ["s", "v"], [1.0, 2.0]),
                               [-25.0 - 2 * 1.5, 1.0], rtol=1e-15)
    np.testing.assert_allclose(sl.derivative(["body.s", "body.v"], ["f"], [1.0]), [0.0, 0.0])
    sl.free()
    g = Slave(fmus.build_fmu(gain_block(2.5), fmi_version=version, cache_dir=cache))
    g.set(u=4.0)
    np.testing.assert_allclose(g.derivative(["y"], ["u", "K"], [1.0, 0.0]), [2.5])
    np.testing.assert_allclose(g.derivative(["y"], ["K"], [1.0]), [4.0])
    g.free()


# --- parameters and start values ----------------------------------------------------------------
@pytest.mark.parametrize("version", VERSIONS)
def test_tunable_parameter_change_takes_effect_at_the_next_step(version, cache):
    blk = msd_block(integrator="rk4", substeps=4)
    sl = Slave(fmus.build_fmu(blk, fmi_version=version, cache_dir=cache))
    st = I.Stepper(blk)
    p = blk.param_defaults.copy()
    x = np.asarray(st.start(p), dtype=float).ravel()
    for k in range(20):
        if k == 10:
            sl.set(k=250.0)
            p[1] = 250.0
        sl.step(5e-3)
        x, _ = st.step(x, [0.0], p, 5e-3)
    np.testing.assert_allclose(sl.get("body.s", "body.v"), x, rtol=1e-12, atol=1e-16)
    sl.free()


@pytest.mark.parametrize("version", VERSIONS)
def test_fixed_parameter_settable_only_until_initialization_ends(version, cache):
    path = fmus.build_fmu(gain_block(2.5), fmi_version=version, cache_dir=cache)
    sl = Slave(path, init=False)
    sl.initialize({"K": 4.0, "u": 2.0})
    assert sl.get("y")[0] == 8.0
    with pytest.raises(FMICallException) as exc:
        sl.set(K=5.0)
    assert exc.value.status == 3
    sl.free()


@pytest.mark.parametrize("version", VERSIONS)
def test_start_value_rules(version, cache):
    # calculated start (depends on s0): follows the parameter, cannot be set directly
    sl = Slave(fmus.build_fmu(msd_block(), fmi_version=version, cache_dir=cache), init=False)
    if sl.fmi3:
        sl.fmu.enterInitializationMode(startTime=0.0)
    else:
        sl.fmu.enterInitializationMode()
    sl.set(s0=0.25)
    assert sl.get("s")[0] == 0.25
    with pytest.raises(FMICallException):
        sl.set(s=0.3)
    with pytest.raises(FMICallException):
        sl.set(m=0.0)  # below the lower bound 1e-6
    sl.fmu.exitInitializationMode()
    assert sl.get("body.s")[0] == 0.25
    sl.free()
    # exact start: settable before the end of initialisation, not after
    lag = Slave(fmus.build_fmu(lag_block(), fmi_version=version, cache_dir=cache), init=False)
    lag.initialize({"y_state": 0.5})
    assert lag.get("y")[0] == 0.5
    with pytest.raises(FMICallException):
        lag.set(y_state=0.1)
    lag.free()


@pytest.mark.parametrize("version", VERSIONS)
def test_discrete_fmu_refuses_a_step_off_the_sample_grid(version, cache):
    sl = Slave(fmus.build_fmu(lag_block(Ts=0.01), fmi_version=version, cache_dir=cache))
    sl.step(0.03)
    with pytest.raises(FMICallException) as exc:
        sl.fmu.doStep(sl.t, 0.015)
    assert exc.value.status == 3
    sl.free()


# --- modelDescription -------------------------------------------------------------------------
@pytest.mark.parametrize("version", VERSIONS)
def test_model_structure_dependencies_and_units(version, cache):
    path = fmus.build_fmu(msd_block(), fmi_version=version, cache_dir=cache)
    md = fmpy.read_model_description(str(path))
    assert md.variableNamingConvention == "structured"
    deps = {u.variable.name: sorted(d.name for d in u.dependencies) for u in md.outputs}
    assert deps == {"body.s": ["s"], "body.v": ["v"], "body.a": ["f", "s", "v"]}
    init = {u.variable.name: sorted(d.name for d in u.dependencies) for u in md.initialUnknowns}
    # the position starts at s0 (calculated start); the velocity's start is exact, so v is a known
    assert init == {"body.s": ["s0"], "body.v": ["v"], "body.a": ["c", "f", "k", "m", "s0", "v"]}
    units = {u.name: u.baseUnit for u in md.unitDefinitions}
    assert (units["N.s/m"].kg, units["N.s/m"].m, units["N.s/m"].s) == (1, 0, -1)
    assert (units["m/s2"].m, units["m/s2"].s) == (1, -2)
    with zipfile.ZipFile(path) as zf:
        cs = ET.fromstring(zf.read("modelDescription.xml")).find("CoSimulation").attrib
    flags = (["canGetAndSetFMUstate", "canSerializeFMUstate", "providesDirectionalDerivative"] if version == "2.0"
             else ["canGetAndSetFMUState", "canSerializeFMUState", "providesDirectionalDerivatives"])
    assert all(cs[f] == "true" for f in flags + ["canHandleVariableCommunicationStepSize"])
    byname = {v.name: v for v in md.modelVariables}
    assert byname["k"].variability == "tunable" and byname["s"].initial == "calculated"


# --- the cache ------------------------------------------------------------------------------
def test_cache_hit_does_not_compile_and_overrides_change_the_key(cache, monkeypatch):
    first = fmus.build_fmu(msd_block(), cache_dir=cache)
    monkeypatch.setattr(fmus.build, "compile_library", lambda *a, **k: pytest.fail("compiled on a cache hit"))
    assert fmus.build_fmu(msd_block(), cache_dir=cache) == first
    monkeypatch.undo()
    other = fmus.build_fmu(msd_block(), cache_dir=cache, params={"k": 250.0})
    assert other != first
    md = fmpy.read_model_description(str(other))
    assert {v.name: v.start for v in md.modelVariables}["k"] in ("250.0", 250.0)
    rec = fmus.build_record(other)
    assert rec["block"] == "msd" and rec["compile_s"] > 0 and rec["parameters"]["k"] == 250.0


def test_concurrent_builds_of_one_block_agree(tmp_path):
    blk = lag_block(T=0.07)
    results: list[Path] = []
    threads = [threading.Thread(target=lambda: results.append(fmus.build_fmu(blk, cache_dir=tmp_path)))
               for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 2 and results[0] == results[1]
    assert validate_fmu(str(results[0])) == []
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".build-")]  # temp dirs cleaned


# --- malformed blocks fail before compiling ------------------------------------------------------
def _nan_output_block() -> Block:
    p, x, u = ca.SX.sym("p", 1), ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return Block.build("bad", params=[Param("a", 1.0)], inputs=[Var("u")], outputs=[Var("root")],
                       states=[Var("z")], p=p, u=u, x=x, ode=-x, out=ca.sqrt(x - p[0]), start=ca.DM([0.0]))


def _inf_start_block() -> Block:
    p, x, u = ca.SX.sym("p", 1), ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return Block.build("bad", params=[Param("tau", 0.0)], inputs=[Var("u")], outputs=[Var("y")],
                       states=[Var("z")], p=p, u=u, x=x, ode=-x, out=x, start=1.0 / p[0])


def _renamed(name: str, unit: str = "V") -> Block:
    p, x, u = ca.SX.sym("p", 1), ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return Block.build("bad", params=[Param("a", 1.0)], inputs=[Var("u")], outputs=[Var(name, unit)],
                       states=[Var("z")], p=p, u=u, x=x, ode=-x, out=x, start=ca.DM([0.0]))


def _none_with_states() -> Block:
    blk = msd_block()
    blk.integrator = "none"
    return blk


def _bad_block_name() -> Block:
    blk = lag_block()
    blk.name = "my-lag"
    return blk


MALFORMED = {
    "unknown override": (lambda: msd_block(), {"params": {"kk": 1.0}}, r"msd.*unknown parameter 'kk'"),
    "override out of bounds": (lambda: msd_block(), {"params": {"m": -1.0}}, r"msd.*'m' = -1.0 is outside"),
    "override not a number": (lambda: msd_block(), {"params": {"m": "heavy"}}, r"msd.*'m' = 'heavy' is not a number"),
    "override not finite": (lambda: msd_block(), {"params": {"c": math.inf}}, r"msd.*'c' = inf must be finite"),
    "non-finite start": (_inf_start_block, {}, r"bad.*start value of state 'z' is inf"),
    "NaN output at the start point": (_nan_output_block, {}, r"bad.*output 'root' is nan"),
    "not a structured name": (lambda: _renamed("leg 1"), {}, r"bad.*'leg 1' is not a structured FMI name"),
    "reserved name time": (lambda: _renamed("time"), {}, r"bad.*'time' clashes"),
    "unknown unit": (lambda: _renamed("y", "Nm"), {}, r"bad.*'y' has unit 'Nm'"),
    "none integrator with states": (_none_with_states, {}, r"msd.*integrator 'none' but 2 states"),
    "bad block name": (_bad_block_name, {}, r"my-lag.*C identifier"),
    "substeps not whole": (lambda: msd_block(integrator="rk4", substeps=2.5), {}, r"msd.*substeps must be a whole"),
    "bad FMI version": (lambda: msd_block(), {"fmi_version": "1.0"}, r"fmi_version '1.0'"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_block_fails_before_any_c_is_compiled(case, tmp_path, monkeypatch):
    make, kwargs, pattern = MALFORMED[case]
    monkeypatch.setattr(fmus.build, "compile_library", lambda *a, **k: pytest.fail("the compiler ran"))
    with pytest.raises(BuildError, match=pattern):
        fmus.build_fmu(make(), cache_dir=tmp_path, **kwargs)


# --- the CLI ------------------------------------------------------------------------------------
@pytest.fixture
def fake_catalog(monkeypatch):
    """A stand-in ``models.blocks`` with the test blocks, so the CLI is tested on its own."""
    mod = types.ModuleType("models.blocks")
    mod.catalog = lambda: {"msd": ["radau", "rk4"], "lag": ["default"]}

    def make(model, fidelity=None, **options):
        if model == "msd":
            return msd_block(integrator=fidelity or "radau", **options)
        return lag_block(**options)

    mod.make = make
    monkeypatch.setitem(sys.modules, "models.blocks", mod)
    # ``import models.blocks as b`` reads the attribute of the parent package first.
    import models
    monkeypatch.setattr(models, "blocks", mod, raising=False)
    return mod


def test_cli_build_with_overrides_and_list(fake_catalog, cache, tmp_path, capsys):
    from cosim import cli

    rc = cli.main(["fmu", "build", "msd", "--fidelity", "rk4", "--set", "k=250", "--set", "substeps=3",
                   "--fmi", "3", "--cache", str(cache), "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert rc == 0
    path = Path(out.strip())
    assert path.parent == tmp_path and path.is_file() and "[fmu] msd" in err
    md = fmpy.read_model_description(str(path))
    assert md.fmiVersion == "3.0" and {v.name: float(v.start) for v in md.modelVariables if v.start}["k"] == 250.0
    rc = cli.main(["fmu", "list", "--cache", str(cache)])
    out, _ = capsys.readouterr()
    assert rc == 0 and "radau, rk4" in out and "msd" in out and "cached FMUs" in out


@pytest.mark.parametrize("argv,message", [
    (["fmu", "build", "robot"], "unknown model 'robot'"),
    (["fmu", "build", "msd", "--fidelity", "euler"], "no fidelity 'euler'"),
    (["fmu", "build", "msd", "--set", "k"], "expected NAME=VALUE"),
    (["fmu", "build", "msd", "--set", "m=-2"], "parameter 'm' = -2.0 is outside"),
])
def test_cli_mistakes_are_one_line(fake_catalog, cache, capsys, argv, message):
    from cosim import cli

    rc = cli.main(argv + ["--cache", str(cache)])
    _, err = capsys.readouterr()
    assert rc == 2
    lines = [ln for ln in err.splitlines() if ln.startswith("rpr-cosim")]
    assert len(lines) == 1 and message in lines[0], err


# --- input slopes (FMI 2.0 canInterpolateInputs) ---------------------------------------------------
def ramp_solution(t: np.ndarray, f0: float, df: float, m=1.0, k=100.0, c=2.0, s0=0.01) -> np.ndarray:
    """``m s'' + c s' + k s = f0 + df t`` from (s0, 0), by SciPy at tight tolerances."""
    from scipy.integrate import solve_ivp

    sol = solve_ivp(lambda tt, y: [y[1], (f0 + df * tt - k * y[0] - c * y[1]) / m], (0, t[-1]), [s0, 0.0],
                    t_eval=t, rtol=1e-12, atol=1e-14, method="DOP853")
    return sol.y.T


@pytest.mark.parametrize("case", ["msd_radau", "msd_rk4"])
def test_input_slopes_make_a_ramp_input_exact_to_the_integrator_order(case, cache):
    """Driven by f = f0 + df t, one call of fmi2SetRealInputDerivatives per step makes the FMU
    follow the ramp inside the step: error against SciPy at the integrator's accuracy, where
    holding the input (its value at the step's start) is first-order wrong; and the FMU equals
    the CasADi step map with the same slope."""
    blk = CASES[case]()
    path = fmus.build_fmu(blk, fmi_version="2.0", cache_dir=cache)
    md = fmpy.read_model_description(str(path))
    assert md.coSimulation.canInterpolateInputs
    f0, df, h, n = 2.0, 30.0, 0.01, 50
    exact = ramp_solution(np.arange(n + 1) * h, f0, df)
    st, p = I.Stepper(blk), blk.param_defaults
    finals = {}
    for slopes in (True, False):
        sl = Slave(path)
        x = np.array([0.01, 0.0])  # msd_block's start (s0, 0)
        for k in range(n):
            sl.set(f=f0 + df * k * h)
            if slopes:
                sl.fmu.setRealInputDerivatives([sl.vr["f"]], [1], [df])
            sl.step(h)
            x, ok = st.step(x, [f0 + df * k * h], p, h, [df] if slopes else None)
            assert ok
        got = sl.get("body.s", "body.v")
        np.testing.assert_allclose(got, x, rtol=0, atol=1e-12)
        if slopes:
            assert sl.get("f")[0] == pytest.approx(f0 + df * n * h)  # the input followed the ramp to t_n
        finals[slopes] = np.abs(got - exact[-1]).max()
        sl.free()
    assert finals[True] < 1e-8 < 1e-5 < finals[False], finals


def test_input_slopes_are_refused_by_a_sampled_fmu_and_beyond_first_order(cache):
    lag = Slave(fmus.build_fmu(lag_block(), fmi_version="2.0", cache_dir=cache))
    assert not lag.md.coSimulation.canInterpolateInputs
    with pytest.raises(FMICallException):
        lag.fmu.setRealInputDerivatives([lag.vr["u"]], [1], [1.0])
    assert any("a sampled block reads its inputs at its samples" in m for _, m in lag.logs)
    msd = Slave(fmus.build_fmu(msd_block(integrator="radau"), fmi_version="2.0", cache_dir=cache))
    with pytest.raises(FMICallException):
        msd.fmu.setRealInputDerivatives([msd.vr["f"]], [2], [1.0])
    assert any("derivative order 2" in m for _, m in msd.logs)


def test_rollback_restores_the_input_slopes(cache):
    sl = Slave(fmus.build_fmu(msd_block(integrator="rk4", substeps=4), fmi_version="2.0", cache_dir=cache))
    sl.set(f=1.0)
    sl.fmu.setRealInputDerivatives([sl.vr["f"]], [1], [50.0])
    s = sl.get_state()
    sl.step(0.01)
    first = sl.get("body.s", "body.v", "f")
    sl.set_state(s)
    sl.t = 0.0
    sl.step(0.01)
    assert np.array_equal(sl.get("body.s", "body.v", "f"), first)
    sl.step(0.01)  # the slope was consumed: the next step holds f = 1.5
    assert sl.get("f")[0] == pytest.approx(1.5)
