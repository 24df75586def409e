"""The native engine's common part: compiling a kernel (:func:`compile_loop`) and the slave
struct array every compiled loop steps (:class:`SlaveArray`).

A kernel is a C file beside its module (``fastloop.c``, ``adaptive_engine.c``,
``iterative_engine.c``) on the common ``native.h`` (the calls every loop makes on a slave: set its
inputs and their slopes, step it, read its outputs) and the breadcrumb's ``crumb.h``
(:mod:`cosim.slaves.crumb`); the types and prototypes they share with Python are generated into
``rpr_decls.h`` from their one declaration, :mod:`cosim.master.entries`.  Compiling goes through
:func:`fmus.c_loader.load` (one compiler choice, cached on disk).
"""
from __future__ import annotations

import ctypes
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from fmus.errors import BuildError
from fmus.fmi_functions import prototype
from fmus.c_loader import NoCompiler, load

from ..errors import UserError
from ..slaves import crumb
from ..slaves.slave import NativeEntry
from .callbacks import CallbackSlave
from .entries import SET_CRUMB, SLAVE, Entry, bind, header, struct

#: The slave struct's fields (C type, name, what it is), declared in :data:`cosim.master.entries.SLAVE`.
SLAVE_FIELDS = SLAVE.fields
#: Its ctypes mirror.
CSlave = struct(SLAVE)

_HERE = Path(__file__).parent


def kernel_files(main: str) -> dict[str, str]:
    """The files of the kernel ``main`` (a C file beside this module): it, ``native.h``,
    ``crumb.h`` and the generated ``rpr_decls.h``."""
    return {"rpr_decls.h": header(), "native.h": (_HERE / "native.h").read_text(),
            "crumb.h": crumb.C_HEADER.read_text(), main: (_HERE / main).read_text()}


def compile_loop(main: str, stem: str, entries: Sequence[Entry] = (), flags: tuple[str, ...] | None = None
                 ) -> ctypes.CDLL:
    """The kernel ``main`` (:func:`kernel_files`) compiled (once; cached on disk by
    :func:`fmus.c_loader.load`) and loaded, ``entries`` bound (:func:`cosim.master.entries.bind`).
    Raises :class:`UserError` when no C compiler works or the source does not compile."""
    try:
        lib = load(kernel_files(main), stem, *(() if flags is None else (flags,)))
    except NoCompiler as exc:
        raise UserError(f"a run needs a C compiler for its master loop, and none works here ({exc}): install gcc "
                        f"or point $CC to a working C compiler") from None
    except BuildError as exc:
        raise UserError(f"compiling the master loop failed: {exc}") from None
    bind(lib, (SET_CRUMB, *entries))
    crumb.register_library(lib)  # its FMI calls write this process's breadcrumb (cosim.slaves.crumb)
    return lib


def called_back(system, i: int, states: bool = False) -> bool:
    """Whether slave ``i`` of ``system`` is stepped through callbacks (:mod:`cosim.master.callbacks`):
    it has no C entry points, or typed ports its push/pull convert, or (``states``: the loop saves
    and restores FMU states) it rolls back only in Python (a model-exchange slave through its
    continuous states), so that its trampolines call its own ``save_state``/``restore_state``."""
    s = system.slaves[i]
    if system.typed.reads[i] or system.typed.inputs[i]:
        return True
    ne = s.native()
    return ne is None or (states and s.can_rollback and not (ne.get_state and ne.set_state))


class SlaveArray:
    """The :class:`CSlave` array of a system's slaves with their entry points and layout filled in
    (:meth:`cosim.slaves.slave.Slave.native`, the system's value-vector offsets and value
    references); the numpy arrays the structs point into are kept alive here (:meth:`keep`)."""

    def __init__(self, system, *, states: bool = False, callbacks: bool = False):
        """``callbacks``: a slave without C entry points, or with typed ports, is called through
        :class:`cosim.master.callbacks.CallbackSlave` (else such a slave raises :class:`UserError`)."""
        n = len(system.slaves)
        self.arr = (CSlave * n)()
        self.entries: list[NativeEntry] = []
        #: per slave, its trampolines when it is a callback slave (else None)
        self.callbacks: list[CallbackSlave | None] = [None] * n
        self._keep: list = []
        self.states = (ctypes.c_void_p * n)()  # the FMU states (states=True), freed by free_states()
        for i, s in enumerate(system.slaves):
            ne = None if called_back(system, i, states and callbacks) else s.native()
            if ne is None:
                if not callbacks:
                    raise UserError(f"{s.name} has no C entry points, and this loop calls none back")
                cb = self.callbacks[i] = CallbackSlave(s)
                state = (cb.address("get_state"), cb.address("set_state")) if s.can_rollback else (0, 0)
                ne = NativeEntry(False, 0, cb.address("do_step"), cb.address("get"), cb.address("set"),
                                 cb.address("set_der"), *state, get_boolean_status=cb.address("bool_status"))
                self.arr[i].callback = 1
            self.entries.append(ne)
            c = self.arr[i]
            c.fmi3, c.n_in, c.n_out = int(ne.fmi3), len(system.in_vrs[i]), len(system.out_vrs[i])
            c.in_off, c.out_off = system.in_off[i], system.out_off[i]
            # the slave's own promise (cosim.slaves.fmu_slave: true unless the algorithm may restore a state)
            c.no_prior, c.rate, c.sub_ns = int(s.no_prior), 1, 0
            c.inst, c.do_step, c.get, c.set = ne.instance, ne.do_step, ne.get_real, ne.set_real
            c.bool_status, c.last_time = ne.get_boolean_status, ne.last_time
            c.memoryless = int(s.description.memoryless)
            if system.in_affine[i] is not None:  # its inputs through their connections' transformations
                c.in_factor, c.in_offset = self.buffer(system.in_affine[i][0]), self.buffer(system.in_affine[i][1])
            if states:
                c.get_state, c.set_state = ne.get_state, ne.set_state
                c.state = self.state_slot(i)
            self.keep(system.in_vrs[i], system.in_src[i], system.out_vrs[i])
            c.in_vr = system.in_vrs[i].ctypes.data if c.n_in else None
            c.in_src = system.in_src[i].ctypes.data if c.n_in else None
            c.out_vr = system.out_vrs[i].ctypes.data if c.n_out else None

    def state_slot(self, i: int) -> int:
        """The address of slave ``i``'s FMU-state pointer in this array (see :meth:`free_states`)."""
        return ctypes.addressof(self.states) + i * ctypes.sizeof(ctypes.c_void_p)

    def reraise(self) -> None:
        """Raise the exception a callback slave's trampoline caught during the last call, if any."""
        for cb in self.callbacks:
            if cb is not None:
                cb.reraise()

    def keep(self, *arrays: np.ndarray) -> None:
        """Keep ``arrays`` alive as long as the structs that point into them."""
        self._keep += arrays

    def buffer(self, values, dtype=np.float64) -> int:
        """The address of a kept contiguous copy of ``values`` (or of ``values`` itself when it is
        already a contiguous array of ``dtype``: the struct then writes into it)."""
        a = values if isinstance(values, np.ndarray) and values.dtype == dtype and values.flags.c_contiguous \
            else np.ascontiguousarray(values, dtype=dtype)
        self.keep(a)
        return a.ctypes.data if a.size else 0

    def __len__(self) -> int:
        return len(self.arr)

    def __getitem__(self, i: int):
        return self.arr[i]

    def free_states(self) -> None:
        """Free the FMU states (before the instances are freed)."""
        for i, ne in enumerate(self.entries):
            if self.states[i] and ne.free_state:
                proto = prototype("fmi3FreeFMUState" if ne.fmi3 else "fmi2FreeFMUstate")
                slot = ctypes.c_void_p.from_address(self.state_slot(i))
                proto(ne.free_state)(ne.instance, ctypes.byref(slot))
                self.states[i] = None


__all__ = ["CSlave", "SLAVE_FIELDS", "SlaveArray", "called_back", "compile_loop", "kernel_files"]
