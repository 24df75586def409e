"""Modelica components (models.modelica through rumoca): the SPEC §6 DC motor written in Modelica
against the hand-written catalog motor (a second formulation), in a scene and in its monolithic
reference; algebraic loops against closed-form solutions; position flanges; and every malformed
file refused with one line naming the file and the line."""
from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rumoca")

import models.blocks as catalog  # noqa: E402
from cosim.run.execute import run  # noqa: E402
from cosim.run.reference import reference  # noqa: E402
from cosim.scenario import SceneError, from_dict, load  # noqa: E402
from models.modelica import ModelicaError, translate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
MOTOR = (SCENES / "user" / "DCMotor.mo").read_text()


def motor():
    return translate(MOTOR, "Motors.DCMotor", "DCMotor.mo", name="dc_motor")


def test_modelica_motor_has_the_interface_and_equations_of_the_catalog_motor():
    mo, ours = motor(), catalog.make("dc_motor", "full")
    for kind in ("params", "inputs", "outputs", "states"):
        assert [(v.name, v.unit) for v in getattr(mo, kind)] == [(v.name, v.unit) for v in getattr(ours, kind)], kind
    assert [p.default for p in mo.params] == pytest.approx([p.default for p in ours.params], rel=1e-15)
    assert mo.integrator == ours.integrator == "exact"
    assert mo.flanges == ours.flanges and mo.feedthrough() == ours.feedthrough()
    fm, fo = mo.functions(), ours.functions()
    rng = np.random.default_rng(7)
    for _ in range(20):
        x, u, p = rng.normal(size=1) * 20, rng.normal(size=2) * [12, 0.5], ours.param_defaults * rng.uniform(0.5, 2, 6)
        for f in ("ode", "out"):
            a, b = np.array(fm[f](x, u, p)).ravel(), np.array(fo[f](x, u, p)).ravel()
            assert np.allclose(a, b, rtol=1e-12, atol=0), f


@pytest.fixture(scope="module")
def pid_runs(tmp_path_factory):
    """pid_step with the catalog motors and with the Modelica ones: co-simulation and reference."""
    out = {}
    for scene in ("pid_step", "pid_step_modelica"):
        path = SCENES / f"{scene}.yaml"
        res = run(path, ["stop_time=0.5"], out_dir=tmp_path_factory.mktemp(scene))
        ref = reference(path, ["stop_time=0.5"])
        assert res.ok and ref.ok, (res.reason, ref.reason)
        out[scene] = (res.trace, ref.trace)
    return out


@pytest.mark.parametrize("which", [0, 1], ids=["cosimulation", "monolithic reference"])
def test_pid_step_with_the_modelica_motors_equals_pid_step(pid_runs, which):
    ours, mo = pid_runs["pid_step"][which], pid_runs["pid_step_modelica"][which]
    assert ours.columns == mo.columns and ours.data.shape == mo.data.shape
    scale = np.abs(ours.data).max(axis=0)
    assert np.all(np.abs(mo.data - ours.data) <= 1e-12 * np.maximum(scale, 1.0))
    assert np.ptp(mo["motor1.i"]) > 1.0  # the motors did work


LOOP = """
model Loop "two resistors in parallel fed through a third: a linear algebraic loop, and a cubic one"
  parameter Real R1(unit = "Ohm") = 2 "first";
  parameter Real R2(unit = "Ohm") = 3 "second";
  parameter Real R3(unit = "Ohm") = 5 "series";
  input Real u(unit = "V") "source voltage";
  output Real i(unit = "A") "source current";
  parameter Real u0(unit = "V") = 1 "voltage scale";
  output Real z(unit = "1") "root of z^3 + z = u/u0";
  Real v(unit = "V") "node voltage";
  Real i1(unit = "A") "current through R1";
  Real i2(unit = "A") "current through R2";
equation
  u = R3 * i + v;
  v = R1 * i1;
  v = R2 * i2;
  i = i1 + i2;
  z ^ 3 + z = u / u0;
end Loop;
"""


def test_algebraic_loops_are_solved_inside_the_block():
    b = translate(LOOP, "Loop", "Loop.mo")
    out = b.functions()["out"]
    assert [v.name for v in b.outputs if not v.local] == ["i", "z"]
    assert [v.name for v in b.outputs if v.local] == ["v", "i1", "i2"]  # the internal variables, recordable
    for u in (-7.0, 0.3, 10.0):
        y = dict(zip([v.name for v in b.outputs], np.array(out([], [u], b.param_defaults)).ravel()))  # u0 = 1 V
        i, z = y["i"], y["z"]
        assert i == pytest.approx(u / (5 + 2 * 3 / 5), rel=1e-14)  # R3 + R1 || R2
        assert (y["v"], y["i1"], y["i2"]) == pytest.approx((u - 5 * i, (u - 5 * i) / 2, (u - 5 * i) / 3), rel=1e-13)
        real = [r.real for r in np.roots([1, 0, 1, -u]) if abs(r.imag) < 1e-12]
        assert z == pytest.approx(real[0], rel=1e-12)


def test_a_nonlinear_loop_newton_cannot_close_gives_nan_not_a_wrong_value():
    text = """model E "exp(z) = u"
  input Real u(unit = "1") "value";
  output Real z(unit = "1") "its logarithm";
equation
  exp(z) = u;
end E;"""
    out = translate(text, "E", "E.mo").functions()["out"]
    assert float(out([], [2.0], [])) == pytest.approx(np.log(2.0), rel=1e-14)
    assert np.isnan(float(out([], [-1.0], [])))  # no real root


SPRING = """
connector Flange "translational flange"
  Real s(unit = "m") "position";
  flow Real f(unit = "N") "cut force";
end Flange;
model Mass "a mass on a spring, its flange a position"
  parameter Real m(unit = "kg") = 2 "mass";
  parameter Real k(unit = "N/m") = 50 "spring to ground";
  Flange flange "where the load pushes";
  Real x(unit = "m", start = 0.1) "position";
  Real v(unit = "m/s", start = 0) "velocity";
equation
  der(x) = v;
  m * der(v) = -k * x + flange.f;
  flange.s = x;
end Mass;
"""


def test_a_position_connector_becomes_a_flow_out_flange_carrying_the_rate():
    b = translate(SPRING, "Mass", "Mass.mo")
    assert [(f.effort, f.flow, f.causality) for f in b.flanges] == [("flange.f", "flange.v", "flow_out")]
    fn = b.functions()
    x, f = np.array([0.03, -0.4]), 1.5
    y = dict(zip([v.name for v in b.outputs], np.array(fn["out"](x, [f], b.param_defaults)).ravel()))
    assert y == {"flange.v": pytest.approx(-0.4), "flange.s": pytest.approx(0.03), "x": 0.03, "v": -0.4}
    assert np.array(fn["ode"](x, [f], b.param_defaults)).ravel() == pytest.approx([-0.4, (-50 * 0.03 + 1.5) / 2])


def test_a_position_connector_whose_position_is_given_integrates_the_partners_rate():
    text = SPRING.split("model Mass")[0] + """model Spring "a spring to ground"
  parameter Real k(unit = "N/m") = 50 "stiffness";
  Flange flange "the free end";
equation
  flange.f = k * flange.s;
end Spring;"""
    b = translate(text, "Spring", "Spring.mo")
    assert [(f.effort, f.flow, f.causality) for f in b.flanges] == [("flange.f", "flange.v", "effort_out")]
    assert [v.name for v in b.inputs] == ["flange.v"] and [v.name for v in b.states] == ["state.flange.s"]
    fn = b.functions()
    assert float(fn["ode"]([0.02], [0.3], b.param_defaults)) == pytest.approx(0.3)  # ds/dt = v
    y = dict(zip([v.name for v in b.outputs], np.array(fn["out"]([0.02], [0.3], b.param_defaults)).ravel()))
    assert y == {"flange.f": pytest.approx(-50 * 0.02), "flange.s": 0.02}  # pulls the partner back; s recordable


BASE = '''model M "m"
  parameter Real k(unit = "1") = 2 "gain"; parameter Real T(unit = "s") = 1 "time constant";
  input Real u(unit = "V") "in";
  output Real y(unit = "V") "out";
  Real x(unit = "V", start = 0) "state";{decl}
equation
  der(x) = (-x + u) / T;
  y = k * x{term};{eqs}
end M;
'''


@pytest.mark.parametrize("decl, term, eqs, line, what", [
    ("", " +", "", 8, "unexpected"),
    ("", " + zz", "", 8, "zz"),
    ("\n  Real q(unit = \"V\") \"q\"; Real r(unit = \"V\") \"r\";", "", "\nalgorithm\n  q := x;\n  r := q;", 10,
     "algorithm: todae failed"),
    ("", " + time", "", 8, "time"),
    ("", "", "\n  y = 2 * x;", None, "unbalanced model: 3 equations, 2 unknowns"),
    ("", " + T", "", 8, "unit mismatch in '+': [kg.m2.s-3.A-1] against T [s]"),
    ("", "", "\n  der(x) = u;", None, "unbalanced"),
    ("\n  Real w(unit = \"m/s\") \"w\";", "", "\n  w = der(x);", 10, "unit mismatch in an equation or '-': w [m/s] "
                                                                    "against der(x) [V/s]"),
    ("\n  Real w(unit = \"1\") \"w\";", "", "\n  w = exp(x);", 10, "the argument of exp() is x [V]"),
])
def test_a_malformed_model_is_refused_with_file_and_line(decl, term, eqs, line, what):
    with pytest.raises(ModelicaError) as err:
        translate(BASE.format(decl=decl, term=term, eqs=eqs), "M", "M.mo")
    msg = str(err.value)
    assert "\n" not in msg and what in msg, msg
    assert msg.startswith(f"M.mo:{line}: " if line else "M.mo: "), msg


def test_external_functions_and_arrays_of_connectors_are_refused():
    ext = 'function f "e"\n  input Real a; output Real b;\nexternal "C" b = g(a);\nend f;\n' + BASE.format(
        decl="", term=" + f(x)", eqs="")
    with pytest.raises(ModelicaError, match=r"^E\.mo:3: external: external functions are not supported"):
        translate(ext, "M", "E.mo")
    arr = 'connector C "c"\n  Real v(unit = "m/s") "v"; flow Real f(unit = "N") "f";\nend C;\n' + BASE.format(
        decl='\n  C c[2] "two";', term="", eqs="\n  c[1].v = x; c[2].v = x;")
    with pytest.raises(ModelicaError, match=r"^A\.mo:\d+: c: arrays of connectors"):
        translate(arr, "M", "A.mo")


def test_a_scene_with_a_broken_modelica_file_gets_one_line_naming_scene_file_and_mo_line(tmp_path):
    (tmp_path / "Bad.mo").write_text(BASE.format(decl="", term="", eqs="\n  when x > 1 then terminate(\"stop\"); end when;"))
    (tmp_path / "scene.yaml").write_text(textwrap.dedent("""\
        stop_time: 0.1
        components:
          m: {modelica: Bad.mo, model: M}
        master: {algorithm: jacobi, step: 1e-3}
        """))
    with pytest.raises(SceneError) as err:
        load(tmp_path / "scene.yaml")
    (msg,) = str(err.value).splitlines()
    assert "scene.yaml:3" in msg and "Bad.mo:9: terminate" in msg, msg


def test_a_missing_modelica_file_or_class_is_one_line(tmp_path):
    data = {"stop_time": 0.1, "components": {"m": {"modelica": "Nope.mo", "model": "M"}},
            "master": {"algorithm": "jacobi", "step": 1e-3}}
    with pytest.raises(SceneError, match="Modelica file 'Nope.mo' not found"):
        from_dict(data, base_dir=tmp_path)
    (tmp_path / "Nope.mo").write_text(BASE.format(decl="", term="", eqs=""))
    data["components"]["m"]["model"] = "Other"
    with pytest.raises(SceneError) as err:
        from_dict(data, base_dir=tmp_path)
    assert len(str(err.value).splitlines()) == 1 and "Nope.mo" in str(err.value)


def test_fmu_show_describes_a_modelica_class(capsys):
    from cosim import cli

    assert cli.main(["fmu", "show", str(SCENES / "user" / "RackPinion.mo") + ":Drive.RackPinion"]) == 0
    out = capsys.readouterr().out
    assert "Tc                0.002 [N.m]  Coulomb friction torque" in out
    assert "flange: effort flange.f, flow flange.v; computes the effort (effort_out)" in out
    assert cli.main(["fmu", "show", str(SCENES / "user" / "RackPinion.mo") + ":Nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "RackPinion.mo" in err and "Drive" in err, err


def test_the_modelica_examples_fmus_pass_fmpy_validation_and_run_under_fmpy():
    """The gear's FMU under FMPy (its own Radau, 1 ms steps) against SciPy's LSODA on the gear
    written in Python (scenarios/user/rack_pinion.py): a torque on the pinion, the leg extending at 0.1 m/s."""
    import importlib.util

    from fmpy import simulate_fmu
    from fmpy.validation import validate_fmu
    from scipy.integrate import solve_ivp

    from cosim.run.execute import build_components

    paths = build_components(load(SCENES / "gear_step.yaml"))
    for comp in ("motor1", "gear1"):
        assert validate_fmu(str(paths[comp])) == [], comp
    res = simulate_fmu(str(paths["gear1"]), stop_time=0.05, step_size=1e-3, output_interval=1e-3,
                       start_values={"shaft.tau": 0.02, "flange.v": 0.1}, output=["shaft.w", "f_mesh"])
    spec = importlib.util.spec_from_file_location("rack_pinion", SCENES / "user" / "rack_pinion.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    py = mod.rack_pinion()
    ode = py.functions()["ode"]
    sol = solve_ivp(lambda t, x: np.array(ode(x, [0.02, 0.1], py.param_defaults)).ravel(), (0, 0.05), [0.0, 0.0],
                    method="LSODA", rtol=1e-10, atol=1e-13, dense_output=True)
    w = sol.sol(res["time"])[0]
    assert np.ptp(res["shaft.w"]) > 1.0
    late = res["time"] >= 5e-3  # after the mesh's transient (~1 ms), which one 1 ms Radau step damps but not exactly
    assert np.abs(res["shaft.w"] - w)[late].max() < 1e-6 * np.abs(w).max()
    assert res["shaft.w"][-1] == pytest.approx(0.1 / 0.05, rel=1e-9)  # the pinion follows the leg: v / rack


LAG = """model Lag
  parameter Real T = 0.5;
  input Real u;
  output Real y;
equation
  T * der(y) = u - y;
end Lag;
"""


def test_units_and_descriptions_are_optional_and_an_unknown_unit_is_said():
    b = translate(LAG, "Lag", "Lag.mo")
    assert [(v.name, v.unit) for v in b.params + b.inputs + b.outputs] == [("T", ""), ("u", ""), ("y", "")]
    assert b.inputs[0].description == "input u (no description; unit unknown: none declared)"
    odd = translate(LAG.replace("input Real u;", 'input Real u(unit = "furlong") "distance";'), "Lag", "Lag.mo")
    assert (odd.inputs[0].unit, odd.inputs[0].description) == ("", "distance (unit 'furlong' unknown here: not "
                                                                    "checked)")


def test_time_in_a_model_without_units_is_not_refused_for_a_unit_nobody_wrote(tmp_path):
    """`der(x) = sin(time)` with no unit anywhere (Modelica makes units optional): translated, and
    its run against x = 1 - cos t; where the model declares units, time is in seconds and the
    same line is refused naming it."""
    plain = 'model S\n  Real x(start = 0, fixed = true);\nequation\n  der(x) = sin(time);\nend S;\n'
    (tmp_path / "S.mo").write_text(plain)
    (tmp_path / "s.yaml").write_text("stop_time: 2.0\ncomponents:\n  s: {modelica: S.mo, model: S}\n"
                                     "master: {algorithm: jacobi, step: 1e-2}\noutputs: [s.x]\n")
    res = run(tmp_path / "s.yaml", [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    assert np.abs(res.trace["s.x"] - (1 - np.cos(res.trace["time"]))).max() < 1e-8
    with pytest.raises(ModelicaError, match=r"S\.mo:4: the argument of sin\(\) is time \[s\]"):
        translate(plain.replace("Real x(", 'Real x(unit = "m", '), "S", "S.mo")


def test_lag_without_units_runs_against_its_analytic_response(tmp_path):
    """Lag.mo (no unit, no description) driven by a free catalog oscillator x = cos t: the lag's
    output against the closed-form response of T y' = cos t - y, y(0) = 0."""
    (tmp_path / "Lag.mo").write_text(LAG)
    (tmp_path / "lag.yaml").write_text(textwrap.dedent("""\
        stop_time: 2.0
        components:
          src: {model: oscillator, params: {m: 1.0, k: 1.0, d: 0.0, x0: 1.0}}
          lag: {modelica: Lag.mo, model: Lag}
        connections: [src.x -> lag.u]
        master: {algorithm: jacobi, step: 1e-4}
        outputs: [lag.y]
        """))
    res = run(tmp_path / "lag.yaml", [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    t, y = res.trace["time"], res.trace["lag.y"]
    T = 0.5
    exact = (np.cos(t) + T * np.sin(t)) / (1 + T * T) - np.exp(-t / T) / (1 + T * T)
    assert np.abs(y - exact).max() < 1e-3 * np.ptp(exact)


SLIDING_MASS = '''model SlidingMass "a mass whose flange is its own position"
  connector Flange "a translational flange, as the MSL's"
    Real s(unit = "m") "position";
    flow Real f(unit = "N") "force on the component";
  end Flange;
  parameter Real m(unit = "kg") = 2 "mass";
  parameter Real d(unit = "N.s/m") = 0 "damping to the ground";
  Real s(unit = "m", start = 0, fixed = true) "position";
  Real v(unit = "m/s", start = 0, fixed = true) "velocity";
  Flange flange "where the drive acts";
equation
  flange.s = s;
  der(s) = v;
  m * der(v) = flange.f - d * v;
end SlidingMass;
'''
DAMPER_ON_FLANGE = '''model GroundDamper "a damper from a position flange to the ground"
  connector Flange "a translational flange, as the MSL's"
    Real s(unit = "m") "position";
    flow Real f(unit = "N") "force on the component";
  end Flange;
  parameter Real d(unit = "N.s/m") = 3 "damping";
  Real x(unit = "m", start = 0, fixed = true) "position";
  Flange flange "the driven end";
equation
  flange.s = x;
  d * der(x) = flange.f;
end GroundDamper;
'''


def test_a_position_flange_on_a_mass_against_a_velocity_source_is_refused_naming_the_index_problem(tmp_path):
    """A top-level position flange fixed to a mass: taking the partner's velocity in, the position
    constraint differentiated once ties the mass's velocity state to it, and its force would need
    the partner's acceleration (index 3), which a bond does not carry.  The flange is derived
    flow_out (force in; m dv/dt = f - d v by hand), and a bond to the mechanism's leg, which
    imposes its velocity, is refused in one line that names the constraint.  A damper on a
    position flange has no such problem (its constraint differentiated once gives the force)."""
    b = translate(SLIDING_MASS, "SlidingMass", "SlidingMass.mo")
    (fl,) = b.flanges
    assert (fl.causality, fl.effort, fl.flow) == ("flow_out", "flange.f", "flange.v")
    assert fl.why.startswith("taking the velocity in leaves an index problem") and "0 = (flange.v-state.v)" in fl.why
    fn, names = b.functions(), [v.name for v in b.states]
    dx = dict(zip(names, np.array(fn["ode"]([0.1, 0.4], [1.5], [2.0, 0.5])).ravel()))
    assert dx == {"state.s": pytest.approx(0.4), "state.v": pytest.approx((1.5 - 0.5 * 0.4) / 2.0)}
    assert translate(DAMPER_ON_FLANGE, "GroundDamper", "GroundDamper.mo").flanges[0].why == ""
    (tmp_path / "SlidingMass.mo").write_text(SLIDING_MASS)
    (tmp_path / "scene.yaml").write_text(textwrap.dedent("""\
        stop_time: 0.1
        components:
          mech: {model: mechanism, fidelity: rigid}
          m: {modelica: SlidingMass.mo, model: SlidingMass}
        connections:
          - m.flange <-> mech.leg[1]
        master: {algorithm: gauss_seidel, step: 1e-3}
        """))
    with pytest.raises(SceneError) as err:
        load(tmp_path / "scene.yaml")
    (msg,) = str(err.value).splitlines()
    assert "both flanges compute the flow (flow_out)" in msg and "m.flange cannot: taking the velocity in leaves an " \
        "index problem: the states are tied by the constraint 0 = (flange.v-state.v)" in msg, msg


STATED = '''connector VFlange "a translational flange by its velocity"
  Real v(unit = "m/s");
  flow Real f(unit = "N");
end VFlange;

model DampedMass "a mass on a spring to the ground, reached through a damper at its flange"
  parameter Real m(unit = "kg") = 1;
  parameter Real k(unit = "N/m") = 4;
  parameter Real d(unit = "N.s/m") = 2;
  VFlange flange;
  Real x(unit = "m", start = 0.1);
  Real v(unit = "m/s", start = 0);
equation
  der(x) = v;
  m * der(v) = -k * x + flange.f;
  flange.f = d * (flange.v - v);
end DampedMass;

model Damper "a damper from its flange to the ground"
  parameter Real d(unit = "N.s/m") = 2;
  VFlange flange;
equation
  flange.f = d * flange.v;
end Damper;

model MassAtFlange "a mass on a spring, its flange on the mass"
  parameter Real m(unit = "kg") = 1;
  parameter Real k(unit = "N/m") = 4;
  VFlange flange;
  Real x(unit = "m", start = 0.1);
  Real v(unit = "m/s", start = 0);
equation
  der(x) = v;
  m * der(v) = -k * x + flange.f;
  flange.v = v;
end MassAtFlange;
'''


def _stated_scene(folder: Path, osc: str, damper: str, step: float, model: str = "DampedMass",
                  causality: str | None = None) -> Path:
    (folder / "Stated.mo").write_text(STATED)
    path = folder / f"{osc}_{step:g}.yaml"
    path.write_text(f"stop_time: 5\ncomponents:\n"
                    f"  osc: {{modelica: Stated.mo, model: {model}, options: {{causality: "
                    f"{causality or '{flange: ' + osc + '}'}}}}}\n"
                    f"  damper: {{modelica: Stated.mo, model: Damper, options: {{causality: {{flange: {damper}}}}}}}\n"
                    f"connections:\n  - osc.flange <-> damper.flange\n"
                    f"master: {{algorithm: iterative, step: {step}}}\noutputs: [osc.x]\n")
    return path


def test_a_scene_states_the_causality_where_the_model_allows_both(tmp_path):
    """A mass on a spring (m = 1, k = 4) reached through a damper (d = 2) at its flange, bonded
    to a damper to the ground (d = 2): each flange allows both causalities (a damper's force
    follows from the velocity and the velocity from the force), so without a stated one both
    would compute the force.  Either way the dampers are in series, c = d d / (d + d) = 1, and
    x = e^(-zeta w0 t) (x0 cos wd t + zeta w0 x0 / wd sin wd t) with w0 = 2, zeta = 0.25.  The
    iterative master solves the algebraic loop at each communication point and holds the force
    across the step, a first-order coupling error: 3.7e-5 m (of x0 = 0.1 m) at h = 1 ms either
    way, half that at 0.5 ms; the tolerance, 5e-5 m, is that first-order term with a margin."""
    w0, zeta, x0 = 2.0, 0.25, 0.1
    wd = w0 * np.sqrt(1 - zeta ** 2)
    errors = {}
    for osc, damper in (("effort_out", "flow_out"), ("flow_out", "effort_out")):
        for step in (1e-3, 5e-4):
            path = _stated_scene(tmp_path, osc, damper, step)
            sc = load(path)
            assert [f.causality for f in sc.components["osc"].description.flanges] == [osc]
            assert [f.causality for f in sc.components["damper"].description.flanges] == [damper]
            res = run(path, [], out_dir=tmp_path / f"out_{osc}_{step:g}")
            assert res.ok, res.reason
            t = np.asarray(res.trace["time"])
            exact = np.exp(-zeta * w0 * t) * (x0 * np.cos(wd * t) + zeta * w0 * x0 / wd * np.sin(wd * t))
            errors[osc, step] = np.abs(np.asarray(res.trace["osc.x"]) - exact).max()
        assert errors[osc, 1e-3] < 5e-5, errors
        assert 1.8 < errors[osc, 1e-3] / errors[osc, 5e-4] < 2.2, errors  # first order in the step


@pytest.mark.parametrize("model, causality, message", [
    ("MassAtFlange", "{flange: effort_out}", "causality flange: effort_out: the equations do not allow it: the "
                                             "states are tied by the constraint 0 = (flange.v-state.v)"),
    ("DampedMass", "{flange: sideways}", "options.causality {'flange': 'sideways'}; expected a mapping flange: "
                                         "effort_out or flow_out"),
    ("DampedMass", "{flang: effort_out}", "causality of 'flang': the model has no such flange (flanges: flange)"),
])
def test_a_stated_causality_the_model_refuses_is_one_line(tmp_path, model, causality, message):
    """The mass at the flange computes its velocity: taking the velocity in is an index problem,
    named; a value other than the two causalities, or a flange the model lacks, names the field."""
    path = _stated_scene(tmp_path, "x", "flow_out", 1e-3, model=model, causality=causality)
    with pytest.raises(SceneError) as exc:
        load(path)
    first = str(exc.value).splitlines()[0]
    assert first.startswith(f"{path}:3: error: component 'osc': ") and message in first, first
