"""Start-up cost of the CLI: ``rpr-cosim --help`` and a one-step ``rpr-cosim run`` of a scene whose
FMUs are cached, against the targets of issue 8 (0.3 s and 0.5 s).

Each figure is the median wall time of fresh Python processes (``python -m cosim ...``), after
one warm-up run that fills the FMU cache (and its recipe index); the script also prints which
heavy modules (CasADi, matplotlib, scipy, FMPy) each command imported, from ``python -X
importtime`` of the same command, and the interpreter's own start-up (``python -c pass``) as the
floor.

The children keep their bytecode in a temporary folder (``PYTHONPYCACHEPREFIX``; the warm-up run
fills it), as an installed package does; the time to the first step is also printed without any
bytecode (``PYTHONDONTWRITEBYTECODE=1``, every module compiled from source on every start).

Time to the first step: the same one-step run, started through a probe that wraps
:meth:`cosim.trace.MemoryTrace.record` and notes the wall clock (``time.time()``) of its first
call: the row at the start time, recorded after every FMU was found, loaded, instantiated and
initialised and immediately before the first doStep.  The figure is that instant minus the
parent's clock just before it spawned the process (interpreter start-up and every import
included), against the 0.5 s target.

Usage: ``python benchmarks/bench_startup.py [--scene scenarios/pid_step.yaml] [--repeat 5]``
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("casadi", "matplotlib", "scipy", "fmpy", "numpy", "yaml")
FIRST_STEP_TARGET = 0.5  # [s] issue 8 item 7
#: Runs the CLI with the first recorded row (the start-time row, just before the first doStep) timed.
PROBE = """
import sys, time
import cosim.trace as _trace
_record = _trace.MemoryTrace.record
def _first(self, rows):
    if not getattr(_trace, "_probe_done", False):
        _trace._probe_done = True
        sys.stderr.write("FIRST_STEP_AT %r %r\\n" % (time.time(), time.process_time()))
    return _record(self, rows)
_trace.MemoryTrace.record = _first
from cosim.cli import main
sys.exit(main(sys.argv[1:]))
"""


#: Where the child processes keep their bytecode (None: they compile every module from source).
BYTECODE_DIR: str | None = None


def _env() -> dict[str, str]:
    """The child's environment: this tree first on the path; bytecode cached in
    :data:`BYTECODE_DIR` (as an installed package has it) or not written at all."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("PYTHONPYCACHEPREFIX", None)
    if BYTECODE_DIR:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = BYTECODE_DIR
    else:
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def wall(make_cmd, repeat: int) -> float:
    """Median wall time [s] of ``make_cmd(i)`` over ``repeat`` fresh processes (each must succeed)."""
    times = []
    for i in range(repeat):
        cmd = make_cmd(i)
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def first_step(make_cmd, repeat: int) -> tuple[float, float]:
    """Median wall time [s] from spawning ``make_cmd(i)`` (a ``python -m cosim ...`` command, run
    through :data:`PROBE`) to its first recorded row, and median CPU time [s] the process had
    used by then (close to the wall time on an idle machine), over ``repeat`` fresh processes."""
    times, cpu = [], []
    for i in range(repeat):
        cmd = make_cmd(i)
        assert cmd[1:3] == ["-m", "cosim"], cmd
        t0 = time.time()
        res = subprocess.run([cmd[0], "-c", PROBE, *cmd[3:]], capture_output=True, text=True, env=_env())
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed: {res.stderr.strip()[-500:]}")
        at = [line.split()[1:] for line in res.stderr.splitlines() if line.startswith("FIRST_STEP_AT ")]
        if not at:
            raise RuntimeError(f"{' '.join(cmd)}: the run recorded no row")
        times.append(float(at[0][0]) - t0)
        cpu.append(float(at[0][1]))
    return statistics.median(times), statistics.median(cpu)


def heavy_imports(cmd: list[str]) -> dict[str, float]:
    """Top-level heavy packages ``cmd`` imported and their cumulative import time [s]."""
    res = subprocess.run([cmd[0], "-X", "importtime", *cmd[1:]], capture_output=True, text=True, env=_env())
    out = {}
    for line in res.stderr.splitlines():
        m = re.match(r"import time:\s+\d+ \|\s+(\d+) \| (\s*)(\S+)$", line)
        if m and m.group(3) in HEAVY:
            out[m.group(3)] = max(out.get(m.group(3), 0.0), int(m.group(1)) / 1e6)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "scenarios" / "pid_step.yaml"))
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    global BYTECODE_DIR
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        BYTECODE_DIR = str(Path(tmp) / "pycache")
        def run(i):  # a fresh output directory per run (a run never overwrites)
            return [py, "-m", "cosim", "run", args.scene, "--set", "stop_time=1e-3", "--out", str(Path(tmp) / f"out{i}")]

        subprocess.run(run("warm"), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env())  # fills the FMU cache
        cases = [("python -c pass (floor)", lambda i: [py, "-c", "pass"], None),
                 ("rpr-cosim --help", lambda i: [py, "-m", "cosim", "--help"], 0.3),
                 (f"rpr-cosim run {Path(args.scene).name}, one step, cached FMUs", run, 0.5)]
        print(f"{'command':58s} {'median s':>9s} {'target':>7s}  heavy imports (cumulative s)")
        for label, make_cmd, target in cases:
            t = wall(make_cmd, args.repeat)
            imp = heavy_imports(make_cmd("imports"))
            verdict = "" if target is None else (f"{target:5.1f} {'ok' if t < target else 'OVER'}")
            print(f"{label:58s} {t:9.3f} {verdict:>7s}  "
                  + (", ".join(f"{k} {v:.2f}" for k, v in sorted(imp.items(), key=lambda kv: -kv[1])) or "none"))
        for label, cache in (("time to the first step (start -> first doStep)", BYTECODE_DIR),
                             ("the same without bytecode (DONTWRITEBYTECODE)", None)):
            BYTECODE_DIR = cache
            t, cpu = first_step(run, args.repeat)
            print(f"{label:58s} {t:9.3f} {FIRST_STEP_TARGET:5.1f} {'ok' if t < FIRST_STEP_TARGET else 'OVER'}  "
                  f"(CPU time of the process by then: {cpu:.3f} s)")
    print(f"({args.repeat} runs each, medians; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
