"""The files a Modelica component is read from (cosim/scenario/modelica_sources.py): only those
its names reach through the source roots, all of them in the FMU's recipe key and the scene hash
(an edit of a sibling Base.mo used to run the old FMU, "up to date", with the old value; every
sibling .mo was parsed, an unrelated one defining the same class failed the scene)."""
from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("rumoca")

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import SceneError, load  # noqa: E402
from cosim.scenario.modelica_sources import ENV_VAR, SourceError, class_file, closure, modelica_class  # noqa: E402

MSL = Path(__file__).resolve().parents[2] / "shared" / "third_party" / "modelica-standard-library"
if not MSL.is_dir():  # a worktree beside the main checkout
    MSL = Path("/work/shared/third_party/modelica-standard-library")
needs_msl = pytest.mark.skipif(not (MSL / "Modelica" / "package.mo").is_file(),
                               reason="the Modelica Standard Library is not in ../shared/third_party")

BASE = """model Base "a constant source"
  parameter Real k = {k};
  output Real y;
equation
  y = k;
end Base;
"""
M = """model M "extends a sibling's class"
  extends Base;
end M;
"""
SCENE = """\
stop_time: 0.01
components:
  m: {modelica: M.mo, model: M}
master: {algorithm: jacobi, step: 1e-3}
outputs: [m.y]
"""


def _user_dir(tmp_path: Path, k: float = 2.0) -> Path:
    d = tmp_path / "user"
    d.mkdir(exist_ok=True)
    (d / "Base.mo").write_text(BASE.format(k=k))
    (d / "M.mo").write_text(M)
    (d / "scene.yaml").write_text(SCENE)
    return d


def test_only_the_files_a_class_reaches_are_read(tmp_path):
    d = _user_dir(tmp_path)
    (d / "Dup.mo").write_text(BASE.format(k=9.0))  # defines Base too: never read
    (d / "Junk.mo").write_text("model Junk this is not Modelica")  # a broken sibling: never read
    src = closure(d / "M.mo", [d])
    assert [p.name for p in src.files] == ["Base.mo"]
    assert set(src.key()) == {"modelica:M.mo", "modelica:Base.mo"}
    scene = load(d / "scene.yaml")  # the broken and duplicate siblings do not fail it
    assert scene.components["m"].block.param_defaults.tolist() == [2.0]


def test_an_edit_of_a_sibling_class_rebuilds_and_changes_the_scene_hash(tmp_path):
    d = _user_dir(tmp_path)
    first = run(d / "scene.yaml", [], out_dir=tmp_path / "one")
    assert first.ok and first.trace["m.y"][-1] == 2.0
    (d / "Base.mo").write_text(BASE.format(k=3.0))
    second = run(d / "scene.yaml", [], out_dir=tmp_path / "two")
    assert second.ok and second.trace["m.y"][-1] == 3.0  # the new value, not the cached FMU's
    assert load(d / "scene.yaml").hash != first.scene.hash


def test_a_library_on_modelicapath_is_found_and_keyed(tmp_path, monkeypatch):
    lib = tmp_path / "libs" / "MyLib"
    lib.mkdir(parents=True)
    (lib / "package.mo").write_text('package MyLib "a user library"\nend MyLib;\n')
    (lib / "Gain.mo").write_text('within MyLib;\nblock Gain "y = k u"\n  parameter Real k = 2;\n  input Real u;\n'
                                 '  output Real y;\nequation\n  y = k * u;\nend Gain;\n')
    (lib / "Unused.mo").write_text("within MyLib;\nmodel Unused broken\n")
    user = tmp_path / "user"
    user.mkdir()
    (user / "G.mo").write_text('model G "uses the library"\n  extends MyLib.Gain(k = 5);\nend G;\n')
    monkeypatch.setenv(ENV_VAR, os.pathsep.join([str(tmp_path / "nowhere"), str(tmp_path / "libs")]))
    from cosim.scenario.modelica_sources import roots_from_env

    mc = modelica_class("G.mo", "G", user, [r for r in roots_from_env() if r.is_dir()])
    assert sorted(mc.sources.key()) == ["modelica:G.mo", "modelica:MyLib/Gain.mo", "modelica:MyLib/package.mo"]
    from models.modelica import translate

    blk = translate(mc.text, "G", "G.mo", compiled=mc.compiled())
    assert blk.param_defaults.tolist() == [5.0]
    before = dict(mc.sources.key())
    (lib / "Gain.mo").write_text((lib / "Gain.mo").read_text().replace("k * u", "k * u + 1"))
    after = modelica_class("G.mo", "G", user, [tmp_path / "libs"]).sources.key()
    assert after["modelica:MyLib/Gain.mo"] != before["modelica:MyLib/Gain.mo"]


def test_a_class_name_without_roots_or_a_missing_root_is_one_line(tmp_path, monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)
    with pytest.raises(SourceError, match="no Modelica source roots"):
        modelica_class("Modelica.Blocks.Examples.PID_Controller", None, tmp_path, [])
    (tmp_path / "scene.yaml").write_text(textwrap.dedent("""\
        stop_time: 0.1
        modelica_path: [no_such_dir]
        components:
          c: {modelica: Modelica.Blocks.Examples.PID_Controller}
        master: {algorithm: jacobi, step: 1e-3}
        """))
    with pytest.raises(SceneError) as err:
        load(tmp_path / "scene.yaml")
    (line,) = str(err.value).splitlines()
    assert "scene.yaml:2" in line and "modelica_path: 'no_such_dir' is not a directory" in line, line
    # connected to another component: still one line (pid_step_msl outside the main checkout said
    # "unknown component 'motor1'" twice more, at the lines of its included scene)
    (tmp_path / "scene.yaml").write_text(textwrap.dedent("""        stop_time: 0.1
        modelica_path: [no_such_dir]
        components:
          c: {modelica: Modelica.Mechanics.Translational.Components.Mass}
          f: {model: oscillator}
        connections: [f.x -> c.u]
        master: {algorithm: jacobi, step: 1e-3}
        """))
    with pytest.raises(SceneError) as err:
        load(tmp_path / "scene.yaml")
    (line,) = str(err.value).splitlines()
    assert "modelica_path: 'no_such_dir' is not a directory" in line, line


@needs_msl
def test_an_msl_class_reads_a_few_hundred_of_the_librarys_files():
    main = class_file("Modelica.Mechanics.Translational.Examples.Oscillator", [MSL])
    assert main == MSL / "Modelica/Mechanics/Translational/Examples/Oscillator.mo"
    src = closure(main, [MSL])
    names = {str(p.relative_to(MSL)) for p in src.files}
    for needed in ("Modelica/Mechanics/Translational/Components/Mass.mo", "Modelica/Blocks/Sources.mo",
                   "Modelica/Units.mo", "Modelica/Mechanics/Translational/Interfaces/PartialCompliant.mo"):
        assert needed in names
    assert not any(n.startswith(("Modelica/Fluid", "Modelica/Media")) for n in names)
    total = sum(1 for _ in MSL.rglob("*.mo"))
    assert len(names) < total / 4, (len(names), total)
