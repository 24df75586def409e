"""Bounded and confined inputs (issue 20, items 3 to 5): batch names, run counts refused before
anything is expanded, archive limits and member names checked the same way by ``fmu check``,
``run`` and SSP, temporary folders removed, the compilers of a build ended with it, integer
options, YAML nesting and complex keys."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
import warnings
import zipfile
from pathlib import Path

import pytest

from cosim import cli
from cosim.batch.spec import BatchError, load_batch
from cosim.errors import UserError
from cosim.scenario import SceneError, load

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
TWO_MASS = SCENES / "two_mass.yaml"


def batch_file(tmp_path: Path, body: str) -> Path:
    p = tmp_path / "b.yaml"
    p.write_text(f"scene: {TWO_MASS}\n{body}")
    return p


# --- batches confined and bounded ---------------------------------------------------------------
@pytest.mark.parametrize("name", ["../../evil", "/abs/evil", ".hidden", "x.prev"])
def test_a_batch_name_obeys_the_scene_name_rules(tmp_path, name):
    path = batch_file(tmp_path, f"name: {name!r}\ngrid:\n  stop_time: [1, 2]\n")
    with pytest.raises(BatchError, match=r"b.yaml:2: error: batch name '" + name.replace(".", r"\.") + "'"):
        load_batch(path)


@pytest.mark.parametrize("body, numbers", [
    ("grid:\n" + "".join(f"  a{i}: {{path: stop_time, values: [1,2,3,4,5,6,7,8,9,10]}}\n" for i in range(10)),
     "10,000,000,000 runs (10 (a0) x 10 (a1) x 10 (a2)"),
    ("random: {seed: 1, samples: 1000000, axes: {s: {path: stop_time, dist: uniform, low: 1, high: 2}}}\n",
     "1,000,000 runs (1,000,000 (random.samples))"),
    ("random: {seed: 1, samples: 1000000000000, axes: {s: {path: stop_time, dist: uniform, low: 1, high: 2}}}\n",
     "1,000,000,000,000 runs (1,000,000,000,000 (random.samples))"),
    ("grid:\n  stop_time: {from: 1, to: 2, num: 1000000000000}\n", "num = 1,000,000,000,000 values, more than the limit"),
])
def test_a_batch_past_the_run_limit_is_refused_in_one_line_at_once(tmp_path, body, numbers):
    path = batch_file(tmp_path, body)
    t0 = time.perf_counter()
    with pytest.raises(BatchError) as err:
        load_batch(path)
    assert time.perf_counter() - t0 < 5  # counted, not expanded
    assert len(err.value.problems) == 1 and numbers in str(err.value.problems[0])
    assert "100,000" in str(err.value.problems[0]) and "$RPR_COSIM_MAX_RUNS" in str(err.value.problems[0])


def test_the_run_limit_is_configurable(tmp_path, monkeypatch):
    path = batch_file(tmp_path, "grid:\n  stop_time: [1, 2, 3]\n")
    assert load_batch(path).n_runs == 3
    monkeypatch.setenv("RPR_COSIM_MAX_RUNS", "2")
    with pytest.raises(BatchError, match=r"the batch makes 3 runs \(3 \(stop_time\)\), more than the limit of 2"):
        load_batch(path)
    assert load_batch(path, max_runs_=3).n_runs == 3


def test_batch_check_of_a_huge_grid_is_one_line_and_quick(tmp_path):
    path = batch_file(tmp_path, "grid:\n" + "".join(f"  a{i}: {{path: stop_time, values: [1,2,3,4,5,6,7,8,9,10]}}\n"
                                                      for i in range(10)))
    res = subprocess.run([sys.executable, "-m", "cosim", "batch", str(path), "--check"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert res.returncode == 2 and "the batch makes 10,000,000,000 runs" in res.stderr
    assert "Traceback" not in res.stderr and len(res.stderr.splitlines()) == 2


# --- archives with limits -----------------------------------------------------------------------
MD = '<?xml version="1.0"?><fmiModelDescription fmiVersion="2.0" modelName="a" guid="1"/>'


def archive(path: Path, members: dict[str, bytes | str]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, data in members.items() if isinstance(members, dict) else members:
            z.writestr(zipfile.ZipInfo(name), data)
    return path


CASES = {
    "absolute": ([("modelDescription.xml", MD), ("/etc/evil", "x")], "member '/etc/evil' has an absolute path or '..'"),
    "dotdot": ([("modelDescription.xml", MD), ("binaries/../../evil", "x")],
               "member 'binaries/../../evil' has an absolute path or '..'"),
    "duplicate": ([("modelDescription.xml", MD), ("modelDescription.xml", "<garbage")],
                  "member 'modelDescription.xml' appears twice"),
    "large": ([("modelDescription.xml", MD), ("binaries/big.bin", b"\0" * 3_000_000)],
              "its members unpack to 3.0 MB, more than the limit of 2.0 MB ($RPR_COSIM_MAX_ARCHIVE_BYTES); "
              "nothing was extracted"),
    "many": ([("modelDescription.xml", MD)] + [(f"resources/{i}", "") for i in range(60)],
             "61 members, more than the limit of 50 ($RPR_COSIM_MAX_ARCHIVE_MEMBERS)"),
}


@pytest.fixture
def small_limits(monkeypatch):
    monkeypatch.setenv("RPR_COSIM_MAX_ARCHIVE_BYTES", "2MB")
    monkeypatch.setenv("RPR_COSIM_MAX_ARCHIVE_MEMBERS", "50")


@pytest.mark.parametrize("case", list(CASES))
def test_fmu_check_and_a_scene_refuse_an_unsafe_archive_the_same_way(tmp_path, capsys, small_limits, case):
    members, message = CASES[case]
    fmu = archive(tmp_path / "x.fmu", members)
    before = set(Path(tempfile.gettempdir()).glob(f"rpr-fmu-{os.getpid()}-*"))
    rc = cli.main(["fmu", "check", str(fmu)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and f"unsafe FMU: {message}" in err and "\n" not in err
    (tmp_path / "s.yaml").write_text("name: s\nstop_time: 1\ncomponents:\n  a: {fmu: x.fmu}\n"
                                     "master: {algorithm: jacobi, step: 1e-3}\n")
    with pytest.raises(SceneError, match=r"s.yaml:4: error: component 'a': .*x.fmu: unsafe FMU: "
                                         + message.replace("(", r"\(").replace(")", r"\)").replace("$", r"\$")
                                         .replace(".", r"\.").replace("*", r"\*")):
        load(tmp_path / "s.yaml")
    assert set(Path(tempfile.gettempdir()).glob(f"rpr-fmu-{os.getpid()}-*")) == before  # nothing was extracted


@pytest.mark.parametrize("case", ["dotdot", "duplicate", "large"])
def test_an_ssp_archive_is_checked_the_same_way(tmp_path, small_limits, case):
    members, message = CASES[case]
    members = [("SystemStructure.ssd" if n == "modelDescription.xml" else n, d) for n, d in members]
    ssp = archive(tmp_path / "x.ssp", members)
    with pytest.raises(SceneError, match="unsafe SSP: " + message.split(" ")[0]) as err:
        load(ssp)
    assert message.replace("modelDescription.xml", "SystemStructure.ssd") in str(err.value)


def test_a_fake_fmi1_fmu_is_named_in_one_line(tmp_path):
    archive(tmp_path / "old.fmu", [("modelDescription.xml", '<?xml version="1.0"?><fmiModelDescription fmiVersion="1.0"/>')])
    (tmp_path / "s.yaml").write_text("name: s\nstop_time: 1\ncomponents:\n  a: {fmu: old.fmu}\n"
                                     "master: {algorithm: jacobi, step: 1e-3}\n")
    with pytest.raises(SceneError, match=r"old.fmu: FMI 1.0 FMUs are not supported; export it as FMI 2.0 or 3.0"):
        load(tmp_path / "s.yaml")


def test_a_failed_unpack_leaves_no_temporary_folder(tmp_path, monkeypatch, cache):
    import fmpy

    from cosim.run.execute import run
    from cosim.slaves import fmu_slave as fmu_module

    def full_disk(path, unzipdir, include=None):
        (Path(unzipdir) / "partial.bin").write_bytes(b"x" * 1000)
        raise OSError(28, "No space left on device")

    pid = SCENES / "pid_step.yaml"
    before = set(Path(tempfile.gettempdir()).glob(f"rpr-fmu-{os.getpid()}-*"))
    monkeypatch.setattr(fmpy, "extract", full_disk)
    monkeypatch.setattr(fmu_module, "_UNZIPPED", {})
    with pytest.raises(UserError, match=r"cannot unpack the FMU into .*\(No space left on device\)"):
        run(pid, ["stop_time=0.01"], cache_dir=cache)
    assert set(Path(tempfile.gettempdir()).glob(f"rpr-fmu-{os.getpid()}-*")) == before


# --- children and leftovers ---------------------------------------------------------------------
def _compilers_under(folder: Path) -> list[int]:
    found = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmd = (proc / "cmdline").read_bytes()
            except OSError:
                continue
            if str(folder).encode() in cmd and b"cosim" not in cmd:
                found.append(int(proc.name))
    return found


def test_a_signal_during_an_fmu_build_ends_the_compilers_too(tmp_path):
    """A fresh cache: the run compiles; SIGTERM while a compiler runs; within a second of the run's
    end no compiler works on the build folder (they are in process groups the build kills)."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(tmp)}
    proc = subprocess.Popen([sys.executable, "-m", "cosim", "run", str(SCENES / "pid_step.yaml"), "--set",
                             "stop_time=0.01", "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not _compilers_under(tmp) and not _compilers_under(tmp_path / "cache"):
        assert proc.poll() is None and time.monotonic() < deadline, "no compiler was seen"
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    time.sleep(1.0)
    assert not _compilers_under(tmp) and not _compilers_under(tmp_path / "cache")


@pytest.mark.parametrize("value, message", [
    (2.5, "max_iter = 2.5 must be a whole number (a count, 1 to 10000)"),
    ("many", "max_iter = 'many' must be a whole number [1]"),
])
def test_an_integer_option_refuses_a_non_integer_with_the_expected_type(value, message):
    with pytest.raises(SceneError) as err:
        load(TWO_MASS, {"master.algorithm": "iterative", "master.options.max_iter": value})
    assert message in str(err.value)
    assert load(TWO_MASS, {"master.algorithm": "iterative", "master.options.max_iter": 7.0}).master.options


# --- YAML ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, message", [
    ("name: x\nstop_time: " + "[" * 600 + "]" * 600 + "\n", "nested more than 100 levels deep"),
    ("name: x\n? [a, b]\n: 1\n", "2: error: a key must be a name or a number, not a list"),
    ("name: x\n? {a: 1}\n: 2\n", "2: error: a key must be a name or a number, not a mapping"),
    ("name: x\nstop_time: [" + ",".join(["1"] * 200_001) + "]\n", "the file holds more than 200,000 YAML values"),
])
def test_odd_yaml_is_one_line_not_a_traceback(tmp_path, text, message):
    for kind in ("scene", "batch"):
        path = tmp_path / f"{kind}.yaml"
        path.write_text(text if kind == "scene" else f"scene: {TWO_MASS}\n" + text.replace("name: x\n", ""))
        with pytest.raises((SceneError, BatchError)) as err:
            load(path) if kind == "scene" else load_batch(path)
        assert message in str(err.value), str(err.value)


@pytest.mark.parametrize("raw", ["many", "0", "-3", "1e999"])
def test_a_run_limit_that_is_no_whole_number_is_one_line(tmp_path, monkeypatch, capsys, raw):
    """A malformed $RPR_COSIM_MAX_RUNS is the user's mistake: one line naming it, exit 2."""
    from cosim.cli import main

    path = batch_file(tmp_path, "grid:\n  stop_time: [1, 2, 3]\n")
    monkeypatch.setenv("RPR_COSIM_MAX_RUNS", raw)
    assert main(["batch", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "$RPR_COSIM_MAX_RUNS: expected a whole number of runs" in err[-1] and "Traceback" not in "\n".join(err)
