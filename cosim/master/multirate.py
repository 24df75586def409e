"""Multirate stepping: a slave that takes ``rate`` doSteps per macro step of the fixed-step master.

A scene declares it per component (``components.mech.rate: 4``): the slave advances from ``t_k``
to ``t_k+1`` in ``rate`` sub-steps of ``step_ns / rate`` nanoseconds (a whole number, checked),
at the exact sub-instants ``t_k + j * step_ns / rate`` (``j = 0 .. rate - 1``, integer
nanoseconds).  Everything else follows the macro step's conventions (:mod:`cosim.master`):

- its inputs are gathered and pushed once, as for any slave, before its first sub-step;
- ``inputs: hold``: they stay held over all its sub-steps;
- ``inputs: linear`` (a slave that can interpolate inputs): before every later sub-step ``j`` each
  input is set to its value at the sub-instant on the macro step's line, ``u_j = u_0 + s * tau_j``
  (``u_0`` and the slope ``s`` those of the macro step: interpolated when the source has already
  stepped under Gauss-Seidel, extrapolated otherwise; ``tau_j = j * step_ns / rate / 1e9``), and
  the slope is set again (an FMU's slopes hold for one doStep);
- its outputs are read once, after its last sub-step: every other slave (and the trace) sees
  its outputs at the macro instants only.  Two fast slaves do not exchange values between macro
  instants.

:func:`substepper` is the Python loop's version; the compiled loop (:mod:`cosim.master.fastloop`,
``advance``) does the same arithmetic in the same order, so the two stay bit-identical.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ..errors import UserError
from ..slaves.slave import FAILING, Status


def check_rates(rates: Sequence[int] | None, step_ns: int, names: Sequence[str]) -> list[int]:
    """``rates`` (one per slave; None: all 1) checked: whole numbers >= 1 dividing ``step_ns``."""
    if rates is None:
        return [1] * len(names)
    rates = list(rates)
    if len(rates) != len(names):
        raise UserError(f"multirate: {len(rates)} rates for {len(names)} slaves")
    for name, r in zip(names, rates):
        problem = rate_problem(r, step_ns)
        if problem:
            raise UserError(f"{name}: {problem}")
    return [int(r) for r in rates]


def rate_problem(rate: object, step_ns: int) -> str:
    """Why ``rate`` doSteps per macro step of ``step_ns`` nanoseconds is not allowed ('' if it is)."""
    if isinstance(rate, bool) or not isinstance(rate, (int, np.integer)) or rate < 1:
        return (f"rate = {rate!r} must be a whole number >= 1 of doSteps per macro step (the slave steps at "
                f"master.step / rate)")
    if step_ns % int(rate):
        good = [d for d in range(2, min(int(rate) * 4, 1000) + 1) if step_ns % d == 0][:5]
        hint = f"; rates that divide it: {', '.join(map(str, good))}" if good else ""
        return (f"rate = {rate} does not divide master.step = {step_ns / 1e9:g} s into whole nanoseconds "
                f"({step_ns} ns / {rate}){hint}")
    return ""


def substepper(alg, i: int) -> Callable[[float, float], int]:
    """Slave ``i``'s doStep over a macro step as ``alg.rates[i]`` sub-steps (module docstring).

    Called as ``do(t, h)`` with ``t = alg.time_at(alg.k)``; counts the sub-steps after the first
    in ``alg.calls[i]`` (the algorithm counts the first).  Returns the first status that is not
    OK/Warning, else the last one."""
    sysm = alg.system
    slave = sysm.slaves[i]
    rate, do, calls = alg.rates[i], slave.do_step, alg.calls
    sub_ns = alg.step_ns // rate
    hs = sub_ns / 1e9
    start_ns, step_ns = alg.start_ns, alg.step_ns
    stop = Status.STOP_REQUESTED

    if not alg.interpolating[i]:
        def held(t: float, h: float) -> int:
            t0 = start_ns + alg.k * step_ns
            st = do(t0 / 1e9, hs)
            for j in range(1, rate):
                if st in FAILING or st == stop:
                    return st
                calls[i] += 1
                st = do((t0 + j * sub_ns) / 1e9, hs)
            return st
        return held

    buf, slope = sysm.in_buf[i], alg.slopes[i]
    base = np.empty_like(buf)
    push, push_slopes = slave.push, slave.push_slopes

    def ramped(t: float, h: float) -> int:
        t0 = start_ns + alg.k * step_ns
        np.copyto(base, buf)  # the values pushed for the first sub-step
        st = do(t0 / 1e9, hs)
        for j in range(1, rate):
            if st in FAILING or st == stop:
                return st
            np.multiply(slope, (j * sub_ns) / 1e9, out=buf)
            np.add(buf, base, out=buf)
            st = push()
            if st in FAILING:
                return st
            st = push_slopes()
            if st in FAILING:
                return st
            calls[i] += 1
            st = do((t0 + j * sub_ns) / 1e9, hs)
        return st
    return ramped
