"""Hardware in the loop against the virtual board (the C daemon on a fake tree, the Python plant
behind it): the 1 kHz loop's timing, the UDP round trip, and the daemon's own tick jitter and CPU.

For each configuration (``--matrix``: quiet and loaded, without and with SCHED_FIFO, without and
with a flood of unauthenticated datagrams):

1. the daemon's CPU per tick with no master (1 s, the kernel's schedstat of its process);
2. UDP round trip on loopback (Python client, one command/sample pair per millisecond): p50/p99;
3. the 1 kHz loop: ``rig_step_hil`` (three PIDs and the hardware FMU, 1 ms steps, real-time
   pacing) for DURATION seconds: lateness p50/p99/max, missed deadlines (more than one step
   late), real-time factor, the FMU's round trip; the board's tick lateness p50/p99/max and CPU
   per tick as the board reported them over the protocol (the FMU's ``board_*`` outputs), and
   its CPU per tick by the kernel's accounting over the loop;
4. with ``--flood``: a separate process sends the issue's flood (50 000 datagrams: junk,
   commands of a wrong session, HELLOs under another key, as fast as it can) 1 s into the loop
   (its session is open by then), once or every ``--flood-every`` seconds; the board's dropped
   and throttled counts.

5. the machine's own floor: ``cyclictest`` (Debian ``rt-tests``, the standard latency probe of
   real-time Linux, a C thread sleeping to 1 ms deadlines) beside the loop for the same seconds at
   the loop's priority: its worst wake-up lateness and the wake-ups more than one period late.
   What it sees late no user program on this machine can keep on time.

``--load N`` runs N busy processes beside (the "loaded" machine); ``--priority P`` runs the loop
under SCHED_FIFO P and the board at P + 10 (root).  ``--target armhf`` runs the daemon's ARM
build under qemu-user (figures of the emulation, not of a BeagleBone).

    python3 benchmarks/bench_hil.py [--duration 5] [--long] [--priority 10] [--load 2] [--flood] [--matrix]
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.run import run  # noqa: E402
from hardware import client, protocol as P  # noqa: E402

BOARD_OUTPUTS = ["rig.leg[*].s", "target.leg[*].s", "pid*.y", "rig.round_trip", "rig.sample_age", "rig.fault",
                 "rig.board_tick_late", "rig.board_tick_p50", "rig.board_tick_p99", "rig.board_tick_max",
                 "rig.board_cpu_per_tick", "rig.board_dropped", "rig.board_throttled"]

FLOOD = """
import os, socket, sys, time
from hardware import protocol as P
port, start_at, stop_at, every = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
time.sleep(max(0.0, start_at - time.time()))  # the loop's session is open by then
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
junk = os.urandom(72)
wrong = P.pack(os.urandom(32), P.COMMAND, 0x5A5A5A5A, 1, 0, P.RUN, 12.0, 12.0, 12.0)
other = os.urandom(32)
hellos = [P.pack(other, P.HELLO, 0, 0, 0, os.urandom(16)) for _ in range(256)]
sent = 0
while time.time() < stop_at:
    t0 = time.monotonic()
    for k in range(50000):
        kind = k % 3
        try:
            s.sendto(junk if kind == 0 else wrong if kind == 1 else hellos[k & 255], ("127.0.0.1", port))
            sent += 1
        except OSError:
            pass
    print(f"{sent} datagrams in {time.monotonic() - t0:.3f} s", flush=True)
    if not every:
        break
    time.sleep(max(0.0, every - (time.monotonic() - t0)))
"""


def start_board(key: Path, priority: int, target: str) -> tuple[subprocess.Popen, str, int]:
    cmd = [sys.executable, "-m", "cosim", "board", "virtual", "--key", str(key), "--listen", "127.0.0.1:0",
           "--target", target]
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


def cpu_ns(pid: int) -> int:
    """CPU time the kernel accounted to every thread of ``pid`` [ns] (schedstat)."""
    return sum(int((t / "schedstat").read_text().split()[0]) for t in Path(f"/proc/{pid}/task").iterdir())


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


def start_cyclictest(duration: float, priority: int) -> subprocess.Popen | None:
    """cyclictest for ``duration`` s, 1 ms interval, histogram to 100 ms (None if not installed)."""
    exe = shutil.which("cyclictest")
    if not exe:
        return None
    cmd = [exe, "-m", "-q", "-i", "1000", "-D", f"{max(1, round(duration))}", "-h", "100000"]
    cmd += ["-p", str(priority)] if priority else []
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def cyclictest_figures(proc: subprocess.Popen | None) -> dict:
    """Max wake-up lateness [us] and wake-ups later than 1 ms from cyclictest's histogram."""
    if proc is None:
        return {"vm_note": "cyclictest not installed (apt install rt-tests)"}
    text = proc.communicate(timeout=60)[0]
    late, total, worst = 0, 0, 0
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].isdigit() and parts[1].isdigit():
            us, n = int(parts[0]), int(parts[1])
            total += n
            late += n if us > 1000 else 0
        elif line.startswith("# Max Latencies:"):
            worst = int(parts[-1])
        elif line.startswith("# Histogram Overflows:"):
            late += int(parts[-1])
    return {"vm_max_us": worst, "vm_late": late, "vm_wakeups": total}


def one(duration: float, priority: int, load: int, flood: bool, target: str, flood_every: float = 0.0) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="bench-hil-"))
    key = P.write_key(tmp / "board.key")
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(load)]
    # the board (the safety side) runs above the loop: a stalled loop must not stall the watchdog
    proc, address, pid = start_board(key, priority + 10 if priority else 0, target)
    out: dict = {"priority": priority, "load": load, "flood": flood}
    flooder = None
    try:
        c0 = cpu_ns(pid)
        time.sleep(1.0)
        out["idle_cpu_per_tick_us"] = (cpu_ns(pid) - c0) / 1e3 / 1000.0
        try:
            rtt = round_trip(address, key, 1000)
            out["udp_rtt_p50_us"], out["udp_rtt_p99_us"] = np.percentile(rtt, [50, 99]) * 1e6
        except client.BoardError as exc:  # a starved board at normal priority: say so, go on
            out["udp_rtt_p50_us"] = out["udp_rtt_p99_us"] = float("nan")
            out["rtt_error"] = str(exc)
        if flood:
            flooder = subprocess.Popen([sys.executable, "-c", FLOOD, address.rsplit(":", 1)[1],
                                        str(time.time() + 1.0), str(time.time() + duration + 3), str(flood_every)], stdout=subprocess.PIPE, text=True,
                                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
        c0, t0 = cpu_ns(pid), time.monotonic()
        probe = start_cyclictest(duration, priority)
        res = run(ROOT / "scenarios/rig_step_hil.yaml",
                  {"stop_time": duration, "components.rig.hardware.address": address,
                   "components.rig.hardware.key": str(key), "master.realtime.priority": priority,
                   "master.realtime.max_misses": 1000000, "outputs": BOARD_OUTPUTS}, out_dir=tmp)
        wall = time.monotonic() - t0
        out.update(cyclictest_figures(probe))
        out["loop_cpu_per_tick_us"] = (cpu_ns(pid) - c0) / 1e3 / (wall * 1000.0)
        rt = res.stats.get("realtime", {})
        tr = res.trace
        out.update(status=res.status, reason=res.reason, steps=rt.get("paced_steps", 0),
                   late_p50_us=rt.get("lateness_p50_s", 0) * 1e6, late_p99_us=rt.get("lateness_p99_s", 0) * 1e6,
                   late_max_ms=rt.get("lateness_max_s", 0) * 1e3, missed=rt.get("missed_deadlines", 0),
                   rtf=res.stats.get("real_time_factor", 0), fifo=rt.get("priority", ""))
        if len(tr.data) > 1:
            last = {n: float(tr[n][-1]) for n in ("rig.board_tick_p50", "rig.board_tick_p99", "rig.board_tick_max",
                                                  "rig.board_cpu_per_tick", "rig.board_dropped",
                                                  "rig.board_throttled")}
            out.update(fmu_rtt_p50_us=np.percentile(tr["rig.round_trip"][1:], 50) * 1e6,
                       fmu_rtt_p99_us=np.percentile(tr["rig.round_trip"][1:], 99) * 1e6,
                       board_p50_us=last["rig.board_tick_p50"] * 1e6, board_p99_us=last["rig.board_tick_p99"] * 1e6,
                       board_max_us=last["rig.board_tick_max"] * 1e6,
                       board_cpu_us=last["rig.board_cpu_per_tick"] * 1e6, dropped=int(last["rig.board_dropped"]),
                       throttled=int(last["rig.board_throttled"]))
    finally:
        if flooder is not None:
            flooder.kill()
            out["flood_sent"] = " ".join(flooder.communicate()[0].split("\n")[:1])
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=10)
        for h in hogs:
            h.kill()
            h.wait()
    return out


def show(r: dict, duration: float) -> None:
    cfg = (f"{'loaded (+' + str(r['load']) + ' busy processes)' if r['load'] else 'no added load'}, "
           f"{'SCHED_FIFO ' + str(r['priority']) if r['priority'] else 'normal priority'}"
           f"{', flood' if r['flood'] else ''}")
    print(f"== {cfg}: rig_step_hil {duration:g} s, status {r.get('status')}"
          + (f" ({r['reason']})" if r.get("reason") else ""))
    print(f"  master lateness p50 {r.get('late_p50_us', 0):.0f} us, p99 {r.get('late_p99_us', 0):.0f} us, "
          f"max {r.get('late_max_ms', 0):.2f} ms; missed deadlines {r.get('missed', 0)} of {r.get('steps', 0)}; "
          f"real-time factor {r.get('rtf', 0):.4f} ({r.get('fifo')})")
    print(f"  UDP round trip (Python client) p50 {r['udp_rtt_p50_us']:.0f} us, p99 {r['udp_rtt_p99_us']:.0f} us"
          f"{' (' + r['rtt_error'] + ')' if r.get('rtt_error') else ''}; "
          f"hardware FMU round trip p50 {r.get('fmu_rtt_p50_us', 0):.0f} us, p99 {r.get('fmu_rtt_p99_us', 0):.0f} us")
    print(f"  board ticks (reported over the protocol): lateness p50 {r.get('board_p50_us', 0):.0f} us, "
          f"p99 {r.get('board_p99_us', 0):.0f} us, max {r.get('board_max_us', 0):.0f} us; CPU per tick "
          f"{r.get('board_cpu_us', 0):.1f} us (kernel: {r['loop_cpu_per_tick_us']:.1f} us serving the loop, "
          f"{r['idle_cpu_per_tick_us']:.1f} us idle)")
    if "vm_max_us" in r:
        print(f"  the machine itself (cyclictest, same seconds and priority): worst wake-up {r['vm_max_us']} us late, "
              f"{r['vm_late']} of {r['vm_wakeups']} wake-ups more than 1 ms late")
    else:
        print(f"  the machine itself: {r.get('vm_note')}")
    if r["flood"]:
        print(f"  flood ({r.get('flood_sent') or 'still sending at the end'}): board dropped {r.get('dropped', 0)} datagrams, "
              f"{r.get('throttled', 0)} of them throttled")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=5.0, help="seconds of the 1 kHz loop (default 5)")
    ap.add_argument("--long", action="store_true", help="the issue's 60 s runs")
    ap.add_argument("--priority", type=int, default=0, help="SCHED_FIFO priority of the loop (board +10; root)")
    ap.add_argument("--load", type=int, default=0, help="busy processes beside the loop")
    ap.add_argument("--flood", action="store_true", help="flood the board with unauthenticated datagrams")
    ap.add_argument("--flood-every", type=float, default=0.0, metavar="S",
                    help="repeat the flood every S seconds (default: once, 1 s into the loop, as in issue 21)")
    ap.add_argument("--matrix", action="store_true", help="quiet/loaded x normal/SCHED_FIFO 10 x flood/none")
    ap.add_argument("--target", default="host", choices=("host", "armhf"), help="daemon build (armhf: qemu-user)")
    args = ap.parse_args()
    duration = 60.0 if args.long else args.duration
    print(f"load average before: {os.getloadavg()[0]:.2f}; {os.cpu_count()} CPUs; daemon {args.target}; "
          f"{duration:g} s per run")
    configs = [(l, p, f) for l in (0, 2) for p in (0, 10) for f in (False, True)] if args.matrix \
        else [(args.load, args.priority, args.flood)]
    for load, prio, flood in configs:
        show(one(duration, prio, load, flood, args.target, args.flood_every), duration)
    return 0


if __name__ == "__main__":
    sys.exit(main())
