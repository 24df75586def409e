"""A Python master-side client of the board protocol (tests, benchmarks, tools).  The hardware
FMU implements the same exchange in C (``hardware/c/hil_fmu.c``).  :meth:`BoardClient.hello`
gets the board's challenge; the session opens with the first :meth:`BoardClient.command`."""
from __future__ import annotations

import socket
import time

from . import protocol as P


class BoardError(RuntimeError):
    """The board did not answer, or answered with a fault."""


class BoardClient:
    """One session with the daemon at ``address``: :meth:`hello`, then :meth:`command`."""

    def __init__(self, address: tuple[str, int], key: bytes, *, timeout: float = 0.05):
        self.address, self.key, self.timeout = address, key, timeout
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(address)
        self.sock.settimeout(timeout)
        self.session = 0
        self.skey = b""
        self.seq = 0

    def close(self) -> None:
        self.sock.close()

    def _recv(self, want_type: int, key: bytes, seq: int | None) -> P.Datagram:
        deadline = time.monotonic() + self.timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BoardError(f"board at {self.address[0]}:{self.address[1]} silent for {self.timeout * 1e3:.0f} ms")
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(2048)
            except (socket.timeout, TimeoutError):
                continue
            except ConnectionRefusedError:
                raise BoardError(f"board at {self.address[0]}:{self.address[1]}: connection refused") from None
            try:
                dg = P.parse(data)
            except P.ProtocolError:
                continue
            if dg.type == want_type and P.authentic(key, dg) and (seq is None or dg.seq == seq):
                return dg

    def hello(self) -> int:
        """Open a session; returns its id."""
        nonce = P.new_nonce()
        self.sock.send(P.pack(self.key, P.HELLO, 0, 0, time.monotonic_ns(), nonce))
        dg = self._recv(P.WELCOME, self.key, None)
        if dg.fields[0] != nonce:
            raise BoardError("WELCOME for another HELLO")
        self.session, self.skey, self.seq = dg.session, P.session_key(self.key, nonce, dg.fields[1]), 0
        return self.session

    def send_command(self, flags: int, volts=(0.0, 0.0, 0.0)) -> int:
        self.seq += 1
        self.sock.send(P.pack(self.skey, P.COMMAND, self.session, self.seq, time.monotonic_ns(), flags, *volts))
        return self.seq

    def command(self, flags: int, volts=(0.0, 0.0, 0.0)) -> dict:
        """Send one command and wait for its sample: state, faults, limits, raw counts, age [s]."""
        seq = self.send_command(flags, volts)
        dg = self._recv(P.SAMPLE, self.skey, seq)
        return sample_fields(dg.fields)


def sample_fields(fields: tuple) -> dict:
    """A SAMPLE's body as a dict: state, faults, limits, raw counts, age [s], dropped, and the
    board's tick lateness (since the last sample, p50, p99, max) [s], CPU per tick [s], throttled."""
    state, limits, faults, r1, r2, r3, _, age_us, dropped, late, p50, p99, mx, cpu_ns, throttled = fields
    return {"state": state, "faults": faults, "limits": limits, "raw": (r1, r2, r3), "age_s": age_us / 1e6,
            "dropped": dropped, "tick_late_s": late / 1e6, "tick_p50_s": p50 / 1e6, "tick_p99_s": p99 / 1e6,
            "tick_max_s": mx / 1e6, "cpu_per_tick_s": cpu_ns / 1e9, "throttled": throttled}
