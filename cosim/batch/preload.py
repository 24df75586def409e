"""Warm-up of local batch workers: what every worker would otherwise do before its first run.

A worker's first run would otherwise import FMPy and the run machinery, read the package
versions written into every trace (``importlib.metadata``), load the compiled master loop
(``gcc --version``, ``dlopen``) and find the Gauss-Seidel stepping order.  :func:`warm` does all of it
once in the process the workers are forked from -- the batch process itself when it forks them,
else the ``forkserver`` (importing this module runs :func:`warm_imports`) -- so that each worker
inherits the result instead of paying it again.
"""
from __future__ import annotations

from collections.abc import Iterable
from .. import interrupts, outputs
from ..analysis import charts
from ..run import execute
from ..trace.traces import package_versions
from ..master import adaptive_engine, fastloop, gauss_seidel_order, iterative_engine
from ..trace import text as tracetext
from ..errors import UserError


def warm_imports() -> None:
    """Import what a run imports lazily, and read the package versions (cached per process)."""
    import fmpy.fmi2  # noqa: F401
    import fmpy.fmi3  # noqa: F401


    package_versions()


def warm(scenes: Iterable = ()) -> None:
    """:func:`warm_imports`, the compiled master loops, and the stepping order of each scene's
    coupling (cached per process by :func:`cosim.master.gauss_seidel_order`)."""

    warm_imports()
    for loop in (fastloop, adaptive_engine, iterative_engine):
        try:
            loop.library()
        except UserError:  # no C compiler: the runs say so (or use the Python loop)
            pass
    tracetext._c_rows()  # the compiled trace-text rewrite (None without a compiler)
    seen = set()
    for scene in scenes:
        if scene.master.order:
            continue
        index = {name: i for i, name in enumerate(scene.components)}
        edges = tuple((index[c.src], index[c.dst]) for c in scene.connections)
        if (len(index), edges) not in seen:
            seen.add((len(index), edges))
            gauss_seidel_order(len(index), edges)


warm_imports()
