"""A scene out as an SSP 1.0 archive (the format and the reader: :mod:`cosim.scenario.ssp_archive`).

:func:`export` writes one FMU per distinct component binary under ``resources/`` (built on a cache
miss), the scene's parameters and start values as one system-level parameter set
``resources/<scene>.ssv`` (hierarchical names ``component.variable``), every signal connection (a
power bond becomes its two signals, each tagged with an ``org.rpr-cosim.bond`` annotation), the
units the connectors and parameters use with their SI base units, ``DefaultExperiment`` (the
scene's start and stop times) and, as an ``org.rpr-cosim.master`` annotation of the default
experiment, our master settings (algorithm, step, input mode, output interval, order, engine, tolerance; a scene
that names no algorithm: its tolerance and no algorithm, so a run of the SSP chooses again) and
the recorded outputs.  Both XML files are validated against the SSP 1.0 schemas that FMPy ships
before the archive is written."""
from __future__ import annotations

import json
import os
import tempfile
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path

from ..scenario.guard_settings import guard_needs
from ..scenario.ssp_archive import (BOND_ANNOTATION, COMPONENT_ANNOTATION, FMU_TYPE, MASTER_ANNOTATION, NS, SSD, SspError,
                            _num, _q, _units_xml, schema_errors)
from .execute import build_components

# --- export -----------------------------------------------------------------------------------
def _ssv(name: str, values: Sequence[tuple[str, float, str]]):
    """An ``ssv:ParameterSet`` element of Real values (name, value, unit)."""
    from lxml import etree

    root = etree.Element(_q("ssv", "ParameterSet"), nsmap={"ssv": NS["ssv"], "ssc": NS["ssc"]},
                         version="1.0", name=name)
    params = etree.SubElement(root, _q("ssv", "Parameters"))
    for pname, value, unit in values:
        p = etree.SubElement(params, _q("ssv", "Parameter"), name=pname)
        attrs = {"value": _num(value)}
        if unit:
            attrs["unit"] = unit
        etree.SubElement(p, _q("ssv", "Real"), attrs)
    _units_xml(root, [u for _, _, u in values], "ssv")
    return root


def ssd_document(scene, fmu_sources: dict[str, str], ssv_source: str):
    """The ``SystemStructureDescription`` element of ``scene`` (FMUs at ``fmu_sources``)."""
    from lxml import etree

    root = etree.Element(_q("ssd", "SystemStructureDescription"),
                         nsmap={k: NS[k] for k in ("ssd", "ssc", "ssv")}, version="1.0", name=scene.name)
    if scene.description:
        root.set("description", scene.description)
    root.set("generationTool", "rpr-cosim")
    system = etree.SubElement(root, _q("ssd", "System"), name=scene.name)
    binds = etree.SubElement(system, _q("ssd", "ParameterBindings"))
    etree.SubElement(binds, _q("ssd", "ParameterBinding"), source=ssv_source)
    elements = etree.SubElement(system, _q("ssd", "Elements"))
    fed = {(c.dst, c.dst_var) for c in scene.connections}
    units: list[str] = []
    for name, comp in scene.components.items():
        el = etree.SubElement(elements, _q("ssd", "Component"), name=name, type=FMU_TYPE, source=fmu_sources[name])
        el.set("implementation", "CoSimulation")
        desc = comp.description
        conns = etree.SubElement(el, _q("ssd", "Connectors"))
        for var in desc.variables.values():
            if var.causality == "output" or (var.causality == "input" and (name, var.name) in fed):
                c = etree.SubElement(conns, _q("ssd", "Connector"), name=var.name, kind=var.causality)
                if var.description:
                    c.set("description", var.description)
                real = etree.SubElement(c, _q("ssc", "Real"))
                if var.unit:
                    real.set("unit", var.unit)
                    units.append(var.unit)
        if not len(conns):
            el.remove(conns)
        if comp.kind == "model" and comp.origin is None:  # a user's block travels as its FMU only
            anns = etree.SubElement(el, _q("ssd", "Annotations"))
            ann = etree.SubElement(anns, _q("ssc", "Annotation"), type=COMPONENT_ANNOTATION)
            attrs = {"model": comp.model, "fidelity": comp.fidelity, "options": json.dumps(comp.options, sort_keys=True)}
            needs = guard_needs(comp)
            if needs is not None:  # the guards' ratings, pose and geometry: an imported FMU stays guarded
                attrs["guards"] = json.dumps(needs.as_dict(), sort_keys=True)
            etree.SubElement(ann, _q("rpr", "Model"), attrs, nsmap={"rpr": NS["rpr"]})
    if scene.connections:
        cs = etree.SubElement(system, _q("ssd", "Connections"))
        for c in scene.connections:
            el = etree.SubElement(cs, _q("ssd", "Connection"), startElement=c.src, startConnector=c.src_var,
                                  endElement=c.dst, endConnector=c.dst_var)
            if c.factor != 1.0 or c.offset != 0.0:
                etree.SubElement(el, _q("ssc", "LinearTransformation"), factor=_num(c.factor), offset=_num(c.offset))
            if c.bond:
                anns = etree.SubElement(el, _q("ssd", "Annotations"))
                ann = etree.SubElement(anns, _q("ssc", "Annotation"), type=BOND_ANNOTATION)
                etree.SubElement(ann, _q("rpr", "Bond"), bond=c.bond, nsmap={"rpr": NS["rpr"]})
    _units_xml(root, units, "ssd")
    exp = etree.SubElement(root, _q("ssd", "DefaultExperiment"), startTime=_num(getattr(scene, "start_time", 0.0)),
                           stopTime=_num(scene.stop_time))
    m = scene.master
    # a scene that names no algorithm travels as its tolerance (a run of the SSP chooses again, on
    # its machine, what the master would choose here), not as the fixed-step placeholder
    attrs = {**({} if m.auto else {"algorithm": m.algorithm}), "step": _num(m.step),
             **({"inputs": m.inputs} if not m.auto or m.inputs_given else {}), "engine": m.engine,
             "outputInterval": _num(m.record_every * m.step), "scene": scene.name}
    if m.tolerance is not None and (m.tolerance_given or m.auto):
        attrs["tolerance"] = _num(m.tolerance)
    if m.order:
        attrs["order"] = " ".join(m.order)
    anns = etree.SubElement(exp, _q("ssd", "Annotations"))
    ann = etree.SubElement(anns, _q("ssc", "Annotation"), type=MASTER_ANNOTATION)
    master = etree.SubElement(ann, _q("rpr", "Master"), attrs, nsmap={"rpr": NS["rpr"]})
    for pattern in scene.outputs:
        etree.SubElement(master, _q("rpr", "Output"), name=pattern)
    return root


def parameter_values(scene) -> list[tuple[str, float, str]]:
    """The scene's parameters and start values as (``component.variable``, value, unit)."""
    out = []
    for name, comp in scene.components.items():
        for var, value in comp.start_values().items():
            out.append((f"{name}.{var}", float(value), comp.description.variables[var].unit))
    return out


def _xml_bytes(root) -> bytes:
    from lxml import etree

    return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)


def export(scene, dest: Path | str, *, cache_dir: Path | None = None, overwrite: bool = False,
           progress: Callable[[str], None] | None = None) -> Path:
    """Write ``scene`` (a :class:`cosim.scenario.Scene`) as the SSP archive ``dest``.

    FMUs come from the cache (built on a miss).  An existing ``dest`` is kept unless
    ``overwrite``; the archive is written beside it and renamed, so a failure leaves nothing.
    Raises :class:`SspError` when the result would not validate (a bug, named element and line)."""

    dest = Path(dest)
    if dest.exists() and not overwrite:
        raise SspError(f"{dest} exists; choose another -o or pass --force to replace it")
    paths = build_components(scene, cache_dir=cache_dir, progress=progress)
    sources: dict[str, str] = {}
    members: dict[str, Path] = {}
    for name, path in paths.items():
        arc = f"resources/{Path(path).name}"
        if arc in members and Path(members[arc]).read_bytes() != Path(path).read_bytes():
            arc = f"resources/{name}_{Path(path).name}"
        members[arc] = Path(path)
        sources[name] = arc
    ssv_source = f"resources/{scene.name}.ssv"
    ssd = ssd_document(scene, sources, ssv_source)
    ssv = _ssv(scene.name, parameter_values(scene))
    for root, schema, what in ((ssd, "SystemStructureDescription.xsd", SSD),
                               (ssv, "SystemStructureParameterValues.xsd", ssv_source)):
        errs = schema_errors(root, schema)
        if errs:
            raise SspError(f"{dest}: the exported {what} does not validate (line {errs[0][0]}: {errs[0][1]})")
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", dir=dest.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr(SSD, _xml_bytes(ssd))
            zf.writestr(ssv_source, _xml_bytes(ssv))
            for arc, path in members.items():
                zf.write(path, arc)
        os.replace(tmp, dest)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return dest


