"""A run never lies and never destroys (issue #7, findings 1, 3, 4 and 5 apart from the physical
guards and compare's status checks): confined outputs, one writer per directory, atomic
placement with the previous good trace kept, disk-full and bounded resources, one-line errors."""
from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from cosim.trace import traces as trace_module

from cosim import cli, outputs
from cosim.errors import UserError
from cosim.run.reference import reference
from cosim.run.execute import check_trace_size, estimate, run
from cosim.scenario import SceneError, load
from cosim.trace.traces import CsvTrace, read_trace

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
PID = SCENES / "pid_step.yaml"
SHORT = ["stop_time=0.05"]
#: PID gains 1e6 and a 1e9 V output limit: the loop diverges (issue #7, finding 2)
WILD = [f"components.pid{i}.params.{k}={v}" for i in (1, 2, 3)
        for k, v in (("Kp", 1e6), ("Ki", 1e6), ("Kd", 1e6), ("u_max", 1e9))]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    path = tmp_path_factory.getbasetemp() / "fmu-cache"
    run(PID, SHORT, cache_dir=path)  # build the scene's FMUs once
    return path


def whole_rows(path: Path) -> int:
    """Number of data rows of a CSV trace, asserting that every row is whole."""
    text = path.read_text()
    assert text.endswith("\n"), "the file ends inside a line"
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    n = len(lines[0].split(","))
    for ln in lines[1:]:
        values = [float(x) for x in ln.split(",")]
        assert len(values) == n, f"a row with {len(values)} values instead of {n}: {ln[:80]}"
    return len(lines) - 1


def sidecar(path: Path) -> dict:
    return json.loads(path.read_text())


# --- finding 1: names are file names inside --out --------------------------------------------------
@pytest.mark.parametrize("name,expect", [
    ("../../somewhere/settings", "must be a plain file name"),
    ("/etc/settings", "must be a plain file name"),
    ("a/b", "must be a plain file name"),
    ("..", "must be a plain file name"),
    (".hidden", "must be a plain file name"),
    ("x" * 300, "is 300 characters long; at most 100"),
])
def test_a_scene_name_that_is_not_a_plain_file_name_is_refused_at_its_line(tmp_path, name, expect):
    text = PID.read_text().replace("name: pid_step", f"name: {json.dumps(name)}")
    scene = tmp_path / "s.yaml"
    scene.write_text(text)
    line = text.splitlines().index(f"name: {json.dumps(name)}") + 1
    with pytest.raises(SceneError) as err:
        load(scene)
    assert f"s.yaml:{line}: error: name" in str(err.value) and expect in str(err.value)


def test_a_traversal_name_writes_nothing_anywhere(tmp_path, cache, capsys):
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    before = sorted(p for p in tmp_path.rglob("*"))
    rc = cli.main(["run", str(PID), "--set", "name=../../escaped", "--out", str(work / "out"), "--cache", str(cache)])
    assert rc == 2 and "must be a plain file name" in capsys.readouterr().err
    assert sorted(tmp_path.rglob("*")) == before


def test_confined_refuses_a_file_that_resolves_outside_the_directory(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "link.csv").symlink_to(tmp_path / "elsewhere.csv")
    with pytest.raises(UserError, match="outside the output directory"):
        outputs.confined(out, "link.csv")
    with pytest.raises(UserError, match="outside the output directory"):
        outputs.confined(out, "../x.csv")
    assert outputs.confined(out, "pid_step.csv") == (out / "pid_step.csv").resolve()


# --- finding 5: --out that is a file or cannot be written: one line, nothing built ---------------
def test_out_that_is_a_file_is_one_line_before_anything_is_built(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    fresh_cache = tmp_path / "cache"
    for out in ("file", "file/sub"):
        rc = cli.main(["run", str(PID), "--out", str(tmp_path / out), "--cache", str(fresh_cache)])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and err.count("\n") == 0 and "is a file, not a directory" in err
    assert not fresh_cache.exists()


def test_out_that_cannot_be_written_is_one_line(tmp_path, capsys, monkeypatch):
    def refuse(*a, **kw):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(outputs.tempfile, "TemporaryFile", refuse)
    rc = cli.main(["run", str(PID), "--out", str(tmp_path / "ro"), "--cache", str(tmp_path / "cache")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "the output directory is not writable (Read-only file system)" in err and "\n" not in err


# --- finding 3: one writer per directory; no silent overwrite ---------------------------------------
def test_a_second_run_into_a_busy_directory_is_refused_naming_the_pid(tmp_path, cache):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from cosim.outputs import OutputLock\n"
                               f"with OutputLock({str(out)!r}):\n    print('locked', flush=True); time.sleep(60)"],
                              cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(UserError, match=rf"in use by another run \(pid {holder.pid}\b.*choose another --out"):
            run(PID, SHORT, out_dir=out, cache_dir=cache)
    finally:
        holder.kill()
        holder.wait()
    res = run(PID, SHORT, out_dir=out, cache_dir=cache)  # the kernel dropped the dead holder's lock
    assert res.ok and not (out / outputs.LOCK_NAME).exists()


def interrupted_run(out: Path, cache: Path, notes: list[str]):
    """A rerun that does not end ok: Ctrl-C after the first chunk."""
    def ctrl_c(done, total):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(PID, ["stop_time=0.3"], out_dir=out, cache_dir=cache, log=notes.append, progress=ctrl_c)


def test_a_failing_rerun_keeps_the_good_trace_as_prev_and_says_so(tmp_path, cache):
    out = tmp_path / "out"
    notes: list[str] = []
    good = run(PID, ["stop_time=0.3"], out_dir=out, cache_dir=cache)
    assert good.ok
    interrupted_run(out, cache, notes)
    assert any("kept the earlier good trace as pid_step.prev.csv (this run is interrupted)" in n for n in notes)
    assert read_trace(out / "pid_step.csv").status == "interrupted"
    prev = read_trace(out / "pid_step.prev.csv")
    assert prev.status == "ok" and sidecar(out / "pid_step.prev.json")["status"] == "ok"
    np.testing.assert_array_equal(prev.data, good.trace.data)
    notes.clear()
    interrupted_run(out, cache, notes)  # a second failure replaces the first, not the good one
    assert any("replaced the earlier trace pid_step.csv (its status was interrupted)" in n for n in notes)
    np.testing.assert_array_equal(read_trace(out / "pid_step.prev.csv").data, good.trace.data)
    assert sorted(p.name for p in out.iterdir()) == ["pid_step.csv", "pid_step.json", "pid_step.prev.csv",
                                                     "pid_step.prev.json"]


# --- finding 3: a full disk --------------------------------------------------------------------
@pytest.mark.parametrize("writer_thread", [True, False], ids=["writer-thread", "inline"])
def test_a_full_disk_ends_the_run_with_its_reason_and_whole_rows(tmp_path, cache, monkeypatch, writer_thread):
    monkeypatch.setattr(trace_module, "WRITER_THREAD", writer_thread)
    budget = {"left": 40_000}
    real_write = os.write

    def full_disk(fd, data):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            target = ""
        if not target.endswith(".csv.part"):
            return real_write(fd, data)
        if budget["left"] <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        n = real_write(fd, bytes(data[:budget["left"]]))  # a short write, as a filling disk does
        budget["left"] -= n
        return n

    monkeypatch.setattr(os, "write", full_disk)
    out = tmp_path / "out"
    res = run(PID, ["stop_time=2"], out_dir=out, cache_dir=cache)
    assert res.status == "failed" and "No space left on device" in res.reason
    rows = whole_rows(out / "pid_step.csv")
    side = sidecar(out / "pid_step.json")
    assert side["status"] == "failed" and "No space left on device" in side["reason"] and side["rows"] == rows
    assert 0 < rows < 2001 and f"{rows} whole rows kept" in side["reason"]
    assert read_trace(out / "pid_step.csv").status == "failed"


def test_a_file_size_limit_in_a_real_process_ends_with_whole_rows(tmp_path, cache):
    out = tmp_path / "out"
    code = ("import resource, signal, sys\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, 1_000_000))\n"
            "from cosim.cli import main\nsys.exit(main(sys.argv[1:]))\n")
    res = subprocess.run([sys.executable, "-c", code, "run", str(PID), "--out", str(out), "--cache", str(cache)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 1, res.stderr
    side = sidecar(out / "pid_step.json")
    assert side["status"] == "failed" and "File too large" in side["reason"]
    rows = whole_rows(out / "pid_step.csv")
    assert side["rows"] == rows and 100 < rows < 5001
    assert "failed" in res.stderr and "File too large" in res.stderr


# --- finding 3: the FMU cache verifies what it serves -------------------------------------------
@pytest.fixture(scope="module")
def own_cache(tmp_path_factory):
    """A cache with one PID FMU, to damage."""
    import fmus
    import models.blocks as blocks

    root = tmp_path_factory.mktemp("damage-cache")
    return root, fmus.build_fmu(blocks.make("pid", "continuous"), cache_dir=root)


@pytest.mark.parametrize("damage,message", [
    ("truncate", r"it is 1000 bytes, the build recorded \d+"),
    ("flip", "its SHA-256 differs from the one recorded at build"),
])
def test_a_damaged_cached_fmu_is_rebuilt_saying_so(own_cache, damage, message):
    import fmus
    import models.blocks as blocks

    root, path = own_cache
    good = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(good[:1000])
    else:
        path.write_bytes(good[:500] + bytes([good[500] ^ 0xFF]) + good[501:])
    said: list[str] = []
    again = fmus.build_fmu(blocks.make("pid", "continuous"), cache_dir=root, progress=said.append)
    assert again == path and path.read_bytes() == good
    assert any("is damaged" in s and __import__("re").search(message, s) and "rebuilding it" in s for s in said), said


def test_a_cache_that_cannot_be_written_falls_back_to_a_temporary_one_on_a_miss(tmp_path):
    import fmus
    import models.blocks as blocks
    from fmus.cache import temporary_root

    (tmp_path / "file").write_text("not a directory")
    said: list[str] = []
    path = fmus.build_fmu(blocks.make("pid", "continuous"), cache_dir=tmp_path / "file" / "cache", progress=said.append)
    assert path.is_file() and temporary_root() in path.parents
    assert any("is not writable" in s and "building into the temporary cache" in s for s in said)


# --- finding 4: bounded resources -------------------------------------------------------------------
def test_the_size_estimate_matches_a_written_trace(tmp_path, cache):
    scene = load(PID, ["stop_time=0.5", "master.algorithm=gauss_seidel", "master.tolerance=none"])  # rows known
    res = run(scene, out_dir=tmp_path, cache_dir=cache)
    est = estimate(scene)
    text = (tmp_path / "pid_step.csv").read_text()
    data = sum(len(ln) + 1 for ln in text.splitlines() if ln and not ln.startswith("#"))
    assert est.steps == 500 and est.rows == len(res.trace.data) == 501 and est.columns == len(res.trace.columns)
    assert est.bytes == pytest.approx(data, rel=0.2)


def test_a_run_whose_trace_is_too_large_is_refused_with_the_numbers_and_the_way_out(tmp_path, capsys):
    rc = cli.main(["run", str(PID), "--set", "stop_time=1e6", "--out", str(tmp_path / "out"),
                   "--cache", str(tmp_path / "cache")])
    err = capsys.readouterr().err
    assert rc == 2 and "1,000,000,001 rows x 25 columns" in err and "beyond the limit of 4.0 GB" in err
    assert "--max-trace" in err and "$RPR_COSIM_MAX_TRACE" in err and not (tmp_path / "cache").exists()
    scene = load(PID, ["stop_time=1e6"])
    assert check_trace_size(scene, "1TB").rows == 1_000_000_001  # a raised limit lets it through
    rc = cli.main(["run", str(PID), "--check"])
    assert rc == 0 and "expected: 5,000 steps, 5,001 rows x 25 columns, trace about" in capsys.readouterr().out


def test_a_trace_written_in_the_stepping_thread_equals_the_writer_threads(tmp_path, cache, monkeypatch):
    """As batch workers write it when every core has a worker: the same file but its dates."""
    threaded = run(PID, ["stop_time=0.5"], out_dir=tmp_path / "a", cache_dir=cache)
    monkeypatch.setattr(trace_module, "WRITER_THREAD", False)
    inline = run(PID, ["stop_time=0.5"], out_dir=tmp_path / "b", cache_dir=cache)
    assert threaded.ok and inline.ok

    def lines(path):
        return [ln for ln in path.read_text().splitlines() if not ln.startswith(("# started", "# statistics"))]

    assert lines(threaded.trace_path) == lines(inline.trace_path) and len(lines(inline.trace_path)) > 500


def test_the_trace_writer_applies_back_pressure(tmp_path, monkeypatch):
    real = CsvTrace._write
    monkeypatch.setattr(CsvTrace, "_write", lambda self, data: (time.sleep(0.002), real(self, data)))
    w = CsvTrace(tmp_path / "t.csv", max_queued_bytes=100_000)
    w.start(["time", "a", "b", "c"], {})
    chunk = np.ones((1000, 4))  # 32 kB each, 1.9 MB in all
    peak = 0
    for k in range(60):
        w.record(chunk * k)
        peak = max(peak, w._queued)
    w.finish("ok", "", {})
    assert peak <= 100_000 + chunk.nbytes
    back = read_trace(tmp_path / "t.csv")
    assert back.status == "ok" and len(back.data) == 60_000 and back.data[-1, 1] == 59


def test_the_compiled_loop_returns_to_python_within_its_time_budget(cache, monkeypatch):
    """With a budget of 1 ns, every call of the C loop returns after 16 steps; the trace is
    bit-identical to the one of unbounded calls."""
    from cosim.master import fastloop
    from cosim import master

    fixed = ["stop_time=0.5", "master.algorithm=gauss_seidel", "master.tolerance=none"]  # chunking, not accuracy
    whole = run(PID, fixed, cache_dir=cache)
    calls = []
    real = master._Compiled.run

    def counted(self, nsteps, rec_every, rec):
        k0 = self.alg.k
        rows = real(self, nsteps, rec_every, rec)
        calls.append(self.alg.k - k0)
        return rows

    monkeypatch.setenv("RPR_COSIM_SUPERVISE", "0")  # the calls are counted in this process
    monkeypatch.setattr(fastloop, "CALL_BUDGET_NS", 1)
    monkeypatch.setattr(master._Compiled, "run", counted)
    chunked = run(PID, fixed, cache_dir=cache)
    # the run's 500 steps and its error estimate's companion run's 1000 (half the step)
    assert chunked.ok and max(calls) == 16 and sum(calls) == 500 + 1000
    np.testing.assert_array_equal(chunked.trace.data, whole.trace.data)


def test_the_reference_has_a_wall_time_cap_and_counts_solver_messages(tmp_path, capfd):
    said: list[str] = []
    t0 = time.perf_counter()
    # the guards off: the wild gains leave the ratings at once, and the reference is guarded too
    unguarded = [f"guards.{g}=off" for g in ("rated", "stroke", "singularity", "unstable")]
    ref = reference(PID, ["stop_time=2", *WILD, *unguarded], out_dir=tmp_path, max_wall_s=1.0, log=said.append)
    assert time.perf_counter() - t0 < 30
    assert ref.status == "failed" and "wall-time cap of 1 s" in ref.reason
    assert sidecar(tmp_path / "pid_step_reference.json")["status"] == "failed"
    captured = capfd.readouterr()
    assert "rhs failed" not in captured.err + captured.out  # collapsed into one count
    assert ref.stats["solver_messages"] >= 1 and any("lines, not shown" in s for s in said)


def test_the_reference_has_a_step_cap():
    ref = reference(PID, ["stop_time=1"], max_steps=50)
    assert ref.status == "failed" and "reached its cap of 50 CVODES steps" in ref.reason


def test_a_yaml_alias_bomb_is_refused(tmp_path):
    lines = ["name: bomb", "a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 9)]
    lines += ["stop_time: *a8"]
    (tmp_path / "bomb.yaml").write_text("\n".join(lines) + "\n")
    with pytest.raises(SceneError, match="expands to more than 200,000 YAML values"):
        load(tmp_path / "bomb.yaml")


def test_a_recursive_alias_is_refused(tmp_path):
    (tmp_path / "loop.yaml").write_text("name: loop\nstop_time: &a [1, *a]\n")
    with pytest.raises(SceneError, match="expands to more than"):
        load(tmp_path / "loop.yaml")


# --- finding 5: one line instead of a traceback --------------------------------------------------
def test_a_latin1_scene_is_one_line_naming_the_line(tmp_path):
    text = PID.read_text().replace("description: PID step", "description: PID \u00e9tape")
    (tmp_path / "s.yaml").write_bytes(text.encode("latin-1"))
    line = text.splitlines().index(next(ln for ln in text.splitlines() if "\u00e9" in ln)) + 1
    with pytest.raises(SceneError, match=rf"s.yaml:{line}: error: the scene is not UTF-8 text \(byte 0xe9"):
        load(tmp_path / "s.yaml")


def fmi1_fmu(path: Path) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("modelDescription.xml", """<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="1.0" modelName="m1" modelIdentifier="m1" guid="{8c4e810f-3df3-4a00-8276-176fa3c9f000}"
  numberOfContinuousStates="0" numberOfEventIndicators="0">
<ModelVariables><ScalarVariable name="y" valueReference="0" causality="output"><Real/></ScalarVariable></ModelVariables>
<Implementation><CoSimulation_StandAlone><Capabilities canHandleVariableCommunicationStepSize="true"/>
</CoSimulation_StandAlone></Implementation></fmiModelDescription>""")
    return path


def test_an_fmi1_fmu_is_refused_in_one_line(tmp_path):
    fmi1_fmu(tmp_path / "old.fmu")
    (tmp_path / "s.yaml").write_text("name: s\nstop_time: 1\ncomponents:\n  a: {fmu: old.fmu}\n"
                                     "master: {algorithm: jacobi, step: 1e-3}\n")
    with pytest.raises(SceneError, match=r"s.yaml:4: error: component 'a': .*old.fmu: FMI 1.0 FMUs are not supported"):
        load(tmp_path / "s.yaml")


@pytest.mark.parametrize("kind,message", [
    ("garbage", "not an FMU: not a zip archive"),
    ("absolute", "unsafe FMU: member '/etc/evil' has an absolute path or '..'"),
    ("dotdot", "unsafe FMU: member '../evil' has an absolute path or '..'"),
])
def test_fmu_check_on_a_broken_archive_is_one_line(tmp_path, capsys, kind, message):
    path = tmp_path / "x.fmu"
    if kind == "garbage":
        path.write_bytes(np.random.default_rng(1).bytes(5000))
    else:
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("modelDescription.xml", "<fmiModelDescription/>")
            z.writestr(zipfile.ZipInfo("/etc/evil" if kind == "absolute" else "../evil"), "x")
    rc = cli.main(["fmu", "check", str(path)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and message in err and "\n" not in err


def test_compare_on_binary_garbage_is_one_line(tmp_path, capsys):
    (tmp_path / "g.csv").write_bytes(np.random.default_rng(2).bytes(3000))
    rc = cli.main(["compare", str(tmp_path / "g.csv"), str(tmp_path / "g.csv")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "not an rpr-cosim trace" in err and "\n" not in err


@pytest.mark.parametrize("verb,words", [("build", "compiles it, and the result is cached by content"),
                                        ("list", "every FMU in the cache"),
                                        ("check", "Validate any FMU")])
def test_fmu_verbs_have_descriptions_in_help(capsys, verb, words):
    with pytest.raises(SystemExit):
        cli.main(["fmu", verb, "--help"])
    assert words in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("member", ["ABS", "../escaped.fmu", "resources/../../escaped.fmu"])
def test_an_ssp_whose_source_leaves_the_archive_is_refused_and_writes_nothing_outside(tmp_path, cache, capsys,
                                                                                     member):
    from test_ssp import FOREIGN_SSD, FOREIGN_SSV, SSD

    from cosim.run.execute import build_components

    member = str(tmp_path / "escaped.fmu") if member == "ABS" else member
    paths = build_components(load(PID), cache_dir=cache)
    path = tmp_path / "evil.ssp"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(SSD, FOREIGN_SSD.replace('source="resources/pid.fmu"', f'source="{member}"'))
        zf.writestr("resources/ctl.ssv", FOREIGN_SSV)
        zf.write(paths["target"], "resources/setpoint.fmu")
        zf.writestr(zipfile.ZipInfo(member), Path(paths["pid1"]).read_bytes())
    rc = cli.main(["run", str(path), "--out", str(tmp_path / "out"), "--cache", str(cache)])
    err = capsys.readouterr().err
    # refused by the archive check shared with fmu check and run (issue 20), before the SSD is read
    assert rc == 2 and f"unsafe SSP: member {member!r} has an absolute path or '..'" in err, err
    assert not (tmp_path / "escaped.fmu").exists() and not list(cache.rglob("escaped.fmu"))


@pytest.mark.parametrize("text, expected", [("1KB", 1000), ("1kB", 1000), ("500 MB", 500_000_000), ("20GB", 2e10),
                                            ("1e9", 1e9), ("2.5k", 2500)])
def test_trace_size_limits_read_as_si_bytes_whatever_the_case(text, expected):
    from cosim.run.execute import parse_bytes

    assert parse_bytes(text) == expected


def test_a_bad_trace_size_limit_is_one_line(capsys):
    from cosim.cli import main

    assert main(["run", str(PID), "--max-trace", "lots", "--check"]) == 2
    err = capsys.readouterr().err
    assert "trace size limit 'lots': expected a size such as 20GB" in err and "Traceback" not in err
