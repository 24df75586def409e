"""What users and strangers hand a run, round three (issue 33, items 2 and 4 to 7): every case
ends in one line and a non-zero exit, writes nothing outside the chosen directory and leaves no
temporary file.  Classes: paths from data confined (run ids of a batch table, a sidecar's trace
name; ``report -o`` anywhere), readers bounded and typed (devices, FIFOs, directories and
oversized files; modules that exit at import; Modelica sizes, expression lengths and a crashing
front end; JSON depth in SSP annotations, sidecars and trace metadata; trace sizes), files
recognised by what they are (OSP in any encoding), comparisons refused when partial either way
or of different scenes, and an FMU unpacked under a file-size limit."""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from cosim import cli
from cosim.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
TWO_MASS = ROOT / "scenarios" / "two_mass.yaml"
THIRD = ROOT.parent / "shared" / "third_party"
if not THIRD.is_dir():  # a worktree beside the main checkout
    THIRD = Path("/work/shared/third_party")


def cli_run(*args, cwd=None, env=None, timeout=120, process=False) -> subprocess.CompletedProcess:
    """The CLI on ``args``: in this process (quick; an uncaught exception fails the test), or
    in a child with ``process`` (what could hang: a FIFO)."""
    if process:
        return subprocess.run([sys.executable, "-m", "cosim", *map(str, args)], cwd=cwd or ROOT, capture_output=True,
                              text=True, timeout=timeout, env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})})
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp:
        for k, v in (env or {}).items():
            mp.setenv(k, v)
        mp.chdir(cwd or ROOT)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = cli.main([str(a) for a in args])
            except SystemExit as exc:
                rc = exc.code
    return subprocess.CompletedProcess(args, rc, out.getvalue(), err.getvalue())


def one_line(res: subprocess.CompletedProcess, *needles: str) -> None:
    assert res.returncode not in (0, None) and "Traceback" not in res.stderr, res.stderr[-3000:]
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert 1 <= len(lines) <= 2, res.stderr
    for n in needles:
        assert n in res.stderr, res.stderr


def tree(d: Path) -> set[str]:
    return {str(p.relative_to(d)) for p in d.rglob("*")}


# --- paths from data ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    spec = root / "b.yaml"
    spec.write_text(f"name: b\nscene: {TWO_MASS}\nset: {{stop_time: 0.05}}\n"
                    "grid:\n  kc: {path: components.mass2.params.kc, values: [10, 20]}\n"
                    "metrics:\n  mass1.x: {measure: [max]}\n")
    assert cli.main(["batch", str(spec), "--out", str(root / "out")]) == 0
    return root / "out"


@pytest.mark.parametrize("run_id", ["../../victim", "../victim", "/tmp/victim", "..", ".", ".hidden", "a/b"])
def test_a_run_id_from_the_table_cannot_leave_the_batch(tmp_path, batch, run_id):
    out = tmp_path / "nest" / "out"
    shutil.copytree(batch, out)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "two_mass.csv").write_text("time,x\n0,1\n")
    (victim / "two_mass.json").write_text(json.dumps({"scene_hash": "x", "trace": "two_mass.csv"}))
    rows = list(csv.reader(open(out / "results.csv")))
    rows[1][0] = run_id
    with open(out / "results.csv", "w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)
    before_v, before_o = tree(victim), tree(out)
    res = cli_run("report", out, "--runs", cwd=tmp_path)
    one_line(res, "is not a run directory name")
    assert tree(victim) == before_v and tree(out) == before_o


def test_a_run_directory_that_is_a_link_outside_is_refused(tmp_path, batch):
    out = tmp_path / "out"
    shutil.copytree(batch, out)
    rid = next(p.name for p in (out / "runs").iterdir())
    shutil.move(out / "runs" / rid, tmp_path / "elsewhere")
    (out / "runs" / rid).symlink_to(tmp_path / "elsewhere")
    before = tree(tmp_path / "elsewhere")
    one_line(cli_run("report", out, "--runs", cwd=tmp_path), "outside")
    assert tree(tmp_path / "elsewhere") == before


@pytest.mark.parametrize("out_rel, o_rel", [(True, True), (True, False), (False, True), (False, False)])
def test_report_output_anywhere(tmp_path, batch, out_rel, o_rel):
    work = tmp_path / "work"
    work.mkdir()
    shutil.copytree(batch, work / "b")
    out = Path("b") if out_rel else work / "b"
    dest = Path("sub/r.html") if o_rel else tmp_path / "abs" / "r.html"
    res = cli_run("report", out, "-o", dest, "--runs", cwd=work)
    assert res.returncode == 0, res.stderr
    page = (work / dest) if o_rel else dest
    assert page.is_file() and "open the report of run" in page.read_text()


def test_a_sidecars_trace_name_is_only_a_name_beside_it(tmp_path):
    from cosim.outputs import settle_stale

    out, victim = tmp_path / "out", tmp_path / "victim.csv"
    out.mkdir()
    victim.write_text("time,x\n0,1\n0.1,2")  # no final newline: settling would cut and append to it
    (out / "r.json").write_text(json.dumps({"status": "running", "pid": 2 ** 22 + 7, "trace": "../victim.csv"}))
    settle_stale(out)
    assert victim.read_text() == "time,x\n0,1\n0.1,2"


# --- readers bounded and typed -----------------------------------------------------------------
def _scene_with_blocks(tmp_path: Path, target: str) -> Path:
    scene = tmp_path / "s.yaml"
    scene.write_text(TWO_MASS.read_text().replace("components:\n", "components:\n  u: {model: mine}\n")
                     + f"blocks: [{json.dumps(target)}]\n")
    return scene


@pytest.mark.parametrize("kind", ["device", "fifo", "directory", "too_large"])
def test_a_blocks_file_that_is_not_a_small_regular_file_is_refused(tmp_path, kind):
    target = {"device": "/dev/zero", "fifo": str(tmp_path / "f.py"), "directory": str(tmp_path / "d.py"),
              "too_large": str(tmp_path / "big.py")}[kind]
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "directory":
        os.mkdir(target)
    elif kind == "too_large":
        Path(target).write_text("BLOCKS = {}\n" + "#" * 5000 + "\n")
    res = cli_run("run", _scene_with_blocks(tmp_path, target), "--check", env={"RPR_COSIM_MAX_FILE_BYTES": "4000"},
                  timeout=60, process=kind == "fifo")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert any(w in res.stderr for w in ("not found", "not a regular file", "more than the limit")), res.stderr


@pytest.mark.parametrize("body, said", [
    ("import sys\nsys.exit(0)\n", "SystemExit(0)"),
    ("import sys\nsys.exit(3)\n", "SystemExit(3)"),
    ("raise SystemExit('bye')\n", "SystemExit('bye')"),
    ("raise KeyboardInterrupt\n", "KeyboardInterrupt"),
    ("def f(n):\n    return f(n + 1)\nf(0)\n", "RecursionError"),
])
def test_a_blocks_module_that_exits_at_import_is_one_line(tmp_path, body, said):
    (tmp_path / "mine.py").write_text(body)
    for verb in (("run", "--check"), ("run",)):
        res = cli_run(*verb[:1], _scene_with_blocks(tmp_path, "mine.py"), *verb[1:], "--out", tmp_path / "o")
        assert res.returncode == 2 and said in res.stderr and "Traceback" not in res.stderr, res.stderr


def test_a_scene_that_is_a_device_or_fifo_is_refused(tmp_path):
    """YAML scenes, SSP archives and OSP files alike (a FIFO blocked the zip reader; /dev/zero
    named x.ssp fed it without end)."""
    targets = ["/dev/zero"]
    for name in ("f.yaml", "f.ssp", "f.xml"):
        os.mkfifo(tmp_path / name)
        targets.append(tmp_path / name)
    (tmp_path / "z.ssp").symlink_to("/dev/zero")
    targets.append(tmp_path / "z.ssp")
    for target in targets:
        res = cli_run("run", target, "--check", timeout=30, process=True)
        assert res.returncode == 2 and "not a regular file" in res.stderr and "Traceback" not in res.stderr, target


def _sum_model(terms: int, nest: int = 0) -> str:
    expr = " + ".join(f"a*{i}" for i in range(terms))
    expr = "(" * nest + expr + ")" * nest
    return (f'model Big\n  parameter Real a(unit="1") = 1 "gain";\n  output Real y(unit="1") "sum";\n'
            f"equation\n  y = {expr};\nend Big;\n")


@pytest.mark.parametrize("terms, nest, said", [
    (2000, 0, "more than 400 operators"),
    (5000, 0, "more than 400 operators"),
    (3, 100, "nested more than 64 deep"),
])
def test_modelica_sources_are_bounded_before_the_front_end(tmp_path, terms, nest, said):
    pytest.importorskip("rumoca")
    (tmp_path / "Big.mo").write_text(_sum_model(terms, nest))
    res = cli_run("fmu", "show", f"{tmp_path / 'Big.mo'}:Big")
    one_line(res, said)


def test_a_modelica_file_over_the_size_limit_is_refused(tmp_path):
    (tmp_path / "Big.mo").write_text(_sum_model(3) + "// " + "x" * 3000 + "\n")
    res = cli_run("fmu", "show", f"{tmp_path / 'Big.mo'}:Big", env={"RPR_COSIM_MAX_MODELICA_BYTES": "2000"})
    one_line(res, "more than the limit")


def test_a_crash_of_the_front_end_is_one_error_and_results_are_cached(monkeypatch):
    """rumoca runs in a forked child: a fatal signal there is a ModelicaError here; a second
    compile of the same source is not run again."""
    pytest.importorskip("rumoca")
    import signal

    import models.modelica as mo

    calls = []
    real = mo._compile

    def crash(*args):
        os.kill(os.getpid(), signal.SIGSEGV)

    monkeypatch.setattr(mo, "_compile", crash)
    with pytest.raises(mo.ModelicaError, match=r"died of SIGSEGV \(signal 11\) while compiling Big"):
        mo.front_end(_sum_model(4), "Big", "Crash.mo")

    def counted(*a):
        calls.append(os.getpid())
        return real(*a)

    monkeypatch.setattr(mo, "_compile", counted)
    text = _sum_model(5)
    first = mo.front_end(text, "Big", "Cached.mo")
    assert mo.front_end(text, "Big", "Cached.mo") is first
    assert mo.translate(text, "Big", "Cached.mo").name == "big"


def test_deep_json_in_an_ssp_guard_annotation_is_one_problem():
    from cosim.readers import loads_json

    for text in ("[" * 100_000 + "]" * 100_000, '{"a":' * 5000 + "1" + "}" * 5000):
        with pytest.raises(UserError, match="nested .* levels deep, more than the limit of 64"):
            loads_json(text, "the guards annotation")
    assert loads_json('{"a": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}', "x")


META = {
    "text_bad": '# text: ["x", 1, 2]',
    "text_short": "# text: [1]",
    "stats_int": "# statistics: 5",
    "units_list": "# units: [1, 2]",
    "units_value": '# units: {"a.x": [1]}',
    "status_num": "# status: 5",
    "reason_obj": '# reason: {"a": 1}',
    "deep": "# scene: " + "[" * 100_000 + "]" * 100_000,
    "deep_stats": "# statistics: " + '{"a":' * 200 + "1" + "}" * 200,
}


@pytest.mark.parametrize("kind", sorted(META))
def test_malformed_trace_metadata_is_one_line_in_compare_and_report(tmp_path, kind):
    bad = tmp_path / "bad.csv"
    bad.write_text(f"# rpr-cosim trace 1\n{META[kind]}\ntime,a.x\n0,1\n0.1,2\n")
    good = tmp_path / "good.csv"
    good.write_text('# rpr-cosim trace 1\n# status: "ok"\ntime,a.x\n0,1\n0.1,2\n')
    for args in (("compare", bad, good), ("compare", good, bad), ("report", bad, "-o", tmp_path / "r.html")):
        one_line(cli_run(*args), "bad.csv:2: ")
    assert not (tmp_path / "r.html").exists()


def test_a_deep_sidecar_is_one_line(tmp_path):
    (tmp_path / "t.csv").write_text("time,a.x\n0,1\n0.1,2\n")
    (tmp_path / "t.json").write_text('{"trace": "t.csv", "statistics": ' + "[" * 50_000 + "]" * 50_000 + "}")
    one_line(cli_run("report", tmp_path / "t.csv"), "nested 50,001 levels deep")


def test_traces_over_the_limit_or_binary_are_refused_up_front(tmp_path):
    t = tmp_path / "t.csv"
    t.write_text("time,a.x\n" + "".join(f"{i / 100},{i}\n" for i in range(2000)))
    one_line(cli_run("compare", t, t, env={"RPR_COSIM_MAX_TRACE": "10000"}), "more than the limit of 10,000",
             "RPR_COSIM_MAX_TRACE")
    sparse = tmp_path / "sparse.csv"
    with open(sparse, "wb") as fh:
        fh.truncate(2 * 10 ** 9)  # a 2 GB hole: no disk, and read a block at a time
    for args in (("compare", sparse, t), ("report", sparse, "-o", tmp_path / "r.html")):
        one_line(cli_run(*args, timeout=60), "binary data")
    head = tmp_path / "head.csv"
    head.write_bytes(b"time," + b"a" * (17 * 2 ** 20) + b"\n0,1\n")
    one_line(cli_run("compare", head, t), "a line longer than")


# --- files recognised by what they are ---------------------------------------------------------
OSP = THIRD / "libcosim-test-data" / "fmi2" / "quarter_truck"


@pytest.mark.skipif(not OSP.is_dir(), reason="needs ../shared/third_party/libcosim-test-data (not in a clone)")
@pytest.mark.parametrize("variant", ["licence", "utf16", "utf16_declared", "utf8_bom"])
def test_an_osp_file_is_recognised_by_its_root_element(tmp_path, variant):
    from cosim.scenario.osp import is_osp

    d = tmp_path / "qt"
    shutil.copytree(OSP, d)
    src = (d / "OspSystemStructure.xml").read_text(encoding="utf-8")
    decl, rest = src.split("?>", 1)
    target = d / "Sys.xml"
    if variant == "licence":
        target.write_text(decl + "?>\n<!-- " + "Licensed under the Mozilla Public License 2.0. " * 200 + "-->\n" + rest)
    elif variant == "utf16":
        target.write_text(rest.lstrip(), encoding="utf-16")
    elif variant == "utf16_declared":
        target.write_text('<?xml version="1.0" encoding="UTF-16"?>' + rest, encoding="utf-16")
    else:
        target.write_bytes(b"\xef\xbb\xbf" + src.encode())
    assert is_osp(target)
    res = cli_run("run", target, "--check")
    assert "a scene is a mapping" not in res.stderr and "Traceback" not in res.stderr
    assert "stop_time is missing" in res.stderr  # what the OSP reader says of this system (as of the original)
    assert not is_osp(Path("/dev/zero")) and not is_osp(tmp_path / "none.xml")


# --- compare: partial either way, different scenes ----------------------------------------------
@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for name, sets in (("short", ["stop_time=0.2"]), ("long", ["stop_time=2"]),
                       ("kc", ["stop_time=0.2", "components.mass2.params.kc=50"]),
                       ("step", ["stop_time=0.2", "master.step=5e-3"])):
        args = ["run", str(TWO_MASS), "--out", str(root / name), "--set", "master.algorithm=gauss_seidel",
                "--set", "master.step=1e-3", "--set", "master.tolerance=none"]  # no verdict: not about accuracy
        for s in sets:
            args += ["--set", s]
        assert cli.main(args) in (0, 1)
        out[name] = root / name / "two_mass.csv"
    return out


def test_compare_refuses_a_partial_comparison_both_ways(runs, capsys):
    for a, b in (("long", "short"), ("short", "long")):
        assert cli.main(["compare", str(runs[a]), str(runs[b]), "--allow-failed"]) == 2
        assert "overlap over 0..0.2 s, 10 % of the" in capsys.readouterr().err
        assert cli.main(["compare", str(runs[a]), str(runs[b]), "--tol", "10", "--allow-failed"]) == 1
        assert cli.main(["compare", str(runs[a]), str(runs[b]), "--allow-failed", "--allow-partial"]) == 0


def test_compare_names_the_entries_of_different_scenes(runs, capsys):
    assert cli.main(["compare", str(runs["short"]), str(runs["kc"])]) == 2
    err = capsys.readouterr().err
    assert "the runs are of different scenes" in err and "components.mass2.params.kc = 100.0 against 50" in err
    assert cli.main(["compare", str(runs["short"]), str(runs["kc"]), "--tol", "10"]) == 1
    assert cli.main(["compare", str(runs["short"]), str(runs["kc"]), "--allow-different-scenes"]) == 0
    out = capsys.readouterr().out  # allowed, still named: a comparison of another scene never passes unsaid
    assert "note: different scenes, compared as asked" in out and "params.kc = 100.0 against 50" in out
    assert cli.main(["compare", str(runs["short"]), str(runs["step"])]) == 0  # the same scene, another step
    assert "the same scene run differently: master.step = 0.001 against 0.005" in capsys.readouterr().out


# --- temporary files on every failure path --------------------------------------------------------
def test_an_fmu_unpacked_past_the_file_size_limit_leaves_no_folder(tmp_path):
    fmu = tmp_path / "big.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("modelDescription.xml", '<?xml version="1.0"?><fmiModelDescription fmiVersion="2.0" '
                   'modelName="x" guid="{1}"><CoSimulation modelIdentifier="x"/><ModelVariables/>'
                   "<ModelStructure/></fmiModelDescription>")
        z.writestr("resources/big.bin", b"\0" * 6_000_000)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    code = ("import resource, sys\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (4_000_000, 4_000_000))\n"
            "from cosim.slaves.fmu_slave import unpack_fmu\nfrom cosim.errors import UserError\n"
            f"try:\n    unpack_fmu({str(fmu)!r})\nexcept UserError as e:\n    print(e, file=sys.stderr); sys.exit(2)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(tmp)})
    one_line(res, "cannot unpack the FMU", "File too large")
    assert list(tmp.iterdir()) == []


@pytest.fixture(scope="module")
def two_mass_ssp(tmp_path_factory):
    path = tmp_path_factory.mktemp("ssp") / "tm.ssp"
    assert cli.main(["ssp", "export", str(TWO_MASS), "-o", str(path)]) == 0
    return path


@pytest.mark.parametrize("guards", ["[" * 100_000 + "]" * 100_000, '{"a":' * 1000 + "1" + "}" * 1000,
                                    '{"identity": ' + "[" * 70 + "]" * 70 + "}"])
def test_an_ssp_guard_annotation_nested_deep_is_one_problem(tmp_path, two_mass_ssp, guards):
    import re

    src = zipfile.ZipFile(two_mass_ssp)
    deep = tmp_path / "deep.ssp"
    with zipfile.ZipFile(deep, "w", zipfile.ZIP_DEFLATED) as z:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == "SystemStructure.ssd":
                attr = guards.replace('"', "&quot;")
                data = re.sub(r'guards="[^"]*"', lambda m: f'guards="{attr}"', data.decode(), count=1).encode()
            z.writestr(info, data)
    res = cli_run("run", deep, "--check")
    assert res.returncode == 2 and "the guards annotation: JSON nested" in res.stderr, res.stderr


@pytest.mark.parametrize("row", ["0.1,abc", "0.1,2,3", "0.1", "0.1,", "0.1,1e999999x", "0x1,2"])
def test_a_trace_row_that_is_not_numbers_names_its_line(tmp_path, row):
    from cosim.trace.traces import read_trace

    t = tmp_path / "t.csv"
    t.write_text("time,a\n0,1\n" + row + "\n0.2,3\n")
    with pytest.raises(UserError, match=r"t.csv:3: expected 2 numbers separated by commas"):
        read_trace(t)
    t.write_text("time,a\n0,nan\n0.1,inf\n0.2,-inf\n0.3,1e-300\n0.4,-0.0\n0.5,2")  # last row without newline kept
    assert read_trace(t).data[:, 1].tolist()[1:] == [float("inf"), float("-inf"), 1e-300, -0.0, 2.0]
