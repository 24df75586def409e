"""The board protocol's C constants (hardware/protocol.py c_header, included by board.h and
hil_fmu.c) against the bytes Python's struct module packs from the same declaration: every
generated offset finds its field's value there, every length is the packed length."""
from __future__ import annotations

import re
import struct

from hardware import protocol as p


def _defines() -> dict[str, int]:
    return {m[1]: int(m[2]) for m in re.finditer(r"#define (\w+) (\d+)\n", p.c_header())}


def test_generated_offsets_find_each_field_in_packed_bytes():
    d = _defines()
    head = p.HEADER.pack(p.MAGIC, p.VERSION, p.SAMPLE, 0xA1B2C3D4, 0x01020304, 0x1122334455667788)
    assert len(head) == d["HDR"] == 20
    assert head[d["HDR_VERSION"]] == p.VERSION and head[d["HDR_TYPE"]] == p.SAMPLE
    assert struct.unpack_from("<I", head, d["HDR_SESSION"])[0] == 0xA1B2C3D4
    assert struct.unpack_from("<I", head, d["HDR_SEQ"])[0] == 0x01020304
    assert struct.unpack_from("<Q", head, d["HDR_TIME_NS"])[0] == 0x1122334455667788
    values = dict(state=2, limits=0x15, faults=0x4321, raw=(111, 222, 333), age_us=7, dropped=8, late_us=9, p50_us=10,
                  p99_us=11, max_us=12, cpu_ns=13, throttled=14)
    flat = [values["state"], values["limits"], values["faults"], *values["raw"], 0,
            *(values[k] for k in ("age_us", "dropped", "late_us", "p50_us", "p99_us", "max_us", "cpu_ns", "throttled"))]
    body = p.BODY[p.SAMPLE].pack(*flat)
    assert len(body) == d["BODY_SAMPLE"] == 44
    assert body[d["SAMPLE_STATE"]] == 2 and body[d["SAMPLE_LIMITS"]] == 0x15
    assert struct.unpack_from("<H", body, d["SAMPLE_FAULTS"])[0] == 0x4321
    assert struct.unpack_from("<3H", body, d["SAMPLE_RAW"]) == (111, 222, 333)
    for k in ("age_us", "dropped", "late_us", "p50_us", "p99_us", "max_us", "cpu_ns", "throttled"):
        assert struct.unpack_from("<I", body, d[f"SAMPLE_{k.upper()}"])[0] == values[k], k
    cmd = p.BODY[p.COMMAND].pack(p.RUN, 1.5, -2.0, 0.25)
    assert len(cmd) == d["BODY_COMMAND"] == 16
    assert cmd[d["COMMAND_FLAGS"]] == p.RUN
    assert struct.unpack_from("<3f", cmd, d["COMMAND_VOLTS"]) == (1.5, -2.0, 0.25)


def test_neither_c_side_writes_the_protocol_again():
    from pathlib import Path

    c = Path(p.__file__).with_name("c")
    for name in ("board.h", "hil_fmu.c"):
        text = (c / name).read_text()
        assert '#include "board_protocol.h"' in text
        assert not re.search(r"#define (HDR|MAC|NONCE|PROTO_VERSION|BODY_\w+) ", text), name
        assert not re.search(r"enum \{ (T_HELLO|F_ARM|S_IDLE|FB_WATCHDOG) =", text), name
