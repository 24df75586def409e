"""SSP 1.0 export and import: schema validity (FMPy's reader and the SSP schemas), bit-identical
round trips, FMPy's own SSP master on our export, a hand-written SSP in another tool's
conventions, and one-line refusals of malformed archives."""
from __future__ import annotations

import shutil
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from cosim.cli import main
from cosim.errors import UserError
from cosim.run.execute import build_components, run
from cosim.scenario import SceneError, load
from cosim.scenario.ssp_archive import SSD
from cosim.run.ssp_export import export

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"


@pytest.fixture(scope="module")
def pid_ssp(cache, tmp_path_factory):
    return export(load(SCENES / "pid_step.yaml"), tmp_path_factory.mktemp("ssp") / "pid_step.ssp", cache_dir=cache)


def test_export_validates_against_the_ssp_schemas(pid_ssp):
    from fmpy.ssp.ssd import read_ssd, read_ssv

    ssd = read_ssd(str(pid_ssp), validate=True)  # FMPy's reader, against the SSP 1.0 XSD it ships
    names = {c.name for c in ssd.system.elements}
    assert names == {"target", "pid1", "pid2", "pid3", "motor1", "motor2", "motor3", "mech"}
    # 9 signals + 3 bonds as two signals each
    assert len(ssd.system.connections) == 15
    ps = read_ssv(str(pid_ssp), resource="resources/pid_step.ssv", validate=True)
    values = {p.name: (float(p.value), p.unit) for p in ps.parameters}
    assert values["pid1.Kp"] == (30.0, "V/m") and values["mech.leg[2].m_act"] == (0.058, "kg")
    with zipfile.ZipFile(pid_ssp) as zf:  # one FMU per distinct binary
        assert sorted(n for n in zf.namelist() if n.endswith(".fmu")) == [
            "resources/dc_motor_full.fmu", "resources/mechanism_rigid.fmu", "resources/pid_continuous.fmu",
            "resources/pose_setpoint_default.fmu"]


def test_export_refuses_to_overwrite(pid_ssp, cache):
    with pytest.raises(UserError, match="exists"):
        export(load(SCENES / "pid_step.yaml"), pid_ssp, cache_dir=cache)


@pytest.mark.parametrize("scene, stop", [("pid_step", 0.3), ("vw_compare", 0.05)])
def test_round_trip_is_bit_identical(scene, stop, cache, tmp_path):
    gs = {"master.algorithm": "gauss_seidel"}  # an SSP carries a named algorithm, not a tolerance's choice
    sc = load(SCENES / f"{scene}.yaml", gs)
    path = export(sc, tmp_path / f"{scene}.ssp", cache_dir=cache)
    direct = run(SCENES / f"{scene}.yaml", {"stop_time": stop, **gs}, cache_dir=cache)
    back = run(path, {"stop_time": stop}, cache_dir=cache)
    assert back.scene.master == direct.scene.master and back.scene.outputs == direct.scene.outputs
    assert direct.status == back.status and direct.status in ("ok", "inaccurate")  # GS at 1 ms: judged alike
    assert back.trace.names == direct.trace.names
    assert np.array_equal(back.trace.data, direct.trace.data)


def test_a_scene_that_names_no_algorithm_travels_as_its_tolerance(cache, tmp_path):
    """pid_step names no algorithm: its SSP carries the tolerance, not the fixed-step placeholder,
    so a run of the SSP chooses as a run of the scene does (same choice, same trace to the bit),
    and a tighter tolerance travels too."""
    sc = load(SCENES / "pid_step.yaml", {"master.tolerance": 3e-3})
    assert sc.master.auto
    path = export(sc, tmp_path / "pid_step.ssp", cache_dir=cache)
    back = load(path)
    assert back.master.auto and back.master.tolerance == 3e-3 and back.master.inputs_given == sc.master.inputs_given
    direct = run(SCENES / "pid_step.yaml", {"stop_time": 0.2, "master.tolerance": 3e-3}, cache_dir=cache)
    again = run(path, {"stop_time": 0.2}, cache_dir=cache)
    assert direct.ok and again.ok
    assert direct.stats["choice"]["algorithm"] == again.stats["choice"]["algorithm"] == "adaptive"
    assert direct.stats["choice"]["settings"] == again.stats["choice"]["settings"]
    assert np.array_equal(again.trace.data, direct.trace.data)


def _fmpy_with_initial_exchange(monkeypatch):
    """FMPy's simulate_ssp starts every connector at 0.0 and does no initial exchange; hand it the
    exchange our master does (inputs from the sources' outputs at t0, repeated until feedthrough
    chains settle), then let FMPy's own loop step."""
    import fmpy.ssp.simulation as sim

    seen = {"conns": [], "comps": []}
    get_connections, instantiate = sim.get_connections, sim.instantiate_fmu

    def connections(system):
        seen["conns"] = get_connections(system)
        seen["n"] = len(sim.find_components(system))
        return seen["conns"]

    def inst(component, *args, **kwargs):
        instantiate(component, *args, **kwargs)
        seen["comps"].append(component)
        if len(seen["comps"]) < seen["n"]:
            return
        for _ in seen["comps"]:
            for c in seen["comps"]:
                for con in c.connectors:
                    if con.kind == "output":
                        con.value = sim.get_value(c, con.name)
            for a, b in seen["conns"]:
                b.value = a.value
            for c in seen["comps"]:
                for con in c.connectors:
                    if con.kind == "input":
                        sim.set_value(c, con.name, con.value)

    monkeypatch.setattr(sim, "get_connections", connections)
    monkeypatch.setattr(sim, "instantiate_fmu", inst)
    return sim


def test_fmpy_simulates_our_export_like_our_jacobi(pid_ssp, cache, monkeypatch):
    """FMPy's loop is Jacobi with held inputs; its row stamped t_k holds the values after the step
    [t_k, t_k+1], so its row k is our row k+1.  With the initial exchange handed over, the two
    agree to the last bit."""
    from fmpy.ssp.ssd import read_ssv

    sim = _fmpy_with_initial_exchange(monkeypatch)
    params = read_ssv(str(pid_ssp), resource="resources/pid_step.ssv")
    res = sim.simulate_ssp(str(pid_ssp), stop_time=0.2, step_size=1e-3, parameter_set=params)
    ours = run(SCENES / "pid_step.yaml", {"stop_time": 0.2, "master.algorithm": "jacobi", "master.inputs": "hold",
                                          "outputs": ["mech.*", "pid*", "motor*", "target.leg[*].s"]}, cache_dir=cache)
    assert len(res) == 200 and len(ours.trace.names) == 51
    worst = max(np.abs(ours.trace[n][1:] - res[n]).max() for n in ours.trace.names)
    assert worst <= 1e-12


def test_fmpy_without_initial_exchange_starts_from_zero_inputs(pid_ssp):
    """Why the alignment above is needed: untouched, FMPy's first step sees every input at 0.0, so
    the PID's first output is 0 where ours (fed the setpoint step at t0) saturates at 12 V."""
    from fmpy.ssp.simulation import simulate_ssp
    from fmpy.ssp.ssd import read_ssv

    params = read_ssv(str(pid_ssp), resource="resources/pid_step.ssv")
    res = simulate_ssp(str(pid_ssp), stop_time=0.003, step_size=1e-3, parameter_set=params)
    assert res["pid1.y"][0] == 0.0 and res["pid1.y"][1] == 12.0


# --- an SSP in another tool's conventions, written by hand to the schema -----------------------
FOREIGN_SSD = """<?xml version="1.0" encoding="UTF-8"?>
<ssd:SystemStructureDescription xmlns:ssd="http://ssp-standard.org/SSP1/SystemStructureDescription"
    xmlns:ssc="http://ssp-standard.org/SSP1/SystemStructureCommon"
    xmlns:ssv="http://ssp-standard.org/SSP1/SystemStructureParameterValues" version="1.0" name="foreign">
  <ssd:System name="Root">
    <ssd:ParameterBindings>
      <ssd:ParameterBinding prefix="sp.">
        <ssd:ParameterValues>
          <ssv:ParameterSet version="1.0" name="setpoint">
            <ssv:Parameters>
              <ssv:Parameter name="x1"><ssv:Real value="-200" unit="mm"/></ssv:Parameter>
            </ssv:Parameters>
          </ssv:ParameterSet>
        </ssd:ParameterValues>
      </ssd:ParameterBinding>
    </ssd:ParameterBindings>
    <ssd:Elements>
      <ssd:Component name="sp" source="resources/setpoint.fmu">
        <ssd:Connectors>
          <ssd:Connector name="leg[1].s" kind="output"><ssc:Real unit="m"/></ssd:Connector>
        </ssd:Connectors>
      </ssd:Component>
      <ssd:Component name="ctl" source="resources/pid.fmu">
        <ssd:Connectors>
          <ssd:Connector name="setpoint" kind="input"><ssc:Real unit="mm"/></ssd:Connector>
          <ssd:Connector name="y" kind="output"><ssc:Real/></ssd:Connector>
        </ssd:Connectors>
        <ssd:ParameterBindings>
          <ssd:ParameterBinding source="resources/ctl.ssv"/>
        </ssd:ParameterBindings>
      </ssd:Component>
    </ssd:Elements>
    <ssd:Connections>
      <ssd:Connection startElement="sp" startConnector="leg[1].s" endElement="ctl" endConnector="setpoint">
        <ssc:LinearTransformation factor="2.0" offset="5.0"/>
      </ssd:Connection>
    </ssd:Connections>
  </ssd:System>
  <ssd:Units>
    <ssc:Unit name="mm"><ssc:BaseUnit m="1" factor="0.001"/></ssc:Unit>
    <ssc:Unit name="m"><ssc:BaseUnit m="1"/></ssc:Unit>
  </ssd:Units>
  <ssd:DefaultExperiment startTime="0.0" stopTime="0.01"/>
</ssd:SystemStructureDescription>
"""
FOREIGN_SSV = """<?xml version="1.0" encoding="UTF-8"?>
<ssv:ParameterSet xmlns:ssv="http://ssp-standard.org/SSP1/SystemStructureParameterValues"
    xmlns:ssc="http://ssp-standard.org/SSP1/SystemStructureCommon" version="1.0" name="ctl">
  <ssv:Parameters>
    <ssv:Parameter name="Kp"><ssv:Real value="0.5" unit="V/mm"/></ssv:Parameter>
    <ssv:Parameter name="Ki"><ssv:Real value="0"/></ssv:Parameter>
    <ssv:Parameter name="Kd"><ssv:Real value="0"/></ssv:Parameter>
    <ssv:Parameter name="u_max"><ssv:Real value="1000"/></ssv:Parameter>
    <ssv:Parameter name="measurement"><ssv:Real value="0.1"/></ssv:Parameter>
  </ssv:Parameters>
  <ssv:Units>
    <ssc:Unit name="V/mm"><ssc:BaseUnit kg="1" m="1" s="-3" A="-1" factor="1000"/></ssc:Unit>
  </ssv:Units>
</ssv:ParameterSet>
"""


@pytest.fixture(scope="module")
def foreign_fmus(cache):
    sc = load(SCENES / "pid_step.yaml")
    paths = build_components(sc, cache_dir=cache)
    return {"setpoint.fmu": paths["target"], "pid.fmu": paths["pid1"]}


def _archive(path: Path, fmus: dict[str, Path], ssd: str | None = FOREIGN_SSD, ssv: str = FOREIGN_SSV) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        if ssd is not None:
            zf.writestr(SSD, ssd)
        zf.writestr("resources/ctl.ssv", ssv)
        for name, src in fmus.items():
            zf.write(src, f"resources/{name}")
    return path


def test_foreign_ssp_runs_with_its_parameters_units_and_transformation(foreign_fmus, tmp_path):
    from fmpy.ssp.ssd import read_ssd

    path = _archive(tmp_path / "foreign.ssp", foreign_fmus)
    read_ssd(str(path), validate=True)  # the hand-written file is valid SSP 1.0 by FMPy's reader
    sc = load(path, {"outputs": ["sp.leg[1].s", "sp.x1", "ctl.y", "ctl.Kp", "ctl.setpoint"]})
    assert sc.master.algorithm == "jacobi" and any("no org.rpr-cosim.master" in str(w) for w in sc.warnings)
    res = run(sc)
    assert res.ok
    tr = res.trace
    assert np.all(tr["sp.x1"] == -0.2)  # -200 mm through the system-level binding with prefix
    assert np.all(tr["ctl.Kp"] == 500.0)  # 0.5 V/mm from the external .ssv, in the FMU's V/m
    # setpoint [mm] = 2 * (s [m] -> mm) + 5 mm, so the FMU sees 2 s + 0.005 m; y = Kp (setpoint - 0.1 m)
    s, y = tr["sp.leg[1].s"], tr["ctl.y"]
    expected = 500.0 * (2.0 * s[:-1] + 0.005 - 0.1)  # Jacobi: y after step k from the input held at t_k
    assert np.allclose(y[1:], expected, rtol=1e-12, atol=1e-9)
    assert np.allclose(tr["ctl.setpoint"][1:], 2.0 * s[:-1] + 0.005, rtol=1e-12)


def test_include_of_an_ssp_in_a_scene(pid_ssp, cache, tmp_path):
    shutil.copy(pid_ssp, tmp_path / "base.ssp")
    (tmp_path / "scene.yaml").write_text(textwrap.dedent("""\
        include: base.ssp
        name: softer
        stop_time: 0.05
        components:
          pid1: {params: {Kp: 10}}
        """))
    sc = load(tmp_path / "scene.yaml")
    assert sc.name == "softer" and sc.components["pid1"].params["Kp"] == 10.0
    assert sc.components["pid2"].params["Kp"] == 30.0 and len(sc.connections) == 15
    assert run(sc, cache_dir=cache).ok


# --- malformed archives: one line each, naming the element ------------------------------------
def _broken(kind: str, fmus: dict[str, Path], tmp_path: Path) -> Path:
    ssd = FOREIGN_SSD
    if kind == "missing ssd":
        ssd = None
    elif kind == "schema":
        ssd = ssd.replace('endConnector="setpoint"', "")
    elif kind == "source":
        ssd = ssd.replace('source="resources/pid.fmu"', 'source="resources/pdi.fmu"')
    elif kind == "connector":
        ssd = ssd.replace('<ssd:Connector name="y" kind="output">', '<ssd:Connector name="u" kind="output">')
    return _archive(tmp_path / f"{kind.replace(' ', '_')}.ssp", fmus, ssd)


@pytest.mark.parametrize("kind, expected", [
    ("missing ssd", "SystemStructure.ssd is missing"),
    ("schema", "Element 'ssd:Connection': The attribute 'endConnector' is required but missing"),
    ("source", "component 'ctl': source 'resources/pdi.fmu' is not in the archive"),
    ("connector", "component 'ctl': connector 'u' does not exist in its FMU pid.fmu"),
])
def test_malformed_ssp_is_one_line_naming_the_element(kind, expected, foreign_fmus, tmp_path, capsys):
    path = _broken(kind, foreign_fmus, tmp_path)
    assert main(["run", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    problems = [line for line in err if ": error: " in line]
    assert len(problems) == 1, err
    assert expected in problems[0] and path.name in problems[0]
    assert not (tmp_path / "out").exists()


# --- a linear transformation written in a scene, through the master and through an SSP --------
TRANSFORM_SCENE = """\
name: scaled
stop_time: 0.01
components:
  sp:  {model: pose_setpoint, params: {x1: -0.2}}
  ctl: {model: pid, params: {Kp: 500, Ki: 0, Kd: 0, u_max: 1000}, start: {measurement: 0.1}}
connections:
  - sp.leg[1].s -> ctl.setpoint * 2.0 + 0.005
master: {algorithm: jacobi, step: 1e-3}
outputs: ["sp.leg[1].s", ctl.y, ctl.setpoint]
"""


@pytest.mark.parametrize("through_ssp", [False, True])
def test_scene_transformation_runs_in_the_compiled_loop(through_ssp, cache, tmp_path):
    (tmp_path / "scaled.yaml").write_text(TRANSFORM_SCENE)
    sc = load(tmp_path / "scaled.yaml")
    assert (sc.connections[0].factor, sc.connections[0].offset) == (2.0, 0.005)
    if through_ssp:
        sc = load(export(sc, tmp_path / "scaled.ssp", cache_dir=cache))
        assert (sc.connections[0].factor, sc.connections[0].offset) == (2.0, 0.005)
    res = run(sc, cache_dir=cache)
    assert res.ok and res.stats["engine"] == "compiled"
    s, y = res.trace["sp.leg[1].s"], res.trace["ctl.y"]
    assert np.allclose(y[1:], 500.0 * (2.0 * s[:-1] + 0.005 - 0.1), rtol=1e-12)
    assert np.allclose(res.trace["ctl.setpoint"][1:], 2.0 * s[:-1] + 0.005, rtol=1e-12)


@pytest.mark.parametrize("text, expected", [
    ("sp.leg[1].s -> ctl.setpoint * two", "a transformation reads '* FACTOR + OFFSET'"),
    ("sp.leg[1].s -> ctl.setpoint * 1e999", "a transformation reads '* FACTOR + OFFSET'"),
])
def test_scene_transformation_mistakes_are_named(text, expected, tmp_path):
    (tmp_path / "bad.yaml").write_text(TRANSFORM_SCENE.replace("sp.leg[1].s -> ctl.setpoint * 2.0 + 0.005", text))
    with pytest.raises(SceneError) as err:
        load(tmp_path / "bad.yaml")
    assert str(err.value).count("\n") == 0 and expected in str(err.value) and "bad.yaml:7" in str(err.value)


def test_a_transformation_gives_the_same_trace_in_both_engines(cache, tmp_path):
    """The compiled loop applies factor and offset as the Python loop does (v * factor + offset):
    the same trace, bit for bit."""
    (tmp_path / "scaled.yaml").write_text(TRANSFORM_SCENE)
    py = run(tmp_path / "scaled.yaml", cache_dir=cache, engine="oracle")
    cc = run(tmp_path / "scaled.yaml", cache_dir=cache, engine="compiled")
    assert (py.stats["engine"], cc.stats["engine"]) == ("oracle", "compiled") and cc.ok
    assert np.array_equal(py.trace.time, cc.trace.time) and np.array_equal(py.trace.data, cc.trace.data)


def test_cli_export_prints_the_path_and_keeps_an_existing_archive(cache, tmp_path, capsys):
    dest = tmp_path / "p.ssp"
    args = ["ssp", "export", str(SCENES / "pid_step.yaml"), "-o", str(dest), "--cache", str(cache)]
    assert main(args) == 0
    assert capsys.readouterr().out.strip() == str(dest)
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "--force" in err[0]
    assert main(args + ["--force"]) == 0
