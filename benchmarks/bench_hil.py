"""Hardware in the loop against the virtual board: the 1 kHz loop's timing, the UDP round trip
and the daemon's CPU use.

1. UDP round trip on loopback (Python client, one command/sample pair per millisecond): p50/p99.
2. The 1 kHz loop: ``rig_step_hil`` (three PIDs and the hardware FMU, 1 ms steps, real-time
   pacing) for DURATION seconds: lateness p50/p99/max, missed deadlines (more than one step
   late), real-time factor, round trip and sample age as the FMU saw them.
3. The daemon's CPU use while serving that loop at 1 kHz ticks: user + system time of its
   process over the loop's wall time (100 % = one core).

Limits: the watchdog is 100 ms, so a loop must never stall that long; a 1 kHz loop should miss
(almost) no deadline.  ``--priority P`` runs the loop under SCHED_FIFO P and the board at P + 10
(root): on a shared machine that is what keeps 1 kHz.

    python3 benchmarks/bench_hil.py [--duration 5] [--long] [--priority 10]
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.run.execute import run  # noqa: E402
from hardware import client, protocol as P  # noqa: E402


def start_board(key: Path, priority: int) -> tuple[subprocess.Popen, str, int]:
    cmd = [sys.executable, "-m", "cosim", "board", "virtual", "--key", str(key), "--listen", "127.0.0.1:0"]
    if priority:
        cmd += ["--rt-priority", str(priority)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    line = proc.stdout.readline()
    if "listening on" not in line:
        raise SystemExit(f"the virtual board did not start: {line!r}")
    address = line.split("listening on ")[1].split()[0]
    time.sleep(0.3)
    kids = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
    return proc, address, int(kids[0])


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def round_trip(address: str, key: Path, n: int) -> np.ndarray:
    host, port = P.parse_address(address)
    c = client.BoardClient((host, port), P.read_key(key), timeout=0.1)
    c.hello()
    c.command(P.ARM)
    rtt = np.empty(n)
    nxt = time.monotonic()
    for k in range(n):
        t = time.perf_counter()
        c.command(P.RUN, (0.0, 0.0, 0.0))
        rtt[k] = time.perf_counter() - t
        nxt += 1e-3
        time.sleep(max(0.0, nxt - time.monotonic()))
    c.command(P.STOP)
    c.close()
    return rtt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=5.0, help="seconds of the 1 kHz loop (default 5)")
    ap.add_argument("--long", action="store_true", help="the issue's 60 s run")
    ap.add_argument("--priority", type=int, default=0, help="SCHED_FIFO priority of board and loop (root)")
    args = ap.parse_args()
    duration = 60.0 if args.long else args.duration
    tmp = Path(tempfile.mkdtemp(prefix="bench-hil-"))
    key = P.write_key(tmp / "board.key")
    # the board (the safety side) runs above the loop: a stalled loop must not stall the watchdog
    proc, address, daemon_pid = start_board(key, args.priority + 10 if args.priority else 0)
    try:
        rtt = round_trip(address, key, 2000)
        print(f"UDP round trip on loopback (2000 x 1 ms, Python client): p50 {np.percentile(rtt, 50) * 1e6:.0f} us, "
              f"p99 {np.percentile(rtt, 99) * 1e6:.0f} us, max {rtt.max() * 1e6:.0f} us")
        cpu0, t0 = cpu_seconds(daemon_pid), time.monotonic()
        res = run(ROOT / "scenarios/rig_step_hil.yaml",
                  [f"stop_time={duration:g}", f"components.rig.hardware.address={address}",
                   f"components.rig.hardware.key={key}", f"master.realtime.priority={args.priority}",
                   "master.realtime.max_misses=1000000"], out_dir=tmp)
        wall = time.monotonic() - t0
        cpu = cpu_seconds(daemon_pid) - cpu0
        rt = res.stats["realtime"]
        steps = rt["paced_steps"]
        tr = res.trace
        print(f"1 kHz loop, rig_step_hil for {duration:g} s ({steps} steps, {rt['priority']}): status {res.status}"
              + (f" ({res.reason})" if res.reason else ""))
        print(f"  lateness p50 {rt['lateness_p50_s'] * 1e6:.0f} us, p99 {rt['lateness_p99_s'] * 1e6:.0f} us, "
              f"max {rt['lateness_max_s'] * 1e3:.2f} ms; missed deadlines {rt['missed_deadlines']} "
              f"({100 * rt['missed_deadlines'] / max(1, steps):.2f} %), longest run {rt['longest_miss_run']}; "
              f"real-time factor {res.stats['real_time_factor']:.4f}")
        if len(tr.data) > 1:
            print(f"  hardware FMU round trip p50 {np.percentile(tr['rig.round_trip'][1:], 50) * 1e6:.0f} us, "
                  f"p99 {np.percentile(tr['rig.round_trip'][1:], 99) * 1e6:.0f} us; sample age p99 "
                  f"{np.percentile(tr['rig.sample_age'][1:], 99) * 1e6:.0f} us")
        print(f"daemon CPU at 1 kHz ticks while serving the loop: {100 * cpu / wall:.1f} % of one core "
              f"({cpu:.2f} s in {wall:.1f} s)")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=10)
    return 0


if __name__ == "__main__":
    sys.exit(main())
