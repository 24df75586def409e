"""The breadcrumb: which component and FMI call the stepping process is in, kept where a
supervising process can read it after a crash or while a call hangs (:mod:`cosim.run.supervise`).

The crumb is a small record in shared memory (an anonymous ``MAP_SHARED`` mapping inherited
through ``fork``, or a file mapped by both sides): ``seq`` (odd while an FMI call runs, even
between calls), ``who`` (a key of the component: a small number from Python, the FMU instance
pointer from the compiled loops), ``call`` (an index into :data:`CALLS`) and ``t`` (the
communication point of a doStep [s]); a JSON table after it names the keys.  Writing it costs a
few stores per FMI call (about 1 ns from C, 0.3 us from Python); without a supervisor it goes to
a private record nobody reads.
"""
from __future__ import annotations

import ctypes
import json
import math
import mmap
import os
from ctypes import c_double, c_int64
from pathlib import Path

#: FMI calls by index (FMI 2.0 names; :func:`call_name` gives the FMI 3.0 one).
CALLS = ("", "loading the binary", "fmi2Instantiate", "fmi2SetReal (start values)", "fmi2SetupExperiment",
         "fmi2EnterInitializationMode", "fmi2ExitInitializationMode", "fmi2DoStep", "fmi2GetReal", "fmi2SetReal",
         "fmi2SetRealInputDerivatives", "fmi2GetFMUstate", "fmi2SetFMUstate", "fmi2Terminate",
         "fmi2FreeInstance", "fmi2Reset", "fmi2GetBooleanStatus", "fmi3EnterEventMode", "fmi3UpdateDiscreteStates",
         "fmi3EnterStepMode")
_FMI3 = {"fmi2Instantiate": "fmi3InstantiateCoSimulation", "fmi2SetReal (start values)": "fmi3Set (start values)",
         "fmi2SetupExperiment": "fmi3EnterInitializationMode", "fmi2GetReal": "fmi3GetFloat64",
         "fmi2SetReal": "fmi3SetFloat64", "fmi2GetFMUstate": "fmi3GetFMUState", "fmi2SetFMUstate": "fmi3SetFMUState"}
CALL = {name: i for i, name in enumerate(CALLS)}
#: The record the compiled loops write (C ``rpr_crumb_t``, generated from this declaration by
#: :func:`cosim.master.entries.header`; its macros ``FMI``/``FMI_T`` are in ``crumb.h`` beside this
#: module): (C type, name, what it is).
RECORD_FIELDS = (
    ("volatile int64_t", "seq", "odd while an FMI call runs, even between calls"),
    ("volatile int64_t", "who", "the component's key (its FMU instance pointer from C)"),
    ("volatile int64_t", "call", "index into CALLS"),
    ("volatile double", "t", "the communication point of a doStep [s]"),
)
#: The C names of the calls the compiled loops make (``C_<name>``, index into :data:`CALLS`).
C_CALLS = {"DO_STEP": "fmi2DoStep", "GET": "fmi2GetReal", "SET": "fmi2SetReal", "SET_DER": "fmi2SetRealInputDerivatives",
           "GET_STATE": "fmi2GetFMUstate", "SET_STATE": "fmi2SetFMUstate", "BOOL_STATUS": "fmi2GetBooleanStatus"}
#: The C side's macros (compiled into every loop).
C_HEADER = Path(__file__).with_name("crumb.h")

SIZE = 1 << 16
_TABLE = 64  # the JSON names table starts here


class Record(ctypes.Structure):
    """The record (:data:`RECORD_FIELDS`), then the length of the names table after it."""

    _fields_ = [*((n, c_double if t.endswith("double") else c_int64) for t, n, _ in RECORD_FIELDS),
                ("table_len", c_int64)]


class _State:
    def __init__(self) -> None:
        self.names: dict[str, list] = {}
        self.next_key = 1
        self.bind(bytearray(SIZE))

    def bind(self, buf) -> None:
        """Write into ``buf``: the record, and int64/float64 views of it (a memoryview item
        assignment costs ~30 ns from Python, a ctypes field ~100 ns)."""
        self.buf = buf
        self.rec = Record.from_buffer(buf)
        self.q = memoryview(buf).cast("B")[:32].cast("q")
        self.d = memoryview(buf).cast("B")[:32].cast("d")


_S = _State()


def shared() -> mmap.mmap:
    """A new shared record for a child to inherit (``fork``): attach it in the child."""
    return mmap.mmap(-1, SIZE)


def new_file() -> str:
    """A new zeroed crumb file (in ``/dev/shm`` when there is one) for a process started by other
    means than ``fork``; both sides map it with :func:`mapped`."""
    import tempfile

    folder = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
    fd, path = tempfile.mkstemp(prefix=f"rpr-crumb-{os.getpid()}-", dir=folder)
    try:
        os.ftruncate(fd, SIZE)
    finally:
        os.close(fd)
    return path


def mapped(path: str) -> mmap.mmap:
    """The crumb file ``path`` mapped shared."""
    fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW)
    try:
        return mmap.mmap(fd, SIZE)
    finally:
        os.close(fd)


def attach(buf: mmap.mmap | None) -> None:
    """Write this process's crumbs into ``buf`` (from :func:`shared`), or a private record."""
    _S.bind(buf if buf is not None else bytearray(SIZE))
    _S.names = {}
    for lib in _LIBRARIES:
        lib.rpr_set_crumb(address())
    _write_table()


_LIBRARIES: list = []  # compiled loops (ctypes.CDLL) whose FMI(...) macros write the crumb


def register_library(lib) -> None:
    """Point a compiled loop's ``rpr_set_crumb`` at the current record (now, and again at every
    :func:`attach`: a supervised child writes into the record its parent reads); its prototype
    is bound by :func:`cosim.master.kernels.compile_loop`."""
    lib.rpr_set_crumb(address())
    if lib not in _LIBRARIES:
        _LIBRARIES.append(lib)


def address() -> int:
    """Address of the current record, for the compiled loops' ``rpr_set_crumb``."""
    return ctypes.addressof(_S.rec)


def key(name: str, fmi3: bool = False, instance: int | None = None) -> int:
    """Register component ``name`` (and its FMU ``instance`` pointer); returns its Python key."""
    k = _S.next_key
    _S.next_key += 1
    _S.names[str(k)] = [name, int(fmi3)]
    if instance:
        _S.names[str(instance)] = [name, int(fmi3)]
    _write_table()
    return k


def name_instance(name: str, fmi3: bool, instance: int) -> None:
    """Name the FMU instance pointer the compiled loops write as the key."""
    if instance:
        _S.names[str(instance)] = [name, int(fmi3)]
        _write_table()


def _write_table() -> None:
    data = json.dumps(_S.names).encode()
    if len(data) > SIZE - _TABLE:  # many components: keep the latest ones
        keep = dict(list(_S.names.items())[-200:])
        data = json.dumps(keep).encode()[:SIZE - _TABLE]
    _S.buf[_TABLE:_TABLE + len(data)] = data
    _S.rec.table_len = len(data)


def enter(k: int, call: int, t: float = math.nan) -> None:
    """An FMI call of component ``k`` starts (``t``: its communication point [s])."""
    q = _S.q
    q[1] = k
    q[2] = call
    _S.d[3] = t
    q[0] += 1


def leave() -> None:
    """The FMI call started by :func:`enter` returned."""
    _S.q[0] += 1


def call_name(call: int, fmi3: bool) -> str:
    name = CALLS[call] if 0 <= call < len(CALLS) else f"call {call}"
    return _FMI3.get(name, name.replace("fmi2", "fmi3")) if fmi3 else name


def read(buf: mmap.mmap) -> dict:
    """What the crumb in ``buf`` says: ``seq``, ``inside`` (an FMI call is running), ``component``,
    ``call`` (its FMI name), ``t`` [s] (nan when not a doStep)."""
    r = Record.from_buffer_copy(buf[:ctypes.sizeof(Record)])
    try:
        table = json.loads(bytes(buf[_TABLE:_TABLE + max(0, min(r.table_len, SIZE - _TABLE))]) or b"{}")
    except ValueError:
        table = {}
    name, fmi3 = table.get(str(r.who), ["", 0])
    return {"seq": r.seq, "inside": bool(r.seq & 1), "component": name,
            "call": call_name(r.call, bool(fmi3)) if r.seq else "", "t": r.t}


def describe(state: dict) -> str:
    """``"pid1.fmi2DoStep at t = 0.25 s"`` (or ``""`` before the first FMI call); the time also for
    the event-mode calls (the event's time)."""
    if not state.get("seq") or not state.get("call"):
        return ""
    where = f"{state['component']}.{state['call']}" if state["component"] else state["call"]
    t = state.get("t")
    timed = state["call"].endswith(("DoStep", "EnterEventMode", "UpdateDiscreteStates", "EnterStepMode"))
    at = f" at t = {t:.6g} s" if t is not None and timed and not math.isnan(t) else ""
    return where + at + ("" if state["inside"] else " (it had returned; the master was between FMI calls)")


__all__ = ["CALL", "CALLS", "C_CALLS", "C_HEADER", "RECORD_FIELDS", "attach", "address", "key", "name_instance", "enter", "leave", "read",
           "describe", "shared"]
