"""The compiled inner loop of the fixed-step master (Jacobi and Gauss-Seidel).

A small C function (``fastloop.c`` beside this module, its entry point declared in
:data:`cosim.master.entries.RUN`), compiled on demand (:func:`cosim.master.kernels.compile_loop`:
cached on disk by source and compiler; never committed), steps FMUs through their
``fmi2DoStep``/``fmi2GetReal``/``fmi2SetReal`` (or FMI 3.0 ``Float64``) entry points, which it
receives as function pointers; a slave without them (a Python slave) or with typed ports is
called through trampolines around its own methods (:mod:`cosim.master.callbacks`).  It
implements exactly the algorithms of :mod:`cosim.master` (see there for the conventions) and
jacobi_extrapolated, FMI 3.0 event mode included (a step ended at an event, the call returned
there for the event iteration in Python: ``fx_ctl``, :class:`cosim.master.entries.FixedEnd`):
the one implementation of their steps; the tests compare it, bit for bit, with its Python twin
(the test oracle, ``tests/oracles/fixed.py``).

All values live in one float64 vector ``v`` owned by the master: each slave reads its bound
variables into ``v[out_off : out_off + n_out]`` and takes its connected inputs from
``v[in_src[j]]``, copied into ``v[in_off : in_off + n_in]`` before being set.
"""
from __future__ import annotations

from ctypes import CDLL
from functools import lru_cache

from .entries import RUN
from .kernels import compile_loop

#: Longest wall time of one call of the compiled loop [ns]; it returns to Python (where signals
#: are handled) at least this often.
CALL_BUDGET_NS = 250_000_000

@lru_cache(maxsize=1)
def library() -> CDLL:
    """Compile (once per source and compiler, cached on disk) and load the loop library.
    Raises :class:`UserError` naming the compiler when none works."""
    return compile_loop("fastloop.c", "rpr_loop", [RUN])

