"""The I/O daemon: owns the rig's pins, samples the ADC, applies voltage commands and enforces
safety on its own, whatever the master does.

State machine (:data:`protocol.STATE_NAMES`)::

    idle --ARM--> armed --RUN command--> running --STOP--> idle
      any --fault--> fault (latched: outputs zero) --RESET--> idle

Safety, every tick and on every command:

- watchdog: armed or running without a valid command for ``watchdog_s`` (100 ms) -> fault;
- commands clamped to ``+-v_max`` and slew-limited (``slew`` V/s); non-finite -> fault;
- software end-of-stroke limits: within ``end_margin`` counts of an end only motion away from it
  is applied (a limit flag, not a fault);
- ADC: unreadable for ``stale_s`` -> fault ``ADC stale``; outside the travel by more than
  ``range_margin`` counts (an unplugged pot reads 4095) -> ``ADC out of range``; driven at more
  than ``stuck_duty`` for ``stuck_s`` while moving at most ``stuck_counts`` -> ``stuck``;
- outputs zeroed (duty 0, DIR low) in idle and fault, on exit, on SIGTERM/SIGINT/SIGHUP and on
  any exception.  (A SIGKILL of the daemon itself cannot be caught: on the rig the drivers'
  PWM inputs need a pull-down so that a dead board stops the motors.)

Datagrams that are malformed, unauthenticated, from an old session, replayed, out of sequence or
stale change nothing and are counted in :attr:`Daemon.counters`.
"""
from __future__ import annotations

import logging
import math
import os
import select
import signal
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

from . import protocol as P
from .convert import PERIOD_NS, Calibration, ideal_counts, volts_to_drive
from .pins import RIG_PINS, LegFiles, LegPins, PinError, read_int, resolve, write_value

log = logging.getLogger("hardware.daemon")
_now = time.monotonic_ns


@dataclass
class Safety:
    """Limits the daemon enforces (SI units, counts for the ADC)."""

    v_max: float = 12.0          # [V] command clamp (driver supply)
    slew: float = 2400.0         # [V/s] 0 -> 12 V in 5 ms
    watchdog_s: float = 0.100    # [s]
    stale_ms: float = 50.0       # [ms] a command older than this (one-way, by the session clock) is dropped
    adc_stale_s: float = 0.020   # [s] ADC unreadable this long -> fault
    travel: tuple[float, float] = (0.0, ideal_counts(0.5))  # [counts] calibrated ends of the stroke
    end_margin: float = 30.0     # [counts] ~5 mm: only motion away from an end inside it
    range_margin: float = 150.0  # [counts] ~2.5 cm beyond the travel: out of range
    stuck_duty: float = 0.25     # driven above this fraction of full duty ...
    stuck_s: float = 0.30        # [s] ... for this long ...
    stuck_counts: int = 3        # ... while moving at most this many counts -> stuck


@dataclass
class _Leg:
    files: LegFiles
    raw: int = -1
    raw_ok_ns: int = 0
    target: float = 0.0   # commanded voltage [V]
    applied: float = 0.0  # after clamp, slew and limits [V]
    duty: int = -1        # last written duty [ns] (-1: unknown, forces a write)
    dir_high: int = -1
    limit: int = 0        # 1 low end, 2 high end
    drive_since: int = 0  # when the current "driven" spell started [ns]
    drive_raw: int = -1   # position when it started


@dataclass
class Session:
    id: int
    key: bytes
    offset_ns: int      # daemon time - master time (minimum seen): maps master stamps to ours
    last_seq: int = 0


class Daemon:
    """The daemon over the sysfs ``root``; :meth:`serve_forever` runs it (see the module doc)."""

    def __init__(self, key: bytes, *, root: Path | str = "/", listen: tuple[str, int] = ("127.0.0.1", 5005),
                 rate: float = 1000.0, pins: tuple[LegPins, ...] = RIG_PINS, safety: Safety | None = None):
        if not (rate > 0 and math.isfinite(rate)):
            raise ValueError(f"rate must be a positive number of Hz, got {rate}")
        self.key = key
        self.root = Path(root)
        self.rate = float(rate)
        self.tick_ns = int(round(1e9 / rate))
        self.safety = safety or Safety()
        self.legs = [_Leg(f) for f in resolve(self.root, pins)]
        # the ADC channels stay open: pread at offset 0 makes sysfs convert again (no open per tick)
        self._adc_fd = [os.open(leg.files.adc, os.O_RDONLY) for leg in self.legs]
        self.state = P.IDLE
        self.faults = 0
        self.session: Session | None = None
        self.last_cmd_ns = 0
        self.counters = {k: 0 for k in ("received", "commands", "malformed", "unauthenticated", "old_session",
                                         "out_of_sequence", "stale", "refused", "sessions", "faults", "ticks",
                                         "writes")}
        self._seen_hello: set[bytes] = set()
        self._last_apply = 0
        self._next_session = int.from_bytes(P.new_nonce()[:4], "little") or 1
        self._stop = False
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(listen)
        self.sock.setblocking(False)
        self.address = self.sock.getsockname()
        self._setup_outputs()

    # --- outputs ---------------------------------------------------------------------------------
    def _setup_outputs(self) -> None:
        for leg in self.legs:
            write_value(leg.files.dir_direction, "out")
            self._write_leg(leg, 0, 0, force=True)
            if read_int(leg.files.period) != PERIOD_NS:
                write_value(leg.files.period, PERIOD_NS)
            write_value(leg.files.enable, 1)

    def _write_leg(self, leg: _Leg, duty: int, dir_high: int, *, force: bool = False) -> None:
        # duty first when it drops, DIR first when it rises: never drive the old direction harder
        if force or duty != leg.duty:
            write_value(leg.files.duty, duty)
            leg.duty = duty
            self.counters["writes"] += 1
        if force or dir_high != leg.dir_high:
            write_value(leg.files.dir_value, dir_high)
            leg.dir_high = dir_high
            self.counters["writes"] += 1

    def zero_outputs(self) -> None:
        """Duty 0 and DIR low on every leg (each attempted even if one fails)."""
        err = None
        for leg in self.legs:
            leg.target = leg.applied = 0.0
            try:
                self._write_leg(leg, 0, 0, force=True)
            except PinError as exc:
                err = exc
        if err is not None:
            raise err

    def _apply(self, now: int) -> None:
        """Move each leg's output toward its target: clamp, slew limit (over the time since the
        last update), end limits; then write."""
        s = self.safety
        dt_s = (now - self._last_apply) / 1e9 if self._last_apply else 0.0
        self._last_apply = now
        active = self.state == P.RUNNING
        lo, hi = s.travel
        for leg in self.legs:
            want = max(-s.v_max, min(s.v_max, leg.target)) if active else 0.0
            leg.limit = 0
            if leg.raw >= 0 and leg.raw <= lo + s.end_margin and want < 0:
                want, leg.limit = 0.0, 1
            elif leg.raw >= 0 and leg.raw >= hi - s.end_margin and want > 0:
                want, leg.limit = 0.0, 2
            if not active:
                v = 0.0
            else:
                step = s.slew * dt_s
                v = leg.applied + max(-step, min(step, want - leg.applied))
                if want == 0.0 and abs(v) < 1e-9:
                    v = 0.0
                if leg.limit:  # at an end stop the motion toward it stops at once
                    v = 0.0 if (leg.limit == 1 and v < 0) or (leg.limit == 2 and v > 0) else v
            leg.applied = v
            d = volts_to_drive(v, v_supply=s.v_max)
            try:
                self._write_leg(leg, d.duty_ns, int(d.dir_high))
            except PinError as exc:
                self._fault(P.F_IO, str(exc))
                return

    # --- sensing ---------------------------------------------------------------------------------
    def _sample(self, now: int) -> None:
        s = self.safety
        for i, (leg, fd) in enumerate(zip(self.legs, self._adc_fd), start=1):
            try:
                leg.raw = int(os.pread(fd, 16, 0))
                leg.raw_ok_ns = now
            except (OSError, ValueError):
                if leg.raw_ok_ns and now - leg.raw_ok_ns > s.adc_stale_s * 1e9:
                    self._fault(P.F_ADC_STALE, f"leg {i}: ADC unreadable for {(now - leg.raw_ok_ns) / 1e6:.0f} ms")
                continue
            lo, hi = s.travel
            if leg.raw < lo - s.range_margin or leg.raw > hi + s.range_margin:
                self._fault(P.F_ADC_RANGE, f"leg {i}: {leg.raw} counts outside {lo:.0f}..{hi:.0f} "
                                           f"(+-{s.range_margin:.0f}): sensor unplugged?")
            driven = abs(leg.applied) >= s.stuck_duty * s.v_max
            if not driven:
                leg.drive_since, leg.drive_raw = 0, -1
            elif leg.drive_since == 0:
                leg.drive_since, leg.drive_raw = now, leg.raw
            elif abs(leg.raw - leg.drive_raw) > s.stuck_counts:
                leg.drive_since, leg.drive_raw = now, leg.raw
            elif now - leg.drive_since > s.stuck_s * 1e9:
                self._fault(P.F_ADC_STUCK, f"leg {i}: driven at {leg.applied:+.1f} V for {s.stuck_s:.2f} s but "
                                           f"the position stayed at {leg.raw} counts")

    # --- state -----------------------------------------------------------------------------------
    def _fault(self, bit: int, why: str) -> None:
        if self.state != P.FAULT:
            self.counters["faults"] += 1
            log.error("fault: %s (%s); outputs zeroed, latched until reset", P.FAULT_NAMES[bit], why)
        self.faults |= bit
        self.state = P.FAULT
        for leg in self.legs:
            leg.target = leg.applied = 0.0
            leg.drive_since = 0
        try:
            self.zero_outputs()
        except PinError as exc:
            self.faults |= P.F_IO
            log.error("could not zero the outputs: %s", exc)

    def tick(self, now: int | None = None) -> None:
        """One periodic update: sample, watchdog, outputs."""
        now = _now() if now is None else now
        self.counters["ticks"] += 1
        self._sample(now)
        if self.state in (P.ARMED, P.RUNNING) and now - self.last_cmd_ns > self.safety.watchdog_s * 1e9:
            self._fault(P.F_WATCHDOG, f"no valid command for {(now - self.last_cmd_ns) / 1e6:.1f} ms")
        if self.state != P.FAULT:
            self._apply(now)

    # --- datagrams -------------------------------------------------------------------------------
    def handle(self, data: bytes, addr, now: int | None = None) -> bytes | None:
        """Act on one datagram; returns the reply (or None).  Never raises for bad input."""
        now = _now() if now is None else now
        c = self.counters
        c["received"] += 1
        try:
            dg = P.parse(data)
        except P.ProtocolError:
            c["malformed"] += 1
            return None
        if dg.type == P.HELLO:
            return self._hello(dg, now)
        if dg.type != P.COMMAND:
            c["malformed"] += 1
            return None
        ses = self.session
        if ses is None or dg.session != ses.id:
            c["old_session"] += 1
            return None
        if not P.authentic(ses.key, dg):
            c["unauthenticated"] += 1
            return None
        if dg.seq <= ses.last_seq:
            c["out_of_sequence"] += 1
            return None
        late = now - (dg.t_ns + ses.offset_ns)
        if late > self.safety.stale_ms * 1e6:
            c["stale"] += 1
            ses.last_seq = dg.seq
            return None
        ses.offset_ns = min(ses.offset_ns, now - dg.t_ns)
        ses.last_seq = dg.seq
        c["commands"] += 1
        flags, volts = dg.fields[0], dg.fields[1:]
        self._command(flags, volts, now)
        return self._sample_reply(dg.seq, now)

    def _hello(self, dg: P.Datagram, now: int) -> bytes | None:
        c = self.counters
        if not P.authentic(self.key, dg):
            c["unauthenticated"] += 1
            return None
        nonce = dg.fields[0]
        if nonce in self._seen_hello:
            c["out_of_sequence"] += 1  # a replayed HELLO
            return None
        if self.state in (P.ARMED, P.RUNNING):
            c["refused"] += 1  # one master at a time; a dead one is cut off by the watchdog
            return None
        self._seen_hello.add(nonce)
        server = P.new_nonce()
        self._next_session = (self._next_session + 1) & 0xFFFFFFFF or 1
        self.session = Session(self._next_session, P.session_key(self.key, nonce, server), now - dg.t_ns)
        c["sessions"] += 1
        log.info("session %08x opened", self.session.id)
        return P.pack(self.key, P.WELCOME, self.session.id, 0, now, nonce, server)

    def _command(self, flags: int, volts: tuple[float, ...], now: int) -> None:
        if flags & P.RESET and self.state == P.FAULT:
            log.info("fault reset (%s)", P.fault_text(self.faults))
            self.state, self.faults = P.IDLE, 0
        if flags & P.STOP:
            if self.state != P.FAULT:
                self.state = P.IDLE
            self.zero_outputs()
            return
        if flags & P.QUERY:
            return
        if flags & P.ARM and self.state == P.IDLE:
            self.state = P.ARMED
            self.last_cmd_ns = now
        if self.state == P.FAULT:
            self.counters["refused"] += 1
            return
        if self.state in (P.ARMED, P.RUNNING):
            self.last_cmd_ns = now
        if flags & P.RUN and self.state in (P.ARMED, P.RUNNING):
            if not all(math.isfinite(v) for v in volts):
                self._fault(P.F_BAD_COMMAND, f"command {volts}")
                return
            self.state = P.RUNNING
            for leg, v in zip(self.legs, volts):
                leg.target = float(v)
            self._sample(now)
            if self.state != P.FAULT:
                self._apply(now)

    def _sample_reply(self, seq: int, now: int) -> bytes:
        ses = self.session
        raws = [max(0, min(65535, leg.raw)) for leg in self.legs]
        age = max((now - leg.raw_ok_ns) // 1000 for leg in self.legs) if all(l.raw_ok_ns for l in self.legs) else 0xFFFFFFFF
        limits = sum(leg.limit << (2 * i) for i, leg in enumerate(self.legs))
        dropped = sum(self.counters[k] for k in ("malformed", "unauthenticated", "old_session", "out_of_sequence",
                                                  "stale"))
        return P.pack(ses.key, P.SAMPLE, ses.id, seq, _now(), self.state, limits, self.faults, *raws, 0,
                      min(int(age), 0xFFFFFFFF), dropped & 0xFFFFFFFF)

    # --- loop ------------------------------------------------------------------------------------
    def stop(self) -> None:
        self._stop = True

    def serve_forever(self, duration_s: float | None = None) -> None:
        """Run until :meth:`stop`, a signal handler, or ``duration_s``; outputs are zeroed on the
        way out whatever happens."""
        try:
            self._loop(duration_s)
        except (SystemExit, KeyboardInterrupt):
            log.info("daemon stopping on a signal; outputs zeroed")
            raise
        except BaseException:
            self.faults |= P.F_EXCEPTION
            log.exception("daemon stopping on an exception; outputs zeroed")
            raise
        finally:
            self.close()

    def _loop(self, duration_s: float | None) -> None:
        start = _now()
        end = start + int(duration_s * 1e9) if duration_s else None
        next_tick = start
        self.tick(start)
        while not self._stop:
            now = _now()
            if end and now >= end:
                break
            if now >= next_tick:
                self.tick(now)
                next_tick += self.tick_ns
                if next_tick < now:  # fell behind: skip the missed ticks, keep the phase
                    next_tick += ((now - next_tick) // self.tick_ns + 1) * self.tick_ns
                continue
            r, _, _ = select.select([self.sock], [], [], (next_tick - now) / 1e9)
            if r:
                for _ in range(64):
                    try:
                        data, addr = self.sock.recvfrom(2048)
                    except (BlockingIOError, InterruptedError):
                        break
                    reply = self.handle(data, addr)
                    if reply is not None:
                        try:
                            self.sock.sendto(reply, addr)
                        except OSError as exc:
                            log.warning("reply to %s failed: %s", addr, exc)

    def close(self) -> None:
        try:
            self.zero_outputs()
            for leg in self.legs:
                try:
                    write_value(leg.files.enable, 0)
                except PinError:
                    pass
        finally:
            self.sock.close()
            for fd in self._adc_fd:
                os.close(fd)
            self._adc_fd = []
            log.info("daemon stopped; counters %s", self.counters)


def install_signal_handlers(daemon: Daemon) -> None:
    """SIGTERM, SIGINT and SIGHUP stop the daemon (outputs zeroed by :meth:`Daemon.serve_forever`)."""
    def handler(signum, frame):
        daemon.stop()
        raise SystemExit(128 + signum)
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, handler)
