"""Master algorithms: fixed-step Jacobi and Gauss-Seidel, error-controlled ``adaptive``, the
power-bond ``ecco`` and strongly coupled ``iterative`` behind one base class and a registry.

Package map (the public names are re-exported here: ``from cosim.master import X``):

``graph``       algebraic loops, topological order, the default Gauss-Seidel order
``system``      :class:`CoupledSystem` (the value vector, value references, indices) and :class:`Link`
``algorithm``   :class:`MasterAlgorithm` (what the registry knows of every algorithm), the fixed-step
                :class:`Algorithm` base class, :data:`ALGORITHMS`, :func:`register`, :func:`algorithm`
``algorithms/`` one module per algorithm (``jacobi``, ``gauss_seidel``, ``adaptive``, ``ecco``,
                ``iterative``), listed in :data:`cosim.master.algorithms.MODULES`
``engine``      who runs the steps: the algorithm's compiled loop (a run needs a C compiler), or the
                Python loop of an algorithm registered without a kernel, chosen in one place for every algorithm
                (:func:`choose_engine`); :func:`fixed_stepper`; the one seam a test oracle plugs into
                (:class:`~cosim.master.engine.Engine`; the Python twins live in ``tests/oracles``)
``entries``     the native kernels' records, end codes and entry points, declared once (the generated
                C header and the ctypes bindings)
``native``      compiling a kernel (C files beside their modules on ``native.h``) and the slave structs;
                the kernels: ``fastloop`` (Jacobi, Gauss-Seidel, jacobi_extrapolated),
                ``adaptive_engine`` (adaptive, ecco), ``iterative_engine``; ``callbacks``: C entry
                points around a Python slave's methods; ``dense``: the Newton step's linear algebra
``stepper``     the one driver loop :func:`~cosim.master.stepper.drive` over the :class:`Stepper` contract
                (pacing, stop requests, events, guards, step observers, traces, text events,
                progress), :class:`StepInfo`, :class:`StepResult`
``run``         :func:`simulate`: an algorithm bound to its engine as a stepper, driven by ``drive``;
                :func:`initialize`, :class:`RunStats`
``multirate``   a slave at ``rate`` doSteps per macro step (Jacobi, Gauss-Seidel; both engines)

Structure (after libcosim and scipy.integrate): a :class:`CoupledSystem` lays the slaves'
connected and recorded variables out in one float64 vector and precomputes every value
reference and index; an :class:`Algorithm` owns its status, the event iteration and the
completion after a stop request, and names its compiled kernel (:attr:`Algorithm.native_code`); an
algorithm without a kernel implements :meth:`Algorithm._step_impl`, its own Python loop, which
:meth:`Algorithm.step` runs; algorithms are found by name in
:data:`ALGORITHMS`; every algorithm, fixed or variable step, runs as a *stepper* through the one
driver loop (:mod:`cosim.master.stepper`: what comes before a step, the step, then the observers).
Recording is the observers' business (:mod:`cosim.trace`), never the algorithm's.

Time is counted in whole steps of an integer number of nanoseconds: ``t_k = k * step_ns / 1e9``
exactly (no accumulated drift).  Communication step ``h = step_ns / 1e9``.

Conventions at communication point ``t_k`` (with ``inputs="hold"``, the default, inputs are held
constant over a step):

Jacobi
    1. every connected input takes the value its source output had when last read, i.e. the
       output at ``t_k`` read after the *previous* exchange;  2. every slave steps ``t_k -> t_k+1``;
    3. every slave's outputs are read.  So a slave's input over ``[t_k, t_k+1]`` is its source's
    output at ``t_k`` -- and for an output with direct feedthrough, that output was evaluated at
    ``t_k`` with its own inputs from ``t_k-1``: each feedthrough hop adds one step of delay
    (the "one-step delay" convention).  Except through a *memoryless* slave (a function of a
    system file: a ``sum`` block, OSP's Sum and VectorSum; no state, its outputs functions of its
    inputs now): after step 3 those are
    evaluated in order (inputs from the outputs just read, then their outputs), so they add no
    delay, as libcosim evaluates its functions (:attr:`Algorithm.exchange`).
Gauss-Seidel
    slaves step one after another in a fixed order; each takes its inputs just before its own
    step, so an input whose source has already stepped sees the source's output at ``t_k+1``,
    the others see it at ``t_k``.  The default order is a topological order of the slave graph
    after cutting the fewest connections that close cycles (an exact search for cycles of up to
    seven slaves, a greedy one beyond); ``master.order`` in a scene overrides it.
Linear inputs (``inputs="linear"``)
    a slave that can follow input slopes (FMI 2.0 ``canInterpolateInputs``) also gets, per
    input, a slope for the coming step: an input whose source has already stepped (Gauss-Seidel)
    is *interpolated*, set to the source's value at ``t_k`` with slope ``(y_k+1 - y_k) / h``; the
    others are *extrapolated*, set to ``y_k`` with slope ``(y_k - y_k-1) / h`` (zero in the first
    step).  Holding makes the coupling first order in ``h``; this makes it second order.  Slaves
    that cannot interpolate keep holding.
Multirate (``rates``, a scene's ``components.X.rate``)
    slave ``i`` crosses each macro step in ``rates[i]`` doSteps at the exact sub-instants, its
    inputs held or set on the macro step's line at each sub-instant, its outputs read after the
    last one (:mod:`cosim.master.multirate`).
Initialisation
    in initialisation mode every slave's outputs are read, then feedthrough outputs are
    propagated in a topological order of the port graph (output -> input connections plus
    input -> output feedthrough inside slaves), so the values at ``t_0`` are consistent.  A
    cycle in that graph is an algebraic loop and is refused (:func:`find_algebraic_loop`), except
    by ``iterative``, which solves it at every communication point.

Failure: a Discard, Error or Fatal status from any call stops the run (a fixed-step master
cannot retry); the status and the slave's last log message become the run's reason.
Stop requests (FMI 3.0 ``terminateSimulation``, FMI 2.0 Discard with ``fmi2Terminated``): the
other slaves complete the step from ``t_k``, the outputs are read, the point ``t_k+1`` is recorded
(on the output grid or not) and the run ends with status "stopped", reason "stopped by C at t".

Types: the value vector carries scalar Float64 variables; other FMI types and arrays go through
:class:`cosim.slaves.typedio.TypedPorts` inside each slave's push/pull (same conventions; the
fixed-step compiled loop calls such a slave through :mod:`cosim.master.callbacks`).
"""
from __future__ import annotations

from . import algorithms  # registers every algorithm module (algorithms.MODULES)
from .algorithm import ALGORITHMS, Algorithm, MasterAlgorithm, algorithm, register
from .algorithms.adaptive import Adaptive
from .algorithms.gauss_seidel import GaussSeidel
from .algorithms.iterative import Iterative
from .algorithms.jacobi import Jacobi
from .engine import _Compiled, choose_engine, fixed_stepper
from .graph import find_algebraic_loop, gauss_seidel_order, topological_order
from .lifecycle import RunStats, initialize, interruption_reason, slave_table
from .simulate import simulate
from .stepper import Outcome, StepInfo, StepResult, Stepper, drive
from .system import CoupledSystem, Link

__all__ = ["ALGORITHMS", "Adaptive", "Algorithm", "CoupledSystem", "GaussSeidel", "Iterative", "Jacobi", "Link", "MasterAlgorithm",
           "Outcome", "RunStats", "StepInfo", "StepResult", "Stepper", "drive", "fixed_stepper",
           "_Compiled", "algorithm", "algorithms", "choose_engine", "find_algebraic_loop", "gauss_seidel_order",
           "initialize", "interruption_reason", "register", "simulate", "slave_table", "topological_order"]
