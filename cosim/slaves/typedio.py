"""Variables the compiled loop does not carry: every FMI type but scalar Float64, and arrays.

The master's value vector ``v`` holds scalar Float64 variables only (:mod:`cosim.master`).  A
coupled system with other variables gets a :class:`TypedPorts`: per slave, buffers of the right
type for the typed variables it reads (connected outputs, recorded variables) and the typed
inputs it is given.  Its ``pull``/``push`` run inside the slave's own (wrapped) ``pull``/``push``,
so the algorithms' conventions (Jacobi, Gauss-Seidel, initialisation order) are unchanged; such a
system runs in the Python loop.  Recorded numbers are mirrored into ``v`` (as float64: integers
beyond 2**53 lose their last digits in the trace) so the trace rows stay plain numbers; String and
Binary values are recorded as text events (``record_text``) when they change.  An array ``y`` of
shape (2, 3) is recorded as columns ``y[1,1]`` ... ``y[2,3]`` (row-major, 1-based).
"""
from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np

from .types import TYPES
from .slave import Slave, Status
from .description import Variable


def variable(slave: Slave, name: str) -> Variable | None:
    return slave.description.variables.get(name)


def is_fast(slave: Slave, name: str) -> bool:
    """A scalar Float64 (or a name the description does not know: the caller reports it)."""
    var = variable(slave, name)
    return var is None or var.fast


def element_names(name: str, shape: tuple[int, ...]) -> list[str]:
    """Column names of the elements of array ``name`` (row-major, 1-based); [name] for a scalar."""
    if not shape:
        return [name]
    return [f"{name}[{','.join(str(i + 1) for i in idx)}]" for idx in itertools.product(*(range(d) for d in shape))]


def _status_of(exc: BaseException) -> int:
    st = getattr(exc, "status", None)
    return int(st) if isinstance(st, int) and st > Status.WARNING else int(Status.ERROR)


class TypedPorts:
    """Typed reads, typed inputs, mirrors into ``v`` and text records of a coupled system."""

    def __init__(self, slaves: list[Slave]):
        self.slaves = slaves
        self.reads: list[dict[str, np.ndarray | list]] = [{} for _ in slaves]
        self.inputs: list[list[tuple[str, Callable[[], object]]]] = [[] for _ in slaves]
        self.mirrors: list[list[tuple[str, int]]] = [[] for _ in slaves]  # (var, offset in v)
        self.texts: list[tuple[str, int, str]] = []  # (column, slave, var)
        self._last_text: dict[str, object] = {}
        self.v: np.ndarray | None = None

    @property
    def active(self) -> bool:
        return any(self.reads) or any(self.inputs)

    def read(self, i: int, var: str) -> None:
        """Read typed variable ``var`` of slave ``i`` at every pull."""
        if var not in self.reads[i]:
            v = variable(self.slaves[i], var)
            t = TYPES[v.type]
            self.reads[i][var] = [None] * v.size if not t.numeric else np.zeros(v.size, dtype=t.dtype)

    def mirror(self, i: int, var: str, offset: int) -> None:
        """Copy the (numeric) values of ``var`` into ``v[offset:offset + size]`` after each pull."""
        self.read(i, var)
        self.mirrors[i].append((var, offset))

    def record_text(self, column: str, i: int, var: str) -> None:
        self.read(i, var)
        self.texts.append((column, i, var))

    def add_input(self, i: int, var: str, source: Callable[[], object]) -> None:
        """Set input ``var`` of slave ``i`` from ``source()`` (values converted to its type) at every push."""
        self.inputs[i].append((var, source))

    def source_of(self, j: int, var: str) -> Callable[[], object]:
        self.read(j, var)
        buf = self.reads[j]
        return lambda: buf[var]

    # binding -------------------------------------------------------------------------------------------
    def wrap(self, v: np.ndarray) -> None:
        """Wrap every slave's bound ``push``/``pull`` with its typed part (after ``slave.bind``)."""
        self.v = v
        for i, s in enumerate(self.slaves):
            if self.reads[i] or self.inputs[i]:
                s.push, s.pull = self._push(i, s, s.push), self._pull(i, s, s.pull)

    def _pull(self, i: int, s: Slave, fast_pull: Callable[[], int]) -> Callable[[], int]:
        groups: dict[str, list[str]] = {}
        for var in self.reads[i]:
            groups.setdefault(variable(s, var).type, []).append(var)
        bufs, mirrors, v = self.reads[i], self.mirrors[i], self.v
        raw_plan, slow_plan = [], []
        for t, names in groups.items():
            vrs, sizes = [variable(s, n).vr for n in names], [variable(s, n).size for n in names]
            if TYPES[t].numeric and hasattr(s, "raw_io"):
                call, raw = s.raw_io("get", t, vrs, sum(sizes))
                copies, k = [], 0
                for n, size in zip(names, sizes):
                    if raw.dtype == bufs[n].dtype:
                        bufs[n] = raw[k:k + size]  # a view: filled by the call itself
                    else:
                        copies.append((bufs[n], raw[k:k + size]))
                    k += size
                raw_plan.append((call, copies))
            else:
                slow_plan.append((t, names, vrs, sizes))
        mirror_plan = [(v[off:off + len(bufs[var])], bufs[var]) for var, off in mirrors]

        def pull() -> int:
            st = fast_pull()
            if st > Status.WARNING:
                return st
            for call, copies in raw_plan:
                st = call()
                if st > Status.WARNING:
                    return st
                for dst, src in copies:
                    dst[:] = src
            try:
                for t, names, vrs, sizes in slow_plan:
                    vals = s.get_values(t, vrs, sum(sizes))
                    k = 0
                    for n, size in zip(names, sizes):
                        bufs[n][:] = vals[k:k + size]
                        k += size
            except Exception as exc:  # fmpy raises on a failing status; the log has the reason
                return _status_of(exc)
            for dst, src in mirror_plan:
                dst[:] = src
            return Status.OK
        return pull

    def _push(self, i: int, s: Slave, fast_push: Callable[[], int]) -> Callable[[], int]:
        raw_items, slow_items = [], []
        for var, source in self.inputs[i]:
            desc = variable(s, var)
            t = TYPES[desc.type]
            if t.numeric and hasattr(s, "raw_io"):
                call, buf = s.raw_io("set", desc.type, [desc.vr], desc.size)
                raw_items.append((call, buf, source))
            else:
                slow_items.append((desc, source))

        def push() -> int:
            for call, buf, source in raw_items:
                buf[:] = source()
                st = call()
                if st > Status.WARNING:
                    return st
            try:
                for desc, source in slow_items:
                    s._accessor("set", desc.type)([desc.vr], list(source()))
            except Exception as exc:  # fmpy raises on a failing status
                return _status_of(exc)
            return fast_push()
        return push

    def text_changes(self) -> list[tuple[str, str]]:
        """(column, value) of the recorded String/Binary variables whose value changed since the
        last call (every one at the first call); Binary as hexadecimal text."""
        out = []
        for col, i, var in self.texts:
            vals = self.reads[i][var]
            val = " ".join(x.hex() if isinstance(x, (bytes, bytearray)) else str(x) for x in vals)
            if self._last_text.get(col) != val:
                self._last_text[col] = val
                out.append((col, val))
        return out
