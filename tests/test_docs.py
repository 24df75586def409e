"""The documentation site: ``mkdocs build --strict`` passes (a warning fails it: a broken link, a
page left out of the nav, a missing page), the reference pages are generated from the code and
change when a declaration changes, every page under docs/ reaches the nav, the Python API page's
cells run, the quoted figures match what their command prints, and the README stays short with
its two quick-start commands."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from docgen import reference

ROOT = Path(__file__).resolve().parents[1]
MKDOCS = Path(sys.executable).with_name("mkdocs")
pytestmark = pytest.mark.skipif(not MKDOCS.is_file(), reason="mkdocs is not installed (pip install -e '.[docs]', "
                                                              "which .ci/setup does)")


def build(config: Path, site: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", PYTHONPATH=str(ROOT))
    return subprocess.run([str(MKDOCS), "build", "--strict", "-f", str(config), "-d", str(site)], capture_output=True,
                          text=True, cwd=config.parent, env=env, timeout=600)


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    res = build(ROOT / "mkdocs.yml", tmp_path / "site")
    assert res.returncode == 0, res.stderr[-4000:]
    site = tmp_path / "site"
    for rel in reference.PAGES:  # the generated pages are in the site
        html = (site / rel.replace(".md", "") / "index.html").read_text()
        assert "generated from the code" in html
    cli = (site / "reference" / "cli" / "index.html").read_text()
    for verb in ("run", "batch", "compare", "report", "study stability", "fmu show", "board virtual"):
        assert f"rpr-cosim {verb}</code>" in cli, verb


def test_a_broken_link_fails_the_build(tmp_path):
    """The strict build can fail: a copy of the site with one dead link does."""
    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    shutil.copy(ROOT / "mkdocs.yml", tmp_path / "mkdocs.yml")
    (tmp_path / "docgen").symlink_to(ROOT / "docgen")
    page = tmp_path / "docs" / "tutorial.md"
    page.write_text(page.read_text() + "\nSee [nowhere](no-such-page.md).\n")
    res = build(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert res.returncode != 0 and "no-such-page.md" in res.stderr


def test_a_page_added_to_docs_reaches_the_nav(tmp_path):
    """A helper's docs/<topic>.md not named in mkdocs.yml is put under 'More topics' by the hook."""
    from docgen import hooks

    (tmp_path / "a.md").write_text("# a")
    (tmp_path / "new-topic.md").write_text("# new")
    config = {"docs_dir": str(tmp_path), "nav": [{"Home": "a.md"}]}
    assert hooks.on_config(config)["nav"] == [{"Home": "a.md"}, {"More topics": ["new-topic.md"]}]


def test_the_scene_reference_changes_when_the_checkers_declarations_change(monkeypatch):
    from cosim.scenario import keys

    before = reference.scene_page()
    for k, meaning in keys.COMPONENT.items():
        assert f"| `{k}` | {meaning.replace('|', chr(92) + '|')} |" in before
    monkeypatch.setitem(keys.COMPONENT, "priority", "a new key of a component")
    after = reference.scene_page()
    assert "| `priority` | a new key of a component |" in after and "`priority`" not in before


def test_the_batch_reference_changes_when_the_batch_checker_changes(monkeypatch):
    from cosim.batch import spec

    monkeypatch.setitem(spec.PLOT_KINDS, "scatter", ("metric", "x"))
    assert "| `scatter` | `metric`, `x` |" in reference.batch_page()


def test_the_algorithm_reference_follows_the_options_each_algorithm_declares(monkeypatch):
    from cosim.master.algorithm import ALGORITHMS, AlgorithmOption

    page = reference.algorithms_page()
    for name, cls in ALGORITHMS.items():
        assert f"## `{name}`" in page
        for o in getattr(cls, "options", ()) or ():
            assert f"| `{o.name}` |" in page
    extra = AlgorithmOption("gain", 0.5, 0.0, 1.0, "1", "a new option")
    monkeypatch.setattr(ALGORITHMS["adaptive"], "options", (*ALGORITHMS["adaptive"].options, extra))
    assert "| `gain` | `0.5` | [0, 1] | 1 | a new option |" in reference.algorithms_page()


def test_the_cli_reference_lists_every_argument_of_every_parser(monkeypatch):
    from cosim.cli import build_parser

    page = reference.cli_page()
    run = reference._subparsers(build_parser())["run"]
    for action in run._actions:
        for opt in action.option_strings:
            if opt not in ("-h", "--help"):
                assert f"`{opt}`" in page, opt
    from cosim.cli import grammar

    def register(sub):
        grammar._run(sub)
        sub.choices["run"].add_argument("--brand-new", help="an argument added to the parser")

    monkeypatch.setattr(grammar, "VERBS", tuple(register if v is grammar._run else v for v in grammar.VERBS))
    assert "| `--brand-new` BRAND_NEW | an argument added to the parser |" in reference.cli_page()


def test_the_python_api_page_runs(tmp_path, monkeypatch):
    """Every Python cell of how-to/python-api.md, in order, in one namespace (as a notebook)."""
    from cosim.run import run

    text = (ROOT / "docs" / "how-to" / "python-api.md").read_text()
    cells = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(cells) >= 4
    (tmp_path / "scenarios").symlink_to(ROOT / "scenarios")
    run(ROOT / "scenarios" / "pid_step.yaml", ["stop_time=0.5"], out_dir=tmp_path / "runs" / "pid_step")
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "docs_page"}  # the batch cell's `if __name__ == "__main__"` does not start workers
    for cell in cells:
        exec(compile(cell.replace("stop_time=2", "stop_time=0.3"), "python-api.md", "exec"), namespace)
    sweep = namespace["sweep"]
    assert list(sweep.index) == [20, 30, 45, 60] and (sweep["status"] == "ok").all()
    assert sweep["phi_max"].is_monotonic_increasing  # a stiffer loop turns the platform faster
    assert (tmp_path / "phi_sweep.png").stat().st_size > 10_000


def test_the_quoted_figures_match_what_their_command_prints(capsys, tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import figures
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    pages = sorted((ROOT / "docs").rglob("*.md"))
    assert figures.check(pages) == 0, capsys.readouterr().out
    assert re.search(r"[1-9]\d* quoted outputs checked, 0 problems", capsys.readouterr().out)
    # and it finds a figure that no longer matches
    page = tmp_path / "stale.md"
    text = (ROOT / "docs" / "reference" / "results.md").read_text()
    page.write_text(text.replace("max |error| 4.3e-05 m", "max |error| 2.1e-05 m"))
    assert figures.check([page]) == 1
    assert "2.1e-05" in capsys.readouterr().out


def test_the_readme_is_short_and_keeps_the_quick_start():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) < 250
    assert "bash .ci/setup && .venv/bin/rpr-cosim run scenarios/pid_step.yaml --plot --animate --reference" in text
    assert "bash .ci/setup && .venv/bin/python -m pytest -q" in text
    for link in re.findall(r"\]\(([^)#]+)\)", text):
        assert (ROOT / link).exists(), link
