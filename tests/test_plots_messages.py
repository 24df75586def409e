"""Plots that draw every recorded variable with units (issue 32, item 7) and messages that help
(item 8): did-you-mean for a misspelt component in a ``--set`` path, ``compare --only`` globs with
character classes as the docs write them."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cosim.analysis import charts
from cosim.analysis.trace_diff import common_names, matches
from cosim.cli import main
from cosim.scenario import load
from cosim.trace.traces import Trace, read_trace, trace_writer

SCENES = Path(__file__).resolve().parents[1] / "scenarios"


def test_vw_compares_run_chart_draws_every_recorded_variable():
    """The issue's measurement: vw_compare.png lacked the multibody half (panels beyond 24 dropped)."""
    scene = load(SCENES / "vw_compare.yaml")
    panels = charts.run_panels(scene.outputs, {})
    drawn = [n for p in panels for n, _ in p.lines]
    assert len(panels) > 24 and sorted(drawn) == sorted(scene.outputs)
    assert any(n.startswith("multibody.") for n in drawn)


def test_a_chart_of_many_panels_is_one_taller_page(tmp_path, monkeypatch):
    names = [f"block_{chr(97 + i // 26)}{chr(97 + i % 26)}.v" for i in range(30)]
    t = np.linspace(0, 1, 11)
    tr = Trace(["time", *names], np.column_stack([t, *[t * k for k in range(30)]]))
    seen = {}
    real = charts._save
    monkeypatch.setattr(charts, "_save", lambda fig, path: seen.setdefault("fig", fig) and real(fig, path))
    charts.plot_run(tr, tmp_path / "many.png", "many", units={n: "m" for n in names})
    axes = [ax for ax in seen["fig"].axes if ax.get_visible()]
    assert len(axes) == 30 and all(ax.get_ylabel() == "[m]" for ax in axes)
    fig = seen["fig"]  # the page's title clear of the first row's titles (it sat on them on a tall page)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()
    top = fig._suptitle.get_window_extent(renderer)
    assert not any(top.overlaps(ax.title.get_window_extent(renderer)) for ax in axes)
    assert (tmp_path / "many.png").stat().st_size > 0


def test_batch_trace_plots_carry_the_unit(tmp_path, monkeypatch):
    from cosim.batch import overview

    for rid, k in (("a1", 1.0), ("b2", 2.0)):
        ob = trace_writer(tmp_path / "runs" / rid / "s.csv")
        ob.start(["time", "m.x"], {"units": {"m.x": "m"}})
        ob.record(np.array([[0.0, 0.0], [1.0, k]]))
        ob.finish("ok", "", {})
    assert read_trace(tmp_path / "runs" / "a1" / "s.csv").meta["units"] == {"m.x": "m"}
    seen = {}
    monkeypatch.setattr(overview, "_save", lambda fig, plt, path: seen.setdefault("fig", fig))
    rows = [{"run_id": "a1", "outcome": "ok"}, {"run_id": "b2", "outcome": "ok"}]
    overview.plot_traces(tmp_path, rows, "m.x", "all", None, [], tmp_path / "p.png")
    assert seen["fig"].axes[0].get_ylabel() == "m.x [m]"
    assert seen["fig"].axes[0].get_title() == "m.x: 2 runs"
    monkeypatch.setattr(overview, "MAX_TRACES", 1)  # beyond the chart's limit, its title says how many it drew
    seen.clear()
    overview.plot_traces(tmp_path, rows, "m.x", "all", None, [], tmp_path / "p.png")
    assert seen["fig"].axes[0].get_title() == "m.x: the first 1 of 2 runs" and len(seen["fig"].axes[0].lines) == 1


def test_batch_metric_charts_carry_the_units_of_their_axes_and_metrics(tmp_path, monkeypatch):
    """The tutorial's batch: Kp and Kd in the PID block's units, overshoot in %, settling time in
    s, a value measure in its signal's unit (the metrics' table, cosim/batch/metrics.py), on the
    PNG charts and on the HTML report's titles."""
    from cosim.analysis.html_report import metric_figures
    from cosim.batch import load_batch, overview
    from cosim.batch.spec import axis_units
    from models import blocks

    gains = {p.name: p.unit for p in blocks.make("pid", "continuous").params}
    batch = load_batch(SCENES / "batch_pid_gains.yaml")
    assert axis_units(batch) == {"Kp": gains["Kp"], "Kd": gains["Kd"]} and gains["Kp"] == "V/m"
    for rid, k in (("a1", 1.0), ("b2", 2.0)):
        ob = trace_writer(tmp_path / "runs" / rid / "s.csv")
        ob.start(["time", "m.x"], {"units": {"m.x": "m"}})
        ob.record(np.array([[0.0, 0.0], [1.0, k]]))
        ob.finish("ok", "", {})
    rows = [{"run_id": "a1", "outcome": "ok", "Kp": 1, "Kd": 1, "m.x:overshoot": 5.0, "m.x:max": 1.0},
            {"run_id": "b2", "outcome": "ok", "Kp": 2, "Kd": 1, "m.x:overshoot": 7.0, "m.x:max": 2.0}]
    units = {**axis_units(batch), **overview.metric_units(tmp_path, rows, ["m.x:overshoot", "m.x:settling_time",
                                                                          "m.x:max"])}
    assert units == {"Kp": "V/m", "Kd": "V.s/m", "m.x:overshoot": "%", "m.x:settling_time": "s", "m.x:max": "m"}
    seen = []
    monkeypatch.setattr(overview, "_save", lambda fig, plt, path: seen.append(fig))
    overview.plot_heatmap(rows, "m.x:overshoot", "Kp", "Kd", tmp_path / "h.png", units=units)
    overview.plot_lines(rows, "m.x:max", "Kp", "Kd", ["Kp", "Kd"], tmp_path / "l.png", units=units)
    heat, lines = seen
    assert heat.axes[0].get_xlabel() == "Kp [V/m]" and heat.axes[0].get_ylabel() == "Kd [V.s/m]"
    assert heat.axes[1].get_ylabel() == "m.x:overshoot [%]"  # the colour bar
    assert lines.axes[0].get_xlabel() == "Kp [V/m]" and lines.axes[0].get_ylabel() == "m.x:max [m]"
    fig = metric_figures(rows, ["Kp", "Kd"], ["m.x:overshoot"], units)[0]
    assert fig.layout.xaxis.title.text == "Kp [V/m]" and fig.data[0].colorbar.title.text == "m.x:overshoot [%]"
    # the batch's description keeps each axis's unit for `rpr-cosim report` (batch.json)
    import json

    from cosim.batch.runner import _describe

    (tmp_path / "batch.json").write_text(json.dumps(_describe(batch, [])))
    assert overview.batch_meta(tmp_path)["axis_units"] == {"Kp": "V/m", "Kd": "V.s/m"}


def test_a_misspelt_component_in_a_set_path_gets_the_closest_name(capsys):
    code = main(["run", str(SCENES / "pid_step.yaml"), "--set", "components.pdi1.params.Kp=40", "--check"])
    err = capsys.readouterr().err
    assert code == 2 and "the scene has no component 'pdi1'; did you mean 'pid1'?" in err
    assert "needs 'model:'" not in err and "Traceback" not in err


@pytest.mark.parametrize("pattern, hint", [("pdi*", "pid*"), ("motr?", "motor?"), ("mtor[12]", "motor[12]"),
                                           ("zz*", None)])
def test_a_misspelt_wildcard_in_a_set_path_or_a_batch_axis_gets_a_pattern_that_matches(tmp_path, capsys, pattern, hint):
    """Issue 32, item 8, a wildcard too (``--set 'components.pdi*.params.Kp=40'``, a batch axis):
    the mended pattern is offered only where it matches components of the scene."""
    import fnmatch

    names = ["target", "pid1", "pid2", "pid3", "motor1", "motor2", "motor3", "mech"]
    if hint:
        assert any(fnmatch.fnmatchcase(n, hint) for n in names)  # the suggestion is one that works
    code = main(["run", str(SCENES / "pid_step.yaml"), "--set", f"components.{pattern}.params.Kp=40", "--check"])
    err = capsys.readouterr().err
    assert code == 2 and f"{pattern!r} in 'components.{pattern}.params.Kp' matches no component" in err
    assert (f"did you mean {hint!r}?" in err) if hint else ("did you mean" not in err)
    batch = tmp_path / "b.yaml"
    batch.write_text(f"name: b\nscene: {SCENES / 'pid_step.yaml'}\ngrid:\n"
                     f"  Kp: {{path: \"components.{pattern}.params.Kp\", values: [20, 40]}}\n")
    assert main(["batch", str(batch), "--check"]) == 2
    err = capsys.readouterr().err
    assert f"{batch}:4: error:" in err and ((f"did you mean {hint!r}?" in err) if hint else ("did you mean" not in err))


def test_a_new_component_set_whole_is_still_allowed():
    scene = load(SCENES / "pid_step.yaml", ["components.extra={model: pid}", "components.extra.params.Kp=3"])
    assert scene.components["extra"].params["Kp"] == 3


@pytest.mark.parametrize("pattern, hits", [
    ("mech.platform.[xy]", ["mech.platform.x", "mech.platform.y"]),  # the issue's pattern
    ("mech.platform.*", ["mech.platform.x", "mech.platform.y", "mech.platform.phi"]),
    ("mech.leg[1].s", ["mech.leg[1].s"]), ("mech.leg[*].s", ["mech.leg[1].s", "mech.leg[2].s"]),
])
def test_only_patterns_work_as_documented(pattern, hits):
    names = ["mech.platform.x", "mech.platform.y", "mech.platform.phi", "mech.leg[1].s", "mech.leg[2].s"]
    assert [n for n in names if matches(n, pattern)] == hits
    tr = Trace(["time", *names], np.zeros((2, 6)))
    assert common_names(tr, tr, [pattern]) == hits


def test_version(capsys):
    """``rpr-cosim --version`` (issue 32, item 11) prints the version pyproject.toml declares."""
    import re

    with pytest.raises(SystemExit) as done:
        main(["--version"])
    declared = re.search(r'^version = "([^"]+)"', (SCENES.parent / "pyproject.toml").read_text(), re.M).group(1)
    assert done.value.code == 0 and capsys.readouterr().out.strip() == f"rpr-cosim {declared}"


def test_every_folder_of_sources_shipped_is_a_listed_package():
    """setuptools warns a wall of text for a folder of package data that Python could import
    ('hardware.c' is absent from packages): every such folder of ours is listed."""
    import tomllib

    conf = tomllib.loads((SCENES.parent / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(conf["packages"]["find"]["include"])
    for folder in ("fmus/c", "hardware/c"):
        assert folder.replace("/", ".") in listed and folder.replace("/", ".") in conf["package-data"]


#: The terms a run summary prints (its fixed words: status, verdict, table headers, labels) -> the
#: glossary entry that explains each.
SUMMARY_TERMS = {"master chose": "choice", "pilot run": "pilot run", "compiled loop": "compiled loop",
                 "real-time factor": "real-time factor", "build": "build", "init": "init",
                 "estimated worst error": "error estimate", "of range": "range", "companion run": "companion run",
                 "verdict": "verdict", "doStep": "doStep", "us/step": "doStep", "share": "doStep",
                 "final values": "final values", "trace": "trace", "scene hash": "scene hash", "status": "status",
                 "inaccurate": "status", "tolerance": "tolerance"}


def summary_terms(lines: list[str]) -> set[str]:
    """The labels a run's printed summary uses, collected from its text: every table's column
    labels, the label before ':' of each line (``verdict``, ``final values``, ``plot``...), the
    heading of a parenthesised result (``monolithic reference (...)``) and the method words of its
    statistics lines."""
    terms: set[str] = set()
    words = re.compile(r"\b(Richardson|companion run|pilot runs?|compiled loop|python loop|real-time factor|h_max|"
                       r"rtol|rejected|build|init|inputs (?:linear|hold)|of range)\b")
    for ln in lines:
        s = ln.strip()
        if re.match(r"^(slave|variable)\s{2,}", s):
            terms |= set(re.split(r"\s{2,}", s))
            continue
        m = re.match(r"^([a-z][a-z -]*?)(?: at t = [^:]*)?:", s)
        if m and not s.startswith(("rpr-cosim", "scene ")):
            terms.add(m.group(1))
        terms |= set(words.findall(s))
        m = re.match(r"^([a-z][a-z -]+?) \(", s)
        if m and not ln.startswith(" "):
            terms.add(m.group(1))
    return terms


def test_every_label_of_a_real_summary_has_a_glossary_entry(tmp_path, cache, capsys):
    """Issue 32, item 8, from what a run prints rather than a list: pid_step with the reference
    table, plot and report; each label :func:`summary_terms` collects is a bold entry of the
    glossary (in a bold term)."""
    gloss = (SCENES.parent / "docs" / "reference" / "glossary.md").read_text().lower()
    code = main(["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=0.05", "--reference", "--plot",
                 "--report", "--out", str(tmp_path), "--cache", str(cache)])
    printed = capsys.readouterr()
    terms = summary_terms((printed.out + printed.err).splitlines())
    assert code == 0 and {"max |diff|", "rms", "us/step", "verdict", "final values", "plot"} <= terms, terms
    entries = " | ".join(re.findall(r"\*\*(.+?)\*\*", gloss))  # the glossary's bold terms
    assert sorted(t for t in terms if t.lower() not in entries) == []


def test_every_term_a_summary_prints_is_in_the_glossary(tmp_path, cache, capsys):
    """Issue 32, item 8: a run that chooses (pilots, companion) and a named one judged inaccurate;
    each term of :data:`SUMMARY_TERMS` is in what they print and has a glossary entry."""
    gloss = (SCENES.parent / "docs" / "reference" / "glossary.md").read_text().lower()
    main(["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=0.05", "--out", str(tmp_path / "a"),
          "--cache", str(cache)])
    main(["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=0.05", "--set", "master.algorithm=gauss_seidel",
          "--out", str(tmp_path / "b"), "--cache", str(cache)])
    printed = capsys.readouterr()
    text = (printed.out + printed.err).lower()
    for term in SUMMARY_TERMS:
        if term in ("scene hash", "status"):
            continue  # printed as [digits] and as the status itself
        assert term.lower() in text, term
    for term, entry in SUMMARY_TERMS.items():
        assert f"**{entry.lower()}" in gloss and term.lower() in gloss, (term, entry)


def test_the_fast_gif_draws_every_frame(tmp_path):
    """Issue 32, item 11: frames blitted on a background rendered once, captions by Pillow: the
    frame count and timing asked for, the legs (green) and the platform (orange) in the last
    frame, and between the first and the last frame only the moving part changed (the speed is
    benchmarks/bench_main_job.py's)."""
    from PIL import Image

    from cosim.analysis import animate as anim

    t = np.linspace(0.0, 1.0, 201)
    tr = Trace(["time", "mech.platform.x", "mech.platform.y", "mech.platform.phi"],
               np.column_stack([t, -0.15 - 0.05 * t, -0.15 + 0.02 * t, 0.2 * t]))
    path = anim.animate(tr, tmp_path / "a.gif", fps=10)
    gif = Image.open(path)
    assert gif.n_frames == 11 and gif.info["duration"] == 100 and gif.info.get("loop") == 0
    first = np.asarray(gif.convert("RGB"), dtype=int)
    gif.seek(10)
    last = np.asarray(gif.convert("RGB"), dtype=int)
    assert last.shape[:2] == (416, 416)
    green = (np.abs(last - np.array([44, 160, 44])).sum(axis=2) < 60).sum()  # tab:green legs
    orange = (np.abs(last - np.array([255, 166, 87])).sum(axis=2) < 90).sum()  # tab:orange at alpha 0.7
    assert green > 300 and orange > 300, (green, orange)
    moved = (np.abs(first - last).sum(axis=2) > 60).mean()
    assert 0.005 < moved < 0.2, moved  # the platform moved and the rest stayed


def test_fmu_show_lists_what_each_option_choice_adds(capsys):
    """Issue 32, item 9: the tutorial's oscillator uses x_in and kc (coupling: spring), which
    ``fmu show oscillator`` (the default coupling: none) did not list; the variants are compared
    with the blocks made at each choice."""
    from models import blocks

    assert main(["fmu", "show", "oscillator"]) == 0
    out = capsys.readouterr().out
    spring = blocks.make("oscillator", "linear", coupling="spring")
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("coupling=spring:"))
    for v in spring.inputs:
        if v.name in ("x_in", "v_in"):
            assert f"+ input {v.name} [{v.unit}]" in line
    assert "+ parameter kc [N/m]" in line
    from cosim.analysis.model_doc import catalog_markdown

    assert "`coupling=spring`: + input x_in [m]" in catalog_markdown()  # the catalog reference page too


@pytest.mark.parametrize("pattern, hint", [("mehc.platform.*", "did you mean 'mech.platform.*'?"),
                                           ("mech.platfrom.x", "did you mean 'mech.platform.x'?")])
def test_compare_only_names_the_closest_component_or_variable(pattern, hint):
    """Issue 32, item 8: did-you-mean wherever a path names a component (compare --only too)."""
    from cosim.errors import UserError

    names = ["mech.platform.x", "mech.platform.y", "pid1.y"]
    tr = Trace(["time", *names], np.zeros((2, 4)))
    with pytest.raises(UserError, match=hint.replace("?", r"\?").replace("*", r"\*").replace(".", r"\.")):
        common_names(tr, tr, [pattern])


def test_a_misspelt_component_in_a_connection_or_an_output_gets_the_closest_name(tmp_path, capsys):
    """The scene's connections and outputs: one line each naming the closest component."""
    text = (SCENES / "pid_step.yaml").read_text()
    assert "mech.leg[1].s -> pid1.measurement" in text and "  - mech.platform.*" in text
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("mech.leg[1].s -> pid1.measurement", "mech.leg[1].s -> pdi1.measurement")
                   .replace("  - mech.platform.*", "  - mehc.platform.*"))
    assert main(["run", str(bad), "--check"]) == 2
    err = capsys.readouterr().err
    assert "unknown component 'pdi1' in 'pdi1.measurement'; did you mean 'pid1'?" in err
    assert "'mehc.platform.*'" in err and "did you mean 'mech.platform." in err


def test_a_comparison_chart_says_how_many_of_the_variables_it_draws(tmp_path):
    """Issue 32, item 7: `run --reference` draws the 8 worst variables of pid_step's 24; the page
    says so (it dropped the other 16 without a word), clear of the first row's titles."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from cosim.analysis.trace_diff import compare

    names = [f"m{k}.x" for k in range(10)]
    t = np.linspace(0, 1, 101)
    test = Trace(["time", *names], np.column_stack([t, *[np.sin(t) * (1 + 1e-3 * k) for k in range(10)]]))
    ref = Trace(["time", *names], np.column_stack([t, *[np.sin(t) for _ in range(10)]]))
    diffs = compare(test, ref)
    fig = charts.comparison_figure(test, ref, diffs, labels=("run", "reference"), units={n: "m" for n in names})
    title = fig._suptitle.get_text()
    assert "the 8 worst of 10 variables" in title and "every one in the printed table" in title
    renderer = FigureCanvasAgg(fig).get_renderer()
    top = fig._suptitle.get_window_extent(renderer)
    assert not any(top.overlaps(ax.title.get_window_extent(renderer)) for ax in fig.axes)
    few = charts.comparison_figure(test, ref, diffs[:3], most=8)
    assert "all 3 variables" in few._suptitle.get_text()


def test_the_report_animation_draws_the_joint_labels_whole():
    """The run report's animation cut "A2" at the plot's right edge (the range ends 8 % beyond the
    joints): the labels are drawn beyond the axes into a margin wide enough for them."""
    from cosim.analysis.html_report import animation_figure

    t = np.linspace(0.0, 1.0, 11)
    tr = Trace(["time", "mech.platform.x", "mech.platform.y", "mech.platform.phi"],
               np.column_stack([t, -0.15 - 0.05 * t, -0.15 + 0.0 * t, 0.2 * t]))
    fig = animation_figure(tr)
    joints = next(d for d in fig.data if d.name == "fixed joints")
    assert list(joints.text[:3]) == ["A1", "A2", "A3"] and joints.textposition == "top right"
    right_most = max(joints.x)
    assert fig.layout.xaxis.range[1] < right_most + 0.05  # the label would reach past the range ...
    assert joints.cliponaxis is False and fig.layout.margin.r >= 25  # ... and is drawn there, whole
