"""Users' own Python blocks (models.user, cosim.scenario.user_blocks): the computed-torque example
against the analytic error dynamics of its closed loop, its FMU under FMPy, the Python gear against
the Modelica one (two formulations), the documentation rule, edits that rebuild, the
``rpr_cosim.blocks`` entry point group, and one-line refusals."""
from __future__ import annotations

import importlib.util
import math
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import models.blocks as catalog
from cosim.run.execute import build_components, run
from cosim.run.reference import reference
from cosim.scenario import SceneError, from_dict, load
from models.block import BlockError
from models.user import require_documented

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"


def _module(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("model", sorted(set(catalog.catalog()) - {"mechanism"}) + ["mechanism"])
def test_every_catalog_block_meets_the_rule_user_blocks_must_meet(model):
    fid = "rigid" if model == "mechanism" else None
    require_documented(catalog.make(model, fid))


@pytest.fixture(scope="module")
def ctc_runs(tmp_path_factory):
    path = SCENES / "computed_torque.yaml"
    res = run(path, out_dir=tmp_path_factory.mktemp("ctc"))
    ref = reference(path)
    assert res.ok and ref.ok, (res.reason, ref.reason)
    return res.trace, ref.trace


def test_computed_torque_closed_loop_follows_the_analytic_error_dynamics(ctc_runs):
    """e'' + Kd e' + Kp e = 0 with Kp = 400, Kd = 40 (a double pole at -20 1/s) from the start
    error (1 cm in x, the path's rate (0.05 pi, 0.05 pi) m/s against a platform at rest)."""
    cosim, ref = ctc_runs
    w, rate = 20.0, 0.05 * math.pi
    for trace, tol in ((ref, 1e-8), (cosim, 1e-5)):  # co-simulation: the 1 ms coupling error
        t = trace.time
        for axis, e0, ed0 in (("x", -0.01, rate), ("y", 0.0, rate), ("phi", 0.0, 0.0)):
            e = trace[f"path.platform.{axis}"] - trace[f"mech.platform.{axis}"]
            exact = (e0 + (ed0 + w * e0) * t) * np.exp(-w * t)
            assert np.abs(e - exact).max() < tol, (axis, np.abs(e - exact).max())


def test_the_computed_torque_fmu_passes_fmpy_validation_and_runs_under_fmpy():
    from fmpy import simulate_fmu
    from fmpy.validation import validate_fmu

    scene = load(SCENES / "computed_torque.yaml")
    paths = build_components(scene)
    fmu = paths["ctc"]
    assert validate_fmu(str(fmu)) == []
    block = scene.components["ctc"].block
    inputs = {"ref.x": -0.25, "ref.y": -0.15, "ref.phi": 0.02, "ref.ax": 0.3, "q.x": -0.24, "q.y": -0.16,
              "q.vx": 0.1, "q.omega": -0.2}
    res = simulate_fmu(str(fmu), stop_time=0.01, output_interval=0.005, start_values=inputs,
                       output=["leg[1].f", "leg[2].f", "leg[3].f"])
    u = [inputs.get(v.name, 0.0) for v in block.inputs]
    expect = np.array(block.functions()["out"]([], u, block.param_defaults)).ravel()
    for i in range(3):
        assert res[f"leg[{i + 1}].f"][-1] == pytest.approx(expect[i], rel=1e-12)


def test_the_python_gear_equals_the_modelica_gear():
    pytest.importorskip("rumoca")
    from models.modelica import translate

    mo = translate((SCENES / "user" / "RackPinion.mo").read_text(), "Drive.RackPinion", "RackPinion.mo")
    py = _module(SCENES / "user" / "rack_pinion.py").rack_pinion()
    assert [(v.name, v.unit) for v in py.params] == [(v.name, v.unit) for v in mo.params]
    assert sorted(v.name for v in py.outputs) == sorted(v.name for v in mo.outputs if not v.local)
    assert py.flanges == mo.flanges and py.integrator == mo.integrator == "radau"
    fp, fm = py.functions(), mo.functions()
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, u = rng.normal(size=2) * [50, 1e-4], rng.normal(size=2) * [0.5, 2.0]
        assert np.allclose(np.array(fp["ode"](x, u, py.param_defaults)).ravel(),
                           np.array(fm["ode"](x, u, mo.param_defaults)).ravel(), rtol=1e-12, atol=1e-9)
        yp = dict(zip([v.name for v in py.outputs], np.array(fp["out"](x, u, py.param_defaults)).ravel()))
        ym = dict(zip([v.name for v in mo.outputs], np.array(fm["out"](x, u, mo.param_defaults)).ravel()))
        ym = {k: v for k, v in ym.items() if k in yp}  # the Modelica gear's internal variables are FMI locals besides
        assert yp == pytest.approx(ym, rel=1e-12, abs=1e-15)


GOOD = '''
from models.user import BlockBuilder

def damper(integrator="rk4"):
    b = BlockBuilder("damper", "mass with viscous friction driven by a force")
    m = b.param("m", 2.0, "kg", "mass", lower=0.0)
    c = b.param("c", 0.5, "N.s/m", "viscous friction coefficient", lower=0.0)
    f = b.input("f", "N", "applied force")
    v = b.state("v", 0.0, "m/s", "velocity")
    b.der(v, (f - c * v) / m)
    b.output("v_out", v, "m/s", "velocity")
    return b.build(integrator=integrator)

BLOCKS = {"damper": damper}
'''


def _scene(tmp_path: Path, module_text: str, params: str = "{}") -> Path:
    (tmp_path / "my_blocks.py").write_text(module_text)
    (tmp_path / "scene.yaml").write_text(textwrap.dedent(f"""\
        blocks: my_blocks.py
        stop_time: 1.0
        components:
          d: {{model: damper, params: {params}, options: {{integrator: rk4}}}}
        master: {{algorithm: jacobi, step: 1e-3}}
        outputs: [d.v_out]
        """))
    return tmp_path / "scene.yaml"


def test_a_scene_block_file_runs_and_matches_the_analytic_solution(tmp_path):
    res = run(_scene(tmp_path, GOOD, "{c: 2.0}"), ["components.d.start.f=4.0"], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    t, v = res.trace.time, res.trace["d.v_out"]
    assert np.abs(v - 2.0 * (1 - np.exp(-t))).max() < 1e-9  # v = f/c (1 - exp(-c t / m))


@pytest.mark.parametrize("bad, what", [
    ('"N.s/m"', "parameter 'c' has no unit"),
    ('"N.s/m", ""', "parameter 'c' has no description"),
])
def test_a_block_missing_a_unit_or_a_description_is_refused_at_load_in_one_line(tmp_path, bad, what):
    text = GOOD.replace('"N.s/m", "viscous friction coefficient"', '"", "viscous"' if "unit" in what else bad)
    with pytest.raises(SceneError) as err:
        load(_scene(tmp_path, text))
    (msg,) = str(err.value).splitlines()
    assert what in msg and "scene.yaml:4" in msg and "my_blocks.py" in msg, msg


@pytest.mark.parametrize("text, what", [
    ("BLOCKS = {'damper': lambda integrator='rk4': 1/0}", "ZeroDivisionError"),
    ("def f(:\n  pass", "my_blocks.py:1: syntax error"),
    ("X = 1", "defines no BLOCKS"),
    ("BLOCKS = {'mechanism': lambda: None}", "is a catalog model"),
    ("BLOCKS = {'damper': lambda integrator='rk4': 3}", "not a models.block.Block"),
])
def test_a_broken_block_module_is_one_line(tmp_path, text, what):
    with pytest.raises(SceneError) as err:
        load(_scene(tmp_path, text))
    (msg,) = str(err.value).splitlines()
    assert what in msg, msg


def test_editing_a_block_module_rebuilds_its_fmu_and_an_unchanged_one_does_not(tmp_path):
    def fmu(folder: str, text: str) -> Path:
        (tmp_path / folder).mkdir()
        return build_components(load(_scene(tmp_path / folder, text)))["d"]

    first, same = fmu("a", GOOD), fmu("b", GOOD)
    edited = fmu("c", GOOD.replace("(f - c * v) / m", "(f - c * v * v) / m"))
    assert first == same and edited != first


def test_a_block_from_an_installed_entry_point(tmp_path, monkeypatch):
    site = tmp_path / "site"
    (site / "rpr_user_damper").mkdir(parents=True)
    (site / "rpr_user_damper" / "__init__.py").write_text(GOOD)
    dist = site / "rpr_user_damper-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: rpr-user-damper\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[rpr_cosim.blocks]\nmy_damper = rpr_user_damper:damper\n")
    monkeypatch.syspath_prepend(str(site))
    data = {"stop_time": 0.5, "components": {"d": {"model": "my_damper", "params": {"m": 1.0, "c": 1.0},
                                                 "start": {"f": 1.0}}},
            "master": {"algorithm": "jacobi", "step": 1e-3}, "outputs": ["d.v_out"]}
    res = run(from_dict(data, base_dir=tmp_path))
    assert res.ok, res.reason
    assert res.trace["d.v_out"][-1] == pytest.approx(1 - math.exp(-0.5), abs=1e-9)
    sys.modules.pop("rpr_user_damper", None)


def test_the_builder_refuses_a_state_without_a_derivative():
    from models.user import BlockBuilder

    b = BlockBuilder("x", "a block")
    b.state("s", 0.0, "m", "position")
    with pytest.raises(BlockError, match="state 's' has no derivative"):
        b.build()


HELPED = GOOD.replace("from models.user import BlockBuilder", "from models.user import BlockBuilder\nimport helper") \
    .replace("(f - c * v) / m", "(f - helper.GAIN * c * v) / m")


def test_the_recipe_index_serves_an_unchanged_user_block_and_misses_an_edited_one(tmp_path, monkeypatch):
    """Indexed under the digests of the scene's blocks files, with the files their import loaded
    (here a helper module beside them) checked at every hit."""
    from fmus.index import IndexedBlock

    monkeypatch.setenv("RPR_COSIM_CACHE", str(tmp_path / "cache"))
    (tmp_path / "helper.py").write_text("GAIN = 1.0\n")
    scene = _scene(tmp_path, HELPED)

    def component():
        s = load(scene)
        return s.components["d"], build_components(s)["d"]

    first, fmu = component()
    assert not isinstance(first.block, IndexedBlock) and str(tmp_path / "helper.py") in first.depends
    again, fmu_again = component()
    assert isinstance(again.block, IndexedBlock) and fmu_again == fmu  # no module imported, no block built
    (tmp_path / "helper.py").write_text("GAIN = 2.0\n")
    edited, fmu_edited = component()
    assert not isinstance(edited.block, IndexedBlock) and fmu_edited != fmu
    (tmp_path / "my_blocks.py").write_text(HELPED + "# a comment\n")
    commented, fmu_commented = component()
    assert not isinstance(commented.block, IndexedBlock) and fmu_commented == fmu_edited  # same C: same FMU
    assert isinstance(component()[0].block, IndexedBlock)


LAG = """model Lag "first-order lag"
  parameter Real T(unit = "s", min = 1e-6) = 0.2 "time constant";
  input Real u(unit = "V") "input";
  output Real y(unit = "V", start = 0, fixed = true) "output";
equation
  T * der(y) = u - y;
end Lag;
"""


def test_the_recipe_index_serves_a_modelica_block_until_its_text_changes(tmp_path, monkeypatch):
    pytest.importorskip("rumoca")
    from fmus.index import IndexedBlock

    monkeypatch.setenv("RPR_COSIM_CACHE", str(tmp_path / "cache"))
    (tmp_path / "Lag.mo").write_text(LAG)
    data = {"stop_time": 0.01, "components": {"g": {"modelica": "Lag.mo", "model": "Lag",
                                                   "options": {"integrator": "rk4"}}},
            "master": {"algorithm": "jacobi", "step": 1e-3}}

    def component():
        s = from_dict(data, base_dir=tmp_path)
        return s.components["g"], build_components(s)["g"]

    first, fmu = component()
    hit, fmu_hit = component()
    assert not isinstance(first.block, IndexedBlock) and isinstance(hit.block, IndexedBlock) and fmu_hit == fmu
    assert hit.block.real().integrator == "rk4"  # the equations when a run needs them: translated again
    (tmp_path / "Lag.mo").write_text(LAG.replace("= 0.2", "= 0.3"))
    edited, fmu_edited = component()
    assert not isinstance(edited.block, IndexedBlock) and fmu_edited != fmu
    assert edited.block.params[0].default == 0.3


def test_fmu_build_and_show_take_a_users_python_block(tmp_path, capsys):
    from fmpy import read_model_description

    from cosim import cli

    (tmp_path / "my_blocks.py").write_text(GOOD)
    what = f"{tmp_path / 'my_blocks.py'}:damper"
    assert cli.main(["fmu", "build", what, "--set", "c=3", "--set", "integrator=radau",
                     "--cache", str(tmp_path / "cache")]) == 0
    fmu = Path(capsys.readouterr().out.strip())
    md = read_model_description(str(fmu))
    starts = {v.name: v.start for v in md.modelVariables}
    assert float(starts["c"]) == 3.0 and "solver.rtol" in starts  # the override and Radau's tolerances
    assert cli.main(["fmu", "show", what]) == 0
    out = capsys.readouterr().out
    assert "damper/default (my_blocks.py)" in out and "c         0.5 [N.s/m]  viscous friction coefficient" in out
    assert cli.main(["fmu", "build", what.replace("damper", "dumper")]) == 2
    assert "has no model 'dumper' (BLOCKS: damper)" in capsys.readouterr().err


def test_a_scene_with_a_user_block_travels_as_ssp_and_runs_the_same(tmp_path, ctc_runs):
    from cosim.run.ssp_export import export

    ssp = tmp_path / "ctc.ssp"
    export(load(SCENES / "computed_torque.yaml"), ssp)
    res = run(ssp, out_dir=tmp_path / "out")
    assert res.ok, res.reason
    ours = ctc_runs[0]
    assert np.abs(res.trace["mech.platform.x"] - ours["mech.platform.x"]).max() == 0.0


def test_a_user_blocks_rating_is_guarded_like_ours(tmp_path):
    """v = f/c (1 - exp(-c t / m)) = 2 (1 - exp(-t)) passes 1 m/s at t = ln 2: the rated guard
    stops the run there, with the partial trace and the reason."""
    rated = GOOD.replace('    return b.build(integrator=integrator)',
                         '    b.rating("v_out", -1.0, 1.0, "rated", "test limit")\n    return b.build(integrator=integrator)')
    res = run(_scene(tmp_path, rated, "{c: 2.0}"), ["components.d.start.f=4.0"], out_dir=tmp_path / "out")
    assert not res.ok and "d.v_out" in res.reason and "rated" in res.reason, res.reason
    assert res.trace.time[-1] == pytest.approx(math.log(2.0), abs=2e-3)
