"""Model-exchange FMUs (cosim.slaves.model_exchange): the Reference FMUs made model-exchange only
(their <CoSimulation> element dropped; with ``nostate`` also their FMU-state capability) run in
scenes against independent sources: Dahlquist against exp(-t), BouncingBall against its analytic
parabolas and impact times, VanDerPol and Stair against FMPy's own ModelExchange loop (CVODE) at
rtol 1e-10; rollback (FMU state, continuous states) against the unrolled run."""
from __future__ import annotations

import dataclasses
import math
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import UserError
from cosim.master.simulate import simulate
from cosim.master.system import CoupledSystem
from cosim.run.execute import run
from cosim.scenario import from_dict
from cosim.slaves import FmuSlave, ModelExchangeSlave, describe_fmu
from cosim.slaves.model_exchange import available

fmpy = pytest.importorskip("fmpy")
pytestmark = pytest.mark.skipif(bool(available()), reason=available() or "model exchange available")

MODELS = ("BouncingBall", "VanDerPol", "Dahlquist", "Stair")


def _me_only(src: Path, dst: Path, no_state: bool) -> Path:
    """A copy of ``src`` without its <CoSimulation> element (and without canGetAndSetFMUstate)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                xml = re.sub(r"<CoSimulation\b[^>]*?/>|<CoSimulation\b[^>]*[^/]>.*?</CoSimulation>", "",
                             data.decode(), flags=re.S)
                if no_state:
                    xml = re.sub(r'canGetAndSetFMU[sS]tate="true"', 'canGetAndSetFMUstate="false"', xml)
                    xml = xml.replace('canGetAndSetFMUstate="false"', 'canGetAndSetFMUState="false"') \
                        if 'fmiVersion="3.0"' in xml else xml
                data = xml.encode()
            zout.writestr(item, data)
    return dst


@pytest.fixture(scope="session")
def me_fmus(reference_fmus, tmp_path_factory) -> dict[str, Path]:
    """``{"2/BouncingBall": path, "3/VanDerPol_nostate": path, ...}``: model-exchange-only copies."""
    out = tmp_path_factory.mktemp("me")
    fmus = {}
    for v in ("2", "3"):
        for m in MODELS:
            for suffix, no_state in (("", False), ("_nostate", True)):
                fmus[f"{v}/{m}{suffix}"] = _me_only(reference_fmus[f"{v}.0/{m}"], out / f"{m}{v}{suffix}.fmu", no_state)
    return fmus


def _scene(fmu: Path, step: float, stop: float, outputs, master: dict | None = None, **comp):
    master = master or {"algorithm": "jacobi", "step": step}
    return from_dict({"name": "me", "components": {"m": {"fmu": str(fmu), **comp}}, "master": master,
                      "stop_time": stop, "outputs": [f"m.{o}" for o in outputs]})


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    """Worst difference relative to the reference's range."""
    return float(np.max(np.abs(a - b)) / max(np.ptp(b), 1e-300))


def bouncing_ball(t: np.ndarray, h0=1.0, e=0.7, g=9.81, v_min=0.1):
    """The Reference FMU's BouncingBall in closed form: height, velocity at ``t`` and the impact
    times (the ball rests once it would rebound slower than v_min)."""
    flights, impacts = [(0.0, h0, 0.0)], []
    tk = math.sqrt(2 * h0 / g)
    v_in = g * tk
    while True:
        impacts.append(tk)
        v_up = e * v_in
        if v_up < v_min:
            flights.append((tk, 0.0, None))
            break
        flights.append((tk, 0.0, v_up))
        tk, v_in = tk + 2 * v_up / g, v_up
    starts = np.array([f[0] for f in flights])
    h, v = np.zeros_like(t), np.zeros_like(t)
    for i, ti in enumerate(t):
        t0, hk, vk = flights[int(np.searchsorted(starts, ti, side="right")) - 1]
        if vk is not None:
            dt = ti - t0
            h[i], v[i] = hk + vk * dt - g / 2 * dt * dt, vk - g * dt
    return h, v, impacts


@pytest.mark.parametrize("v", ["2", "3"])
def test_model_exchange_only_is_described_and_refused_nowhere(me_fmus, v):
    d = describe_fmu(me_fmus[f"{v}/BouncingBall"])
    assert (d.interface, d.continuous_states, d.event_indicators, d.rollback_through) == ("model exchange", 2, 1,
                                                                                         "FMU state")
    assert describe_fmu(me_fmus[f"{v}/VanDerPol_nostate"]).rollback_through == "continuous states"
    stair = describe_fmu(me_fmus[f"{v}/Stair_nostate"])
    assert stair.discrete_states == ("counter",) and stair.rollback_through == "" and not stair.can_get_set_state


@pytest.mark.parametrize("v", ["2", "3"])
@pytest.mark.parametrize("rtol,tol", [(1e-10, 1e-6), (None, 1e-3)])
def test_dahlquist_against_the_exponential(me_fmus, v, rtol, tol):
    res = run(_scene(me_fmus[f"{v}/Dahlquist"], 0.1, 10.0, ["x"], **({"rtol": rtol} if rtol else {})))
    assert res.status == "ok", res.reason
    assert _rel(res.trace["m.x"], np.exp(-res.trace.time)) < tol


@pytest.mark.parametrize("v", ["2", "3"])
@pytest.mark.parametrize("rtol,tol", [(1e-10, 1e-6), (None, 1e-3)])
def test_bouncing_ball_against_its_parabolas(me_fmus, v, rtol, tol):
    res = run(_scene(me_fmus[f"{v}/BouncingBall"], 0.01, 3.0, ["h", "v"], **({"rtol": rtol} if rtol else {})))
    assert res.status == "ok", res.reason
    h, vel, impacts = bouncing_ball(res.trace.time)
    assert _rel(res.trace["m.h"], h) < tol and _rel(res.trace["m.v"], vel) < tol
    me = res.stats["model_exchange"]["m"]  # the sidecar: the slave's solver figures and its events
    assert me["state_events"] == 11 and me["solver_steps"] > 100
    assert np.max(np.abs(np.array([t for t, _ in me["events"]]) - impacts)) < 1e3 * tol


@pytest.mark.parametrize("v", ["2", "3"])
def test_bouncing_ball_impacts_within_a_nanosecond(me_fmus, v):
    """The slave's own event log (CVODES's roots) against the analytic impact times."""
    path = me_fmus[f"{v}/BouncingBall"]
    slave = ModelExchangeSlave("ball", path, dataclasses.replace(describe_fmu(path), solver_rtol=1e-12))
    system = CoupledSystem([slave], [], [(0, "h")])
    stats = simulate(system, "jacobi", step_ns=10_000_000, n_steps=300)
    assert stats.status == "ok", stats.reason
    found = [t for t, kind in slave.events() if kind == "state event"]
    _, _, impacts = bouncing_ball(np.array([0.0]))
    assert len(found) == len(impacts) == 11
    assert max(abs(a - b) for a, b in zip(found, impacts)) < 1e-9


def _fmpy_me(path: Path, stop: float, interval: float, names):
    return fmpy.simulate_fmu(str(path), fmi_type="ModelExchange", relative_tolerance=1e-10,
                             output_interval=interval, stop_time=stop, output=list(names))


@pytest.mark.parametrize("v", ["2", "3"])
@pytest.mark.parametrize("rtol,tol", [(1e-10, 1e-6), (None, 1e-3)])
def test_vanderpol_against_fmpy(me_fmus, v, rtol, tol):
    path = me_fmus[f"{v}/VanDerPol"]
    res = run(_scene(path, 0.01, 20.0, ["x0", "x1"], **({"rtol": rtol} if rtol else {})))
    ref = _fmpy_me(path, 20.0, 0.01, ["x0", "x1"])
    assert res.status == "ok", res.reason
    np.testing.assert_allclose(res.trace.time, ref["time"], atol=1e-12)
    for n in ("x0", "x1"):
        assert _rel(res.trace[f"m.{n}"], ref[n]) < tol, n


@pytest.mark.parametrize("v", ["2", "3"])
def test_stair_against_fmpy_event_for_event(me_fmus, v):
    """Time events: the counter at each communication point is FMPy's value after the event
    there (FMPy writes two rows at an event); the FMU ends the run at t = 9 s, where its counter
    became 10 (FMPy stops on terminateSimulation before writing that row: it has 9 there)."""
    path = me_fmus[f"{v}/Stair"]
    res = run(_scene(path, 0.2, 10.0, ["counter"]))
    ref = _fmpy_me(path, 10.0, 0.2, ["counter"])
    assert res.status == "stopped" and "at t = 9 s" in res.reason, res.reason
    after = {}
    for t, c in zip(ref["time"], ref["counter"]):
        after[round(t, 9)] = c  # the later of two rows at one time: after the event
    ours = dict(zip(np.round(res.trace.time, 9), res.trace["m.counter"]))
    assert sorted(ours) == sorted(after)
    assert all(ours[t] == after[t] for t in ours if t < 9.0)
    assert (ours[9.0], after[9.0]) == (10, 9)


@pytest.mark.parametrize("v", ["2", "3"])
@pytest.mark.parametrize("model,stop,outputs,nostate", [
    ("VanDerPol", 5.0, ["x0", "x1"], ""), ("VanDerPol", 5.0, ["x0", "x1"], "_nostate"),
    ("Dahlquist", 5.0, ["x"], ""), ("Dahlquist", 5.0, ["x"], "_nostate"),
    ("BouncingBall", 2.0, ["h", "v"], ""),  # without FMU state: its stop is a hidden discrete state (next test)
])
def test_rollback_reproduces_the_step(me_fmus, v, model, stop, outputs, nostate):
    """save, step, restore, step again: the same outputs to the bit (FMU state, or continuous
    states where the FMU declares none), through the scene's adaptive master too."""
    path = me_fmus[f"{v}/{model}{nostate}"]
    slave = FmuSlave("m", path)
    assert isinstance(slave, ModelExchangeSlave) and slave.can_rollback
    system = CoupledSystem([slave], [], [(0, n) for n in outputs])
    slave.instantiate()
    slave.set_start({})
    system.bind()
    slave.enter_initialization(0.0, stop)
    slave.exit_initialization()
    t, h = 0.0, 0.05
    while t < stop - 1e-9:
        slave.save_state()
        assert slave.do_step(t, h) == 0
        slave.pull()
        first = system.v.copy()
        slave.restore_state()
        assert slave.do_step(t, h) == 0
        slave.pull()
        assert np.array_equal(system.v, first), t
        t += h
    slave.terminate()
    slave.release()
    res = run(_scene(path, 0.01, stop, outputs, {"algorithm": "adaptive", "step": 0.01}))
    assert res.status == "ok", res.reason


@pytest.mark.parametrize("v", ["2", "3"])
def test_a_hidden_discrete_state_stops_a_rollback_through_continuous_states(me_fmus, v):
    """BouncingBall sets its gravity to 0 when it comes to rest (an undeclared discrete state):
    restoring its continuous states across that instant is refused, naming the derivative."""
    slave = FmuSlave("ball", me_fmus[f"{v}/BouncingBall_nostate"])
    assert slave.description.rollback_through == "continuous states"
    system = CoupledSystem([slave], [], [(0, "h")])
    slave.instantiate()
    slave.set_start({})
    system.bind()
    slave.enter_initialization(0.0, 3.0)
    slave.exit_initialization()
    assert slave.do_step(0.0, 2.4) == 0
    slave.save_state()
    assert slave.do_step(2.4, 0.2) == 0  # the ball comes to rest at 2.499 s
    with pytest.raises(UserError, match=r"ball: restoring the state failed \(rollback through the continuous states: "
                                        r"at t = 2.4 s the derivative of state 1 is 0, -9.81"):
        slave.restore_state()
    slave.release()


def test_an_fmu_with_both_interfaces_runs_as_asked(reference_fmus):
    path = reference_fmus["3.0/VanDerPol"]
    res = run(_scene(path, 0.01, 2.0, ["x0"], interface="model_exchange", rtol=1e-10))
    ref = _fmpy_me(path, 2.0, 0.01, ["x0"])
    assert res.status == "ok" and _rel(res.trace["m.x0"], ref["x0"]) < 1e-6
    with pytest.raises(Exception, match=r"interface = 'me'; expected co_simulation or model_exchange"):
        _scene(path, 0.01, 2.0, ["x0"], interface="me")
    with pytest.raises(Exception, match=r"rtol applies to a model-exchange FMU"):
        _scene(path, 0.01, 2.0, ["x0"], rtol=1e-8)


@pytest.mark.parametrize("name,says", [
    ("3/Stair_nostate", ["model exchange: integrated by SUNDIALS CVODES", "0 continuous state(s)",
                         "no rollback (no FMU state, and discrete variable(s) counter)", "[a scene gets this one]"]),
    ("2/VanDerPol_nostate", ["rollback through its continuous states", "2 continuous state(s)"]),
    ("2/BouncingBall", ["1 event indicator(s): state events located by CVODES's root finding",
                        "rollback through its FMU state plus a solver restart"]),
])
def test_fmu_check_says_how_a_model_exchange_fmu_runs(me_fmus, capsys, name, says):
    from cosim import cli

    assert cli.main(["fmu", "check", str(me_fmus[name])]) == 0
    out = capsys.readouterr().out
    assert "co-simulation:" not in out
    for text in says:
        assert text in out, text


def test_fmu_check_of_both_interfaces_names_the_default_and_the_other(reference_fmus, capsys):
    from cosim import cli

    assert cli.main(["fmu", "check", str(reference_fmus["3.0/Stair"])]) == 0
    out = capsys.readouterr().out
    assert "co-simulation: stepped by doStep" in out
    assert "declares event mode: under jacobi, gauss_seidel, adaptive, ecco and iterative" in out
    assert "[a scene gets this one]" in out.split("model exchange:")[0]
    assert "[interface: model_exchange]" in out.split("model exchange:")[1]


# --- a coupled pair of model-exchange FMUs in a loop ---------------------------------------------------
#: a: der(x) = -x - u, b: der(x) = -2 x + u, a.x -> b.u, b.x -> a.u: the monolithic x' = A x, x(0) = (1, 0)
PAIR_A = np.array([[-1.0, -1.0], [1.0, -2.0]])


def _pair(fmu: Path, master: dict, stop: float):
    return from_dict({"name": "pair", "components": {
        "a": {"fmu": str(fmu), "params": {"k": 1.0, "g": -1.0}, "start": {"x": 1.0}},
        "b": {"fmu": str(fmu), "params": {"k": 2.0, "g": 1.0}}},
        "connections": ["a.x -> b.u", "b.x -> a.u"], "master": master, "stop_time": stop, "outputs": ["a.x", "b.x"]})


def _monolithic_error(res) -> float:
    from scipy.linalg import expm

    ref = np.array([expm(PAIR_A * t) @ [1.0, 0.0] for t in res.trace.time])
    return max(_rel(res.trace["a.x"], ref[:, 0]), _rel(res.trace["b.x"], ref[:, 1]))


@pytest.mark.parametrize("v", ["2", "3"])
def test_a_loop_of_two_model_exchange_fmus_against_the_monolithic_solution(lag_fmus, v):
    res = run(_pair(lag_fmus[v], {"algorithm": "gauss_seidel", "step": 1e-3, "estimate": False}, 2.0))
    assert res.status == "ok", res.reason
    assert _monolithic_error(res) < 1e-3
    res = run(_pair(lag_fmus[v], {"algorithm": "adaptive", "step": 0.01, "estimate": False}, 0.1))
    assert res.status == "ok", res.reason
    assert _monolithic_error(res) < 1e-3


@pytest.mark.parametrize("v", ["2", "3"])
def test_iterative_rollback_through_fmu_state_and_through_continuous_states_agree(lag_fmus, v):
    """The iterative master rolls every step back until the loop converges: restoring the FMU
    state and restoring the continuous states (the FMU-state capability removed from the XML)
    give the same run to the bit, close to the monolithic solution."""
    master = {"algorithm": "iterative", "step": 0.01, "estimate": False}
    with_state = run(_pair(lag_fmus[v], master, 2.0))
    through_x = run(_pair(lag_fmus[f"{v}_nostate"], master, 2.0))
    assert with_state.status == through_x.status == "ok", (with_state.reason, through_x.reason)
    assert with_state.stats["rollbacks"] > 100
    assert np.array_equal(with_state.trace.data, through_x.trace.data)
    assert _monolithic_error(through_x) < 1e-2


@pytest.mark.parametrize("v", ["2", "3"])
@pytest.mark.parametrize("fault,last,says", [
    (1, 0.5, r"a returned DISCARD in the step from t = 0.5 s .*CVODES failed at t = 0.5\d* s .*the derivative of "
             r"continuous state 0 is nan at t = 0.5"),
    (2, 0.5, r"a returned ERROR in the step from t = 0.5 s .*more than 1000 events in one communication step "
             r"\[0.5, 0.51\] s \(chattering\)"),
    (3, 0.49, r"a returned ERROR in the step from t = 0.49 s .*the event iteration at t = 0.5 s did not settle in "
              r"100 rounds"),
    (4, 0.5, r"a returned DISCARD in the step from t = 0.5 s .*event indicator 0 is nan at t = 0.5"),
])
def test_a_misbehaving_model_exchange_fmu_ends_the_run_naming_it(lag_fmus, v, fault, last, says):
    """NaN derivatives, chattering, an event iteration that does not settle, a NaN indicator: the
    run ends with the component, the time and what happened (tests/data/me_lag's fault parameter)."""
    scene = from_dict({"name": "bad", "components": {"a": {"fmu": str(lag_fmus[v]), "params": {"fault": fault},
                                                           "start": {"x": 1.0}}},
                       "master": {"algorithm": "jacobi", "step": 0.01, "estimate": False}, "stop_time": 1.0,
                       "outputs": ["a.x"]})
    res = run(scene)
    assert res.status == "failed"
    assert re.search(says, res.reason), res.reason
    assert res.trace.time[-1] == pytest.approx(last)  # the partial trace up to the last good point


def test_run_check_says_how_a_model_exchange_component_runs(me_fmus, tmp_path, capsys):
    from cosim import cli

    scene = tmp_path / "ball.yaml"
    scene.write_text(f"name: ball\ncomponents:\n  ball: {{fmu: {me_fmus['3/VanDerPol_nostate']}, rtol: 1e-9}}\n"
                     f"master: {{algorithm: adaptive, step: 0.01}}\nstop_time: 1\noutputs: [ball.x0]\n")
    assert cli.main(["run", str(scene), "--check"]) == 0
    out = capsys.readouterr().out
    assert ("model exchange, integrated by CVODES (rtol 1e-09); 2 continuous state(s), 0 event indicator(s); its "
            "events are handled inside its steps and reach the other components at the next communication point; "
            "rollback through its continuous states") in out


SSD_ME = """<?xml version="1.0" encoding="UTF-8"?>
<ssd:SystemStructureDescription xmlns:ssd="http://ssp-standard.org/SSP1/SystemStructureDescription"
    xmlns:ssc="http://ssp-standard.org/SSP1/SystemStructureCommon" version="1.0" name="vdp">
  <ssd:System name="Root">
    <ssd:Elements>
      <ssd:Component name="m" source="resources/vdp.fmu" implementation="{implementation}">
        <ssd:Connectors>
          <ssd:Connector name="x0" kind="output"><ssc:Real/></ssd:Connector>
        </ssd:Connectors>
      </ssd:Component>
    </ssd:Elements>
  </ssd:System>
  <ssd:DefaultExperiment startTime="0.0" stopTime="2.0"/>
</ssd:SystemStructureDescription>
"""


@pytest.mark.parametrize("implementation,interface", [("ModelExchange", "model exchange"),
                                                      ("CoSimulation", "co-simulation")])
def test_an_ssp_component_runs_through_the_implementation_it_names(reference_fmus, tmp_path, implementation,
                                                                   interface):
    from cosim.scenario import load

    path = tmp_path / "vdp.ssp"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("SystemStructure.ssd", SSD_ME.format(implementation=implementation))
        z.write(reference_fmus["2.0/VanDerPol"], "resources/vdp.fmu")
    scene = load(path, {"outputs": ["m.x0"], "master": {"algorithm": "jacobi", "step": 0.01}})
    assert scene.components["m"].description.interface == interface
    res = run(scene)
    assert res.ok, res.reason
    if interface == "model exchange":
        ref = _fmpy_me(reference_fmus["2.0/VanDerPol"], 2.0, 0.01, ["x0"])
        assert _rel(res.trace["m.x0"], ref["x0"]) < 1e-3
        assert "model_exchange" in res.stats


@pytest.mark.parametrize("v", ["2", "3"])
def test_the_compiled_loops_step_a_model_exchange_fmu_as_the_python_loop_does(me_fmus, lag_fmus, v):
    """The slave's C entry points in the compiled master loops: the same trace to the bit (Jacobi
    on VanDerPol; adaptive, which saves and restores states in C, on the loop of two lags)."""
    runs = {}
    for engine in ("oracle", "compiled"):
        res = run(_scene(me_fmus[f"{v}/VanDerPol"], 0.01, 5.0, ["x0", "x1"],
                         {"algorithm": "jacobi", "step": 0.01, "engine": engine, "estimate": False}))
        assert res.status == "ok" and res.stats["engine"] == engine, res.reason
        runs[engine] = res.trace.data
    assert np.array_equal(runs["oracle"], runs["compiled"])
    for engine in ("oracle", "compiled"):
        res = run(_pair(lag_fmus[v], {"algorithm": "adaptive", "step": 0.01, "engine": engine, "estimate": False},
                        0.05))
        assert res.status == "ok" and res.stats["engine"] == engine, res.reason
        runs[engine] = res.trace.data
    assert np.array_equal(runs["oracle"], runs["compiled"])


@pytest.mark.parametrize("v", ["2", "3"])
def test_fmu_check_flags_a_derivative_that_names_no_state(me_fmus, tmp_path, capsys, v):
    """The standard: every derivative of <ModelStructure> names its continuous state (derivative=).
    VanDerPol with that attribute dropped from der(x0): fmu check counts the departure."""
    from cosim import cli

    src, dst = me_fmus[f"{v}/VanDerPol"], tmp_path / "bad.fmu"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                xml = data.decode()
                i = xml.index('name="der(x0)"')
                head, tail = xml[:i], xml[i:]
                tail = re.sub(r'\s*derivative="\d+"', "", tail, count=1)
                data = (head + tail).encode()
            zout.writestr(item, data)
    assert cli.main(["fmu", "check", str(me_fmus[f"{v}/VanDerPol"])]) == 0
    capsys.readouterr()
    assert cli.main(["fmu", "check", str(dst)]) >= 1
    out = capsys.readouterr()
    assert "derivative 'der(x0)' names no state (no derivative= attribute)" in out.out


@pytest.mark.parametrize("v", ["2", "3"])
def test_the_adaptive_kernel_rolls_back_a_slave_without_fmu_state_as_the_oracle_does(me_fmus, v):
    """A model-exchange FMU without FMU state rolls back through its continuous states, in Python:
    the adaptive kernel calls it back (its trampolines around its own save/restore) and takes the
    oracle's steps to the bit, rejections included."""
    runs = {}
    for engine in ("oracle", "compiled"):
        res = run(_scene(me_fmus[f"{v}/VanDerPol_nostate"], 0.01, 5.0, ["x0", "x1"],
                         {"algorithm": "adaptive", "step": 0.01, "engine": engine, "estimate": False}))
        assert res.status == "ok" and res.stats["engine"] == engine, res.reason
        runs[engine] = res
    py, cc = runs["oracle"], runs["compiled"]
    assert np.array_equal(py.trace.time, cc.trace.time) and np.array_equal(py.trace.data, cc.trace.data)
    assert py.stats["accepted_steps"] == cc.stats["accepted_steps"] > 10
    assert py.stats["rejected_steps"] == cc.stats["rejected_steps"]
