"""``rpr-cosim board``: key files and one-line errors for user mistakes."""
from __future__ import annotations

import os
import stat

import pytest

from cosim import cli


def test_keygen_makes_an_owner_only_key_and_never_overwrites(tmp_path, capsys):
    key = tmp_path / "sub" / "board.key"
    assert cli.main(["board", "keygen", str(key)]) == 0
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    assert len(bytes.fromhex(key.read_text().strip())) == 32
    before = key.read_text()
    assert cli.main(["board", "keygen", str(key)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "refusing to overwrite" in err[0]
    assert key.read_text() == before


@pytest.mark.parametrize("problem, message", [("readable", "readable by others"), ("garbage", "64 hex digits"),
                                              ("missing", "No such file"), ("no_tree", "no IIO device"),
                                              ("bad_listen", "HOST:PORT")])
def test_serve_mistakes_are_one_line(tmp_path, capsys, problem, message):
    key = tmp_path / "k.key"
    if problem != "missing":
        key.write_text("zz\n" if problem == "garbage" else os.urandom(32).hex() + "\n")
        os.chmod(key, 0o644 if problem == "readable" else 0o600)
    listen = "127.0.0.1" if problem == "bad_listen" else "127.0.0.1:0"
    listen = "localhost:notaport" if problem == "bad_listen" else listen
    rc = cli.main(["board", "serve", "--key", str(key), "--root", str(tmp_path / "empty"), "--listen", listen,
                   "--duration", "0.1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err


def _elf(path) -> dict:
    """Class, machine and whether a program interpreter is asked for, from the ELF header."""
    import struct

    data = path.read_bytes()
    assert data[:4] == b"\x7fELF"
    bits = 32 if data[4] == 1 else 64
    machine = struct.unpack_from("<H", data, 18)[0]
    if bits == 32:
        phoff, phentsize, phnum = struct.unpack_from("<I", data, 28)[0], *struct.unpack_from("<HH", data, 42)
    else:
        phoff, phentsize, phnum = struct.unpack_from("<Q", data, 32)[0], *struct.unpack_from("<HH", data, 54)
    types = [struct.unpack_from("<I", data, phoff + k * phentsize)[0] for k in range(phnum)]
    return {"bits": bits, "machine": machine, "interp": 3 in types}  # PT_INTERP = 3


@pytest.mark.parametrize("target", ["host", "armhf"])
def test_build_writes_the_daemon_for_the_board(tmp_path, capsys, target):
    from hardware import daemon

    if daemon.unavailable(target):
        pytest.skip(daemon.unavailable(target))
    out = tmp_path / f"rpr-board-{target}"
    assert cli.main(["board", "build", "--target", target, "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out and os.access(out, os.X_OK)
    elf = _elf(out)
    if target == "armhf":  # 32-bit ARM (EM_ARM = 40), statically linked: runs on any Debian of the board
        assert elf == {"bits": 32, "machine": 40, "interp": False}
    else:
        assert elf["bits"] == 64 and elf["interp"]
