"""PID controller with a filtered derivative, an output limiter and optional anti-windup.

Inputs ``setpoint`` and ``measurement`` (unit option ``unit_in``, default ``m``: leg lengths in
the thesis's scene); outputs ``y`` (the limited control, unit option ``unit_out``, default ``V``:
the motor voltage) and ``e = setpoint - measurement``.  The gains' units follow (``Kp`` in
``unit_out/unit_in``).

Forms (construction option ``form``):

- ``"parallel"``: ``y = Kp e + I + D`` with ``dI/dt = Ki e`` and a first-order filtered derivative
  ``Tf dD/dt + D = Kd ds/dt``;
- ``"standard"`` (20-sim's PID): ``y = Kp (e + I' + uD)`` with ``dI'/dt = e / Ti`` and
  ``beta Td duD/dt + uD = Td ds/dt`` (beta = 0.1); the filter time constant is ``beta Td``.

``s`` is the signal the derivative acts on (option ``derivative``): ``"error"`` (default, as in
20-sim and the thesis; a setpoint step gives a kick of ``Kd * step / Tf``, clipped by the limiter)
or ``"measurement"`` (``s = -measurement``: no setpoint kick).  The filter is realised with a
state ``w`` tracking ``s``: ``dw/dt = (s - w) / Tf`` and ``D = Kd (s - w) / Tf``, so the state has
the unit of ``s``; its start value ``w0`` should equal the initial ``s`` to avoid a start kick.
The default ``Tf`` = 1 ms is close to the pure derivative of the thesis's parallel reading (the
closed-loop scene's phi peak is 0.303 rad with 1 ms, 0.307 with 0.1 ms, 0.267 with 10 ms; see
:mod:`models.blocks.motor`) and keeps the filter pole (-1000 1/s) stable for RK4 at a 1 ms step.

States: ``state.I``, the integral part of the output in output units (so a gain change does
not bump the output), and ``state.w``.

Output limit ``y = clip(v, -u_max, u_max)`` of the unlimited ``v``.  Anti-windup (option
``anti_windup``): ``"none"``; ``"clamp"`` (conditional integration: the integral is frozen while
the output is limited and the error drives further into the limit); ``"backcalc"`` (back
calculation: ``dI/dt = Ki e + (y - v) / Tt``; Åström's rule of thumb ``Tt ~ sqrt(Ti Td)`` is
0.5 s for the thesis's gains).

Fidelities: ``continuous`` (RK4) and ``discrete`` at ``sample_period`` ``T``: at each sample
``I += T (dI/dt)`` (forward Euler) and ``w += (1 - exp(-T/Tf)) (s - w)`` (the filter's exact
zero-order-hold update); the output is computed from the inputs at the sample.  Both tend to the
continuous controller as ``T -> 0``.
"""
from __future__ import annotations

import casadi as ca

from ..block import Block, Sample, Var
from ..units import compose
from ._common import ParamSet, solver_params

FORMS = ("parallel", "standard")
DERIVATIVE = ("error", "measurement")
ANTI_WINDUP = ("none", "clamp", "backcalc")


def _law(form: str, derivative: str, anti_windup: str, unit_in: str = "m", unit_out: str = "V"):
    """Parameters, symbols and the continuous right-hand side ``(dI/dt, dw/dt, Tf)`` plus outputs.
    ``unit_in`` is the unit of setpoint and measurement, ``unit_out`` that of the output (the
    gains' units follow from them)."""
    ps = ParamSet()
    per = compose((unit_out, 1), (unit_in, -1))  # one '/' however the units are written (N/(m/s) -> N.s/m)
    if form == "parallel":
        Kp = ps.add("Kp", 30.0, per, "proportional gain (Table 6.7)")
        Ki = ps.add("Ki", 80.0, compose((unit_out, 1), (unit_in, -1), ("s", -1)),
                    "integral gain (Table 6.7 read as parallel gains)")
        Kd = ps.add("Kd", 20.0, compose((unit_out, 1), ("s", 1), (unit_in, -1)),
                    "derivative gain (Table 6.7 read as parallel gains)")
        Tf = ps.add("Tf", 1e-3, "s", "derivative filter time constant", lower=1e-9)
        ki, kd = Ki, Kd
    else:
        Kp = ps.add("Kp", 30.0, per, "proportional gain (Table 6.7)")
        Ti = ps.add("Ti", 80.0, "s", "integral time (Table 6.7)", lower=1e-12)
        Td = ps.add("Td", 20.0, "s", "derivative time (Table 6.7)", lower=1e-12)
        beta = ps.add("beta", 0.1, "1", "derivative filter: time constant beta Td (20-sim)", lower=1e-9)
        ki, kd, Tf = Kp / Ti, Kp * Td, beta * Td
    u_max = ps.add("u_max", 12.0, unit_out, "output limit: y in [-u_max, u_max] (Table 6.7: 12 V)", lower=0.0)
    Tt = ps.add("Tt", 0.5, "s", "anti-windup tracking time constant (backcalc only)", lower=1e-9) \
        if anti_windup == "backcalc" else None
    I0 = ps.add("I0", 0.0, unit_out, "start value of the integral part")
    w0 = ps.add("w0", 0.0, unit_in, "start value of the derivative filter state (the initial derivative "
                                    "signal avoids a start kick)")
    u = ca.SX.sym("uin", 2)
    sp, meas = u[0], u[1]
    xs = ca.SX.sym("xs", 2)
    I, w = xs[0], xs[1]
    e = sp - meas
    s = e if derivative == "error" else -meas
    D = kd * (s - w) / Tf
    v = Kp * e + I + D
    y = ca.fmin(ca.fmax(v, -u_max), u_max)
    dI = ki * e
    if anti_windup == "clamp":
        pushing = ca.logic_or(ca.logic_and(v > u_max, dI > 0), ca.logic_and(v < -u_max, dI < 0))
        dI = ca.if_else(pushing, 0.0, dI)
    elif anti_windup == "backcalc":
        dI = dI + (y - v) / Tt
    dw = (s - w) / Tf
    return ps, u, xs, (dI, dw, Tf, s), ca.vertcat(y, e), ca.vertcat(I0, w0)


def _variables(unit_in: str, unit_out: str) -> tuple[list[Var], list[Var], list[Var]]:
    """Inputs, outputs and states with their units."""
    return ([Var("setpoint", unit_in, "reference value"), Var("measurement", unit_in, "measured value")],
            [Var("y", unit_out, "limited control output"), Var("e", unit_in, "error setpoint - measurement")],
            [Var("state.I", unit_out, "integral part of the output"),
             Var("state.w", unit_in, "derivative filter state")])


def continuous(form: str = "parallel", derivative: str = "error", anti_windup: str = "none",
               integrator: str = "auto", substeps: int = 1, unit_in: str = "m", unit_out: str = "V") -> Block:
    """Continuous PID.  ``integrator="auto"``: ``exact`` (the step's exact solution,
    :func:`models.integrators.exact_kernel`) when the law is linear (no anti-windup: the
    limiter acts on the output only), else ``radau``; both are stable at any step, whereas RK4
    diverges once the step exceeds 2.8 ``Tf`` (the filter pole ``-1/Tf``)."""
    ps, u, xs, (dI, dw, _, _), out, start = _law(form, derivative, anti_windup, unit_in, unit_out)
    inputs, outputs, states = _variables(unit_in, unit_out)
    if integrator == "auto":
        integrator = "exact" if anti_windup == "none" else "radau"
    solver_params(ps, integrator)
    return Block.build(
        "pid", description=f"PID controller, {form} form, derivative on {derivative}, anti-windup {anti_windup}",
        params=ps.params, inputs=inputs, outputs=outputs, states=states, p=ps.vector(),
        u=u, x=xs, ode=ca.vertcat(dI, dw), out=out, start=start, integrator=integrator, substeps=substeps,
        fidelity="continuous")


TIMING = ("periodic", "events")


def discrete(form: str = "parallel", derivative: str = "error", anti_windup: str = "none",
             sample_period: float = 1e-3, unit_in: str = "m", unit_out: str = "V", timing: str = "periodic") -> Block:
    """Sampled PID: forward-Euler integral, exact zero-order-hold update of the derivative filter.

    ``timing="periodic"``: a discrete block (the communication step must be a whole multiple of
    the sample period); ``"events"``: the samples are time events at ``k T`` (events design page),
    the state ``(I, w)`` is a pair of modes updated there, so any communication step works and a
    sample inside a step is taken at its instant with the input at that instant."""
    T = float(sample_period)
    ps, u, xs, (dI, dw, Tf, s), out, start = _law(form, derivative, anti_windup, unit_in, unit_out)
    inputs, outputs, states = _variables(unit_in, unit_out)
    I, w = xs[0], xs[1]
    update = ca.vertcat(I + T * dI, w + (1 - ca.exp(-T / Tf)) * (s - w))
    if timing == "events":
        return Block.build(
            "pid", description=f"discrete PID (T = {T:g} s, samples as time events), {form} form, derivative on "
                               f"{derivative}, anti-windup {anti_windup}",
            params=ps.params, inputs=inputs, outputs=outputs, states=[], p=ps.vector(), u=u, x=ca.SX(0, 1),
            ode=ca.SX(0, 1), out=out, start=ca.SX(0, 1), integrator="none", modes=states, m=xs, mode_start=start,
            sample_times=[Sample(T, 0.0, update, "sample")], fidelity="discrete")
    return Block.build(
        "pid", description=f"discrete PID (T = {T:g} s), {form} form, derivative on {derivative}, "
                           f"anti-windup {anti_windup}",
        params=ps.params, inputs=inputs, outputs=outputs, states=states, p=ps.vector(),
        u=u, x=xs, ode=update, out=out, start=start, integrator="discrete", sample_period=T, fidelity="discrete")
