"""The model catalog: the thesis's components as :class:`~models.block.Block` objects.

``make(model, fidelity=None, **options)`` builds one block; ``options`` are construction options
(listed by :func:`options`) and overrides of parameter defaults by parameter name.  Every mistake
raises :class:`~models.block.BlockError` with a one-line message naming the model, fidelity and
the bad name, with the closest valid name as a suggestion.

| model | fidelities (first = default) | module |
|---|---|---|
| ``mechanism`` | ``rigid``, ``multibody``, ``kinematic`` | :mod:`.mechanism` |
| ``dc_motor`` | ``full``, ``quasistatic``, ``ideal`` | :mod:`.motor` (option ``friction=stiction``: stick and slip modes) |
| ``pid`` | ``continuous``, ``discrete`` | :mod:`.pid` |
| ``pose_setpoint`` | ``default`` | :mod:`.setpoint` |
| ``oscillator`` | ``linear`` | :mod:`.oscillator` (master-algorithm test scenes) |
| ``linear_actuator`` | ``rig``, ``single``, ``motor`` | :mod:`.actuator` |
| ``sum`` | ``vector`` | :mod:`.sums` (OSP's Sum and VectorSum functions) |
| ``task_trajectory`` | ``planned`` | :mod:`.task` (a planned task: toppra, ruckig or a spline) |
| ``pendulum`` | ``stop`` | :mod:`.pendulum` (located events: impacts on a stop) |
| ``sliding_mass`` | ``stiction``, ``smooth`` | :mod:`.friction` (Coulomb friction: stick and slip modes, or the tanh law) |
| ``sampled`` | ``adc``, ``pwm`` | :mod:`.sampled` (the board's 12-bit ADC and PWM duty, samples as time events) |
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from ..block import Block, BlockError
from ..user import with_defaults
from . import actuator, friction, mechanism, motor, oscillator, pendulum, pid, sampled, setpoint, sums, task
from ._common import CONFIG, SUBSTEPS, Option, integrator_option, positive_float, positive_int, suggest, unit_text

#: Integrators of blocks whose equations are linear: ``exact`` (the default) and the two general ones.
LINEAR_INTEGRATORS = ("exact", "radau", "rk4")


@dataclass(frozen=True)
class _Entry:
    build: Callable[..., Block]
    options: tuple[Option, ...]


def task_options() -> tuple[Option, ...]:
    """Construction options of ``task_trajectory``: the task's keys (:mod:`models.task`); the
    default task is the pid_step move (Table 6.8) as a ruckig motion."""
    from ..trajectory import METHODS

    def is_list(v):
        return None if isinstance(v, (list, tuple)) else "must be a list"

    def is_map(v):
        return None if v is None or isinstance(v, dict) else "must be a mapping"

    def is_time(v):
        return None if isinstance(v, (int, float)) and not isinstance(v, bool) else "must be a time in s"

    return (CONFIG,
            Option("waypoints", [[-0.15, -0.15, 0.0], [-0.2, -0.15, 0.2]], "waypoints [[x, y, phi], ...] in m, m, rad",
                   check=is_list),
            Option("method", "ruckig", "ruckig (jerk-limited), toppra (time-optimal) or spline (given times)",
                   choices=METHODS),
            Option("times", None, "one time [s] per waypoint (method spline)",
                   check=lambda v: None if v is None else is_list(v)),
            Option("limits", None, "limits (models.trajectory.Limits keys: leg_speed, leg_accel, drive, u_max, m_act, "
                                   "pose_speed, pose_accel, pose_jerk)", check=is_map),
            Option("margins", None, "dexterity margins of the motion check (det, dsi, dsi_phi)", check=is_map),
            Option("start", 0.0, "delay [s] before the motion", check=is_time))


def _entries() -> dict[str, dict[str, _Entry]]:
    sample = Option("sample_period", 1e-3, "sample period [s] of the discrete controller", check=positive_float)
    pid_opts = (Option("form", "parallel", "PID form: parallel gains (Kp, Ki, Kd, Tf) or the 20-sim standard "
                                           "form (Kp, Ti, Td, beta)", choices=pid.FORMS),
                Option("derivative", "error", "signal the derivative acts on", choices=pid.DERIVATIVE),
                Option("anti_windup", "none", "integrator anti-windup at the output limit", choices=pid.ANTI_WINDUP),
                Option("unit_in", "m", "unit of setpoint and measurement (leg lengths in the thesis)", check=unit_text),
                Option("unit_out", "V", "unit of the output (motor voltage in the thesis)", check=unit_text))
    rotor = Option("rotor", "lumped", "rotor inertia: 'lumped' (DESIGN option (b), inertia-free motor; lump "
                                      "m_reflected into the mechanism's leg[i].m_act) or 'state' (option (a): rotor "
                                      "state and a stiff spring-damper bond)", choices=motor.ROTOR)
    fric = Option("friction", "viscous", "rotor friction: 'viscous' (b w) or 'stiction' (Coulomb torque Tc and "
                                         "breakaway torque Ts, stick and slip modes located as events; rotor "
                                         "'state' only)", choices=motor.FRICTION)
    act = Option("actuator", "fa200", "actuator preset giving the parameter defaults: Firgelli FA-200-L-12 or "
                                      "the thesis's 'X' actuator", choices=tuple(actuator.ACTUATORS))
    channels = Option("channels", 1, "number of channels (legs), 1 to 64",
                      check=lambda v: positive_int(v) or (None if v <= 64 else "must be at most 64"))
    stops = Option("end_stops", "clamp", "end stops, located as events: 'clamp' (the rod held on the stop, the motor "
                                         "speed running on) or 'impact' (restitution e, "
                                         "rest on the stop)", choices=actuator.END_STOPS)
    return {
        "mechanism": {
            "rigid": _Entry(mechanism.rigid, (CONFIG, integrator_option("rk4"), SUBSTEPS)),
            "multibody": _Entry(mechanism.multibody, (CONFIG, integrator_option("radau"), SUBSTEPS)),
            "kinematic": _Entry(mechanism.kinematic, (CONFIG,)),
        },
        "dc_motor": {
            "full": _Entry(motor.full, (rotor, integrator_option("exact", LINEAR_INTEGRATORS), SUBSTEPS, fric)),
            "quasistatic": _Entry(motor.quasistatic, (rotor, integrator_option("exact", LINEAR_INTEGRATORS),
                                                      SUBSTEPS, fric)),
            "ideal": _Entry(motor.ideal, ()),
        },
        "pid": {
            "continuous": _Entry(pid.continuous, pid_opts + (integrator_option("auto", ("auto",) + LINEAR_INTEGRATORS),
                                                             SUBSTEPS)),
            "discrete": _Entry(pid.discrete, pid_opts + (sample, Option(
                "timing", "periodic", "samples: 'periodic' (a discrete block: the step a multiple of the sample "
                                      "period) or 'events' (time events: any step)", choices=pid.TIMING))),
        },
        "pose_setpoint": {
            "default": _Entry(setpoint.pose_setpoint, (CONFIG, Option("profile", "step", "trajectory profile",
                                                                      choices=setpoint.PROFILES))),
        },
        "oscillator": {
            "linear": _Entry(oscillator.oscillator, (
                Option("coupling", "none", "interface: 'none' (force in) or 'spring' (velocity in, coupling spring "
                                           "force out)", choices=oscillator.COUPLING),
                integrator_option("rk4", LINEAR_INTEGRATORS), Option("substeps", 40, "integrator substeps per communication step",
                                                 check=SUBSTEPS.check),
                Option("stop", "none", "end stops: 'none' or 'impact' (located impacts with restitution, rest on a "
                                       "stop; coupling 'none' only)", choices=oscillator.STOPS))),
        },
        "linear_actuator": {
            "rig": _Entry(actuator.rig, (act, integrator_option("rk4"), SUBSTEPS, stops)),
            "single": _Entry(actuator.single, (act, integrator_option("rk4"), SUBSTEPS, stops)),
            "motor": _Entry(actuator.motor_rig, (integrator_option("rk4"), Option(
                "substeps", 4, "integrator substeps per communication step", check=SUBSTEPS.check))),
        },
        "task_trajectory": {
            "planned": _Entry(task.task_trajectory, task_options()),
        },
        "pendulum": {
            "stop": _Entry(pendulum.stop, (integrator_option("rk4"),
                                           Option("substeps", 10, "integrator substeps per communication step",
                                                  check=SUBSTEPS.check))),
        },
        "sliding_mass": {
            "stiction": _Entry(friction.stiction, (integrator_option("rk4"),
                                                   Option("substeps", 10, "integrator substeps per communication step",
                                                          check=SUBSTEPS.check))),
            "smooth": _Entry(friction.smooth, (integrator_option("radau"),
                                               Option("substeps", 10, "integrator substeps per communication step",
                                                      check=SUBSTEPS.check))),
        },
        "sampled": {
            "adc": _Entry(sampled.adc, (channels, Option("period", 1e-3, "sample period [s] (time events)",
                                                         check=positive_float))),
            "pwm": _Entry(sampled.pwm, (channels, Option("period", 1e-3, "duty update period [s] (time events)",
                                                         check=positive_float))),
        },
        "sum": {
            "vector": _Entry(sums.vector_sum, (
                Option("inputs", 2, "number of summed inputs (vectors)", check=positive_int),
                Option("dimension", 1, "elements per input and of the output (1: a scalar sum)",
                       check=positive_int))),
        },
    }


_CATALOG = _entries()


def catalog() -> dict[str, list[str]]:
    """Model name -> its fidelities (the first is the default)."""
    return {model: list(fids) for model, fids in _CATALOG.items()}


#: Fidelity levels from the most to the least detailed, where that differs from the catalog's order
#: (whose first level is the default).
_DETAIL = {"mechanism": ("multibody", "rigid", "kinematic"), "dc_motor": ("full", "quasistatic", "ideal"),
           "pid": ("continuous", "discrete")}


def detail_order(model: str) -> list[str]:
    """The fidelity levels of ``model``, most detailed first."""
    levels = list(_CATALOG[model]) if model in _CATALOG else []
    ranked = [f for f in _DETAIL.get(model, ()) if f in levels]
    return ranked + [f for f in levels if f not in ranked]


def _entry(model: str, fidelity: str | None) -> tuple[str, _Entry]:
    if model not in _CATALOG:
        raise BlockError(f"unknown model {model!r}{suggest(str(model), list(_CATALOG))} "
                         f"(expected one of {', '.join(_CATALOG)})")
    fids = _CATALOG[model]
    if fidelity is None:
        fidelity = next(iter(fids))
    if fidelity not in fids:
        raise BlockError(f"{model}: unknown fidelity {fidelity!r}{suggest(str(fidelity), list(fids))} "
                         f"(expected one of {', '.join(fids)})")
    return fidelity, fids[fidelity]


def options(model: str, fidelity: str | None = None) -> dict[str, Option]:
    """The construction options of ``model`` at ``fidelity`` (name -> :class:`Option`)."""
    _, entry = _entry(model, fidelity)
    return {o.name: o for o in entry.options}


def make(model: str, fidelity: str | None = None, **opts: Any) -> Block:
    """Build the block ``model`` at ``fidelity`` (default: the model's first fidelity).

    ``opts`` holds construction options (see :func:`options`) and parameter overrides by name
    (they become the parameters' defaults, i.e. the FMU's start values; bounds are checked)."""
    fidelity, entry = _entry(model, fidelity)
    where = f"{model} ({fidelity})"
    known = {o.name: o for o in entry.options}
    construction = {name: o.default for name, o in known.items()}
    overrides: dict[str, Any] = {}
    for name, value in opts.items():
        if name in known:
            construction[name] = known[name].validate(where, value)
        else:
            overrides[name] = value
    blk = entry.build(**construction)
    return with_defaults(blk, where, overrides, list(known)) if overrides else blk


__all__ = ["make", "catalog", "options", "detail_order", "Option"]
