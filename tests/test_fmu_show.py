"""``rpr-cosim fmu show``: every catalog parameter has a unit and a description, the FMU file view
agrees with FMPy's reading of the modelDescription, and the documentation site's model catalog is
the generated text (documentation cannot drift from the code)."""
from __future__ import annotations

from pathlib import Path

import pytest

import models.blocks as blocks
from cosim.analysis import model_doc
from cosim.cli import main

ROOT = Path(__file__).resolve().parents[1]
CATALOG = [(m, f) for m, fids in blocks.catalog().items() for f in fids]


@pytest.mark.parametrize("model, fidelity", CATALOG)
def test_every_catalog_parameter_has_a_unit_and_a_description(model, fidelity):
    blk = blocks.make(model, fidelity)
    missing = [p.name for p in blk.params if not p.unit or not p.description.strip()]
    assert not missing, f"{model}/{fidelity}: parameters without unit or description: {missing}"
    loose = [v.name for v in blk.inputs + blk.outputs + blk.states if not v.unit or not v.description.strip()]
    assert not loose, f"{model}/{fidelity}: signals without unit or description: {loose}"


@pytest.mark.parametrize("model, fidelity", CATALOG)
def test_fmu_show_lists_every_parameter_with_unit_and_description(model, fidelity, capsys):
    assert main(["fmu", "show", f"{model}/{fidelity}"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    for p in blocks.make(model, fidelity).params:
        row = next((ln for ln in lines if ln.split() and ln.split()[0] == p.name), None)
        assert row is not None, f"{p.name} not listed"
        assert f"[{p.unit}]" in row and p.description in row and f"{p.default:.6g}" in row


def test_fmu_show_of_a_file_agrees_with_fmpy(tmp_path, capsys):
    import fmpy

    import fmus

    path = fmus.build_fmu(blocks.make("dc_motor", "full"), cache_dir=tmp_path.parent / "fmu-cache")
    info = model_doc.fmu_info(path)
    md = fmpy.read_model_description(str(path))
    expected = {v.name: (v.unit, float(v.start), v.description) for v in md.modelVariables if v.causality == "parameter"}
    assert {p.name: (p.unit, p.default, p.description) for p in info.params} == expected
    assert [v.name for v in info.inputs] == [v.name for v in md.modelVariables if v.causality == "input"]
    assert main(["fmu", "show", str(path)]) == 0
    assert "canInterpolateInputs" in capsys.readouterr().out


def test_markdown_page_is_the_same_content(tmp_path):
    page = tmp_path / "pid.md"
    assert main(["fmu", "show", "pid/discrete", "--markdown", str(page)]) == 0
    text = page.read_text()
    assert text.startswith("# `pid/discrete`") and "discrete update every 0.001 s" in text
    for p in blocks.make("pid", "discrete").params:
        assert f"| `{p.name}` | {p.unit} |" in text


def test_the_docs_model_catalog_is_what_fmu_show_markdown_prints(capsys):
    """The site's model catalog is generated at build time from the same pages `fmu show --markdown` prints."""
    from docgen.reference import models_page

    page = models_page()
    for model, fids in blocks.catalog().items():
        for fid in fids:
            assert main(["fmu", "show", f"{model}/{fid}", "--markdown"]) == 0
            printed = capsys.readouterr().out
            assert printed.replace(f"# `{model}/{fid}`", f"### `{model}/{fid}`", 1) in page, (model, fid)


def test_fmu_show_readme_rewrites_a_marked_section(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{model_doc.BEGIN}\nstale\n{model_doc.END}\nend\n")
    assert model_doc.update_readme(readme) and model_doc.readme_section(readme) == model_doc.catalog_markdown()
    assert not model_doc.update_readme(readme)


@pytest.mark.parametrize("what, expected", [("pdi", "did you mean 'pid'"), ("pid/analog", "no fidelity 'analog'"),
                                            ("missing.fmu", "no such FMU file")])
def test_fmu_show_mistakes_are_one_line(what, expected, capsys):
    assert main(["fmu", "show", what]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0]
