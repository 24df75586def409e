"""``rpr-cosim board``: the rig's I/O daemon, its key, its build for the board, the virtual board.

    rpr-cosim board keygen FILE
    rpr-cosim board serve --key FILE [--listen ADDR:PORT] [--root DIR] [--rate HZ] [--gpio MODE]
    rpr-cosim board build [--target host|armhf] [--out FILE]
    rpr-cosim board virtual --key FILE [--listen ADDR:PORT] [--noise C] [--latency S] [--stuck LEG] ...
    rpr-cosim board record [--out FILE] [--seconds S] [--fidelity motor] [--set R=4.8] [--calibration 1:35:3600] ...

``serve`` runs the C daemon ``rpr-board`` (:mod:`hardware.daemon`; built and cached on first
use) on the pins under ``--root`` ("/" on the board).  ``build --target armhf`` writes the
statically linked binary that is copied to the BeagleBone (where it runs without Python).
``virtual`` runs the same daemon on a temporary fake sysfs tree and plays the rig behind it
(:mod:`hardware.virtual`); its plant takes true parameters (``--set``), per-leg pot calibrations
(``--calibration``), noise and latency.  ``record`` drives that plant open-loop on synthetic time
and writes a trace (:mod:`hardware.record`) to replay and fit (``rpr-cosim fit``).  Both listen on loopback unless told otherwise.  The work is in
:mod:`hardware`; this module is the command line.
"""
from __future__ import annotations

import ctypes
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from ..errors import UserError
from hardware import daemon, faketree, protocol, virtual
from hardware.convert import Calibration
from hardware.record import record
from fmus import BuildError


def _plant_options(args, **extra):
    """The plant options of the command line (a UserError names a malformed one)."""

    try:
        start = tuple(float(x) for x in args.start.split(","))
        assert len(start) == 3
    except (ValueError, AssertionError):
        raise UserError(f"--start {args.start!r}: expected three leg lengths in metres, e.g. 0.31,0.36,0.2") from None
    params = {}
    for item in args.sets:
        name, sep, value = item.partition("=")
        m = re.fullmatch(r"(?:components\.[^.]+\.params\.)?(.+)", name.strip())
        try:
            params[m.group(1)] = float(value)
        except ValueError:
            raise UserError(f"--set {item!r}: expected NAME=NUMBER, e.g. R=4.8") from None
        if not sep:
            raise UserError(f"--set {item!r}: expected NAME=NUMBER, e.g. R=4.8")
    cals = [virtual.RIG_CALIBRATION] * 3
    for item in args.calibration:
        parts = item.split(":")
        try:
            legs = (1, 2, 3) if parts[0] == "all" else (int(parts[0]),)
            zero, full = float(parts[1]), float(parts[2])
            assert len(parts) == 3 and all(leg in (1, 2, 3) for leg in legs)
            for leg in legs:
                cals[leg - 1] = Calibration(raw_zero=zero, raw_full=full, s_offset=virtual.RIG_CALIBRATION.s_offset)
        except (ValueError, IndexError, AssertionError):
            raise UserError(f"--calibration {item!r}: expected LEG:ZERO:FULL, e.g. 2:35:3650 (leg 1..3 or all)") \
                from None
    return virtual.PlantOptions(actuator=args.actuator, start=start, noise=args.noise, latency=args.latency,
                                seed=args.seed, fidelity=args.fidelity, params=params, calibration=tuple(cals), **extra)


def _record(args) -> int:

    opts = _plant_options(args)
    out = args.out or Path("runs") / "record" / "rig_recording.csv"
    try:
        path = record(out, opts, seconds=args.seconds, rate=args.rate, current_noise=args.current_noise)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    print(f"rpr-cosim board record: {path} ({args.seconds:g} s at {args.rate:g} Hz, {args.fidelity} plant)")
    return 0


def _keygen(args) -> int:

    try:
        protocol.write_key(args.file)
    except FileExistsError:
        raise UserError(f"{args.file} exists; refusing to overwrite a key (remove it first)") from None
    except OSError as exc:
        raise UserError(f"cannot create {args.file}: {exc.strerror or exc}") from None
    print(f"key written to {args.file} (mode 600); copy it to the board and to the master, nowhere else")
    return 0


def _binary(target: str = "host") -> list[str]:

    try:
        return daemon.command(target)
    except BuildError as exc:
        raise UserError(str(exc)) from None


def _build(args) -> int:

    try:
        path = daemon.build(args.target)
    except BuildError as exc:
        raise UserError(str(exc)) from None
    out = args.out or Path(f"rpr-board-{args.target}")
    try:
        shutil.copyfile(path, out)
        os.chmod(out, 0o755)
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None
    static = " (statically linked: needs no library on the board)" if args.target != "host" else ""
    print(f"rpr-board for {args.target} written to {out}{static}")
    return 0


def _common(args) -> list[str]:
    """Check the options (one-line errors) and return the daemon's own options."""

    try:
        protocol.read_key(args.key)
        protocol.parse_address(args.listen)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if not (args.rate > 0) or args.rate > 20000:
        raise UserError(f"--rate {args.rate}: expected 1..20000 Hz")
    if args.rt_priority and not 1 <= args.rt_priority <= 99:
        raise UserError(f"--rt-priority {args.rt_priority}: expected 1..99")
    opts = ["--key", str(args.key), "--listen", args.listen, "--rate", f"{args.rate:g}"]
    opts += ["--duration", f"{args.duration:g}"] if args.duration else []
    opts += ["--rt-priority", str(args.rt_priority)] if args.rt_priority else []
    return opts + (["-v"] if args.verbose else [])


def _die_with_parent() -> None:
    """In the daemon's process: SIGTERM when this command dies (even by SIGKILL), so that the
    daemon zeroes the outputs rather than drive on without its owner (Linux)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _spawn(cmd: list[str], **kw) -> subprocess.Popen:
    return subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, preexec_fn=_die_with_parent, **kw)


def _relay(stream, out) -> threading.Thread:
    def run():
        for line in stream:
            out.write(line)
            out.flush()
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def _serve(args) -> int:
    opts = _common(args) + ["--root", str(args.root), "--gpio", args.gpio]
    if args.travel:
        opts += ["--travel", args.travel]
    child = _spawn([*_binary(args.target), *opts])
    err = _relay(child.stderr, sys.stderr)
    forward = lambda signum, frame: child.send_signal(signum)  # noqa: E731
    old = {s: signal.signal(s, forward) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        rc = child.wait()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)
            rc = child.wait()
        err.join(timeout=2)
    return rc


def _memory_dir() -> str | None:
    """/dev/shm where the machine has it: the fake tree lives in memory, as sysfs does (a disk
    file system would add its journal to the daemon's cost per write)."""
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK | os.X_OK) else None


def _plant_priority(prio: int) -> None:
    """The plant plays a physical rig, which never stalls: under SCHED_FIFO just below the
    daemon's, so that a loaded machine does not hold the simulated motion back (a plant starved
    for milliseconds integrates a stale drive over them: 1 mm off the co-simulation in tests)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(1, prio)))
    except (AttributeError, OSError) as exc:
        print(f"rpr-cosim board virtual: the plant stays at normal priority ({getattr(exc, 'strerror', exc)})",
              file=sys.stderr, flush=True)


def _virtual(args) -> int:

    opts = _common(args)
    opts_plant = _plant_options(args, stuck=tuple(args.stuck), unplugged=tuple(args.unplug),
                                driver_fault=tuple(args.driver_fault))
    tmp = None
    if args.tree is None:
        tmp = Path(tempfile.mkdtemp(prefix="rpr-virtual-board-", dir=_memory_dir()))
        tree = tmp
    else:
        tree = args.tree
        if tree.exists() and any(tree.iterdir()):
            raise UserError(f"--tree {tree} exists and is not empty; give a new directory")
    faketree.make_fake_tree(tree)
    try:
        plant = virtual.Plant(tree, opts_plant)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    child = _spawn([*_binary(args.target), *opts, "--root", str(tree)], stdout=subprocess.PIPE)
    err = _relay(child.stderr, sys.stderr)
    stopping = {"flag": False}

    def on_signal(signum, frame):
        stopping["flag"] = True
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        line = child.stdout.readline()
        m = re.search(r"listening on (\S+)", line)
        if not m:
            child.wait(timeout=10)
            err.join(timeout=2)
            raise UserError(f"the daemon did not start (exit code {child.returncode})")
        what = f"{args.actuator} actuators" if args.fidelity == "rig" else f"{args.fidelity} plant"
        print(f"rpr-cosim board virtual: listening on {m.group(1)} (fake tree {tree}, {what})", flush=True)
        if args.rt_priority:
            _plant_priority(args.rt_priority - 1)
        plant.run(args.duration, stop=lambda: stopping["flag"] or child.poll() is not None)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)
        try:
            child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        out = child.stdout.read()
        err.join(timeout=2)
        if out:
            print(out.strip(), flush=True)
        plant.close()
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0
