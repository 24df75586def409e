"""No report runs a stranger's script (issue 33, item 1): a script planted in every field a
report shows (a scene's name, a trace's column names and units, a sidecar's status, reason and
statistics down to ``statistics.slaves.*``, a batch's name, axis names, metric columns, run ids
and cells, a study table's cells) is shown as text.  Each report is loaded in headless Chromium
and the test asserts that no planted script ran; a positive control shows the harness sees one
that does.  In CI (``$CI`` set) a missing Chromium fails these tests instead of skipping them.

The payloads mark the page (``data-pwned`` on the root element) when they run, through every
route: ``</script>`` closing the JSON's script block, an ``<img onerror>`` in HTML text or an
attribute, ``<!--<script>`` inside a script, a ``javascript:`` link and U+2028 in JSON."""
from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from cosim.cli import main
from cosim.analysis.safe_html import href, label, script_json, text

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--virtual-time-budget=6000", "--window-size=1200,900"]

MARK = "document.documentElement.setAttribute('data-'+'pwned', 'x')"  # the page says data-pwned only if it ran
PAYLOADS = [
    f"</script><script>{MARK}</script>",
    f"\"'><img src=x onerror=\"{MARK}\">",
    f"<!--<script>{MARK}</script>",
    f"<svg onload=\"{MARK}\"></svg>\u2028\u2029",
    f"<a href=\"javascript:{MARK}\">x</a>",
]
#: Run ids name directories: no slash, so only the slash-free payloads
RUN_IDS = [f"<img src=x onerror={MARK.replace(' ', '')}>", "ab12cd34ef56ab78"]


def _chromium() -> str:
    if CHROMIUM is None:
        msg = "headless Chromium is not installed (as root: apt-get install -y chromium; .ci/setup does it)"
        if os.environ.get("CI"):
            pytest.fail(msg + "; CI must run the report tests")
        pytest.skip(msg)
    return CHROMIUM


def dom_of(page: Path) -> str:
    """The DOM of ``page`` after its scripts ran (headless Chromium, network off)."""
    exe = _chromium()
    with tempfile.TemporaryDirectory() as profile:
        res = subprocess.run([exe, *FLAGS, f"--user-data-dir={profile}", "--dump-dom", page.resolve().as_uri()],
                             capture_output=True, text=True, timeout=180)
    assert "</html>" in res.stdout, res.stderr[-2000:]
    return res.stdout


def pwned(page: Path) -> bool:
    return "data-pwned" in dom_of(page)


def test_the_harness_sees_a_planted_script_run(tmp_path):
    """The positive control: a payload placed raw in a page runs (in a script's JSON as
    ``json.dumps`` writes it, in HTML text)."""
    for k, (where, p) in enumerate((("script", PAYLOADS[0]), ("text", PAYLOADS[1]), ("text", PAYLOADS[3]))):
        page = tmp_path / f"raw{k}.html"
        body = f"<script>var x = {json.dumps(p)};</script>" if where == "script" else f"<p>{p}</p>"
        page.write_text(f"<!DOCTYPE html><html><head><title>t</title></head><body>{body}</body></html>")
        assert pwned(page), p


def test_the_helper_escapes_every_route():
    for p in PAYLOADS:
        for out in (text(p), label(p)):
            assert "<" not in out and ">" not in out
        assert "'" not in text(p) and '"' not in text(p)
        js = script_json({"k": p, p: [p, float("nan")]})
        assert not any(c in js for c in "<>&\u2028\u2029") and json.loads(js)["k"] == p
    assert ":" not in href("javascript:alert(1)")
    assert href("runs/ab/x.html") == "runs/ab/x.html"


def _p(k: int) -> str:
    return PAYLOADS[k % len(PAYLOADS)]


def _run_dir(root: Path) -> Path:
    """A received run whose every shown field carries a payload: trace columns, units, the
    sidecar's scene, hash, start, algorithm, status, reason and statistics."""
    d = root / "run"
    d.mkdir()
    cols = ["time", f"a.x{_p(0)}", f"a.v{_p(1)}", f"b.y{_p(2)}", "mech.platform.x", "mech.platform.y",
            "mech.platform.phi"]
    with open(d / "r.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(cols)
        for i in range(21):
            t = 0.01 * i
            w.writerow([t, t, 2 * t, -t, 0.01 * t, 0.01 * t, 0.01 * t])
    stats = {"algorithm": _p(0), "engine": _p(1), "step": _p(2), "steps_done": _p(3), "wall_s": _p(4),
             "slaves": {_p(0): {"do_step_calls": _p(1), "wall_s": _p(2)}, "b": {"do_step_calls": 3, "wall_s": 1e-3}},
             "guards": {"warnings": [_p(3), _p(4)]}}
    side = {"scene": _p(0), "scene_hash": _p(1), "started": _p(2), "algorithm": _p(3), "trace": "r.csv",
            "format": "rpr-cosim trace 1", "units": {cols[1]: _p(4), cols[2]: _p(0)},
            "connections": [f"a.x{_p(0)} -> c.setpoint", f"b.y{_p(2)} -> c.measurement"],
            "status": "failed", "reason": _p(1), "rows": 21, "statistics": stats}
    (d / "r.json").write_text(json.dumps(side))
    return d / "r.csv"


def _batch_dir(root: Path, name: str, axes: list[str]) -> Path:
    """A batch's directory: its name, axis names, metric column, run ids and cells carry payloads."""
    out = root / name
    metric = f"y{_p(1)}:max"
    columns = ["run_id", "index", *axes, "outcome", "reason", metric]
    rows = []
    for k, rid in enumerate(RUN_IDS):
        rows.append([rid, k, *[float(k + j) for j, _ in enumerate(axes)], "ok" if k else _p(2), _p(3), 0.5 * k])
        run = out / "runs" / rid
        run.mkdir(parents=True)
        with open(run / "s.csv", "w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(["time", f"y{_p(1)}", f"z{_p(4)}"])
            for i in range(11):
                w.writerow([0.1 * i, i * (k + 1), -i])
        (run / "s.json").write_text(json.dumps({"scene_hash": "0", "trace": "s.csv", "format": "rpr-cosim trace 1",
                                                "status": "ok", "reason": "", "rows": 11, "statistics": {}}))
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(columns)
        w.writerows(rows)
    (out / "batch.json").write_text(json.dumps({"batch": _p(0), "axes": [{"name": a} for a in axes],
                                                "metrics": [{"column": metric}]}))
    return out


def _study_tables(root: Path) -> list[Path]:
    prec = root / f"s_precision.csv"
    with open(prec, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["algorithm", "inputs", "step", "tolerance", "status", "wall_s", "worst_relative", "do_steps",
                    "worst_signal"])
        for k in range(3):
            w.writerow([_p(k), _p(k + 1), 0.01 * (k + 1), _p(k + 2), "ok", 0.1 * (k + 1), 1e-3 / (k + 1), _p(k + 3),
                        _p(k + 4)])
    stab = root / f"t_stability.csv"
    with open(stab, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["algorithm", "inputs", "step", f"kc{_p(1)}", "outcome", "rho_measured", "rho_analytic",
                    "reason"])
        for k in range(4):
            w.writerow([_p(0), _p(2), 0.01 * (1 + k % 2), 10.0 * (1 + k // 2), _p(k), _p(k + 1), _p(k + 2), _p(k + 3)])
    return [prec, stab]


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    pages = {}
    trace = _run_dir(root)
    assert main(["report", str(trace), "-o", str(root / "run.html")]) == 0
    pages["run"] = root / "run.html"
    for name, axes in (("grid2", [_p(0), _p(4)]), ("grid1", [_p(0)]), ("grid0", [])):
        out = _batch_dir(root, name, axes)
        assert main(["report", str(out), "-o", str(root / f"{name}.html")]) == 0
        pages[name] = root / f"{name}.html"
    for table in _study_tables(root):
        assert main(["report", str(table)]) == 0
        pages[table.stem] = table.with_suffix(".html")
    return pages


@pytest.mark.parametrize("which", ["run", "grid2", "grid1", "grid0", "s_precision", "t_stability"])
def test_no_planted_script_runs_in_a_report(reports, which):
    dom = dom_of(reports[which])
    assert "data-pwned" not in dom
    assert "js-plotly-plot" in dom  # the charts were drawn: the page's own scripts ran
    assert "&lt;/script&gt;&lt;script&gt;" in dom or "&lt;img" in dom  # the payloads are shown as text
