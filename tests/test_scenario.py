"""Scene loading and validation: every malformed-scene case gives its own one-line message with
the file, the line and (where there is one) the closest valid name; includes, overrides and
wildcards work; the CLI prints one line per problem and exits with 2."""
from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

from cosim.errors import UserError
from cosim.scenario import SceneError, load, parse_set

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))

BASE = """\
name: small
stop_time: 1.0
components:
  target: {model: pose_setpoint}
  pid1: {model: pid, params: {Kp: 30}}
  motor1: {model: dc_motor, fidelity: ideal}
  mech: {model: mechanism, fidelity: rigid}
connections:
  - target.leg[1].s -> pid1.setpoint
  - mech.leg[1].s -> pid1.measurement
  - pid1.y -> motor1.u
  - motor1.flange <-> mech.leg[1]
master: {algorithm: gauss_seidel, step: 1e-3}
outputs:
  - mech.platform.*
"""


def write(tmp_path: Path, text: str, name: str = "s.yaml") -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def problems(tmp_path: Path, text: str, overrides=None) -> list[str]:
    with pytest.raises(SceneError) as ei:
        load(write(tmp_path, text), overrides)
    return [str(p) for p in ei.value.problems if p.severity == "error"]


def edit(old: str, new: str) -> str:
    assert old in BASE, old
    return BASE.replace(old, new)


def test_the_base_scene_is_valid_and_warns_about_unconnected_inputs(tmp_path):
    sc = load(write(tmp_path, BASE))
    assert sc.n_steps == 1000 and sc.master.step_ns == 1_000_000
    assert [str(c) for c in sc.connections][-2:] == ["motor1.flange.f -> mech.leg[1].f",
                                                    "mech.leg[1].v -> motor1.flange.v"]
    warned = {w.message.split()[1] for w in sc.warnings}
    assert warned == {"mech.leg[2].f", "mech.leg[3].f"}
    assert all(w.severity == "warning" and w.file.endswith("s.yaml") and w.line == 7 for w in sc.warnings)
    assert sc.outputs == [f"mech.platform.{k}" for k in ("x", "y", "phi", "vx", "vy", "omega")]


# (scene text, line, message) -- one case per kind of mistake
CASES = [
    ("yaml-syntax", edit("stop_time: 1.0", "stop_time: 1.0: 2"), 2, r"YAML syntax: mapping values are not allowed here"),
    ("duplicate-key", edit("stop_time: 1.0\n", "stop_time: 1.0\nstop_time: 2.0\n"), 3, r"duplicate key 'stop_time' \(first at line 2\)"),
    ("unknown-top-key", edit("outputs:", "outputz:"), 14, r"unknown key 'outputz' in the scene; did you mean 'outputs'\?"),
    ("unknown-component-key", edit("{model: dc_motor, fidelity: ideal}", "{model: dc_motor, fidelty: ideal}"), 6,
     r"unknown key 'fidelty' in component 'motor1'; did you mean 'fidelity'\?"),
    ("unknown-model", edit("model: mechanism", "model: mechansm"), 7, r"unknown model 'mechansm'; did you mean 'mechanism'\?"),
    ("unknown-fidelity", edit("fidelity: rigid", "fidelity: rigd"), 7, r"has no fidelity 'rigd'; did you mean 'rigid'\?"),
    ("unknown-option", edit("fidelity: rigid}", "fidelity: rigid, options: {confg: cross_leg}}"), 7,
     r"mechanism/rigid has no option 'confg'; did you mean 'config'\?"),
    ("bad-option-value", edit("fidelity: rigid}", "fidelity: rigid, options: {config: cross}}"), 7,
     r"option config='cross' is not valid"),
    ("unknown-parameter", edit("{Kp: 30}", "{Kpp: 30}"), 5, r"has no parameter 'Kpp'; did you mean 'Kp'\?"),
    ("option-as-parameter", edit("fidelity: rigid}", "fidelity: rigid, params: {config: cross_leg}}"), 7,
     r"'config' is a construction option, not a parameter; put it under 'options:'"),
    ("parameter-out-of-bounds", edit("{Kp: 30}", "{Kp: 30, u_max: -1}"), 5, r"parameter u_max = -1 is outside \[0\.0, inf\]"),
    ("parameter-not-a-number", edit("{Kp: 30}", "{Kp: thirty}"), 5, r"parameter Kp = 'thirty' is not a finite number"),
    ("start-of-an-output", edit("{Kp: 30}}", "{Kp: 30}, start: {y: 1.0}}"), 5, r"'y' is an output; outputs are computed"),
    ("start-of-a-calculated-state", edit("fidelity: rigid}", "fidelity: rigid, start: {q.x: 0.1}}"), 7,
     r"state 'q\.x' starts from the parameters"),
    ("unknown-component", edit("pid1.y -> motor1.u", "pid4.y -> motor1.u"), 11, r"unknown component 'pid4' in 'pid4\.y'; did you mean 'pid1'\?"),
    ("unknown-variable", edit("-> pid1.setpoint", "-> pid1.setpont"), 9, r"has no variable 'setpont'; did you mean 'setpoint'\?"),
    ("two-outputs", edit("pid1.y -> motor1.u", "pid1.y -> motor1.flange.f"), 11,
     r"connects two outputs \(pid1\.y and motor1\.flange\.f\); a connection goes from an output to an input"),
    ("two-inputs", edit("pid1.y -> motor1.u", "pid1.setpoint -> motor1.u"), 11, r"connects two inputs"),
    ("reversed", edit("pid1.y -> motor1.u", "motor1.u -> pid1.y"), 11, r"is reversed: .*write 'pid1\.y -> motor1\.u'"),
    ("parameter-as-target", edit("pid1.y -> motor1.u", "pid1.y -> motor1.gain"), 11,
     r"motor1\.gain is a parameter, not an input; set it under components\.motor1\.params"),
    ("input-fed-twice", edit("  - pid1.y -> motor1.u\n", "  - pid1.y -> motor1.u\n  - pid1.e -> motor1.u\n"), 12,
     r"input motor1\.u is already connected \(from pid1\.y, line 11\)"),
    ("flange-with-arrow", edit("motor1.flange <-> mech.leg[1]", "motor1.flange -> mech.leg[1]"), 12,
     r"motor1\.flange is a flange; join flanges with '<->'"),
    ("unknown-flange", edit("motor1.flange <-> mech.leg[1]", "motor1.flange <-> mech.leg[4]"), 12,
     r"has no flange 'leg\[4\]'; did you mean 'leg\[\d\]'\? \(flanges: leg\[1\], leg\[2\], leg\[3\]\)"),
    ("variable-as-flange", edit("motor1.flange <-> mech.leg[1]", "motor1.flange <-> mech.leg[1].f"), 12,
     r"has no flange 'leg\[1\]\.f' \('leg\[1\]\.f' is a variable, not a flange\)"),
    ("same-causality-bond", edit("  mech: {model: mechanism, fidelity: rigid}\n",
                                 "  mech: {model: mechanism, fidelity: rigid}\n  motor2: {model: dc_motor, fidelity: ideal}\n")
     .replace("motor1.flange <-> mech.leg[1]", "motor1.flange <-> motor2.flange"), 13,
     r"bond motor1\.flange <-> motor2\.flange: both flanges compute the effort \(effort_out\)"),
    ("not-a-connection", edit("pid1.y -> motor1.u", "pid1.y => motor1.u"), 11, r"must read 'a\.out -> b\.in'"),
    ("algebraic-loop", edit("  mech: {model: mechanism, fidelity: rigid}\n",
                            "  mech: {model: mechanism, fidelity: rigid}\n  pid2: {model: pid}\n")
     .replace("  - target.leg[1].s -> pid1.setpoint\n", "  - pid2.y -> pid1.setpoint\n  - pid1.e -> pid2.setpoint\n"), 10,
     r"algebraic loop \(a cycle of direct feedthrough\): pid\w\.\w+ -> .*pid\w\.\w+"),
    ("negative-step", edit("step: 1e-3", "step: -1e-3"), 13, r"master\.step = -0\.001 must be positive"),
    ("step-not-whole-ns", edit("step: 1e-3", "step: 1.5e-10"), 13, r"not a whole number of nanoseconds"),
    ("missing-step", edit("{algorithm: gauss_seidel, step: 1e-3}", "{algorithm: gauss_seidel}"), 13, r"master\.step is missing"),
    ("negative-stop", edit("stop_time: 1.0", "stop_time: -1"), 2, r"stop_time = -1\.0 must be positive"),
    ("stop-not-whole-steps", edit("stop_time: 1.0", "stop_time: 1.0005"), 2,
     r"stop_time = 1\.0005 s is not a whole number of steps of 0\.001 s; use 1 or 1\.001"),
    ("output-interval", edit("step: 1e-3}", "step: 1e-3, output_interval: 1.5e-3}"), 13,
     r"output_interval = 0\.0015 s must be a positive whole multiple of master\.step"),
    ("step-vs-sample-period", edit("{model: pid, params: {Kp: 30}}", "{model: pid, fidelity: discrete, options: {sample_period: 2e-3}}"),
     13, r"master\.step = 0\.001 s is not a whole multiple of the sample period 0\.002 s of pid1"),
    ("unknown-algorithm", edit("gauss_seidel", "gauss_siedel"), 13, r"unknown master algorithm 'gauss_siedel'; did you mean 'gauss_seidel'\?"),
    ("unknown-engine", edit("step: 1e-3}", "step: 1e-3, engine: compild}"), 13, r"master\.engine = 'compild'; did you mean 'compiled'\?"),
    ("unknown-inputs", edit("step: 1e-3}", "step: 1e-3, inputs: linaer}"), 13,
     r"master\.inputs = 'linaer'; did you mean 'linear'\?.*expected hold .* or linear"),
    ("order-incomplete", edit("step: 1e-3}", "step: 1e-3, order: [mech, pid1]}"), 13, r"master\.order must list every component; missing: target, motor1"),
    ("order-unknown", edit("step: 1e-3}", "step: 1e-3, order: [mech, pid1, motor1, targt]}"), 13,
     r"master\.order names unknown component 'targt'; did you mean 'target'\?"),
    ("output-matches-nothing", edit("  - mech.platform.*", "  - mech.platfrm.x"), 15,
     r"output pattern 'mech\.platfrm\.x' matches no input or output; did you mean 'mech\.platform\.x'\?"),
    ("model-and-fmu", edit("{model: dc_motor, fidelity: ideal}", "{model: dc_motor, fmu: m.fmu}"), 6, r"has both 'model:' and 'fmu:'"),
    ("fmu-missing", edit("{model: dc_motor, fidelity: ideal}", "{fmu: nothing.fmu}"), 6, r"FMU file 'nothing\.fmu' not found"),
    ("no-components", "name: x\nstop_time: 1\nmaster: {step: 1e-3}\n", 1, r"the scene needs 'components:'"),
]


@pytest.mark.parametrize("text,line,message", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_malformed_scene_is_reported_with_file_line_and_advice(tmp_path, text, line, message):
    found = problems(tmp_path, text)
    hits = [p for p in found if __import__("re").search(message, p)]
    assert hits, f"expected /{message}/ among:\n" + "\n".join(found)
    assert f"s.yaml:{line}: error: " in hits[0], hits[0]


def test_every_problem_is_collected_not_just_the_first(tmp_path):
    text = edit("step: 1e-3", "step: -1").replace("fidelity: rigid", "fidelity: rigd").replace("{Kp: 30}", "{Kpp: 30}")
    found = problems(tmp_path, text)
    assert len(found) >= 3
    assert any("Kpp" in p for p in found) and any("rigd" in p for p in found) and any("master.step" in p for p in found)


def test_include_merges_and_overrides_by_key(tmp_path):
    write(tmp_path, BASE, "base.yaml")
    child = write(tmp_path, """\
        include: base.yaml
        name: child
        components:
          mech: {fidelity: kinematic}
          pid1: {params: {Ki: 5}}
          motor1: null
        connections:
          - target.leg[1].s -> pid1.measurement
        master: {step: 5e-4}
        outputs: ["mech.leg[*].f"]
        """, "child.yaml")
    with pytest.raises(SceneError) as ei:
        load(child)
    # motor1 was deleted, so its connections now name an unknown component: reported at the base's lines
    msgs = [str(p) for p in ei.value.problems if p.severity == "error"]
    assert any(m.startswith("base.yaml:11:") or ":11: error: unknown component 'motor1'" in m for m in msgs), msgs


def test_include_deep_merge_keeps_the_rest(tmp_path):
    write(tmp_path, BASE, "base.yaml")
    child = write(tmp_path, """\
        include: base.yaml
        name: child
        components:
          pid1: {params: {Ki: 5}}
        connections:
          - target.leg[1].s -> pid1.measurement
          - mech.leg[1].s -> pid1.setpoint
        master: {step: 5e-4}
        """, "child.yaml")
    sc = load(child)
    assert sc.name == "child" and sc.master.step == 5e-4 and sc.master.algorithm == "gauss_seidel"
    assert sc.n_steps == 2000
    assert sc.components["pid1"].params == {"Kp": 30.0, "Ki": 5.0}
    conns = [str(c) for c in sc.connections]
    # the child's connections into pid1's inputs replace the base's
    assert "target.leg[1].s -> pid1.measurement" in conns and "mech.leg[1].s -> pid1.setpoint" in conns
    assert "target.leg[1].s -> pid1.setpoint" not in conns and "mech.leg[1].s -> pid1.measurement" not in conns
    assert "pid1.y -> motor1.u" in conns


def test_replacing_a_model_replaces_the_whole_component(tmp_path, gain_fmu):
    shutil.copy(gain_fmu, tmp_path / "gain.fmu")
    write(tmp_path, BASE, "base.yaml")
    child = write(tmp_path, """\
        include: base.yaml
        components:
          pid1: {fmu: gain.fmu}
        connections:
          - target.leg[1].s -> pid1.u
        """, "child.yaml")
    with pytest.raises(SceneError) as ei:
        load(child)
    msgs = [str(p) for p in ei.value.problems if p.severity == "error"]
    # pid1 is now the gain FMU (no 'Kp' parameter left over from the base, no 'setpoint' input)
    assert not any("Kp" in m for m in msgs)
    assert any("base.yaml:10:" in m and "has no variable 'measurement'" in m for m in msgs), msgs


def test_include_problems(tmp_path):
    write(tmp_path, "include: b.yaml\n", "a.yaml")
    write(tmp_path, "include: a.yaml\n", "b.yaml")
    with pytest.raises(SceneError, match=r"include cycle: .*a\.yaml -> .*b\.yaml -> .*a\.yaml"):
        load(tmp_path / "a.yaml")
    with pytest.raises(SceneError, match=r"included scene 'bse\.yaml' not found next to c\.yaml; did you mean 'b\.yaml'\?"):
        load(write(tmp_path, "include: bse.yaml\n", "c.yaml"))


def test_overrides_reach_parameters_with_dotted_names(tmp_path):
    sc = load(write(tmp_path, BASE), ["components.mech.params.leg[1].m_act=0.058", "master.step=2e-3",
                                      "components.pid1.params.Kp=40", "master.algorithm=jacobi"])
    assert sc.components["mech"].params == {"leg[1].m_act": 0.058}
    assert sc.components["pid1"].params == {"Kp": 40.0}
    assert (sc.master.step, sc.master.algorithm, sc.n_steps) == (2e-3, "jacobi", 500)


def test_a_bad_override_names_itself(tmp_path):
    found = problems(tmp_path, BASE, ["components.pid1.params.Kq=1"])
    assert found == ["--set components.pid1.params.Kq=1: error: component 'pid1' (pid/continuous) has no parameter "
                     "'Kq'; did you mean 'Kp'?"]
    with pytest.raises(UserError, match="expected PATH=VALUE"):
        parse_set("master.step")


def test_wildcards_treat_brackets_literally(tmp_path):
    sc = load(write(tmp_path, edit("  - mech.platform.*", '  - "mech.leg[*].f"\n  - "*1.y"')))
    assert sc.outputs == ["mech.leg[1].f", "mech.leg[2].f", "mech.leg[3].f", "pid1.y"]


def test_exact_output_names_may_be_states(tmp_path):
    sc = load(write(tmp_path, edit("  - mech.platform.*", "  - pid1.state.I")))
    assert sc.outputs == ["pid1.state.I"]


@pytest.fixture(scope="module")
def gain_fmu(tmp_path_factory):
    import fmus
    from test_fmu_integrators import gain_block

    return fmus.build_fmu(gain_block(), cache_dir=tmp_path_factory.getbasetemp() / "fmu-cache")


def fake_fmu(path: Path, variables: str) -> Path:
    """An FMU archive with only a modelDescription.xml: enough for validation, which runs
    before anything is loaded."""
    xml = f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="fake" guid="{{00000000-0000-0000-0000-000000000001}}">
  <CoSimulation modelIdentifier="fake"/>
  <ModelVariables>{variables}</ModelVariables>
  <ModelStructure><Outputs><Unknown index="1"/></Outputs></ModelStructure>
</fmiModelDescription>"""
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("modelDescription.xml", xml)
    return path


def test_type_mismatch_between_an_integer_output_and_a_real_input(tmp_path):
    fake_fmu(tmp_path / "counter.fmu", """
    <ScalarVariable name="n" valueReference="1" causality="output" variability="discrete"><Integer/></ScalarVariable>""")
    text = edit("  mech: {model: mechanism, fidelity: rigid}\n",
                "  mech: {model: mechanism, fidelity: rigid}\n  counter: {fmu: counter.fmu}\n") \
        .replace("pid1.y -> motor1.u", "counter.n -> motor1.u")
    found = problems(tmp_path, text)
    assert any(":12: error: type mismatch: counter.n is Integer but motor1.u is Real" in p for p in found), found


def test_external_fmu_component_is_described_from_its_model_description(tmp_path, gain_fmu):
    shutil.copy(gain_fmu, tmp_path / "gain.fmu")
    sc = load(write(tmp_path, edit("  mech: {model: mechanism, fidelity: rigid}\n",
                                   "  mech: {model: mechanism, fidelity: rigid}\n  g: {fmu: gain.fmu}\n")
                    .replace("pid1.y -> motor1.u", "pid1.y -> g.u")
                    .replace("  - motor1.flange <-> mech.leg[1]\n", "  - g.y -> motor1.u\n  - motor1.flange <-> mech.leg[1]\n")))
    g = sc.components["g"]
    assert g.kind == "fmu" and g.fmu == (tmp_path / "gain.fmu").resolve()
    assert g.description.feedthrough == {"y": ["u"]}


def test_cli_prints_one_line_per_problem_and_exits_2(tmp_path):
    text = edit("step: 1e-3", "step: -1").replace("{Kp: 30}", "{Kpp: 30}")
    p = write(tmp_path, text)
    res = subprocess.run([sys.executable, "-m", "cosim", "run", str(p), "--out", str(tmp_path / "out")],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    errors = [ln for ln in lines if ": error: " in ln]
    assert len(errors) == 2 and all("s.yaml:" in ln for ln in errors)
    assert "Traceback" not in res.stderr
    assert lines[-1].endswith("2 problems; nothing was run")
    assert not (tmp_path / "out").exists()


def test_cli_check_validates_and_describes_without_running(tmp_path):
    p = write(tmp_path, BASE)
    res = subprocess.run([sys.executable, "-m", "cosim", "run", str(p), "--check"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "scene small: 4 components, 5 connections (1 bond), gauss_seidel at 0.001 s, stop 1 s (1000 steps)" in res.stdout
    assert "motor1.flange.f -> mech.leg[1].f   [bond motor1.flange <-> mech.leg[1]]" in res.stdout
    assert res.stderr.count("warning: input mech.leg[") == 2
