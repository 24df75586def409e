"""What a run will do with an FMU, per interface it has (``rpr-cosim fmu check`` prints it): which
interface a scene gets by default, how it is stepped or integrated, how it rolls back, what
happens to its events; and the inconsistencies between its capability flags that the XML shows."""
from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from .description import INTERFACES, SlaveDescription, describe_fmu
from .model_exchange import DEFAULT_RTOL, MAX_EVENTS_PER_STEP, available


def _me_line(d: SlaveDescription) -> str:

    events = []
    if d.event_indicators:
        events.append(f"{d.event_indicators} event indicator(s): state events located by CVODES's root finding")
    events.append("time events at the FMU's next event time")
    if d.needs_completed_integrator_step:
        events.append("step events (CompletedIntegratorStep after every solver step)")
    rollback = {"FMU state": "rollback through its FMU state plus a solver restart",
                "continuous states": "rollback through its continuous states (it declares no FMU state and no "
                                     "discrete variable; a hidden discrete state is caught at the restore)",
                "": f"no rollback (no FMU state, and discrete variable(s) {', '.join(d.discrete_states[:5])}"
                    f"{' ...' if len(d.discrete_states) > 5 else ''}): adaptive and iterative refuse it"}[d.rollback_through]
    why = available()
    return (f"model exchange: integrated by SUNDIALS CVODES inside its slave (BDF, rtol {DEFAULT_RTOL:g} unless the "
            f"scene's rtol: or the FMU's DefaultExperiment is tighter), {d.continuous_states} continuous state(s); "
            f"{'; '.join(events)}; handled inside each communication step (event iteration at most 100 rounds, at "
            f"most {MAX_EVENTS_PER_STEP} events per step); {rollback}"
            + (f"; NOT AVAILABLE HERE: {why}" if why else ""))


def _me_departures(md) -> list[str]:
    """What the XML shows against the standard's rules for continuous states (FMI 2.0 3.3.1, FMI 3.0
    2.4.8): every listed derivative names its state (``derivative=``), a continuous real variable."""
    out = []
    real = ("Real", "Float64", "Float32")
    for u in md.derivatives:
        var = u.variable
        state = getattr(var, "derivative", None)
        if state is None:
            out.append(f"<ModelStructure>: derivative {var.name!r} names no state (no derivative= attribute): a "
                       f"model-exchange run cannot tell which variable it integrates")
        elif state.variability != "continuous" or state.type not in real:
            out.append(f"<ModelStructure>: state {state.name!r} of derivative {var.name!r} is {state.type} "
                       f"{state.variability}; a continuous state must be a continuous real variable")
    return out


def _cs_line(d: SlaveDescription, md) -> str:
    cs = md.coSimulation
    rollback = ("rollback through its FMU state" if d.can_get_set_state
                else "no rollback (no FMU state): adaptive and iterative refuse it")
    line = f"co-simulation: stepped by doStep at the communication points; {rollback}"
    if md.fmiVersion.startswith("3"):
        if getattr(cs, "hasEventMode", False):
            line += ("; declares event mode: under jacobi, gauss_seidel, adaptive, ecco and iterative it is "
                     "instantiated with event mode and early return, its events end the step for the whole coupling "
                     "(event iteration, two trace rows); jacobi_extrapolated leaves its events inside its doStep")
        else:
            line += "; no event mode: its events are handled inside its doStep"
    else:
        line += "; its events are handled inside its doStep (FMI 2.0)"
    return line


def component_line(d: SlaveDescription) -> str:
    """One line on how a run steps a component of description ``d`` ('' for a plain co-simulation
    component): a model-exchange FMU's solver, events and rollback."""
    if d.interface != "model exchange":
        return ""

    rtol = d.solver_rtol if d.solver_rtol is not None else min(DEFAULT_RTOL, d.default_experiment.get("tolerance",
                                                                                                       DEFAULT_RTOL))
    rollback = {"FMU state": "rollback through its FMU state", "continuous states":
                "rollback through its continuous states", "": "no rollback"}[d.rollback_through if d.can_get_set_state
                                                                           else ""]
    return (f"model exchange, integrated by CVODES (rtol {rtol:g}); {d.continuous_states} continuous state(s), "
            f"{d.event_indicators} event indicator(s); its events are handled inside its steps and reach the other "
            f"components at the next communication point; {rollback}")


def run_plan(path: Path) -> tuple[list[str], list[str]]:
    """(lines saying what a run does with each interface of the FMU ``path``, departures from the
    standard seen in its capability flags).  Raises :class:`UserError` for an unreadable FMU."""
    import fmpy

    md = fmpy.read_model_description(str(path), validate=False)
    lines, departures = [], []
    default = None
    for key, name in INTERFACES.items():
        if getattr(md, "coSimulation" if key == "co_simulation" else "modelExchange") is None:
            continue
        try:
            d = describe_fmu(path, key)
        except UserError as exc:
            departures.append(str(exc))
            continue
        if default is None:
            default = name
        text = _me_line(d) if key == "model_exchange" else _cs_line(d, md)
        lines.append(f"{text}{' [a scene gets this one]' if default == name else ' [interface: ' + key + ']'}")
    if getattr(md, "scheduledExecution", None) is not None:
        lines.append("scheduled execution: not supported (a scene gets a one-line refusal when it has nothing else)")
    if md.modelExchange is not None:
        departures += _me_departures(md)
    cs = md.coSimulation
    if cs is not None and getattr(cs, "canReturnEarlyAfterIntermediateUpdate", False) \
            and not getattr(cs, "providesIntermediateUpdate", False):
        departures.append("<CoSimulation>: canReturnEarlyAfterIntermediateUpdate=true needs providesIntermediateUpdate="
                          "true (FMI 3.0, 4.3.1: early return is asked for in the intermediate update callback)")
    return lines, departures


__all__ = ["component_line", "run_plan"]
