"""The hardware FMU (hand-written C): its HMAC against Python's, FMI validation, the board's
absence, silence or fault reported as an FMI error rather than a hang, and a first step that a
slow start cannot make trip the watchdog; against the C daemon (:class:`hardware.daemon.Served`)."""
from __future__ import annotations

import ctypes
import hashlib
import hmac
import os
import socket
import subprocess
import time
import zipfile

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from hardware import convert, daemon, faketree, pins, protocol as P
from hardware.hil_fmu import C_DIR, build_hil_fmu

#: As on the rig, the board runs under SCHED_FIFO when it may (root): on a loaded machine a board
#: at normal priority can be descheduled for longer than the FMU's 50 ms timeout.
RT = 20 if os.geteuid() == 0 else 0
TARGETS = [pytest.param(t, id=t, marks=pytest.mark.skipif(bool(daemon.unavailable(t)),
                                                          reason=daemon.unavailable(t) or "-"))
           for t in ("host", "armhf")]


@pytest.fixture(scope="module")
def c_hmac(tmp_path_factory):
    d = tmp_path_factory.mktemp("hmac")
    lib = d / "libhmac.so"
    subprocess.run(["gcc", "-O2", "-std=c99", "-shared", "-fPIC", str(C_DIR / "hmac_sha256.c"), "-o", str(lib)],
                   check=True)
    so = ctypes.CDLL(str(lib))
    so.hmac_sha256.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_char_p]
    return so


@pytest.mark.parametrize("key_len", [0, 1, 32, 64, 65, 200])
@pytest.mark.parametrize("msg_len", [0, 1, 55, 56, 63, 64, 65, 119, 1000])
def test_c_hmac_sha256_matches_python(c_hmac, key_len, msg_len):
    rng = np.random.default_rng(key_len * 1009 + msg_len)
    key, msg = rng.bytes(key_len), rng.bytes(msg_len)
    out = ctypes.create_string_buffer(32)
    c_hmac.hmac_sha256(key, key_len, msg, msg_len, out)
    assert out.raw == hmac.new(key, msg, hashlib.sha256).digest()


@pytest.fixture(scope="module")
def keyfile(tmp_path_factory):
    return P.write_key(tmp_path_factory.mktemp("key") / "board.key")


@pytest.fixture(scope="module")
def hil_fmu(keyfile):
    """One build (the default start values); each test points it at its board and key through
    the string parameters ``address`` and ``key_file``."""
    return str(build_hil_fmu())


def test_hardware_fmu_validates_and_cannot_roll_back(hil_fmu):
    path = hil_fmu
    assert validate_fmu(path) == []
    md = fmpy.read_model_description(path)
    assert md.coSimulation.canGetAndSetFMUstate is False
    names = {v.name for v in md.modelVariables}
    assert {"leg[1].u", "leg[3].s", "leg[2].raw", "sample_age", "fault", "address", "key_file"} <= names
    with zipfile.ZipFile(path) as z:  # C sources travel with it, no Python inside
        assert {"sources/hil_fmu.c", "sources/hmac_sha256.c"} <= set(z.namelist())


def _free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.mark.parametrize("board", ["absent", "silent", "wrong_key"])
def test_missing_board_is_an_fmi_error_not_a_hang(hil_fmu, keyfile, tmp_path, board):
    listener = None
    if board == "absent":
        port = _free_port()
    elif board == "silent":  # a socket that reads and never answers
        listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        listener.bind(("127.0.0.1", 0))
        port = listener.getsockname()[1]
    else:
        tree = faketree.make_fake_tree(tmp_path / "tree")
        listener = daemon.Served(P.write_key(tmp_path / "other.key"), tree, rt_priority=RT)  # another key
        port = listener.address[1]
    messages = []
    t0 = time.monotonic()
    try:
        with pytest.raises(Exception, match="status 3"):
            fmpy.simulate_fmu(hil_fmu, stop_time=0.01, step_size=1e-3, start_values={"address": f"127.0.0.1:{port}", "key_file": str(keyfile)},
                              logger=lambda *a: messages.append(a[-1].decode() if isinstance(a[-1], bytes) else str(a[-1])))
    finally:
        if isinstance(listener, daemon.Served):
            listener.stop()
        elif listener is not None:
            listener.close()
    assert time.monotonic() - t0 < 2.0
    text = " ".join(messages)
    assert ("refused" in text) if board == "absent" else ("silent" in text and "50 ms" in text)


@pytest.mark.parametrize("target", TARGETS)
def test_board_fault_is_an_fmi_error_with_the_reason(hil_fmu, keyfile, tmp_path, target):
    from fmpy.fmi2 import FMU2Slave, defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE

    tree = faketree.make_fake_tree(tmp_path / "tree")  # nothing moves the ADC: driving looks stuck
    d = daemon.Served(keyfile, tree, target=target, rt_priority=RT)
    md = fmpy.read_model_description(hil_fmu)
    vr = {v.name: v.valueReference for v in md.modelVariables}
    messages = []
    cb = fmi2CallbackFunctions()
    cb.logger = fmi2CallbackLoggerTYPE(lambda env, name, status, cat, msg: messages.append(msg.decode()))
    cb.allocateMemory, cb.freeMemory = defaultCallbacks.allocateMemory, defaultCallbacks.freeMemory
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=fmpy.extract(hil_fmu), modelIdentifier="rpr_hil_board",
                    instanceName="rig")
    fmu.instantiate(callbacks=cb)
    error, steps = None, 0
    try:
        fmu.setString([vr["address"], vr["key_file"]], [f"127.0.0.1:{d.address[1]}", str(keyfile)])
        fmu.setReal([vr["timeout"]], [0.2])
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        fmu.setReal([vr["leg[1].u"]], [12.0])
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5.0:
            try:
                fmu.doStep(steps * 1e-3, 1e-3)
            except Exception as exc:  # fmpy's FMICallException
                error = exc
                break
            steps += 1
            time.sleep(1e-3)
        state, fault = fmu.getReal([vr["state"], vr["fault"]])
    finally:
        fmu.terminate()
        fmu.freeInstance()
        final = d.stop()
    assert error is not None and "status 3" in str(error)
    assert steps > 0 and final["fault_bits"] & P.F_ADC_STUCK and state == P.FAULT and int(fault) & P.F_ADC_STUCK
    assert any("is in fault (position stuck while driven)" in m for m in messages)
    # how to clear it, for the component the FMU is (issue 32, item 8)
    assert any("run again with --set components.rig.params.reset_fault=true" in m for m in messages), messages
    assert [f.duty.read_text() for f in pins.resolve(tree, export=False)] == ["0", "0", "0"]


@pytest.mark.parametrize("target", TARGETS)
def test_fmpy_runs_the_hardware_fmu_against_a_board_with_a_home_relative_key(hil_fmu, tmp_path, monkeypatch, target):
    home = tmp_path / "home"
    key = P.write_key(home / ".config" / "rpr-cosim" / "board.key")
    monkeypatch.setenv("HOME", str(home))  # the FMU expands a leading ~/ with $HOME
    tree = faketree.make_fake_tree(tmp_path / "tree", adc_counts=(1000, 2000, 3000))
    d = daemon.Served(key, tree, target=target, rt_priority=RT)
    try:
        res = fmpy.simulate_fmu(hil_fmu, stop_time=0.02, step_size=1e-3,
                                start_values={"address": f"127.0.0.1:{d.address[1]}",
                                              "key_file": "~/.config/rpr-cosim/board.key"},
                                output=["leg[1].raw", "leg[3].s", "state", "board_tick_p99", "board_tick_max",
                                        "board_cpu_per_tick", "board_dropped"])
    finally:
        final = d.stop()
    cal = convert.Calibration(s_offset=0.1)  # the FMU's default calibration (the virtual rig's)
    assert res["leg[1].raw"][-1] == 1000 and res["leg[3].s"][-1] == pytest.approx(cal.leg_length(3000))
    assert res["state"][-1] == P.RUNNING
    assert final["state"] == P.IDLE and final["fault_bits"] == 0  # fmi2Terminate stopped the board
    # the board's figures came over the protocol: ordered, and within the 20 ms run
    assert 0 <= res["board_tick_p99"][-1] <= res["board_tick_max"][-1] < 0.02
    assert res["board_dropped"][-1] == 0


def test_a_slow_start_never_trips_the_watchdog(keyfile, tmp_path):
    """Arming at the first step: 50 sessions of an FMU from a cold cache (built here first), each
    through fmi2Reset and a new initialisation, with 120-500 ms (more than the 100 ms watchdog)
    between initialisation and the first step, as when the master compiles its loop there: every
    first step succeeds and the board runs, never faults."""
    from fmpy.fmi2 import FMU2Slave

    fmu_path = str(build_hil_fmu(cache_dir=tmp_path / "cold-cache"))
    md = fmpy.read_model_description(fmu_path)
    vr = {v.name: v.valueReference for v in md.modelVariables}
    tree = faketree.make_fake_tree(tmp_path / "tree")
    d = daemon.Served(keyfile, tree, rt_priority=RT)
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=fmpy.extract(fmu_path), modelIdentifier="rpr_hil_board",
                    instanceName="rig")
    fmu.instantiate()
    states = []
    try:
        for rep in range(50):
            if rep:
                fmu.reset()  # back to instantiated: the next session starts from scratch
            fmu.setString([vr["address"], vr["key_file"]], [f"127.0.0.1:{d.address[1]}", str(keyfile)])
            fmu.setReal([vr["timeout"]], [0.2])  # this test is about the watchdog, not a loaded machine's latency
            fmu.setupExperiment(startTime=0.0)
            fmu.enterInitializationMode()
            fmu.exitInitializationMode()
            time.sleep(0.5 if rep % 10 == 0 else 0.12)
            for k in range(3):
                fmu.doStep(k * 1e-3, 1e-3)  # raises on fmi2Error
            states.append(fmu.getReal([vr["state"], vr["fault"]]))
            fmu.terminate()
    finally:
        fmu.freeInstance()
        final = d.stop()
    assert len(states) == 50 and all(s == [P.RUNNING, 0.0] for s in states)
    assert final["fault_bits"] == 0 and final["faults"] == 0 and final["sessions"] == 50


def test_lost_datagrams_cost_a_resend_not_the_run(hil_fmu, keyfile, tmp_path):
    """A link that loses every other datagram to the board (a lossy cable, a full socket queue
    under a flood): the FMU resends under a new sequence number and every step succeeds."""
    import select
    import threading

    tree = faketree.make_fake_tree(tmp_path / "tree")
    d = daemon.Served(keyfile, tree, rt_priority=RT)
    front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    front.bind(("127.0.0.1", 0))
    back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    back.connect(d.address)
    seen = {"in": 0, "dropped": 0}
    stop = threading.Event()

    def proxy():
        peer = None
        while not stop.is_set():
            r, _, _ = select.select([front, back], [], [], 0.05)
            if front in r:
                data, peer = front.recvfrom(2048)
                seen["in"] += 1
                if seen["in"] % 2 == 0:
                    seen["dropped"] += 1
                else:
                    back.send(data)
            if back in r and peer is not None:
                front.sendto(back.recv(2048), peer)
    th = threading.Thread(target=proxy, daemon=True)
    th.start()
    try:
        res = fmpy.simulate_fmu(hil_fmu, stop_time=0.05, step_size=1e-3,
                                start_values={"address": f"127.0.0.1:{front.getsockname()[1]}",
                                              "key_file": str(keyfile)}, output=["state", "round_trip"])
    finally:
        stop.set()
        th.join()
        front.close()
        back.close()
        final = d.stop()
    assert res["state"][-1] == P.RUNNING and len(res) == 51
    assert seen["dropped"] >= 25 and final["fault_bits"] == 0
    assert res["round_trip"].max() >= 0.004  # some steps waited for their resend (5 ms)
