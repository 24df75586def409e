"""Block checks and C code generation: the CasADi functions of :mod:`models.integrators` as C,
plus the model header ``rpr_model.h`` that parameterises the generic core (``fmus/c``).

Everything here happens before the compiler runs, so a malformed block fails with a message
naming the block and the variable, never with a compiler log.
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import fmpy
import numpy as np

from models.block import Block, BlockError
from models.integrators import SAMPLE_TOL, IntegratorError, Stepper

from .errors import BuildError
from .model_description import Interface, can_interpolate_inputs, check_names, interface

_IDENT = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_INTEGRATOR_CODE = {"none": 0, "rk4": 1, "radau": 2, "discrete": 3, "exact": 4}


def with_parameters(block: Block, overrides: Mapping[str, float] | None) -> Block:
    """A copy of ``block`` whose parameter defaults (the FMU's start values) are ``overrides``;
    unknown names, non-numbers, non-finite values and values outside the bounds are refused."""
    if not overrides:
        return block
    index = {p.name: i for i, p in enumerate(block.params)}
    params = list(block.params)
    for name, value in overrides.items():
        if name not in index:
            raise BuildError(f"block {block.name}: unknown parameter {name!r} in the overrides; expected one of "
                             f"{', '.join(index) or '(none)'}")
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise BuildError(f"block {block.name}: parameter {name!r} = {value!r} is not a number") from None
        prm = params[index[name]]
        if not math.isfinite(v):
            raise BuildError(f"block {block.name}: parameter {name!r} = {v} must be finite")
        if not (prm.lower <= v <= prm.upper):
            raise BuildError(f"block {block.name}: parameter {name!r} = {v} is outside [{prm.lower}, {prm.upper}]")
        params[index[name]] = dataclasses.replace(prm, default=v)
    return dataclasses.replace(block, params=params)


def model_identifier(block: Block) -> str:
    """The FMU's model identifier (a C identifier): the block name, plus the fidelity if any."""
    ident = f"{block.name}_{block.fidelity}" if block.fidelity else block.name
    return re.sub(r"[^A-Za-z0-9_]", "_", ident)


def check_block(block: Block) -> Stepper:
    """Every check the exporter needs before generating code; returns the block's stepper.

    Beyond :meth:`Block.check`: the name is a C identifier, variable names are structured FMI
    names with readable units, start values and the equations are finite at the start point
    (states at their start, inputs 0, parameters at their defaults), and the integrator fits
    the states."""
    try:
        block.check()
    except BlockError as exc:
        raise BuildError(str(exc)) from None
    if not _IDENT.match(block.name):
        raise BuildError(f"block {block.name!r}: the name must be a C identifier (letters, digits, '_', "
                         f"starting with a letter)")
    check_names(block)
    if isinstance(block.substeps, bool) or not isinstance(block.substeps, (int, np.integer)):
        raise BuildError(f"block {block.name}: substeps must be a whole number, got {block.substeps!r}")
    try:
        stepper = Stepper(block)
    except BlockError as exc:
        raise BuildError(str(exc)) from None
    plain = stepper.block  # the block between events (modes as trailing parameters) or the block itself
    p0 = plain.param_defaults
    x0 = np.asarray(stepper.start(p0), dtype=float).reshape(-1)
    for i, v in enumerate(x0):
        if not math.isfinite(v):
            raise BuildError(f"block {block.name}: the start value of state {block.states[i].name!r} is {v} "
                             f"at the default parameters; it must be finite")
    u0 = np.zeros(block.u.numel())
    checks = [("output", block.outputs, stepper.out(x0, u0, p0))]
    if block.x.numel():
        checks.append(("ode of state", block.states, plain.functions()["ode"](x0, u0, p0)))
    if block.has_events:
        nz = block.indicators.numel()
        z0 = event_functions(block)["indicators"](0.0, x0, u0, p0) if nz else []
        checks.append(("event indicator", [type("E", (), {"name": nm}) for nm in block.event_names], z0))
    for what, seq, val in checks:
        for i, v in enumerate(np.asarray(val, dtype=float).reshape(-1)):
            if not math.isfinite(v):
                raise BuildError(f"block {block.name}: {what} {seq[i].name!r} is {v} at the start point "
                                 f"(states at their start values, inputs 0, parameters at their defaults)")
    if block.integrator == "discrete":
        ts = float(block.sample_period)
        if not math.isfinite(ts):
            raise BuildError(f"block {block.name}: sample_period {ts} must be finite")
    return stepper


def event_functions(block: Block) -> dict[str, ca.Function]:
    """The event functions of ``block`` in the core's arguments (``pm = [p; m]``, as the kernels of
    its continuous view): ``indicators(t, x, u, pm) -> z``, ``update(k, t, x, u, pm) -> (x, m)``,
    ``mode_start(p) -> m0``, ``ode(x, u, pm) -> xdot`` (the Hermite dense output's slopes) and
    ``zdot(t, x, u, du, pm)``, the indicators' rates along the trajectory (the side an indicator
    leaves zero to after an event)."""
    ef = block.event_functions()
    nx, nu, np_, nm = block.x.numel(), block.u.numel(), block.p.numel(), block.m.numel()
    k, t, x, u, pm = (ca.MX.sym(n, s) for n, s in (("k", 1), ("t", 1), ("x", nx), ("u", nu), ("pm", np_ + nm)))
    p, m = pm[:np_], pm[np_:]
    name = block.name
    ode = block.continuous_view().functions()["ode"]
    # dz/dt along the trajectory: time, states (their ode) and inputs (their slopes du)
    ts, xs, us, dus, pms = (ca.SX.sym(n, s) for n, s in (("t", 1), ("x", nx), ("u", nu), ("du", nu), ("pm", np_ + nm)))
    zs = ef["indicators"](ts, xs, us, pms[:np_], pms[np_:])
    zdot = ca.jtimes(zs, ca.vertcat(ts, xs, us), ca.vertcat(1.0, ode(xs, us, pms), dus))
    return {
        "zdot": ca.Function(f"{name}_event_zdot", [ts, xs, us, dus, pms], [zdot], ["t", "x", "u", "du", "pm"], ["zdot"]),
        "indicators": ca.Function(f"{name}_event_z", [t, x, u, pm], [ef["indicators"](t, x, u, p, m)],
                                  ["t", "x", "u", "pm"], ["z"]),
        "update": ca.Function(f"{name}_event_update", [k, t, x, u, pm], list(ef["update"](k, t, x, u, p, m)),
                              ["k", "t", "x", "u", "pm"], ["x_new", "m_new"]),
        "mode_start": ca.Function(f"{name}_event_m0", [block.p], [block.mode_start], ["p"], ["m0"]),
        "ode": ca.Function(f"{name}_event_ode", [x, u, pm], [ode(x, u, pm)], ["x", "u", "pm"], ["xdot"]),
    }


#: Default event time tolerance of the core: a crossing's bracket is narrowed below
#: ``EVENT_TOL_ABS + EVENT_TOL_REL |t|`` seconds.
EVENT_TOL_ABS, EVENT_TOL_REL = 1e-12, 1e-12
#: Bounds of the core's event handling: rounds of one event iteration, events in one communication step.
EVENT_MAX_ROUNDS, EVENT_MAX_PER_STEP = 100, 1000


def _event_header(block: Block, ev: dict[str, ca.Function]) -> list[str]:
    nz, ns = block.indicators.numel(), len(block.sample_times)
    names = list(block.event_names) + [s.name or f"sample[{j}]" for j, s in enumerate(block.sample_times)]
    return [
        "#define RPR_EVENTS 1\n",
        f"#define RPR_NM {block.m.numel()}\n#define RPR_NZ {nz}\n#define RPR_NS {ns}\n",
        f"#define RPR_SUBSTEPS {int(block.substeps)}\n",
        f"#define RPR_EVENT_TOL_ABS {_c_double(EVENT_TOL_ABS)}\n#define RPR_EVENT_TOL_REL {_c_double(EVENT_TOL_REL)}\n",
        f"#define RPR_EVENT_MAX_ROUNDS {EVENT_MAX_ROUNDS}\n#define RPR_EVENT_MAX_PER_STEP {EVENT_MAX_PER_STEP}\n",
        f"#define RPR_F_IND {ev['indicators'].name()}\n#define RPR_F_UPD {ev['update'].name()}\n",
        f"#define RPR_F_MSTART {ev['mode_start'].name()}\n#define RPR_F_ODE {ev['ode'].name()}\n",
        f"#define RPR_F_ZDOT {ev['zdot'].name()}\n",
        _c_array("int", "rpr_direction", [str(int(d)) for d in block.directions]),
        _c_array("double", "rpr_sample_period", [_c_double(s.period) for s in block.sample_times]),
        _c_array("double", "rpr_sample_offset", [_c_double(s.offset) for s in block.sample_times]),
        _c_array("char *const", "rpr_event_names", [_c_string(nm) for nm in names]),
    ]


@dataclass
class Generated:
    """Generated C sources (file name -> text) and the interface they implement."""

    iface: Interface
    files: dict[str, str]
    function_names: dict[str, str]


def _c_double(x: float) -> str:
    if math.isinf(x):
        return "INFINITY" if x > 0 else "(-INFINITY)"
    return repr(float(x))


def _c_array(ctype: str, name: str, values: list[str]) -> str:
    body = ", ".join(values) if values else "0"
    return f"static const {ctype} {name}[{max(len(values), 1)}] = {{{body}}};\n"


def _c_string(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def generate(block: Block, stepper: Stepper, *, guid: str, ident: str) -> Generated:
    """C sources for ``block``: ``rpr_casadi.c`` (the CasADi functions) and ``rpr_model.h``."""
    memory = stepper.memory_kernel  # a kernel that keeps state between steps (Radau's factors)
    fns = {"step": memory if memory is not None else stepper.kernel, "out": stepper.out, "start": stepper.start,
           "jac": stepper.out_jacobian}
    cg = ca.CodeGenerator("rpr_casadi.c", {"with_header": False, "with_export": False, "casadi_int": "long long int"})
    ev = event_functions(block) if block.has_events else {}
    for f in list(fns.values()) + list(ev.values()):
        cg.add(f)
    code = cg.dump()
    bad = [ln.strip() for ln in code.splitlines() if ln.lstrip().startswith("#error")]
    if bad:
        raise BuildError(f"block {block.name}: its step function uses a CasADi feature that cannot be "
                         f"code-generated ({bad[0]}); use plain expressions or rootfinder 'fast_newton' "
                         f"with linear_solver 'qr' (not newton, kinsol, cvodes or idas)")
    iface = interface(block)
    pv = iface.of_kind("parameter")
    xs = iface.of_kind("state")  # (modes sit between the parameters and the states)
    lo = [_c_double(v.min if v.min is not None else -math.inf) for v in iface.variables]
    hi = [_c_double(v.max if v.max is not None else math.inf) for v in iface.variables]
    names = {k: f.name() for k, f in fns.items()}
    header = [
        "/* Generated by fmus/codegen.py for block " + block.name + ": do not edit. */\n",
        "#ifndef RPR_MODEL_H\n#define RPR_MODEL_H\n#include <math.h>\n",
        f"#define RPR_MODEL_IDENTIFIER {_c_string(ident)}\n",
        f"#define RPR_BLOCK_NAME {_c_string(block.name)}\n",
        f"#define RPR_GUID {_c_string(guid)}\n",
        f"#define RPR_NP {len(pv)}\n#define RPR_NX {len(xs)}\n",
        f"#define RPR_NU {block.u.numel()}\n#define RPR_NY {block.out.numel()}\n",
        f"#define RPR_INTEGRATOR {_INTEGRATOR_CODE[block.integrator]}\n",
        f"#define RPR_SAMPLE_PERIOD {_c_double(float(block.sample_period or 0.0))}\n",
        f"#define RPR_SAMPLE_TOL {_c_double(SAMPLE_TOL)}\n",
        f"#define RPR_CAN_INTERPOLATE {int(can_interpolate_inputs(block))}\n",
        f"#define RPR_STEP_MEMORY {int(memory is not None)}\n",
        f"#define RPR_NF {memory.size1_in(5) if memory is not None else 0}\n",
        f"#define RPR_F_STEP {names['step']}\n#define RPR_F_OUT {names['out']}\n",
        f"#define RPR_F_START {names['start']}\n#define RPR_F_JAC {names['jac']}\n",
        _c_array("double", "rpr_p_default", [_c_double(v.start) for v in pv]),
        _c_array("double", "rpr_u_start", ["0.0"] * block.u.numel()),
        _c_array("unsigned char", "rpr_tunable", ["1" if v.variability == "tunable" else "0" for v in pv]),
        _c_array("unsigned char", "rpr_x_exact", ["1" if v.initial == "exact" else "0" for v in xs]),
        _c_array("double", "rpr_min", lo),
        _c_array("double", "rpr_max", hi),
        _c_array("char *const", "rpr_names", [_c_string(v.name) for v in iface.variables]),
        *(_event_header(block, ev) if ev else ["#define RPR_EVENTS 0\n#define RPR_NM 0\n"]),
        "#endif\n",
    ]
    return Generated(iface, {"rpr_casadi.c": code, "rpr_model.h": "".join(header)}, names)


C_DIR = Path(__file__).with_name("c")
FMI_HEADER_DIR = Path(fmpy.__file__).with_name("c-code")  # the standard's headers, as FMPy ships them
CORE_SOURCES = ("rpr_core.c", "rpr_core.h")
FMI_HEADERS = {"2.0": ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h"),
               "3.0": ("fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")}
WRAPPERS = {"2.0": "fmi2_wrapper.c", "3.0": "fmi3_wrapper.c"}


def static_sources(fmi_version: str) -> dict[str, str]:
    """The hand-written C files (core, wrapper) and the FMI headers for ``fmi_version``."""
    ours = {n: (C_DIR / n).read_text() for n in CORE_SOURCES + (WRAPPERS[fmi_version],)}
    return ours | {n: (FMI_HEADER_DIR / n).read_text() for n in FMI_HEADERS[fmi_version]}


__all__ = ["check_block", "generate", "event_functions", "with_parameters", "model_identifier", "static_sources",
           "Generated", "IntegratorError"]
