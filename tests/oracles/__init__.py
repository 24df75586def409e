"""Test oracles: the Python twins of the master's compiled kernels (``cosim/master/*.c``), which
are the product's one implementation of each algorithm's steps.  The bit-for-bit tests compare
the kernel with its twin here (``tests/engine_pair.py``), beside the independent checks (analytic
maps, peers, the monolithic reference) that a design error shared by both cannot pass.

:data:`ORACLE` plugs them into the product's one seam, an engine (:class:`cosim.master.engine.Engine`:
the class a run instantiates, a fixed-step runner, a variable-step loop); ``tests/conftest.py``
registers it, so that ``master.engine: oracle`` (a scene, ``run(engine="oracle")``,
``simulate(engine="oracle")``) runs the twins.  An algorithm registered without a kernel (its
Python loop is product code, the extension point) runs that loop under ``oracle``."""
from __future__ import annotations

from cosim.master.engine import Engine, register_engine
from cosim.master.stepper import python_runner

from .fixed import oracle_algorithm
from .variable import Loop, oracle_stepping

#: the engine of the oracles
ORACLE = Engine("oracle", runner=python_runner, loop=Loop, algorithm=oracle_algorithm, stepping=oracle_stepping)


def register() -> None:
    """Make ``oracle`` an engine of this process (``master.engine: oracle``)."""
    register_engine(ORACLE)


__all__ = ["ORACLE", "register"]
