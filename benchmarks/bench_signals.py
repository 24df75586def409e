"""How fast a signal ends a run, and what the trace writer costs in memory (issue #7).

For each case a real ``rpr-cosim run`` process is started, left running for ``--after`` seconds,
then sent the signal; printed: the time from the signal to the process's exit, its exit code,
the sidecar's status, whether every CSV row is whole, and the process's peak resident memory
(``ru_maxrss`` of the child).  The limit (issue #7): a signal takes effect within 1 s.

Cases: pid_step recording every step (the trace writer is the bottleneck: back-pressure keeps
its queue at 1 MB, so draining it is bounded); pid_step_multibody (0.5 ms per step inside the
FMU); the monolithic reference of a diverging scene (CVODES grinding in C).

    python3 benchmarks/bench_signals.py [--after 5] [--signal INT]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
WILD = [x for i in (1, 2, 3) for k, v in (("Kp", 1e6), ("Ki", 1e6), ("Kd", 1e6), ("u_max", 1e9))
        for x in ("--set", f"components.pid{i}.params.{k}={v}")]
CASES = {
    "pid_step, a row every step": ["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=3000", "--max-trace", "10GB"],
    "pid_step_multibody": ["run", str(SCENES / "pid_step_multibody.yaml"), "--set", "stop_time=300"],
    "reference of a diverging scene": ["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=2", *WILD,
                                       "--reference"],
}


def whole(path: Path) -> bool:
    if not path.exists():
        return False
    text = path.read_text()
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    n = len(lines[0].split(","))
    return text.endswith("\n") and all(len(ln.split(",")) == n for ln in lines[1:])


def one(name: str, args: list[str], after: float, sig: signal.Signals) -> None:
    out = Path(tempfile.mkdtemp(prefix="bench-signals-"))
    proc = subprocess.Popen([sys.executable, "-m", "cosim", *args, "--out", str(out)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(after)
    t0 = time.perf_counter()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=600)
    dt = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    sides = {p.name: json.loads(p.read_text()).get("status") for p in out.glob("*.json")}
    rows_ok = all(whole(p) for p in out.glob("*.csv"))
    print(f"{name:<32} {sig.name} after {after:.0f} s: exit {proc.returncode} in {dt:5.2f} s; sidecars {sides}; "
          f"whole rows: {rows_ok}; peak RSS (largest child so far) {rss:.0f} MB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--after", type=float, default=5.0, help="seconds of running before the signal")
    ap.add_argument("--signal", default="INT", help="INT, TERM or HUP")
    a = ap.parse_args()
    sig = signal.Signals[f"SIG{a.signal.upper()}"]
    os.environ.setdefault("PYTHONPATH", str(ROOT))
    for name, args in CASES.items():
        one(name, args, a.after, sig)


if __name__ == "__main__":
    main()
