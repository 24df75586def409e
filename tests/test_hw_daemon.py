"""The I/O daemon's safety rules and protocol on fake sysfs trees (issues 11 and 21 acceptance),
against the C daemon built for this machine and for the BeagleBone (armhf, under qemu-user),
with DIR through sysfs and through the GPIO character device.

The tests drive the daemon's ``--step`` harness (:class:`hardware.daemon.Stepped`)
deterministically: datagrams go through ``handle(data, addr, now)`` and ticks through
``tick(now)`` with synthetic monotonic times, so the rules are checked without depending on the
machine's load.  Signals and the real loop are in tests/test_hw_signals.py."""
from __future__ import annotations

import math
import os

import pytest

from hardware import convert, daemon, faketree, protocol as P

MS = 1_000_000
ADDR = ("127.0.0.1", 9)


def leg_params(targets=("host", "armhf"), gpios=("sysfs", "chardev"), *, single=False):
    """(target, gpio) legs (one value each with ``single``, for a fixture); a target this
    machine cannot build or run is skipped with the reason."""
    out = []
    for t in targets:
        why = daemon.unavailable(t)
        for g in gpios:
            values = ((t, g),) if single else (t, g)
            out.append(pytest.param(*values, id=f"{t}-{g}", marks=pytest.mark.skipif(bool(why), reason=why or "-")))
    return out


def make_daemon(tree, key, target, gpio):
    """The stepped daemon on ``tree``: a character-device tree gets the fake kernel preloaded (so
    the binary is dynamically linked for armhf too; the static one serves sysfs trees)."""
    pre = faketree.fake_gpiochip_library(target) if gpio == "chardev" else None
    return daemon.Stepped(key, root=tree, target=target, static=False if pre and target != "host" else None,
                          preload=pre)


class Master:
    """A master speaking the protocol through ``Daemon.handle`` at chosen times."""

    def __init__(self, d: daemon.Stepped, key: bytes):
        self.d, self.key, self.seq = d, key, 0

    def hello(self, now: int) -> None:
        nonce = P.new_nonce()
        reply = self.d.handle(P.pack(self.key, P.HELLO, 0, 0, now, nonce), ADDR, now)
        dg = P.parse(reply)
        assert P.authentic(self.key, dg) and dg.fields[0] == nonce
        self.session, self.skey = dg.session, P.session_key(self.key, nonce, dg.fields[1])

    def datagram(self, flags: int, volts=(0.0, 0.0, 0.0), now: int = 0, seq: int | None = None) -> bytes:
        if seq is None:
            self.seq += 1
            seq = self.seq
        return P.pack(self.skey, P.COMMAND, self.session, seq, now, flags, *volts)

    def send(self, flags: int, volts=(0.0, 0.0, 0.0), now: int = 0) -> dict | None:
        reply = self.d.handle(self.datagram(flags, volts, now), ADDR, now)
        if reply is None:
            return None
        dg = P.parse(reply)
        assert P.authentic(self.skey, dg) and dg.seq == self.seq
        state, limits, faults, *_ = dg.fields
        return {"state": state, "faults": faults, "limits": limits}


@pytest.fixture(params=leg_params(single=True))
def board(request, tmp_path):
    target, gpio = request.param
    tree = faketree.make_fake_tree(tmp_path / "tree", gpio=gpio)
    key = os.urandom(32)
    d = make_daemon(tree, key, target, gpio)
    yield d, Master(d, key), tree
    d.close()


def outputs(d: daemon.Stepped) -> list[tuple[int, int]]:
    return [(int(f.duty.read_text()), int(f.dir_value.read_text())) for f in d.files]


def set_adc(d: daemon.Stepped, leg: int, counts: int | str) -> None:
    d.files[leg - 1].adc.write_text(f"{counts}\n")


def running(board, volts, t0=1000 * MS):
    d, m, _ = board
    m.hello(t0)
    m.send(P.ARM, now=t0)
    for k in range(12):  # slew: 6 V takes 2.5 ms at 2400 V/s
        now = t0 + k * MS
        m.send(P.RUN, volts, now)
        d.tick(now)
    return t0 + 11 * MS


def test_commands_become_duty_and_dir(board):
    d = board[0]
    running(board, (6.0, -3.0, 0.0))
    assert d.state == P.RUNNING
    assert outputs(d) == [(25_000, 0), (12_500, 1), (0, 0)]


def test_slew_limit(board):
    d, m, _ = board
    t0 = 1000 * MS
    m.hello(t0)
    m.send(P.ARM, now=t0)
    d.tick(t0)
    m.send(P.RUN, (12.0, 12.0, 12.0), t0 + 1 * MS)  # 1 ms after the last update: at most 2.4 V
    assert outputs(d)[0][0] == convert.volts_to_drive(2.4).duty_ns


def test_watchdog_zeroes_and_latches(board):
    d, m, _ = board
    last = running(board, (6.0, 6.0, 6.0))
    d.tick(last + 99 * MS)
    assert d.state == P.RUNNING and outputs(d)[0] == (25_000, 0)
    d.tick(last + 101 * MS)
    assert d.state == P.FAULT and d.faults & P.F_WATCHDOG
    assert outputs(d) == [(0, 0)] * 3
    r = m.send(P.RUN, (6.0, 6.0, 6.0), last + 102 * MS)  # latched: commands refused
    d.tick(last + 103 * MS)
    assert r["state"] == P.FAULT and outputs(d) == [(0, 0)] * 3
    r = m.send(P.RESET | P.ARM, now=last + 104 * MS)
    assert r["state"] == P.ARMED and r["faults"] == 0


@pytest.mark.parametrize("end, volts, blocked", [("high", 6.0, True), ("high", -6.0, False),
                                                  ("low", -6.0, True), ("low", 6.0, False)])
def test_end_stop_allows_only_motion_away(board, end, volts, blocked):
    d, m, _ = board
    lo, hi = d.safety.travel
    set_adc(d, 1, int(hi - 10) if end == "high" else int(lo + 10))
    last = running(board, (volts, 0.0, 0.0))
    r = m.send(P.RUN, (volts, 0.0, 0.0), last + MS)
    duty, dir_high = outputs(d)[0]
    assert d.state == P.RUNNING  # a limit, not a fault
    if blocked:  # the SAMPLE's limit flags: 2 bits per leg, 1 low end, 2 high end
        assert (duty, dir_high) == (0, 0) and r["limits"] & 3 == (2 if end == "high" else 1)
    else:
        assert duty == 25_000 and dir_high == int(volts < 0) and r["limits"] == 0


def test_stuck_sensor_faults(board):
    d, m, _ = board
    last = running(board, (12.0, 0.0, 0.0))  # the ADC files never change: a stuck sensor
    for k in range(1, 400):
        now = last + k * MS
        m.send(P.RUN, (12.0, 0.0, 0.0), now)
        d.tick(now)
        if d.state == P.FAULT:
            break
    assert d.faults == P.F_ADC_STUCK
    assert (k - 1) * MS >= d.safety.stuck_s * 1e9 - 12 * MS  # not before stuck_s of driving
    assert outputs(d) == [(0, 0)] * 3


def test_unplugged_sensor_faults(board):
    d = board[0]
    last = running(board, (6.0, 6.0, 6.0))
    set_adc(d, 2, 4095)  # pot unplugged: the divider node sits at 1.8 V
    d.tick(last + MS)
    assert d.faults == P.F_ADC_RANGE and outputs(d) == [(0, 0)] * 3


def test_unreadable_adc_is_stale(board):
    d, m, _ = board
    last = running(board, (6.0, 6.0, 6.0))
    set_adc(d, 3, "")  # the driver returns nothing
    for k in range(1, 30):
        m.send(P.RUN, (6.0, 6.0, 6.0), last + k * MS)
        d.tick(last + k * MS)
        if d.state == P.FAULT:
            break
    assert d.faults == P.F_ADC_STALE and k >= 20 and outputs(d) == [(0, 0)] * 3


def test_nan_command_faults(board):
    d, m, _ = board
    last = running(board, (6.0, 6.0, 6.0))
    m.send(P.RUN, (6.0, math.nan, 6.0), last + MS)
    assert d.faults == P.F_BAD_COMMAND and outputs(d) == [(0, 0)] * 3


BAD = ["random", "truncated", "wrong_key", "old_session", "replayed", "out_of_sequence", "stale", "hello_wrong_key"]


@pytest.mark.parametrize("kind", BAD)
def test_bad_datagrams_change_nothing_and_are_counted(board, kind):
    d, m, tree = board
    t0 = 1000 * MS
    m.hello(t0)
    m.send(P.ARM, now=t0)
    old = m.datagram(P.RUN, (6.0, 6.0, 6.0), t0 + MS)  # a valid command of the first session
    m.send(P.STOP, now=t0 + 2 * MS)
    m.hello(t0 + 3 * MS)  # second session
    m.send(P.ARM, now=t0 + 3 * MS)
    m.send(P.RUN, (3.0, 3.0, 3.0), t0 + 4 * MS)
    d.tick(t0 + 5 * MS)
    m.send(P.RUN, (3.0, 3.0, 3.0), t0 + 6 * MS)
    before, counters = faketree.snapshot(tree), dict(d.counters)
    now = t0 + 7 * MS
    if kind == "random":
        data = os.urandom(72)
    elif kind == "truncated":
        data = m.datagram(P.RUN, (12.0, 12.0, 12.0), now)[:-5]
    elif kind == "wrong_key":
        data = P.pack(os.urandom(32), P.COMMAND, m.session, m.seq + 1, now, P.RUN, 12.0, 12.0, 12.0)
    elif kind == "old_session":
        data = old
    elif kind == "replayed":
        data = m.datagram(P.RUN, (12.0, 12.0, 12.0), now, seq=m.seq)
    elif kind == "out_of_sequence":
        data = m.datagram(P.RUN, (12.0, 12.0, 12.0), now, seq=m.seq - 1)
    elif kind == "stale":
        data = m.datagram(P.RUN, (12.0, 12.0, 12.0), now - 200 * MS)
    else:
        data = P.pack(os.urandom(32), P.HELLO, 0, 0, now, P.new_nonce())
    assert d.handle(data, ADDR, now) is None
    assert faketree.snapshot(tree) == before
    expected = {"random": "malformed", "truncated": "malformed", "wrong_key": "unauthenticated",
                "old_session": "old_session", "replayed": "out_of_sequence", "out_of_sequence": "out_of_sequence",
                "stale": "stale", "hello_wrong_key": "unauthenticated"}[kind]
    changed = {k: d.counters[k] - counters[k] for k in counters if d.counters[k] != counters[k]}
    assert changed == {"received": 1, expected: 1}


@pytest.mark.parametrize("target, gpio", leg_params())
def test_daemon_writes_only_its_own_pins(tmp_path, target, gpio):
    tree = faketree.make_fake_tree(tmp_path / "tree", gpio=gpio)
    before = faketree.snapshot(tree)
    key = os.urandom(32)
    d = make_daemon(tree, key, target, gpio)
    m = Master(d, key)
    last = running((d, m, tree), (6.0, -6.0, 12.0))
    assert outputs(d) == [(25_000, 0), (25_000, 1), (50_000, 0)]
    d.tick(last + 200 * MS)  # watchdog fault
    files = d.files
    d.close()
    after = faketree.snapshot(tree)
    assert set(after) == set(before)
    changed = {k for k in after if after[k] != before[k]}
    owned = {str(p.relative_to(tree)) for f in files for p in f.written()}
    if gpio == "chardev":  # the fake kernel records who holds a line (released at close)
        owned |= {str((f.dir / "consumer").relative_to(tree)) for f in files}
    assert changed and changed <= owned
    for f in files:  # and it leaves them safe: duty 0, DIR an output at low, PWM disabled
        assert (f.duty.read_text(), f.dir_value.read_text(), f.enable.read_text()) == ("0", "0", "0")
        assert f.dir_direction.read_text() == "out"
    if gpio == "chardev":
        assert all((f.dir / "consumer").read_text() == "" for f in files)  # lines released


@pytest.mark.parametrize("target", ["host", "armhf"])
def test_the_board_has_both_gpio_interfaces_and_the_daemon_takes_the_character_device(tmp_path, target):
    if daemon.unavailable(target):
        pytest.skip(daemon.unavailable(target))
    tree = faketree.make_fake_tree(tmp_path / "tree", gpio="both")
    key = os.urandom(32)
    d = make_daemon(tree, key, target, "chardev")
    try:
        assert d.status()["gpio"] == "chardev"
        chardev = [tree / "dev/gpiochip2.lines/30", tree / "dev/gpiochip0.lines/28", tree / "dev/gpiochip2.lines/31"]
        assert [(p / "consumer").read_text() for p in chardev] == ["rpr-board"] * 3
        m = Master(d, key)
        running((d, m, tree), (-6.0, -6.0, 6.0))
        assert [(p / "value").read_text() for p in chardev] == ["1", "1", "0"]
        assert [(tree / f"sys/class/gpio/gpio{k}/value").read_text() for k in (30, 60, 31)] == ["0"] * 3
    finally:
        d.close()


@pytest.mark.parametrize("target", ["host", "armhf"])
def test_sysfs_only_board(tmp_path, target):
    if daemon.unavailable(target):
        pytest.skip(daemon.unavailable(target))
    tree = faketree.make_fake_tree(tmp_path / "tree", gpio="sysfs")
    d = make_daemon(tree, os.urandom(32), target, "sysfs")
    try:
        assert d.status()["gpio"] == "sysfs"
        assert [f.dir_direction.read_text() for f in d.files] == ["out"] * 3
    finally:
        d.close()


@pytest.mark.parametrize("target, gpio", leg_params(gpios=("sysfs",)))
def test_replayed_hello_gets_a_challenge_it_cannot_answer(tmp_path, target, gpio):
    """A HELLO and a session recorded from one daemon run, replayed to the next run with the same
    key, open nothing and disturb nobody: the legitimate master's session goes on."""
    tree = faketree.make_fake_tree(tmp_path / "tree", gpio=gpio)
    key = os.urandom(32)
    t0 = 1000 * MS
    first = make_daemon(tree, key, target, gpio)
    nonce = P.new_nonce()
    hello = P.pack(key, P.HELLO, 0, 0, t0, nonce)
    welcome = P.parse(first.handle(hello, ADDR, t0))
    skey = P.session_key(key, nonce, welcome.fields[1])
    recorded = [P.pack(skey, P.COMMAND, welcome.session, s, t0 + s * MS, P.ARM | P.RUN, 6.0, 6.0, 6.0)
                for s in range(1, 6)]
    assert all(first.handle(dg, ADDR, t0 + k * MS) is not None for k, dg in enumerate(recorded, 1))
    first.close()

    d = make_daemon(tree, key, target, gpio)  # the daemon restarted
    try:
        m = Master(d, key)
        m.hello(t0)
        assert m.send(P.ARM, now=t0)["state"] == P.ARMED  # the legitimate master's session
        reply = d.handle(hello, ADDR, t0 + MS)
        assert reply is None and d.counters["refused"] == 1  # armed: no new session at all
        m.send(P.STOP, now=t0 + 2 * MS)
        reply = d.handle(hello, ADDR, t0 + 3 * MS)  # idle: a challenge, fresh, not the recorded one
        challenge = P.parse(reply)
        assert P.authentic(key, challenge) and challenge.fields[1] != welcome.fields[1]
        before = d.counters
        for k, dg in enumerate(recorded, 4):  # the recorded session answers the old challenge: nothing
            assert d.handle(dg, ADDR, t0 + k * MS) is None
        after = d.counters
        assert after["sessions"] == before["sessions"] and after["commands"] == before["commands"]
        assert after["old_session"] - before["old_session"] == len(recorded)
        assert m.send(P.ARM | P.RUN, (3.0, 3.0, 3.0), t0 + 10 * MS)["state"] == P.RUNNING  # undisturbed
        assert d.counters["sessions"] == 1
    finally:
        d.close()


@pytest.mark.parametrize("target, gpio", leg_params(gpios=("sysfs",)))
def test_hello_flood_is_throttled_and_commands_go_on(tmp_path, target, gpio):
    """Each datagram costs at most one MAC, HELLOs at most ``hello_per_tick`` MACs a tick: a
    flood of HELLOs under another key between two ticks is dropped and counted (throttled), and
    the running master's commands are answered in between."""
    tree = faketree.make_fake_tree(tmp_path / "tree", gpio=gpio)
    key = os.urandom(32)
    d = make_daemon(tree, key, target, gpio)
    try:
        m = Master(d, key)
        last = running((d, m, tree), (6.0, 6.0, 6.0))
        before = d.counters
        other = os.urandom(32)
        answered = 0
        for k in range(200):
            d.handle(P.pack(other, P.HELLO, 0, 0, last, P.new_nonce()), ADDR, last + MS)
            if k % 50 == 0:
                answered += m.send(P.RUN, (6.0, 6.0, 6.0), last + MS) is not None
        after = d.counters
        per_tick = d.safety.hello_per_tick
        assert after["unauthenticated"] - before["unauthenticated"] == per_tick
        assert after["throttled"] - before["throttled"] == 200 - per_tick
        assert answered == 4 and d.state == P.RUNNING
        d.tick(last + 2 * MS)  # the budget comes back with the tick
        d.handle(P.pack(other, P.HELLO, 0, 0, last, P.new_nonce()), ADDR, last + 2 * MS)
        assert d.counters["unauthenticated"] - after["unauthenticated"] == 1
    finally:
        d.close()


@pytest.mark.parametrize("sender", [2 ** 63, 2 ** 64 - 1, 2 ** 63 - 1, 2 ** 63 + 1000 * MS])
def test_sender_times_at_the_extremes_are_stale_and_move_no_offset(board, sender):
    """Issue 33: a sender time of 2^63 overflowed ``now - (t + offset)`` (signed 64-bit) and was
    accepted, moving the session's clock offset so that a 10 s old command was accepted next.
    The arithmetic saturates; a time that is negative as a signed value, or far in the future,
    is stale and changes nothing."""
    d, m, tree = board
    t0 = 100_000 * MS
    m.hello(t0)
    m.send(P.ARM, now=t0)
    before, counters = faketree.snapshot(tree), dict(d.counters)
    now = t0 + MS
    assert d.handle(m.datagram(P.RUN, (12.0, 12.0, 12.0), sender), ADDR, now) is None
    assert faketree.snapshot(tree) == before
    changed = {k: d.counters[k] - counters[k] for k in counters if d.counters[k] != counters[k]}
    assert changed == {"received": 1, "stale": 1}
    # the offset did not move: a 10 s old command is still stale, a fresh one still runs
    assert d.handle(m.datagram(P.RUN, (12.0, 12.0, 12.0), now - 10_000 * MS), ADDR, now + MS) is None
    assert d.counters["stale"] == counters["stale"] + 2
    assert m.send(P.RUN, (3.0, 3.0, 3.0), now + 2 * MS)["state"] == P.RUNNING
