"""The board protocol: small authenticated UDP datagrams between a master and the I/O daemon.

Every datagram is ``header | body | mac`` (little-endian):

===========  =========================================================================
header (20)  magic ``b"RP"``, version (u8), type (u8), session id (u32), sequence (u32),
             sender's monotonic time [ns] (u64)
body         per type, below
mac (32)     HMAC-SHA256 over header and body
===========  =========================================================================

Types and bodies:

- ``HELLO`` (master -> board, MAC with the shared key): client nonce (16 bytes).
- ``WELCOME`` (board -> master, shared key): the client nonce echoed, the board's challenge
  (16 fresh random bytes); the header carries the proposed session id.
- ``COMMAND`` (master -> board, session key): flags (u8: ARM, RUN, STOP, RESET, QUERY), three
  voltages [V] (f32).
- ``SAMPLE`` (board -> master, session key; sequence = the command's): state (u8), limit flags
  (u8), faults (u16), three raw ADC counts (u16), age of the ADC reading [us] (u32), datagrams
  dropped so far (u32); the board's real-time figures of the session: the largest tick
  lateness since the previous sample, tick lateness p50, p99 and max [us], CPU time per tick
  [ns] (u32 each), and the datagrams dropped unauthenticated because of the per-tick budget
  (throttled, u32).

The session key is ``HMAC(key, "rpr-session" | client nonce | challenge)`` and the session opens
only when the first COMMAND under it arrives: a recorded HELLO replayed later (even to a
restarted daemon) earns a challenge it cannot answer and changes nothing; every datagram of an
earlier session fails here; sequence numbers must grow strictly within a session (replays and
reordering are dropped before any MAC is computed).
"""
from __future__ import annotations

import hashlib
import hmac
import os
import struct
from dataclasses import dataclass
from pathlib import Path

MAGIC = b"RP"
VERSION = 2
#: The header's fields, (name, struct code): the Python packing and the C offsets (``HDR_<NAME>``).
HEADER_FIELDS = (("magic", "2s"), ("version", "B"), ("type", "B"), ("session", "I"), ("seq", "I"), ("time_ns", "Q"))
HEADER = struct.Struct("<" + "".join(code for _, code in HEADER_FIELDS))
MAC_LEN = 32
NONCE_LEN = 16
KEY_LEN = 32

HELLO, WELCOME, COMMAND, SAMPLE = 1, 2, 3, 4
TYPE_NAMES = {HELLO: "HELLO", WELCOME: "WELCOME", COMMAND: "COMMAND", SAMPLE: "SAMPLE"}

# COMMAND flags
ARM, RUN, STOP, RESET, QUERY = 1, 2, 4, 8, 16

_HELLO = struct.Struct(f"<{NONCE_LEN}s")
_WELCOME = struct.Struct(f"<{NONCE_LEN}s{NONCE_LEN}s")
#: The COMMAND and SAMPLE bodies' fields, (name, struct code), declared once: the Python packing
#: and the C side's offsets (``COMMAND_<NAME>``, ``SAMPLE_<NAME>`` in :func:`c_header`) come from them.
COMMAND_FIELDS = (("flags", "B"), ("pad", "3x"), ("volts", "3f"))
SAMPLE_FIELDS = (("state", "B"), ("limits", "B"), ("faults", "H"), ("raw", "3H"), ("pad", "H"), ("age_us", "I"),
                 ("dropped", "I"), ("late_us", "I"), ("p50_us", "I"), ("p99_us", "I"), ("max_us", "I"),
                 ("cpu_ns", "I"), ("throttled", "I"))


def _body(fields: tuple[tuple[str, str], ...]) -> struct.Struct:
    return struct.Struct("<" + "".join(code for _, code in fields))


def offsets(fields: tuple[tuple[str, str], ...]) -> dict[str, int]:
    """Each field's byte offset in its body."""
    out, at = {}, 0
    for name, code in fields:
        out[name] = at
        at += struct.calcsize("<" + code)
    return out


_COMMAND = _body(COMMAND_FIELDS)
_SAMPLE = _body(SAMPLE_FIELDS)
BODY = {HELLO: _HELLO, WELCOME: _WELCOME, COMMAND: _COMMAND, SAMPLE: _SAMPLE}

# daemon states
IDLE, ARMED, RUNNING, FAULT = 0, 1, 2, 3
STATE_NAMES = {IDLE: "idle", ARMED: "armed", RUNNING: "running", FAULT: "fault"}

# fault bits (latched until RESET)
F_WATCHDOG = 1 << 0      # no valid command for the watchdog period while armed or running
F_BAD_COMMAND = 1 << 1   # a non-finite voltage
F_ADC_STALE = 1 << 2     # ADC channel unreadable for longer than the stale limit
F_ADC_RANGE = 1 << 3     # ADC counts outside the calibrated travel plus a margin (unplugged pot)
F_ADC_STUCK = 1 << 4     # driven but the position did not change (stuck sensor, driver or motor fault)
F_IO = 1 << 5            # writing an output failed
F_EXCEPTION = 1 << 6     # the daemon hit an internal error (it then stops)
FAULT_NAMES = {F_WATCHDOG: "watchdog", F_BAD_COMMAND: "non-finite command", F_ADC_STALE: "ADC stale",
               F_ADC_RANGE: "ADC out of range", F_ADC_STUCK: "position stuck while driven", F_IO: "output write failed",
               F_EXCEPTION: "daemon exception"}


#: COMMAND flags, daemon states and fault bits by name, for the C sides (:func:`c_header`)
FLAG_NAMES = {"ARM": ARM, "RUN": RUN, "STOP": STOP, "RESET": RESET, "QUERY": QUERY}
FAULT_BITS = {"WATCHDOG": F_WATCHDOG, "BAD_COMMAND": F_BAD_COMMAND, "ADC_STALE": F_ADC_STALE,
              "ADC_RANGE": F_ADC_RANGE, "ADC_STUCK": F_ADC_STUCK, "IO": F_IO, "EXCEPTION": F_EXCEPTION}


def c_header() -> str:
    """``board_protocol.h``: this module's declarations as C, for the board daemon (``board.h``)
    and the hardware FMU (``hil_fmu.c``), so neither writes the protocol again: the magic, the
    version, the header, MAC and nonce lengths, each body's length and its fields' offsets
    (``COMMAND_*``, ``SAMPLE_*``), the types (``T_*``), the
    COMMAND flags (``F_*``), the daemon states (``S_*``) and the fault bits (``FB_*``)."""
    defines = {"PROTO_MAGIC0": f"'{chr(MAGIC[0])}'", "PROTO_MAGIC1": f"'{chr(MAGIC[1])}'", "PROTO_VERSION": VERSION,
               "HDR": HEADER.size, "MAC": MAC_LEN, "NONCE": NONCE_LEN,
               **{f"BODY_{TYPE_NAMES[t]}": body.size for t, body in BODY.items()},
               **{f"HDR_{n.upper()}": at for n, at in offsets(HEADER_FIELDS).items()},
               **{f"COMMAND_{n.upper()}": at for n, at in offsets(COMMAND_FIELDS).items() if n != "pad"},
               **{f"SAMPLE_{n.upper()}": at for n, at in offsets(SAMPLE_FIELDS).items() if n != "pad"}}
    enums = [("T_", {n: t for t, n in TYPE_NAMES.items()}), ("F_", FLAG_NAMES),
             ("S_", {n.upper(): v for v, n in STATE_NAMES.items()}), ("FB_", FAULT_BITS)]
    lines = ["/* Generated from hardware/protocol.py: do not edit. */"]
    lines += [f"#define {k} {v}" for k, v in defines.items()]
    lines += ["enum { " + ", ".join(f"{prefix}{n} = {v}" for n, v in names.items()) + " };" for prefix, names in enums]
    return "\n".join(lines) + "\n"


class ProtocolError(ValueError):
    """A datagram that is not well formed (wrong length, magic, version or type)."""


@dataclass(frozen=True)
class Datagram:
    type: int
    session: int
    seq: int
    t_ns: int
    fields: tuple
    signed: bytes  # header + body (what the MAC covers)
    mac: bytes


def fault_text(faults: int) -> str:
    """Names of the set fault bits, e.g. ``"watchdog, ADC stale"`` (``"none"`` for 0)."""
    names = [n for bit, n in FAULT_NAMES.items() if faults & bit]
    return ", ".join(names) or "none"


def mac(key: bytes, data: bytes) -> bytes:
    return hmac.new(key, data, hashlib.sha256).digest()


def session_key(key: bytes, client_nonce: bytes, server_nonce: bytes) -> bytes:
    return mac(key, b"rpr-session" + client_nonce + server_nonce)


def pack(key: bytes, type_: int, session: int, seq: int, t_ns: int, *fields) -> bytes:
    """A signed datagram of ``type_`` with its body ``fields``."""
    data = HEADER.pack(MAGIC, VERSION, type_, session, seq, t_ns) + BODY[type_].pack(*fields)
    return data + mac(key, data)


def parse(data: bytes) -> Datagram:
    """Split a datagram (no authentication yet); :class:`ProtocolError` if malformed."""
    if len(data) < HEADER.size + MAC_LEN:
        raise ProtocolError(f"datagram of {len(data)} bytes is too short")
    magic, version, type_, session, seq, t_ns = HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise ProtocolError("bad magic or version")
    body = BODY.get(type_)
    if body is None:
        raise ProtocolError(f"unknown type {type_}")
    if len(data) != HEADER.size + body.size + MAC_LEN:
        raise ProtocolError(f"{TYPE_NAMES[type_]} of {len(data)} bytes; expected {HEADER.size + body.size + MAC_LEN}")
    signed = data[:-MAC_LEN]
    return Datagram(type_, session, seq, t_ns, body.unpack_from(data, HEADER.size), signed, data[-MAC_LEN:])


def authentic(key: bytes, dg: Datagram) -> bool:
    return hmac.compare_digest(mac(key, dg.signed), dg.mac)


def new_nonce() -> bytes:
    return os.urandom(NONCE_LEN)


# --- keys -------------------------------------------------------------------------------------
def write_key(path: Path | str) -> Path:
    """Create a new random key file (hex, owner-only permissions 0600); never overwrites."""
    path = Path(path).expanduser()
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(os.urandom(KEY_LEN).hex() + "\n")
    os.chmod(path, 0o600)
    return path


def read_key(path: Path | str) -> bytes:
    """The key in ``path`` (64 hex digits); ValueError naming the file otherwise."""
    path = Path(path).expanduser()
    try:
        text = path.read_text().strip()
    except OSError as exc:
        raise ValueError(f"key file {path}: {exc.strerror or exc}") from None
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_LEN:
        raise ValueError(f"key file {path}: expected {2 * KEY_LEN} hex digits (make one with "
                         f"'rpr-cosim board keygen FILE')")
    if os.name == "posix" and path.stat().st_mode & 0o077:
        raise ValueError(f"key file {path} is readable by others (mode {oct(path.stat().st_mode & 0o777)}); "
                         f"chmod 600 it")
    return key


def parse_address(text: str, default_port: int = 5005) -> tuple[str, int]:
    """``"HOST:PORT"`` (or ``"HOST"``) as a (host, port) pair; ValueError if malformed."""
    host, sep, port = str(text).rpartition(":")
    if not sep:
        host, port = str(text), str(default_port)
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"address {text!r}: the port must be a number (HOST:PORT)") from None
    if not host or not (0 <= p < 65536):
        raise ValueError(f"address {text!r}: expected HOST:PORT, e.g. 127.0.0.1:5005")
    return host, p
