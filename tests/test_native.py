"""The native engine's common parts and its compiled ecco loop.

* The FMI C signatures, declared once in fmus/fmi_functions.py, against the standard's own
  headers (as FMPy ships them): every generated typedef must be assignment-compatible with the
  header's function type (the C compiler checks it, warnings as errors).
* The slave struct's ctypes mirror against the C struct: field offsets and the size, read back
  from the compiled prelude (``offsetof``), not from the same Python list.
* ``ecco``'s compiled loop against its reference, the Python loop of
  cosim/master/algorithms/ecco.py: the same steps and values bit for bit, the same bond
  statistics and the same ending (ok, a step floor that ends the run as unstable).
"""
from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cosim.run.execute import run

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def _compile(tmp_path: Path, code: str, *flags: str) -> Path:
    from fmus.compile import compiler

    src, lib = tmp_path / "t.c", tmp_path / "t.so"
    src.write_text(code)
    res = subprocess.run([compiler(), "-std=c11", "-shared", "-fPIC", "-Werror", *flags, "-o", str(lib), str(src)],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    return lib


@pytest.mark.parametrize("version", ["2", "3"])
def test_generated_fmi_typedefs_match_the_standard_headers(tmp_path, version):
    from fmus.codegen import FMI_HEADER_DIR
    from fmus.fmi_functions import FUNCTIONS, c_typedef

    names = [n for n in FUNCTIONS if n.startswith(f"fmi{version}")]
    status = f"fmi{version}Status"
    lines = [f'#include "fmi{version}Functions.h"', "#include <stdint.h>", "#include <stdbool.h>"]
    for n in names:
        # the table returns int (the status as the master reads it); the header's enum in its place
        lines.append(c_typedef(n).replace("typedef int ", f"typedef {status} ", 1))
        lines.append(f"{n}TYPE *check_{n} = ({n}_t)0;")
    _compile(tmp_path, "\n".join(lines) + "\n", f"-I{FMI_HEADER_DIR}")
    assert len(names) >= 8


def test_ctypes_prototypes_follow_the_table():
    from fmus.fmi_functions import prototype

    step = prototype("fmi3DoStep")
    assert step._restype_ is ctypes.c_int
    assert step._argtypes_[3] is ctypes.c_bool and step._argtypes_[4] is ctypes.POINTER(ctypes.c_bool)
    raw = prototype("fmi2GetInteger", raw=True)._argtypes_
    assert (raw[1], raw[2], raw[3]) == (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p)
    assert prototype("fmi2SetReal")._argtypes_[3] is ctypes.POINTER(ctypes.c_double)


def _c_layout(tmp_path: Path, record, header: str) -> list[int]:
    """offsetof() of every field of ``record`` and its sizeof(), from the C compiler reading ``header``."""
    names = [n for _, n, _ in record.fields]
    body = "\n".join(f"    out[{k}] = (int64_t)offsetof({record.name}, {n});" for k, n in enumerate(names))
    code = header + f"void layout(int64_t *out) {{\n{body}\n    out[{len(names)}] = (int64_t)sizeof({record.name});\n}}\n"
    lib = ctypes.CDLL(str(_compile(tmp_path, code, "-Wall", "-Wextra")))
    out = (ctypes.c_int64 * (len(names) + 1))()
    lib.layout(out)
    return list(out)


def _mirror_layout(record, mirror) -> list[int]:
    return [getattr(mirror, n).offset for _, n, _ in record.fields] + [ctypes.sizeof(mirror)]


@pytest.mark.parametrize("name", ["rpr_crumb_t", "rpr_slave", "fx_ctl", "ad_ctl", "ec_ctl", "it_ctl"])
def test_every_record_mirror_has_the_c_layout(tmp_path, name):
    """offsetof() of every field and sizeof() from the compiler reading the generated header,
    against the ctypes mirror the bindings use (the crumb: against the record the supervisor reads)."""
    from cosim.master.entries import RECORDS, header, struct
    from cosim.slaves.crumb import Record

    record = next(r for r in RECORDS if r.name == name)
    c = _c_layout(tmp_path, record, header())
    if name == "rpr_crumb_t":  # the supervisor's record: the C record, then the names table's length
        assert c == _mirror_layout(record, Record)[:-1] + [Record.table_len.offset]
    else:
        assert c == _mirror_layout(record, struct(record))


def test_a_layout_mismatch_fails_the_check(tmp_path):
    """The check above can fail: a mirror whose first field is declared wider than in C, or a C
    header with two fields swapped, gives another layout."""
    from cosim.master.entries import SLAVE, Record, ctypes_struct, header

    c = _c_layout(tmp_path, SLAVE, header())
    wider = Record(SLAVE.name, (("int64_t", *SLAVE.fields[0][1:]), *SLAVE.fields[1:]))
    assert _mirror_layout(SLAVE, ctypes_struct(wider)) != c
    swapped = Record(SLAVE.name, (SLAVE.fields[8], *SLAVE.fields[:8], *SLAVE.fields[9:]))  # sub_ns first
    text = header().replace(SLAVE.c(), swapped.c())
    assert swapped.c() in text
    (tmp_path / "swapped").mkdir()  # a library of its own (dlopen keeps the first of a path)
    assert _c_layout(tmp_path / "swapped", SLAVE, text) != c


def test_entry_point_bindings_follow_their_declaration():
    """The ctypes argument types of every entry point come from its one declaration: as many as
    the C prototype has, a record by pointer to its mirror."""
    from cosim.master import adaptive_engine, fastloop, iterative_engine
    from cosim.master.entries import ADAPT_RUN, ECCO_RUN, ITER_RUN, RUN, argtype

    for lib, entry in ((fastloop.library(), RUN), (adaptive_engine.library(), ADAPT_RUN),
                       (adaptive_engine.library(), ECCO_RUN), (iterative_engine.library(), ITER_RUN)):
        fn = getattr(lib, entry.name)
        assert fn.argtypes == [argtype(t) for t, _, _ in entry.args] and fn.restype is ctypes.c_int64
        assert entry.c().count(",") == len(entry.args) - 1
    assert argtype("ad_ctl *") is ctypes.POINTER(adaptive_engine.CControl)


def test_an_entry_point_declared_otherwise_than_defined_does_not_compile(tmp_path):
    """The generated prototypes are what the compiler checks each kernel's definition against: a
    declaration with one argument of another type (the ctypes binding would follow it) is an
    error, as the true one is not."""
    from dataclasses import replace

    from cosim.master.entries import RUN
    from cosim.master.kernels import kernel_files
    from fmus.compile import compiler
    from fmus.c_loader import FLAGS

    k = next(j for j, (t, _, _) in enumerate(RUN.args) if t == "int64_t")  # k0: int64_t -> int32_t
    wrong = replace(RUN, args=(*RUN.args[:k], ("int32_t", *RUN.args[k][1:]), *RUN.args[k + 1:]))
    results = []
    for name, entry in (("right", RUN), ("wrong", wrong)):
        folder = tmp_path / name
        folder.mkdir()
        files = kernel_files("fastloop.c")
        files["rpr_decls.h"] = files["rpr_decls.h"].replace(RUN.c(), entry.c())
        for n, text in files.items():
            (folder / n).write_text(text)
        res = subprocess.run([compiler(), *FLAGS, "-fsyntax-only", f"-I{folder}", str(folder / "fastloop.c")],
                             capture_output=True, text=True)
        results.append((res.returncode, res.stderr))
    assert results[0][0] == 0, results[0][1]
    assert results[1][0] != 0 and "conflicting types" in results[1][1]


def test_kernels_compile_without_warnings(tmp_path):
    """Every kernel (and the trace writer's C) under -Wall -Wextra -Werror, from its own C file
    with the generated header."""
    from cosim.master.kernels import kernel_files
    from cosim.trace.text import C_FILE
    from fmus.compile import compiler
    from fmus.c_loader import FLAGS

    for main in ("fastloop.c", "adaptive_engine.c", "iterative_engine.c"):
        folder = tmp_path / main
        folder.mkdir()
        for name, text in kernel_files(main).items():
            (folder / name).write_text(text)
        res = subprocess.run([compiler(), *FLAGS, "-Werror", "-fsyntax-only", f"-I{folder}", str(folder / main)],
                             capture_output=True, text=True)
        assert res.returncode == 0, f"{main}: {res.stderr}"
    res = subprocess.run([compiler(), *FLAGS, "-Werror", "-fsyntax-only", str(C_FILE)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


ECCO_CASES = {
    # the thesis's closed loop with the mechanism declared non-rollback (ecco's scene)
    "pid_step": ("pid_step.yaml", {"stop_time": 0.3, "components.mech.rollback": False}),
    # a tolerance no step meets: the run ends at the step floor, unstable, with the bond's name
    "pid_step_floor": ("pid_step.yaml", {"stop_time": 0.05, "components.mech.rollback": False,
                                         "master.options": {"atol": 1e-30, "rtol": 1e-12, "h_min": 1e-6,
                                                            "h_init": 1e-6}}),
}


@pytest.fixture(scope="module", params=sorted(ECCO_CASES))
def ecco_both(request):
    scene, sets = ECCO_CASES[request.param]
    sets = {"master.algorithm": "ecco", **sets}
    py = run(SCENARIOS / scene, sets, engine="oracle")
    c = run(SCENARIOS / scene, sets, engine="compiled")
    return request.param, py, c


def test_ecco_compiled_engine_ran(ecco_both):
    _, py, c = ecco_both
    assert (py.stats["engine"], c.stats["engine"]) == ("oracle", "compiled")


def test_ecco_same_steps_and_values_bit_for_bit(ecco_both):
    _, py, c = ecco_both
    assert py.trace.data.shape == c.trace.data.shape
    assert np.array_equal(py.trace.data, c.trace.data, equal_nan=True)


def test_ecco_same_statistics_and_ending(ecco_both):
    name, py, c = ecco_both
    keys = ("status", "reason", "accepted_steps", "smallest_step", "largest_step", "simulated_s", "bonds")
    assert {k: py.stats[k] for k in keys} == {k: c.stats[k] for k in keys}
    assert ({s: d["do_step_calls"] for s, d in py.stats["slaves"].items()}
            == {s: d["do_step_calls"] for s, d in c.stats["slaves"].items()})
    if name == "pid_step_floor":
        assert c.status == "unstable" and "stayed over its tolerance for 100 steps" in c.reason
    else:
        assert c.status == "ok", c.reason


def test_ecco_runs_compiled_by_default():
    res = run(SCENARIOS / "pid_step.yaml", {"master.algorithm": "ecco", "stop_time": 0.01,
                                            "components.mech.rollback": False})
    assert res.stats["engine"] == "compiled"


KC, H = 1000.0, 0.005
ITERATIVE_CASES = {
    # the stiff spring where Jacobi is unstable at this step: Newton on one cut, held and linear inputs
    "two_mass_hold": ("two_mass.yaml", {"components.mass2.params.kc": KC, "stop_time": 1.0, "master.step": H, "master.tolerance": "none",
                                        "master.inputs": "hold"}),
    "two_mass_linear": ("two_mass.yaml", {"components.mass2.params.kc": KC, "stop_time": 1.0, "master.step": H, "master.tolerance": "none",
                                          "master.inputs": "linear"}),
    # a start time other than 0: the kernel's times are start + k h as the Python loop's
    "two_mass_late_start": ("two_mass.yaml", {"components.mass2.params.kc": KC, "start_time": 0.5, "stop_time": 1.5,
                                              "master.step": H, "master.tolerance": "none", "master.inputs": "linear"}),
    "two_mass_fixed_point": ("two_mass.yaml", {"components.mass2.params.kc": KC, "stop_time": 1.0, "master.step": H, "master.tolerance": "none",
                                               "master.options": {"method": "fixed_point", "omega": 0.5}}),
    # a stiffer spring at a longer step: the Jacobian is built in the first step (directional
    # derivatives, or finite differences of the slave's step), then Broyden's updates
    "two_mass_directional": ("two_mass.yaml", {"components.mass2.params.kc": 1e4, "stop_time": 1.0,
                                               "master.step": 0.01}),
    "two_mass_fd": ("two_mass.yaml", {"components.mass2.params.kc": 1e4, "stop_time": 1.0, "master.step": 0.01,
                                      "master.options": {"jacobian": "finite_difference"}}),
    # stiffer still: the coupled solution blows up and the run's guard ends it as unstable
    "two_mass_unstable": ("two_mass.yaml", {"components.mass2.params.kc": 1e5, "stop_time": 1.0, "master.step": 0.01,
                                            "master.options": {"jacobian": "finite_difference"}}),
    # an over-relaxed fixed point: the iteration diverges in the first step
    "two_mass_diverged": ("two_mass.yaml", {"components.mass2.params.kc": 1e4, "stop_time": 0.5, "master.step": 0.01,
                                            "master.options": {"method": "fixed_point", "omega": 2.0}}),
    # the algebraic loop (three cuts): Newton from directional derivatives, from finite differences,
    # and the under-relaxed fixed point
    "force_loop": ("force_loop.yaml", {"stop_time": 0.2}),
    "force_loop_fd": ("force_loop.yaml", {"stop_time": 0.2, "master.options": {"jacobian": "finite_difference"}}),
    "force_loop_fixed_point": ("force_loop.yaml", {"stop_time": 0.1,
                                                   "master.options": {"method": "fixed_point", "omega": 0.15}}),
    # a cap the fixed point cannot meet within a step: the run ends unstable with the step and the connection
    "force_loop_cap": ("force_loop.yaml", {"stop_time": 0.1,
                                           "master.options": {"method": "fixed_point", "omega": 0.15,
                                                              "max_iter": 12}}),
}


@pytest.fixture(scope="module", params=sorted(ITERATIVE_CASES))
def iterative_both(request):
    scene, sets = ITERATIVE_CASES[request.param]
    sets = {"master.algorithm": "iterative", **sets}
    py = run(SCENARIOS / scene, sets, engine="oracle")
    c = run(SCENARIOS / scene, sets, engine="compiled")
    return request.param, py, c


def test_iterative_compiled_engine_ran(iterative_both):
    name, py, c = iterative_both
    assert (py.stats["engine"], c.stats["engine"]) == ("oracle", "compiled")
    if name == "two_mass_late_start":  # its rows on start + k h, in integer nanoseconds
        n = round((1.5 - 0.5) / H)
        assert np.array_equal(c.trace.time, np.array([(500_000_000 + k * 5_000_000) / 1e9 for k in range(n + 1)]))


def test_iterative_same_values_bit_for_bit(iterative_both):
    _, py, c = iterative_both
    assert py.trace.data.shape == c.trace.data.shape
    assert np.array_equal(py.trace.data, c.trace.data, equal_nan=True)


def test_iterative_same_statistics_and_ending(iterative_both):
    name, py, c = iterative_both
    keys = ("status", "reason", "iterations_mean", "iterations_max", "iterations_total", "start_iterations",
            "rollbacks", "jacobians", "directional_derivatives", "finite_difference_steps", "broyden_updates",
            "cut_connections", "simulated_s")
    assert {k: py.stats.get(k) for k in keys} == {k: c.stats.get(k) for k in keys}
    assert ({s: d["do_step_calls"] for s, d in py.stats["slaves"].items()}
            == {s: d["do_step_calls"] for s, d in c.stats["slaves"].items()})
    if name == "force_loop_cap":
        assert c.status == "unstable" and "did not converge within max_iter = 12" in c.reason
    elif name == "two_mass_diverged":
        assert c.status == "unstable" and "diverged in the step from t = 0 s" in c.reason
        assert "mass2.f -> mass1.f" in c.reason
    elif name == "two_mass_unstable":
        assert c.status == "unstable" and "mass2.f = " in c.reason and "beyond" in c.reason
    elif name in ("two_mass_hold", "two_mass_fixed_point", "two_mass_directional", "two_mass_fd"):
        # inputs held on the stiff spring: converged in every step, yet far from the coupled solution
        # (two_mass_hold: 1.16 of mass1.x's range off the monolithic reference, measured); the run's
        # own error estimate ends it unstable, in both engines alike (above)
        assert c.status == "unstable" and c.reason.startswith("the estimated error of "), c.reason
        assert c.stats["rollbacks"] > 0
    else:
        assert c.status == "ok", c.reason
        assert c.stats["rollbacks"] > 0
    if name in ("force_loop", "two_mass_directional"):
        assert c.stats["directional_derivatives"] > 0 and c.stats["broyden_updates"] > 0
    if name == "two_mass_fd":
        assert c.stats["finite_difference_steps"] > 0 and c.stats["directional_derivatives"] == 0


def test_iterative_runs_compiled_by_default():
    res = run(SCENARIOS / "two_mass.yaml", {"master.algorithm": "iterative", "stop_time": 0.05})
    assert res.stats["engine"] == "compiled"


def test_dense_helpers_agree_with_lapack_and_blas():
    """The fixed-order linear algebra of the Newton step against numpy (BLAS/LAPACK) to round-off,
    and a singular matrix is reported as such."""
    from cosim.master import dense

    rng = np.random.default_rng(7)
    for m in (1, 2, 3, 5):
        a, b = rng.normal(size=(m, m)) + 3 * np.eye(m), rng.normal(size=m)
        np.testing.assert_allclose(dense.solve(a, b), np.linalg.solve(a, b), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(dense.matvec(a, b), a @ b, rtol=1e-13, atol=1e-15)
        c = rng.normal(size=(m, 2))
        np.testing.assert_allclose(dense.matmul(a, c), a @ c, rtol=1e-13, atol=1e-15)
        assert dense.dot(b, b) == pytest.approx(float(b @ b), rel=1e-14)
    assert dense.solve(np.array([[1.0, 2.0], [2.0, 4.0]]), np.array([1.0, 1.0])) is None
    # a zero leading entry needs the row swap
    np.testing.assert_allclose(dense.solve(np.array([[0.0, 1.0], [1.0, 0.0]]), np.array([2.0, 3.0])), [3.0, 2.0])


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_a_stop_request_ends_iterative_alike_in_both_engines(reference_fmus, fmi):
    """The Modelica Reference FMU Stair asks to stop at t = 9 s (FMI 3.0 terminateSimulation, FMI
    2.0 Discard + fmi2Terminated): the compiled iterative loop completes the step and ends
    "stopped" with the Python loop's reason, at the same instants."""
    from cosim.scenario import from_dict

    scene = {"name": "stair", "outputs": [], "components": {"s": {"fmu": str(reference_fmus[f"{fmi}/Stair"])}},
             "master": {"algorithm": "iterative", "step": 0.1, "inputs": "linear"}}
    # (linear inputs: no FMI 3.0 event mode, which the Python loop alone would use, ending in the event iteration)
    py = run(from_dict(scene), engine="oracle")
    c = run(from_dict(scene), engine="compiled")
    assert (py.stats["engine"], c.stats["engine"]) == ("oracle", "compiled")
    assert c.status == py.status == "stopped" and c.reason == py.reason and "asked to terminate" in c.reason
    assert np.array_equal(py.trace.data, c.trace.data) and c.trace.time[-1] == py.trace.time[-1]
    assert c.stats["iterations_total"] == py.stats["iterations_total"]


def test_run_time_c_is_compiled_once_per_source_and_flags(tmp_path, monkeypatch):
    """fmus.c_loader: a source compiled once into the cache (a second load reuses the file), a new
    file for other flags, the compiler's own message for a source that does not compile, and a
    missing compiler named as such."""
    from fmus.errors import BuildError
    from fmus.c_loader import FLAGS, NoCompiler, library_path, load

    monkeypatch.setenv("RPR_COSIM_CACHE", str(tmp_path / "fmus"))
    src = "double twice(double x) { return 2.0 * x; }\n"
    lib = load(src, "t")
    lib.twice.restype, lib.twice.argtypes = ctypes.c_double, [ctypes.c_double]
    assert lib.twice(21.0) == 42.0
    first = library_path(src, "t")
    mtime = first.stat().st_mtime_ns
    assert library_path(src, "t") == first and first.stat().st_mtime_ns == mtime
    assert first.parent == tmp_path / "master"
    other = library_path(src, "t", (*FLAGS, "-DVARIANT"))
    assert other != first and other.exists()
    with pytest.raises(BuildError, match="error"):
        load("double broken(double x) { return x +; }\n", "t")
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    with pytest.raises(NoCompiler, match="no-such-cc"):
        load(src + "/* new */\n", "t")
