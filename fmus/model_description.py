"""The FMU's variable table and its ``modelDescription.xml`` (FMI 2.0 and 3.0 co-simulation).

Value references (shared with the C core, ``fmus/c/rpr_core.h``): 0 is ``time``, then the
parameters, modes, states, inputs and outputs in the block's declaration order.

- parameters: ``causality="parameter"``, ``variability="tunable"`` (``"fixed"`` when structural:
  settable until the end of initialisation), ``initial="exact"``;
- states: ``causality="local"``, ``initial="exact"`` with their start value when ``start(p)`` does
  not depend on the parameters (they may then be set before the end of initialisation), else
  ``initial="calculated"`` (they follow the parameters);
- modes (discrete states of a block with events): ``causality="local"``,
  ``variability="discrete"``, ``initial="calculated"`` (from ``mode_start(p)``; not settable);
- inputs: ``start`` 0; outputs: ``initial="calculated"``.

Units are parsed into SI base-unit exponents (``kg.m2``, ``m/s2``, ``N.m.s/rad``...) so that
``UnitDefinitions`` carries real ``BaseUnit`` elements; an unknown symbol is a build error.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from models.block import Block

from .errors import BuildError
from .names import UNIT_SYMBOLS, check_names, parse_unit  # noqa: F401  (re-exported)

GENERATION_TOOL = "rpr-cosim fmus"

@dataclass(frozen=True)
class FmuVariable:
    """One scalar variable of the FMU (see the module docstring for the conventions)."""

    vr: int
    name: str
    kind: str  # "time", "parameter", "state", "input", "output"
    causality: str
    variability: str
    initial: str | None
    start: float | None
    unit: str
    description: str
    min: float | None = None
    max: float | None = None


@dataclass
class Interface:
    """Everything the XML and the C header need to know about a block's FMU."""

    block: Block
    variables: list[FmuVariable]
    #: output vr -> vrs of the inputs and states it depends on during stepping
    output_deps: dict[int, list[int]] = field(default_factory=dict)
    #: output vr -> vrs of the parameters, inputs and exact-start states it depends on at init
    initial_deps: dict[int, list[int]] = field(default_factory=dict)

    def of_kind(self, kind: str) -> list[FmuVariable]:
        return [v for v in self.variables if v.kind == kind]

    @property
    def units(self) -> list[str]:
        seen: list[str] = []
        for v in self.variables:
            if v.unit and v.unit not in seen:
                seen.append(v.unit)
        return seen


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def interface(block: Block) -> Interface:
    """The variable table and ModelStructure dependencies of ``block`` (already checked)."""
    p0 = block.param_defaults
    x_start = np.asarray(block.functions()["start"](p0), dtype=float).reshape(-1)
    exact = [not ca.depends_on(block.start[i], block.p) if block.p.numel() else True
             for i in range(block.x.numel())]
    state_var = "discrete" if block.integrator == "discrete" else "continuous"
    vs: list[FmuVariable] = [FmuVariable(0, "time", "time", "independent", "continuous", None, None, "s",
                                         "simulation time")]
    for prm in block.params:
        vs.append(FmuVariable(len(vs), prm.name, "parameter", "parameter",
                              "fixed" if prm.structural else "tunable", "exact", float(prm.default),
                              prm.unit, prm.description, _finite(prm.lower), _finite(prm.upper)))
    m_start = np.asarray(ca.Function("m0", [block.p], [block.mode_start])(p0), dtype=float).reshape(-1) \
        if block.m.numel() else []
    for i, md in enumerate(block.modes):
        vs.append(FmuVariable(len(vs), md.name, "mode", "local", "discrete", "calculated", None, md.unit,
                              md.description or f"mode (discrete state; start {m_start[i]:g} at the defaults)"))
    for i, st in enumerate(block.states):
        vs.append(FmuVariable(len(vs), st.name, "state", "local", state_var,
                              "exact" if exact[i] else "calculated",
                              float(x_start[i]) if exact[i] else None, st.unit,
                              st.description or "state"))
    for v in block.inputs:
        vs.append(FmuVariable(len(vs), v.name, "input", "input", "continuous", None, 0.0, v.unit, v.description))
    for v in block.outputs:
        vs.append(FmuVariable(len(vs), v.name, "output", "local" if v.local else "output", "continuous",
                              "calculated", None, v.unit, v.description))
    iface = Interface(block, vs)
    vr_p = [v.vr for v in iface.of_kind("parameter")]
    vr_x = [v.vr for v in iface.of_kind("state")]
    vr_u = [v.vr for v in iface.of_kind("input")]
    vr_y = [v.vr for v in iface.of_kind("output")]
    ny = len(vr_y)
    if ny:
        sp_u = ca.jacobian_sparsity(block.out, block.u) if block.u.numel() else None
        sp_x = ca.jacobian_sparsity(block.out, block.x) if block.x.numel() else None
        # at initialisation: calculated states follow start(p), exact ones are knowns
        xs_init = ca.vertcat(*[block.x[i] if exact[i] else block.start[i] for i in range(block.x.numel())]) \
            if block.x.numel() else block.x
        y_init = ca.substitute(block.out, block.x, xs_init) if block.x.numel() else block.out
        if block.m.numel():  # modes start at mode_start(p)
            y_init = ca.substitute(y_init, block.m, block.mode_start)
        sp_init = {name: (ca.jacobian_sparsity(y_init, sym) if sym.numel() else None)
                   for name, sym in (("p", block.p), ("u", block.u), ("x", block.x))}
        for k, vr in enumerate(vr_y):
            dep = [vr_x[j] for j in range(len(vr_x)) if sp_x is not None and sp_x.has_nz(k, j)]
            dep += [vr_u[j] for j in range(len(vr_u)) if sp_u is not None and sp_u.has_nz(k, j)]
            iface.output_deps[vr] = sorted(dep)
            ini = [vr_p[j] for j in range(len(vr_p)) if sp_init["p"] is not None and sp_init["p"].has_nz(k, j)]
            ini += [vr_x[j] for j in range(len(vr_x)) if exact[j] and sp_init["x"] is not None
                    and sp_init["x"].has_nz(k, j)]
            ini += [vr_u[j] for j in range(len(vr_u)) if sp_init["u"] is not None and sp_init["u"].has_nz(k, j)]
            iface.initial_deps[vr] = sorted(ini)
    return iface


# --- XML ------------------------------------------------------------------------------------
LOG_CATEGORIES = (
    ("logStatusError", "errors: wrong calls, refused values, failed evaluations"),
    ("logStatusDiscard", "discarded steps: Newton non-convergence or a non-finite state"),
    ("logStatusWarning", "warnings"),
    ("logNonlinearSystems", "Radau IIA Newton residual of every step"),
    ("logCalls", "instantiation and other calls"),
    ("logEvents", "events located and handled inside doStep: time, indicator, rounds of the event iteration"),
)


def _fmt(x: float) -> str:
    return repr(float(x))


def _unit_definitions(parent: ET.Element, units: list[str]) -> None:
    if not units:
        return
    defs = ET.SubElement(parent, "UnitDefinitions")
    for name in units:
        factor, exps = parse_unit(name)
        unit = ET.SubElement(defs, "Unit", name=name)
        attrs = {k: str(v) for k, v in exps.items()}
        if factor != 1.0:
            attrs["factor"] = _fmt(factor)
        ET.SubElement(unit, "BaseUnit", attrs)


def can_interpolate_inputs(block: Block) -> bool:
    """Whether the FMU follows first-order input slopes over a step (FMI 2.0
    ``canInterpolateInputs``): every continuous block; a sampled block reads its inputs at its
    samples."""
    return block.integrator != "discrete"


def model_description(iface: Interface, *, fmi_version: str, guid: str, model_identifier: str,
                      sources: list[str], stop_time: float = 1.0) -> str:
    """The ``modelDescription.xml`` text for FMI ``"2.0"`` or ``"3.0"``."""
    blk = iface.block
    fmi3 = fmi_version == "3.0"
    root = ET.Element("fmiModelDescription", {"fmiVersion": fmi_version, "modelName": model_identifier,
                                              ("instantiationToken" if fmi3 else "guid"): guid,
                                              "description": blk.description or blk.name,
                                              "generationTool": GENERATION_TOOL,
                                              "variableNamingConvention": "structured"})
    if not fmi3:
        root.set("numberOfEventIndicators", "0")
    cs = {"modelIdentifier": model_identifier, "needsExecutionTool": "false",
          "canHandleVariableCommunicationStepSize": "true",
          "canBeInstantiatedOnlyOncePerProcess": "false"}
    if fmi3:
        events = "true" if blk.has_events else "false"  # event mode and early return at events
        cs.update({"canGetAndSetFMUState": "true", "canSerializeFMUState": "true",
                   "providesDirectionalDerivatives": "true", "hasEventMode": events,
                   "mightReturnEarlyFromDoStep": events, "canReturnEarlyAfterIntermediateUpdate": "false"})
    else:
        cs.update({"canInterpolateInputs": "true" if can_interpolate_inputs(blk) else "false", "maxOutputDerivativeOrder": "0",
                   "canRunAsynchronuously": "false", "canNotUseMemoryManagementFunctions": "true",
                   "canGetAndSetFMUstate": "true", "canSerializeFMUstate": "true",
                   "providesDirectionalDerivative": "true"})
    cs_el = ET.SubElement(root, "CoSimulation", cs)
    if not fmi3 and sources:
        files = ET.SubElement(cs_el, "SourceFiles")
        for s in sources:
            ET.SubElement(files, "File", name=s)
    _unit_definitions(root, iface.units)
    cats = ET.SubElement(root, "LogCategories")
    for name, text in LOG_CATEGORIES:
        ET.SubElement(cats, "Category", name=name, description=text)
    step = float(blk.sample_period) if blk.integrator == "discrete" else 1e-3
    ET.SubElement(root, "DefaultExperiment", startTime="0.0", stopTime=_fmt(stop_time), stepSize=_fmt(step))
    mv = ET.SubElement(root, "ModelVariables")
    for v in iface.variables:
        attrs = {"name": v.name, "valueReference": str(v.vr), "causality": v.causality,
                 "variability": v.variability}
        if v.initial:
            attrs["initial"] = v.initial
        if v.description:
            attrs["description"] = v.description
        typed = {}
        if v.unit:
            typed["unit"] = v.unit
        if v.min is not None:
            typed["min"] = _fmt(v.min)
        if v.max is not None:
            typed["max"] = _fmt(v.max)
        if v.start is not None:
            typed["start"] = _fmt(v.start)
        if fmi3:
            ET.SubElement(mv, "Float64", {**attrs, **typed})
        else:
            sv = ET.SubElement(mv, "ScalarVariable", attrs)
            ET.SubElement(sv, "Real", typed)
    ms = ET.SubElement(root, "ModelStructure")
    outputs = [v for v in iface.of_kind("output") if v.causality == "output"]  # locals are no unknowns

    def deps(vrs: list[int]) -> dict[str, str]:
        refs = [str(r) if fmi3 else str(r + 1) for r in vrs]  # FMI 2 uses 1-based indices
        return {"dependencies": " ".join(refs), "dependenciesKind": " ".join(["dependent"] * len(refs))}

    if fmi3:
        for v in outputs:
            ET.SubElement(ms, "Output", {"valueReference": str(v.vr), **deps(iface.output_deps[v.vr])})
        for v in outputs:
            ET.SubElement(ms, "InitialUnknown", {"valueReference": str(v.vr), **deps(iface.initial_deps[v.vr])})
    else:
        if outputs:
            el = ET.SubElement(ms, "Outputs")
            for v in outputs:
                ET.SubElement(el, "Unknown", {"index": str(v.vr + 1), **deps(iface.output_deps[v.vr])})
            el = ET.SubElement(ms, "InitialUnknowns")
            for v in outputs:
                ET.SubElement(el, "Unknown", {"index": str(v.vr + 1), **deps(iface.initial_deps[v.vr])})
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def build_description(model_identifier: str, sources: list[str]) -> str:
    """FMI 3.0 ``sources/buildDescription.xml`` listing the C sources to compile."""
    root = ET.Element("fmiBuildDescription", fmiVersion="3.0")
    conf = ET.SubElement(root, "BuildConfiguration", modelIdentifier=model_identifier)
    fs = ET.SubElement(conf, "SourceFileSet", language="C99")
    for s in sources:
        ET.SubElement(fs, "SourceFile", name=s)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
