"""``rpr-cosim board``: the rig's I/O daemon, its key, and the virtual board.

    rpr-cosim board keygen FILE
    rpr-cosim board serve --key FILE [--listen ADDR:PORT] [--root DIR] [--rate HZ]
    rpr-cosim board virtual --key FILE [--listen ADDR:PORT] [--noise C] [--latency S] [--stuck LEG] ...

``serve`` runs on the BeagleBone (root "/"): it owns the pins of SPEC §7 and enforces the safety
rules of :mod:`hardware.daemon`.  ``virtual`` runs the same daemon, as a child process, on a
temporary fake sysfs tree and plays the rig behind it (:mod:`hardware.virtual`).  Both listen on
loopback unless told otherwise.  The work is in :mod:`hardware`; this module is the command line.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from ..errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("board", help="the rig's I/O daemon (BeagleBone), its key, and the virtual board",
                       description="Hardware in the loop: the BeagleBone I/O daemon and the virtual board.")
    verbs = p.add_subparsers(dest="board_verb", metavar="ACTION")
    verbs.required = True
    k = verbs.add_parser("keygen", help="make a new shared key file (owner-only permissions)")
    k.add_argument("file", type=Path)
    k.set_defaults(handler=_keygen)
    for name, text in (("serve", "run the I/O daemon on the board's pins"),
                       ("virtual", "run the daemon on a fake sysfs tree with a simulated rig behind it")):
        s = verbs.add_parser(name, help=text)
        s.add_argument("--key", type=Path, required=True, help="shared key file (rpr-cosim board keygen)")
        s.add_argument("--listen", default="127.0.0.1:5005", metavar="ADDR:PORT",
                       help="UDP address (default 127.0.0.1:5005, loopback only; port 0 picks a free one)")
        s.add_argument("--rate", type=float, default=1000.0, metavar="HZ", help="daemon ticks per second (1000)")
        s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
        s.add_argument("--rt-priority", type=int, default=0, metavar="P",
                       help="run under SCHED_FIFO at priority P (1..99; needs root or CAP_SYS_NICE): keeps a 1 kHz "
                            "loop on time on a busy machine")
        s.add_argument("-v", "--verbose", action="store_true", help="log sessions and faults")
        if name == "serve":
            s.add_argument("--root", type=Path, default=Path("/"), help="sysfs root (default /; a fake tree in tests)")
            s.set_defaults(handler=_serve)
        else:
            s.add_argument("--tree", type=Path, default=None, help="create the fake tree here (default: a temp dir, "
                                                                   "removed at exit)")
            s.add_argument("--actuator", default="fa200", choices=("fa200", "x"))
            s.add_argument("--start", default="0.31086,0.35586,0.20428", metavar="L1,L2,L3",
                           help="leg lengths at the start [m] (default: Table 6.12's start pose)")
            s.add_argument("--noise", type=float, default=0.0, metavar="COUNTS", help="ADC noise (std dev, counts)")
            s.add_argument("--latency", type=float, default=0.0, metavar="S", help="sensor latency [s]")
            for flag, what in (("--stuck", "sensor of leg N frozen"), ("--unplug", "pot of leg N unplugged"),
                               ("--driver-fault", "driver of leg N gives no voltage")):
                s.add_argument(flag, type=int, action="append", default=[], metavar="N", choices=(1, 2, 3), help=what)
            s.set_defaults(handler=_virtual)


def _keygen(args) -> int:
    from hardware import protocol

    try:
        protocol.write_key(args.file)
    except FileExistsError:
        raise UserError(f"{args.file} exists; refusing to overwrite a key (remove it first)") from None
    except OSError as exc:
        raise UserError(f"cannot create {args.file}: {exc.strerror or exc}") from None
    print(f"key written to {args.file} (mode 600); copy it to the board and to the master, nowhere else")
    return 0


def _common(args):
    from hardware import protocol

    try:
        key = protocol.read_key(args.key)
        host, port = protocol.parse_address(args.listen)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if not (args.rate > 0) or args.rate > 20000:
        raise UserError(f"--rate {args.rate}: expected 1..20000 Hz")
    import logging

    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="[board] %(levelname)s %(message)s", stream=sys.stderr)
    if args.rt_priority:
        if not 1 <= args.rt_priority <= 99:
            raise UserError(f"--rt-priority {args.rt_priority}: expected 1..99")
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
        except (AttributeError, OSError) as exc:
            raise UserError(f"--rt-priority {args.rt_priority}: SCHED_FIFO refused "
                            f"({getattr(exc, 'strerror', None) or exc}); run as root or drop the option") from None
    return key, (host, port)


def _serve(args) -> int:
    from hardware import daemon
    from hardware.pins import PinError

    key, listen = _common(args)
    if listen[0] not in ("127.0.0.1", "localhost", "::1"):
        print(f"[board] listening on {listen[0]}: reachable from the network (authenticated, not encrypted)",
              file=sys.stderr)
    try:
        d = daemon.Daemon(key, root=args.root, listen=listen, rate=args.rate)
    except PinError as exc:
        raise UserError(f"pins under {args.root}: {exc}") from None
    except OSError as exc:
        raise UserError(f"cannot listen on {args.listen}: {exc.strerror or exc}") from None
    daemon.install_signal_handlers(d)
    print(f"rpr-cosim board: listening on {d.address[0]}:{d.address[1]} (root {args.root}, {args.rate:g} Hz)",
          flush=True)
    try:
        d.serve_forever(args.duration)
    except SystemExit:
        pass
    print(f"rpr-cosim board: stopped; outputs zeroed; counters {d.counters}", flush=True)
    return 0


def _virtual(args) -> int:
    from hardware import faketree, virtual

    _common(args)
    try:
        start = tuple(float(x) for x in args.start.split(","))
        assert len(start) == 3
    except (ValueError, AssertionError):
        raise UserError(f"--start {args.start!r}: expected three leg lengths in metres, e.g. 0.31,0.36,0.2") from None
    tmp = None
    if args.tree is None:
        tmp = Path(tempfile.mkdtemp(prefix="rpr-virtual-board-"))
        tree = tmp
    else:
        tree = args.tree
        if tree.exists() and any(tree.iterdir()):
            raise UserError(f"--tree {tree} exists and is not empty; give a new directory")
    faketree.make_fake_tree(tree)
    opts = virtual.PlantOptions(actuator=args.actuator, start=start, noise=args.noise, latency=args.latency,
                                stuck=tuple(args.stuck), unplugged=tuple(args.unplug),
                                driver_fault=tuple(args.driver_fault))
    plant = virtual.Plant(tree, opts)
    cmd = [sys.executable, "-m", "cosim", "board", "serve", "--key", str(args.key), "--listen", args.listen,
           "--root", str(tree), "--rate", str(args.rate)] + (["-v"] if args.verbose else []) \
        + (["--rt-priority", str(args.rt_priority)] if args.rt_priority else [])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parent.parent)]
                                                       + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else [])))
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env)
    stopping = {"flag": False}

    def on_signal(signum, frame):
        stopping["flag"] = True
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        line = child.stdout.readline()
        m = re.search(r"listening on (\S+)", line)
        if not m:
            child.wait(timeout=10)
            raise UserError(f"the daemon did not start (exit code {child.returncode})")
        print(f"rpr-cosim board virtual: listening on {m.group(1)} (fake tree {tree}, {args.actuator} actuators)",
              flush=True)
        plant.run(args.duration, stop=lambda: stopping["flag"] or child.poll() is not None)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)
        try:
            out, _ = child.communicate(timeout=5)
        except subprocess.TimeoutExpired:
            child.kill()
            out, _ = child.communicate()
        if out:
            print(out.strip(), flush=True)
        plant.close()
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0
