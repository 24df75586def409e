"""The master algorithms, one module each.  Importing this package imports every module listed in
:data:`MODULES`, whose ``@register`` classes thereby enter :data:`cosim.master.ALGORITHMS`.

A new algorithm is a module here holding a class decorated with :func:`cosim.master.register`: a
fixed-step :class:`cosim.master.Algorithm` subclass (its kernel's ``native_code``, or without a
kernel its own ``_step_impl``; its Python twin as a test oracle in ``tests/oracles``), or a variable-step
:class:`cosim.master.MasterAlgorithm` subclass naming its stepper (``stepper_for``, see
:mod:`cosim.master.stepper`), plus its name in :data:`MODULES` (a test checks that every module
of this package is listed)."""
from __future__ import annotations

import importlib

#: the algorithm modules, in registry order (the order of defaults such as the study's algorithms)
MODULES = ("jacobi", "gauss_seidel", "adaptive", "ecco", "iterative", "jacobi_extrapolated")

for _name in MODULES:
    importlib.import_module(f"{__name__}.{_name}")
