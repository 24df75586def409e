"""What a slave looks like before it runs: its variables (causality, type, unit), feedthrough and flanges."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING


from models.interface import Flange

from ..errors import UserError
from .types import canonical
from .archive import check_archive

if TYPE_CHECKING:
    from models.block import Block


@dataclass(frozen=True)
class Variable:
    """One variable (a scalar, or an FMI 3.0 array of ``shape``): FMI ``causality`` (parameter,
    structuralParameter, calculatedParameter, input, output, local, independent),
    ``variability``, canonical ``type`` (:mod:`cosim.slaves.types`: ``Real`` for FMI 2.0 Real and FMI 3.0
    Float64, ``Integer`` for Integer/Int32, else the FMI 3.0 name), ``start`` (a float for numeric
    scalars, None when it has none or is not a number; ``raw_start`` as written), unit and value
    reference (None until an FMU exists)."""

    name: str
    causality: str
    variability: str = "continuous"
    type: str = "Real"
    start: float | None = None
    unit: str = ""
    description: str = ""
    vr: int | None = None
    fmi_type: str = ""  # the type as the modelDescription writes it (Float64, Int32, Integer, ...)
    shape: tuple[int, ...] = ()  # array dimensions (FMI 3.0); () for a scalar
    initial: str | None = None  # exact, approx or calculated (FMI), None when not given
    dims: tuple = ()  # per dimension: a fixed size (int) or the name of the structural parameter
    raw_start: object = None  # the start value as written (text, or a list for an array)

    @property
    def size(self) -> int:
        """Number of values (1 for a scalar)."""
        n = 1
        for d in self.shape:
            n *= d
        return n

    @property
    def fast(self) -> bool:
        """A scalar Float64: carried by the master's value vector and the compiled loop."""
        return self.type == "Real" and not self.shape


@dataclass
class SlaveDescription:
    """What a scene needs to know about a component before anything runs.

    ``feedthrough`` maps each output to the inputs it depends on *directly* (within one
    communication point); ``flanges`` are its power ports; ``sample_period`` [s] is set for a
    sampled (discrete) slave, whose communication step must be a whole multiple of it.
    """

    kind: str  # "block", "fmu" or "python"
    source: str  # "model/fidelity", the FMU path, or the class name
    variables: dict[str, Variable]
    feedthrough: dict[str, list[str]]
    flanges: list[Flange] = field(default_factory=list)
    sample_period: float | None = None
    fmi_version: str | None = None
    can_get_set_state: bool = False
    can_interpolate_inputs: bool = False  # follows first-order input slopes (FMI 2.0 canInterpolateInputs)
    default_experiment: dict = field(default_factory=dict)  # start, stop, tolerance, step [s] as the FMU gives them
    interfaces: tuple[str, ...] = ()  # FMI interface kinds the FMU has (co-simulation, model exchange, ...)
    guid: str = ""  # the FMU's GUID / instantiation token and model identifier ("" until read from an FMU)
    model_identifier: str = ""
    provides_directional_derivative: bool = False  # FMI get directional derivative (partials at the current instant)
    dependencies_declared: bool = True  # False: no output lists its dependencies (FMI: each depends on every input)
    feedthrough_source: str = "declared"  # declared, measured (cosim.slaves.probe) or scene (the scene's feedthrough:)
    workarounds: tuple[str, ...] = ()  # from the behavioural check (cosim.slaves.behaviour): always_no_prior
    rollback_reason: str = ""  # why rollback was taken away although the FMU declares it (behavioural check)
    #: no state, no sampling: its outputs are functions of its inputs now (a catalog block such as ``sum``,
    #: known from the scene; fixed-step Jacobi evaluates it within the exchange, see cosim.master)
    memoryless: bool = False
    #: the interface a run steps it through: "co-simulation", or "model exchange" (integrated by
    #: CVODES inside the slave, cosim.slaves.model_exchange)
    interface: str = "co-simulation"
    continuous_states: int = 0  # model exchange: number of continuous states
    event_indicators: int = 0  # model exchange: number of event indicators
    needs_completed_integrator_step: bool = False  # model exchange: call CompletedIntegratorStep after each step
    discrete_states: tuple[str, ...] = ()  # local and output variables of variability discrete (modes, counters)
    #: how a rollback restores it: "FMU state", "continuous states" (model exchange without FMU
    #: state and without discrete states), or "" (it cannot roll back)
    rollback_through: str = ""
    solver_rtol: float | None = None  # model exchange: CVODES's relative tolerance (the scene's rtol:)
    has_event_mode: bool = False  # FMI 3.0 co-simulation: hasEventMode (event mode and early return usable)

    @property
    def has_events(self) -> bool:
        """It may have events: FMI 3.0 event mode, event indicators, model exchange (time events at
        least), discrete variables (modes, counters, samples)."""
        return (self.has_event_mode or bool(self.event_indicators) or self.interface == "model exchange"
                or bool(self.discrete_states)
                or any(v.variability == "discrete" and v.causality in ("local", "output") for v in self.variables.values()))

    def of(self, *causalities: str) -> list[str]:
        """Names of the variables with one of the given causalities, in declaration order."""
        return [v.name for v in self.variables.values() if v.causality in causalities]

    def flange(self, name: str) -> Flange | None:
        for f in self.flanges:
            if f.name == name:
                return f
        return None


def describe_block(block: Block, source: str = "") -> SlaveDescription:
    """The description of ``block`` as its exported FMU will present it (value references are
    unknown until the FMU exists)."""
    vs: dict[str, Variable] = {}
    for p in block.params:
        vs[p.name] = Variable(p.name, "parameter", "fixed" if p.structural else "tunable", "Real",
                              float(p.default), p.unit, p.description)
    for s in block.states:
        vs[s.name] = Variable(s.name, "local", "discrete" if block.integrator == "discrete" else "continuous",
                              "Real", None, s.unit, s.description)
    for md in block.modes:  # discrete states of a block with events (docs/explanation/events.md)
        vs[md.name] = Variable(md.name, "local", "discrete", "Real", None, md.unit, md.description)
    for u in block.inputs:
        vs[u.name] = Variable(u.name, "input", "continuous", "Real", 0.0, u.unit, u.description)
    for y in block.outputs:
        vs[y.name] = Variable(y.name, "local" if y.local else "output", "continuous", "Real", None, y.unit,
                              y.description)
    period = float(block.sample_period) if block.integrator == "discrete" and block.sample_period else None
    return SlaveDescription("block", source or block.name, vs, block.feedthrough(), list(block.flanges),
                            period, None, True)


def _interfaces(md) -> tuple[str, ...]:
    kinds = [("co-simulation", md.coSimulation), ("model exchange", md.modelExchange),
             ("scheduled execution", getattr(md, "scheduledExecution", None))]
    return tuple(k for k, present in kinds if present is not None)


def _fmu_variable(v, fmi_version: str) -> Variable:

    start = None
    if v.start is not None and not v.dimensions:
        try:
            start = float(v.start)
        except (TypeError, ValueError):
            start = None
    dims = tuple(d.variable.name if d.variable is not None else int(d.start) for d in v.dimensions)
    causality = v.causality or "local"
    return Variable(v.name, causality, v.variability or "continuous", canonical(v.type), start, v.unit or "",
                    v.description or "", v.valueReference, v.type, tuple(int(n) for n in (v.shape or ())),
                    getattr(v, "initial", None), dims, v.start)


def resolve_shapes(desc: SlaveDescription, structural: dict[str, int]) -> SlaveDescription:
    """``desc`` with array shapes recomputed for the structural parameter values ``structural``
    (the others keep their start values)."""
    if not any(v.dims for v in desc.variables.values()):
        return desc
    size = {n: int(v.raw_start) for n, v in desc.variables.items() if v.causality == "structuralParameter"
            and v.raw_start is not None}
    size.update({k: int(x) for k, x in structural.items()})
    vs = {}
    for n, v in desc.variables.items():
        if v.dims:
            shape = tuple(d if isinstance(d, int) else size.get(d, 0) for d in v.dims)
            v = dataclasses.replace(v, shape=shape)
        vs[n] = v
    return dataclasses.replace(desc, variables=vs)


def _declared_version(path: Path) -> str | None:
    """The ``fmiVersion`` attribute of the FMU's model description (None when unreadable: the
    full reader then says why)."""
    import zipfile

    from lxml import etree

    try:
        with zipfile.ZipFile(path) as z:
            data = z.read("modelDescription.xml")
        root = etree.fromstring(data, etree.XMLParser(resolve_entities=False, no_network=True, huge_tree=False))
    except Exception:  # noqa: BLE001 - any unreadable description: fmpy's reader reports it
        return None
    v = root.get("fmiVersion")
    return str(v) if v is not None else None


#: The values of a component's ``interface:`` key -> the interface's name in a description.
INTERFACES = {"co_simulation": "co-simulation", "model_exchange": "model exchange"}


def _chosen_interface(path: Path, md, kinds: tuple[str, ...], interface: str | None) -> str:
    """The interface a run uses: ``interface`` (a key of :data:`INTERFACES`) when given, else
    co-simulation where the FMU has it, else model exchange.  Raises :class:`UserError`."""
    if interface is not None:
        if interface not in INTERFACES:
            raise UserError(f"{path}: interface {interface!r}; expected one of {', '.join(INTERFACES)}")
        name = INTERFACES[interface]
        if name not in kinds:
            raise UserError(f"{path}: interface {interface} asked, but the FMU has {' and '.join(kinds) or 'no interface'}"
                            f" only")
        return name
    if md.coSimulation is not None:
        return "co-simulation"
    if md.modelExchange is not None:
        return "model exchange"
    raise UserError(f"{path}: the FMU has {' and '.join(kinds) or 'no interface'} only; rpr-cosim runs co-simulation "
                    f"and model-exchange FMUs (Scheduled Execution, with clocks, is not supported)")


def describe_fmu(path: Path, interface: str | None = None) -> SlaveDescription:
    """Read an FMU's ``modelDescription.xml`` for the interface a run will use (``interface``:
    ``co_simulation`` or ``model_exchange``; None: co-simulation where the FMU has it, else model
    exchange).  Raises :class:`UserError` naming the file when it is not a readable FMU of a
    supported interface."""
    import fmpy


    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such FMU file")
    check_archive(path)  # names, duplicates and sizes, before any reader unpacks a byte
    version = _declared_version(path)
    if version is not None and not version.startswith(("2", "3")):
        raise UserError(f"{path}: FMI {version} FMUs are not supported; export it as FMI 2.0 or 3.0 co-simulation")
    try:
        md = fmpy.read_model_description(str(path), validate=False)
    except Exception as exc:  # fmpy raises bare Exceptions for any malformed archive or XML
        raise UserError(f"{path}: not a readable FMU ({exc})") from None
    if not str(md.fmiVersion or "").startswith(("2", "3")):
        raise UserError(f"{path}: FMI {md.fmiVersion} FMUs are not supported; export it as FMI 2.0 or 3.0 "
                        f"co-simulation")
    kinds = _interfaces(md)
    chosen = _chosen_interface(path, md, kinds, interface)
    vs: dict[str, Variable] = {v.name: _fmu_variable(v, md.fmiVersion) for v in md.modelVariables}
    de = md.defaultExperiment
    default = {}
    for k, x in (() if de is None else (("start", de.startTime), ("stop", de.stopTime), ("tolerance", de.tolerance),
                                        ("step", de.stepSize))):
        if x is not None:
            try:
                default[k] = float(x)
            except (TypeError, ValueError):
                attr = {"start": "startTime", "stop": "stopTime", "tolerance": "tolerance", "step": "stepSize"}[k]
                raise UserError(f"{path}: <DefaultExperiment>: {attr}={x!r} is not a number") from None
    inputs = [v.name for v in md.modelVariables if v.causality == "input"]
    ft: dict[str, list[str]] = {}
    listed = {u.variable.name: u for u in md.outputs}
    declared = any(u.dependencies is not None for u in md.outputs)
    for v in md.modelVariables:
        if v.causality != "output":
            continue
        unknown = listed.get(v.name)
        if unknown is None or unknown.dependencies is None:
            ft[v.name] = list(inputs)  # FMI: no dependency list means "depends on every known"
        else:
            ft[v.name] = [d.name for d in unknown.dependencies if d.causality == "input"]
    period = None
    cs = md.coSimulation if chosen == "co-simulation" else md.modelExchange
    can_state = bool(getattr(cs, "canGetAndSetFMUstate", False) or getattr(cs, "canGetAndSetFMUState", False))
    interp = chosen == "co-simulation" and md.fmiVersion.startswith("2") and bool(getattr(cs, "canInterpolateInputs", False))
    ddx = bool(getattr(cs, "providesDirectionalDerivative", False) or getattr(cs, "providesDirectionalDerivatives", False))
    discrete = tuple(v.name for v in md.modelVariables if v.variability == "discrete"
                     and (v.causality or "local") in ("local", "output"))
    me = {}
    if chosen == "model exchange":
        nx = int(md.numberOfContinuousStates or 0)
        through = "FMU state" if can_state else ("continuous states" if nx and not discrete else "")
        me = dict(interface=chosen, continuous_states=nx, event_indicators=int(md.numberOfEventIndicators or 0),
                  needs_completed_integrator_step=bool(getattr(cs, "needsCompletedIntegratorStep", False)),
                  rollback_through=through)
        can_state = bool(through)
    else:
        me = dict(rollback_through="FMU state" if can_state else "",
                  has_event_mode=md.fmiVersion.startswith("3") and bool(getattr(cs, "hasEventMode", False)))
    return SlaveDescription("fmu", str(path), vs, ft, [], period, md.fmiVersion, can_state, interp, default, kinds,
                            md.guid or "", cs.modelIdentifier or "", ddx, declared, discrete_states=discrete, **me)



