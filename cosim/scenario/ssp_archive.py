"""SSP 1.0 (System Structure and Parameterization) archives as a scene source, and the format's
names, units and schemas that the export (:mod:`cosim.run.ssp_export`) shares.

An ``.ssp`` is a zip holding ``SystemStructure.ssd`` (the system: components, their connectors,
connections, units, the default experiment) and resources (the FMUs, ``.ssv`` parameter sets).

Import (:func:`scene_tree`) turns an archive into a scene tree (the YAML structure of
:mod:`cosim.scenario`), so ``rpr-cosim run FILE.ssp`` and ``include: FILE.ssp`` validate and run
it like any scene: components become ``fmu:`` components (extracted into the FMU cache under
``ssp/<archive hash>/``), parameter bindings (inline or external ``.ssv``, system or component
level, with ``prefix``) become ``params:``/``start:`` by the FMU variable's causality, connections
become signals with their ``LinearTransformation`` and unit conversions folded into one
``factor``/``offset`` (SSP order: unit conversion first, then the transformation, unless
``suppressUnitConversion``).  Without our annotation the master is Jacobi with held inputs at the
smallest ``DefaultExperiment stepSize`` of the FMUs (else 1 ms), with a warning.

Refused at load with the element named (one line each): a missing or malformed ``.ssd``, a schema
violation, nested systems, signal dictionaries, non-FMU or model-exchange components, a component
source not in the archive, a connector that the FMU does not have or with the wrong kind,
connections to the system's own connectors, Boolean/Integer/Enumeration mappings, parameter
mappings, non-Real parameter values, units that do not convert.
"""
from __future__ import annotations

import os
import tempfile
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fmus.cache import file_digest

from ..errors import UserError
from .problems import Problem, suggest
from .yamlfile import YList, YMap, _display
from ..slaves.archive import archive_problem
from ..outputs import confined
from ..slaves.description import describe_fmu
from ..readers import loads_json
from ..master.algorithms.ecco import OPTIONS
from .osp import ECCO_ELEMENTS, ecco_options

SSD = "SystemStructure.ssd"
NS = {
    "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
    "ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
    "ssv": "http://ssp-standard.org/SSP1/SystemStructureParameterValues",
    "ssm": "http://ssp-standard.org/SSP1/SystemStructureParameterMapping",
    "ssb": "http://ssp-standard.org/SSP1/SystemStructureSignalDictionary",
    "rpr": "https://github.com/rpr-cosim/ssp/1.0",
    "osp": "http://opensimulationplatform.com/SSP/OSPAnnotations",
}
#: libcosim's annotation of the default experiment (its algorithm and base step)
OSP_ANNOTATION = "com.opensimulationplatform"
MASTER_ANNOTATION = "org.rpr-cosim.master"
COMPONENT_ANNOTATION = "org.rpr-cosim.component"
BOND_ANNOTATION = "org.rpr-cosim.bond"
FMU_TYPE = "application/x-fmu-sharedlibrary"
SSV_TYPE = "application/x-ssp-parameter-set"
#: Master used for an SSP without our annotation (FMPy's loop is the same fixed-step Jacobi).
FOREIGN_MASTER = {"algorithm": "jacobi", "inputs": "hold"}
BASE_UNITS = ("kg", "m", "s", "A", "K", "mol", "cd", "rad")


class SspError(UserError):
    """An SSP that cannot be written or read; the message names the file and the element."""


def _q(prefix: str, tag: str) -> str:
    return f"{{{NS[prefix]}}}{tag}"


def _num(x: float) -> str:
    """A float as the shortest text that reads back to the same double."""
    return repr(float(x))


# --- schemas ----------------------------------------------------------------------------------
def schema_dir() -> Path:
    """The SSP 1.0 XML schemas shipped with FMPy."""
    import fmpy.ssp

    return Path(fmpy.ssp.__file__).parent / "schema"


_SCHEMAS: dict[str, Any] = {}


def schema_errors(root, schema: str) -> list[tuple[int, str]]:
    """(line, message) of every violation of ``schema`` (a file name in :func:`schema_dir`)."""
    from lxml import etree

    if schema not in _SCHEMAS:
        _SCHEMAS[schema] = etree.XMLSchema(file=str(schema_dir() / schema))
    xsd = _SCHEMAS[schema]
    if xsd.validate(root):
        return []
    return [(e.line, e.message.replace(f"{{{NS['ssd']}}}", "ssd:").replace(f"{{{NS['ssc']}}}", "ssc:")
             .replace(f"{{{NS['ssv']}}}", "ssv:")) for e in xsd.error_log]


# --- units ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Unit:
    """A unit as SSP defines it: ``value_SI = factor * value + offset`` with base exponents."""

    name: str
    factor: float
    offset: float
    exponents: tuple[tuple[str, int], ...]


def our_unit(name: str) -> Unit | None:
    """The unit ``name`` from our unit grammar (:func:`fmus.model_description.parse_unit`), or None."""
    from fmus.model_description import parse_unit

    try:
        factor, exps = parse_unit(name)
    except ValueError:
        return None
    return Unit(name, factor, 0.0, tuple(sorted(exps.items())))


def _units_xml(parent, names: Iterable[str], ns: str) -> None:
    from lxml import etree

    units = [u for u in (our_unit(n) for n in sorted(set(names)) if n) if u is not None]
    if not units:
        return
    node = etree.SubElement(parent, _q(ns, "Units"))
    for u in units:
        el = etree.SubElement(node, _q("ssc", "Unit"), name=u.name)
        attrs = {k: str(v) for k, v in u.exponents}
        if u.factor != 1.0:
            attrs["factor"] = _num(u.factor)
        etree.SubElement(el, _q("ssc", "BaseUnit"), attrs)


def _read_units(node) -> dict[str, Unit]:
    out: dict[str, Unit] = {}
    if node is None:
        return out
    for u in node.findall("ssc:Unit", NS):
        b = u.find("ssc:BaseUnit", NS)
        attrs = dict(b.attrib) if b is not None else {}
        exps = tuple(sorted((k, int(attrs[k])) for k in BASE_UNITS if int(attrs.get(k, 0))))
        out[u.get("name")] = Unit(u.get("name"), float(attrs.get("factor", 1.0)), float(attrs.get("offset", 0.0)), exps)
    return out


def conversion(src: str, dst: str, units: dict[str, Unit]) -> tuple[float, float] | None:
    """``(a, b)`` with ``value_dst = a * value_src + b``; (1, 0) when either unit is empty or they
    are equal; None when they do not convert (unknown unit or other dimensions)."""
    if not src or not dst or src == dst or src == "1" or dst == "1":
        return 1.0, 0.0
    us, ud = units.get(src) or our_unit(src), units.get(dst) or our_unit(dst)
    if us is None or ud is None or us.exponents != ud.exponents:
        return None
    return us.factor / ud.factor, (us.offset - ud.offset) / ud.factor


def _compose(*maps: tuple[float, float]) -> tuple[float, float]:
    a, b = 1.0, 0.0
    for f, o in maps:  # apply in order: x -> f x + o
        a, b = f * a, f * b + o
    return a, b



# --- import -----------------------------------------------------------------------------------
class _Reader:
    """Reads one archive into a scene tree, collecting problems (file, line, message)."""

    def __init__(self, path: Path, problems: list, cache_dir: Path | None = None):

        self.path, self.problems, self.cache_dir = Path(path), problems, cache_dir
        self.label = _display(self.path)
        self.where_ssd = f"{self.label}/{SSD}"
        self.units: dict[str, Unit] = {}

    def err(self, line: int | None, msg: str, where: str | None = None) -> None:

        self.problems.append(Problem(where or self.where_ssd, line or 0, msg))

    def warn(self, line: int | None, msg: str) -> None:

        self.problems.append(Problem(self.where_ssd, line or 0, msg, "warning"))

    def loc(self, el) -> tuple[str, int]:
        return (self.where_ssd, el.sourceline or 0)

    # archive -------------------------------------------------------------------------------------
    def read(self):
        from lxml import etree


        problem = archive_problem(self.path, "SSP", None)
        if problem and not problem.startswith("not an SSP"):  # names and sizes before anything is read
            self.err(0, problem, self.label)
            return None
        try:
            zf = zipfile.ZipFile(self.path)
        except (zipfile.BadZipFile, OSError) as exc:
            self.err(0, f"not an SSP archive (a zip file expected): {exc}", self.label)
            return None
        with zf:
            names = set(zf.namelist())
            if SSD not in names:
                self.err(0, f"{SSD} is missing; an SSP archive holds its system description there "
                            f"(found: {', '.join(sorted(names)[:5]) or 'nothing'})", self.label)
                return None
            try:
                root = etree.fromstring(zf.read(SSD))
            except etree.XMLSyntaxError as exc:
                self.err(exc.lineno, f"XML syntax: {exc.msg}")
                return None
            errs = schema_errors(root, "SystemStructureDescription.xsd")
            for line, msg in errs:
                self.err(line, f"schema: {msg}")
            if errs:
                return None
            self.zf, self.names = zf, names
            self.units = _read_units(root.find("ssd:Units", NS))
            return self.tree(root)

    def extract(self, member: str) -> Path:
        """``member`` extracted under the FMU cache (``ssp/<archive hash>/``), once."""
        from fmus import cache_root

        if not hasattr(self, "digest"):
            self.digest = file_digest(self.path)[:16]

        dest = confined(cache_root(self.cache_dir) / "ssp" / self.digest, member)
        if not dest.is_file():
            dest.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=dest.parent)
            with os.fdopen(fd, "wb") as fh:
                fh.write(self.zf.read(member))
            os.replace(tmp, dest)
        return dest

    # the system ------------------------------------------------------------------------------------
    def tree(self, root):

        system = root.find("ssd:System", NS)
        tree = YMap()
        tree.where = self.loc(root)
        ok = self.unsupported(system)
        comps = self.components(system)
        if not ok or any(p.severity == "error" for p in self.problems):
            return None  # connections to a refused component would only repeat the reason
        for bind_el, binding in self.bindings(system, prefix_required=True):
            self.apply(binding, comps, bind_el, None)
        master, outputs, name = self.master(root, comps)
        conns = self.connections(system, comps)
        if any(p.severity == "error" for p in self.problems) or conns is None:
            return None
        tree["name"] = name or root.get("name")
        tree.locs["name"] = self.loc(root)
        if root.get("description"):
            tree["description"] = root.get("description")
        exp = root.find("ssd:DefaultExperiment", NS)
        stop = float(exp.get("stopTime")) if exp is not None and exp.get("stopTime") is not None else None
        if stop is None:
            self.warn(root.sourceline, "no DefaultExperiment stopTime; running 1 s (set stop_time=...)")
            stop = 1.0
        tree["stop_time"] = stop
        tree.locs["stop_time"] = self.loc(exp if exp is not None else root)
        if exp is not None and exp.get("startTime") is not None and float(exp.get("startTime")) != 0.0:
            tree["start_time"] = float(exp.get("startTime"))
            tree.locs["start_time"] = self.loc(exp)
        cmap = YMap()
        cmap.where = self.loc(system)
        for cname, (el, spec, _) in comps.items():
            cmap[cname] = spec
            cmap.locs[cname] = self.loc(el)
        tree["components"] = cmap
        clist = YList()
        clist.where = self.loc(system)
        for text, el in conns:
            clist.append(text)
            clist.locs.append(self.loc(el))
        tree["connections"] = clist
        tree["master"] = master
        tree.locs["master"] = master.where
        if outputs is not None:
            tree["outputs"] = outputs
            tree.locs["outputs"] = outputs.where
        return tree

    def unsupported(self, system) -> bool:
        ok = True
        for tag, what in (("ssd:Elements/ssd:System", "a nested system (flatten it into one system)"),
                          ("ssd:Elements/ssd:SignalDictionaryReference", "a signal dictionary reference"),
                          ("ssd:SignalDictionaries", "signal dictionaries"),
                          ("ssd:Connectors/ssd:Connector", "a connector of the system itself (system inputs "
                                                            "and outputs)")):
            for el in system.findall(tag, NS):
                self.err(el.sourceline, f"element {el.tag.split('}')[1]} {el.get('name') or ''!s}: {what} is not "
                                        f"supported by rpr-cosim".replace("  ", " "))
                ok = False
        return ok

    def components(self, system):

        out: dict[str, tuple[Any, Any, Any]] = {}
        for el in system.findall("ssd:Elements/ssd:Component", NS):
            name = el.get("name")
            kind = el.get("type", FMU_TYPE)
            if kind != FMU_TYPE:
                self.err(el.sourceline, f"component {name!r}: type {kind!r} is not supported (expected {FMU_TYPE})")
                continue
            implementation = el.get("implementation", "any")
            if implementation == "ScheduledExecution":
                self.err(el.sourceline, f"component {name!r}: implementation ScheduledExecution is not supported; "
                                        f"rpr-cosim runs co-simulation and model-exchange FMUs")
                continue
            interface = {"ModelExchange": "model_exchange", "CoSimulation": "co_simulation"}.get(implementation)
            src = el.get("source")
            member = src[2:] if src.startswith("./") else src
            parts = member.replace("\\", "/").split("/")
            if member.startswith(("/", "\\")) or ".." in parts or ":" in parts[0]:
                self.err(el.sourceline, f"component {name!r}: source {src!r} points outside the archive (an absolute "
                                        f"path or '..'); sources are relative to the archive's root")
                continue
            if member not in self.names:
                near = [n for n in self.names if n.endswith(".fmu")]
                self.err(el.sourceline, f"component {name!r}: source {src!r} is not in the archive "
                                        f"(FMUs in it: {', '.join(sorted(near)) or 'none'})")
                continue
            fmu = self.extract(member)
            try:
                desc = describe_fmu(fmu, interface)
            except UserError as exc:
                self.err(el.sourceline, f"component {name!r}: {exc}")
                continue
            if not self.check_connectors(el, name, desc):
                continue
            spec = YMap({"fmu": str(fmu)})
            spec.where = self.loc(el)
            spec.locs = {"fmu": self.loc(el)}
            if interface is not None:  # SSP implementation="ModelExchange" / "CoSimulation"
                spec["interface"] = interface
                spec.locs["interface"] = spec.where
            guards = self.guard_data(el, name)
            if guards is not None:
                spec["guard_data"] = guards
                spec.locs["guard_data"] = spec.where
            out[name] = (el, spec, desc)
        for name, (el, spec, desc) in out.items():
            for bind_el, binding in self.bindings(el):
                self.apply(binding, out, bind_el, name)
        return out

    def guard_data(self, el, name: str):
        """What the physical guards know of component ``el`` (its catalog ratings, pose and
        geometry), from our component annotation's ``guards`` attribute; None without one."""
        model = el.find(f"ssd:Annotations/ssc:Annotation[@type='{COMPONENT_ANNOTATION}']/rpr:Model", NS)
        text = model.get("guards") if model is not None else None
        if not text:
            return None

        try:
            data = loads_json(text, "the guards annotation")
        except UserError as exc:
            self.err(model.sourceline, f"component {name!r}: {exc}")
            return None
        if not isinstance(data, dict):
            self.err(model.sourceline, f"component {name!r}: the guards annotation must be a JSON object")
            return None
        return data

    def check_connectors(self, el, name: str, desc) -> bool:

        ok = True
        for c in el.findall("ssd:Connectors/ssd:Connector", NS):
            cname, kind = c.get("name"), c.get("kind")
            var = desc.variables.get(cname)
            if var is None:
                self.err(c.sourceline, f"component {name!r}: connector {cname!r} does not exist in its FMU "
                                       f"{Path(el.get('source')).name}{suggest(cname, desc.variables)}")
                ok = False
                continue
            if kind != var.causality:
                self.err(c.sourceline, f"component {name!r}: connector {cname!r} is declared {kind} but the FMU's "
                                       f"variable is {var.causality}")
                ok = False
                continue
            typ = next((t for t in c if isinstance(t.tag, str) and t.tag.startswith(f"{{{NS['ssc']}}}")), None)
            if typ is not None and typ.tag.split("}")[1] != "Real":
                self.err(c.sourceline, f"component {name!r}: connector {cname!r} is {typ.tag.split('}')[1]}; only "
                                       f"Real connectors can be connected so far")
                ok = False
        return ok

    def connector_unit(self, comp_el, name: str) -> str | None:
        for c in comp_el.findall("ssd:Connectors/ssd:Connector", NS):
            if c.get("name") == name:
                real = c.find("ssc:Real", NS)
                return real.get("unit") if real is not None else None
        return None

    # parameters ------------------------------------------------------------------------------------
    def bindings(self, el, prefix_required: bool = False):
        """(element, [(name, value, unit, element)]) of each parameter binding of ``el``."""
        from lxml import etree

        for b in el.findall("ssd:ParameterBindings/ssd:ParameterBinding", NS):
            if b.find("ssd:ParameterMapping", NS) is not None:
                self.err(b.sourceline, "element ParameterMapping: parameter mappings are not supported; "
                                       "name the FMU variables in the parameter set")
                continue
            kind = b.get("type", SSV_TYPE)
            if kind != SSV_TYPE:
                self.err(b.sourceline, f"ParameterBinding of type {kind!r} is not supported (expected {SSV_TYPE})")
                continue
            sets = []
            src = b.get("source")
            if src is not None:
                member = src[2:] if src.startswith("./") else src
                where = f"{self.label}/{member}"
                if member not in self.names:
                    self.err(b.sourceline, f"ParameterBinding: source {src!r} is not in the archive")
                    continue
                try:
                    root = etree.fromstring(self.zf.read(member))
                except etree.XMLSyntaxError as exc:
                    self.err(exc.lineno, f"XML syntax: {exc.msg}", where)
                    continue
                errs = schema_errors(root, "SystemStructureParameterValues.xsd")
                for line, msg in errs:
                    self.err(line, f"schema: {msg}", where)
                if errs:
                    continue
                sets.append((root, where))
            for ps in b.findall("ssd:ParameterValues/ssv:ParameterSet", NS):
                sets.append((ps, self.where_ssd))
            values = []
            prefix = b.get("prefix", "")
            for ps, where in sets:
                units = {**self.units, **_read_units(ps.find("ssv:Units", NS))}
                for p in ps.findall("ssv:Parameters/ssv:Parameter", NS):
                    real = p.find("ssv:Real", NS)
                    if real is None:
                        kind = next((t.tag.split("}")[1] for t in p if isinstance(t.tag, str)), "?")
                        self.err(p.sourceline, f"parameter {p.get('name')!r}: {kind} values are not supported "
                                               f"(only Real)", where)
                        continue
                    values.append((prefix + p.get("name"), float(real.get("value")), real.get("unit") or "", units,
                                   (where, p.sourceline or 0)))
            yield b, values

    def apply(self, values, comps, bind_el, owner: str | None) -> None:
        """Put each bound value into its component's ``params`` or ``start`` (by causality)."""

        for name, value, unit, units, loc in values:
            if owner is None:
                comp = next((c for c in sorted(comps, key=len, reverse=True) if name.startswith(c + ".")), None)
                if comp is None:
                    self.warn(bind_el.sourceline, f"parameter {name!r} names no component of the system"
                                                  f"{suggest(name.split('.')[0], comps)}; ignored (SSP ignores "
                                                  f"unmatched names)")
                    continue
                var = name[len(comp) + 1:]
            else:
                comp, var = owner, name
            el, spec, desc = comps[comp]
            v = desc.variables.get(var)
            if v is None:
                self.warn(bind_el.sourceline, f"component {comp!r} has no variable {var!r}"
                                              f"{suggest(var, desc.variables)}; the binding is ignored")
                continue
            conv = conversion(unit, v.unit, units)
            if conv is None:
                self.problems.append(_problem(loc, f"parameter {name!r} in {unit!r} does not convert to the FMU's "
                                                   f"unit {v.unit!r}"))
                continue
            key = "params" if v.causality == "parameter" else "start"
            if key not in spec:
                spec[key] = YMap()
                spec[key].where = loc
                spec.locs[key] = loc
            spec[key][var] = conv[0] * value + conv[1]
            spec[key].locs[var] = loc

    # connections -------------------------------------------------------------------------------
    def connections(self, system, comps):
        out = []
        for el in system.findall("ssd:Connections/ssd:Connection", NS):
            a, ac, b, bc = (el.get("startElement"), el.get("startConnector"), el.get("endElement"),
                            el.get("endConnector"))
            label = f"{a or '(system)'}.{ac} -> {b or '(system)'}.{bc}"
            if not a or not b:
                self.err(el.sourceline, f"connection {label}: connections to the system's own connectors are not "
                                        f"supported")
                continue
            bad = False
            for comp, conn in ((a, ac), (b, bc)):
                if comp not in comps:
                    self.err(el.sourceline, f"connection {label}: unknown component {comp!r}")
                    bad = True
                elif not any(c.get("name") == conn for c in comps[comp][0].findall("ssd:Connectors/ssd:Connector", NS)):
                    self.err(el.sourceline, f"connection {label}: component {comp!r} declares no connector {conn!r}")
                    bad = True
            if bad:
                continue
            for tag in ("BooleanMappingTransformation", "IntegerMappingTransformation",
                        "EnumerationMappingTransformation"):
                if el.find(f"ssc:{tag}", NS) is not None:
                    self.err(el.sourceline, f"connection {label}: element {tag} is not supported")
                    bad = True
            if bad:
                continue
            fa, fb = comps[a][2].variables[ac].unit, comps[b][2].variables[bc].unit
            ua, ub = self.connector_unit(comps[a][0], ac) or fa, self.connector_unit(comps[b][0], bc) or fb
            steps = [conversion(fa, ua, self.units)]
            if el.get("suppressUnitConversion", "false") not in ("true", "1"):
                steps.append(conversion(ua, ub, self.units))
            lt = el.find("ssc:LinearTransformation", NS)
            if lt is not None:
                steps.append((float(lt.get("factor", 1.0)), float(lt.get("offset", 0.0))))
            steps.append(conversion(ub, fb, self.units))
            if any(s is None for s in steps):
                self.err(el.sourceline, f"connection {label}: units {fa or ua!r} -> {ub or fb!r} do not convert")
                continue
            factor, offset = _compose(*steps)
            text = f"{a}.{ac} -> {b}.{bc}"
            if factor != 1.0:
                text += f" * {factor!r}"
            if offset != 0.0:
                text += f" {'-' if offset < 0 else '+'} {abs(offset)!r}"
            out.append((text, el))
        return out

    # master ------------------------------------------------------------------------------------------
    def master(self, root, comps):
        """(master mapping, outputs list or None, scene name or None) from our annotation or defaults."""

        exp = root.find("ssd:DefaultExperiment", NS)
        ann = root.find(f"ssd:DefaultExperiment/ssd:Annotations/ssc:Annotation[@type='{MASTER_ANNOTATION}']/rpr:Master",
                        NS)
        node = YMap()
        osp = root.find(f"ssd:DefaultExperiment/ssd:Annotations/ssc:Annotation[@type='{OSP_ANNOTATION}']/osp:Algorithm",
                        NS)
        if ann is None and osp is not None:
            return self.osp_master(osp), None, None
        if ann is None:
            step = self.foreign_step(comps)
            node.update({**FOREIGN_MASTER, "step": step})
            node.where = self.loc(exp if exp is not None else root)
            node.locs = {k: node.where for k in node}
            self.warn(node.where[1], f"no {MASTER_ANNOTATION} annotation: running {FOREIGN_MASTER['algorithm']} with "
                                     f"{FOREIGN_MASTER['inputs']} inputs at {step:g} s (override with --set master.step=...)")
            return node, None, None
        node.where = self.loc(ann)
        for key, attr in (("algorithm", "algorithm"), ("inputs", "inputs"), ("engine", "engine")):
            if ann.get(attr) is not None:
                node[key] = ann.get(attr)
        for key, attr in (("step", "step"), ("output_interval", "outputInterval"), ("tolerance", "tolerance")):
            if ann.get(attr) is not None:
                node[key] = float(ann.get(attr))
        if ann.get("order"):
            node["order"] = YList(ann.get("order").split())
        node.locs = {k: node.where for k in node}
        outs = ann.findall("rpr:Output", NS)
        outputs = None
        if outs:
            outputs = YList([o.get("name") for o in outs])
            outputs.where = self.loc(ann)
            outputs.locs = [self.loc(o) for o in outs]
        return node, outputs, ann.get("scene")

    def osp_master(self, el):
        """libcosim's annotation: ``FixedStepAlgorithm baseStepSize`` -> jacobi at that step (libcosim's
        fixed step exchanges at t_k, then steps every slave); ``EccoAlgorithm`` -> ecco."""

        node = YMap()
        node.where = self.loc(el)
        fixed, ecco = el.find("osp:FixedStepAlgorithm", NS), el.find("osp:EccoAlgorithm", NS)
        alg = fixed if fixed is not None else ecco
        if alg is None:
            kids = [c.tag.split("}")[-1] for c in el if isinstance(c.tag, str)]
            self.err(el.sourceline, f"{OSP_ANNOTATION} Algorithm: {', '.join(kids) or 'nothing'}; expected "
                                    f"FixedStepAlgorithm or EccoAlgorithm")
            return node
        attr = "baseStepSize" if alg is fixed or alg.get("baseStepSize") is not None else "stepSize"
        try:
            step = float(alg.get(attr))
        except (TypeError, ValueError):
            self.err(alg.sourceline, f"{alg.tag.split('}')[-1]}: {attr} = {alg.get(attr)!r}; expected a step in seconds")
            return node
        node.update({"algorithm": "jacobi" if alg is fixed else "ecco", "step": step})
        if alg is ecco:  # the EccoConfiguration of OspSystemStructure.xml as attributes (cosim.scenario.osp)

            given = {}
            for key in ECCO_ELEMENTS:
                raw = alg.get(key[0].lower() + key[1:])
                if raw is not None:
                    try:
                        given[key] = float(raw)
                    except ValueError:
                        self.err(alg.sourceline, f"EccoAlgorithm: {key[0].lower() + key[1:]} = {raw!r}; expected a number")
            values, notes = ecco_options(given, next(o.default for o in OPTIONS if o.name == "k_i"))
            for _elem, text in notes:
                loc = self.loc(alg)
                self.problems.append(Problem(loc[0], loc[1], text.replace("EccoConfiguration ", "EccoAlgorithm "), "note"))
            opts = YMap(values)
            opts.where = self.loc(alg)
            opts.locs = {k: self.loc(alg) for k in values}
            if opts:
                node["options"] = opts
        node.locs = {k: self.loc(alg) for k in node}
        return node

    def foreign_step(self, comps) -> float:
        import fmpy

        steps = []
        for _, spec, _ in comps.values():
            md = fmpy.read_model_description(spec["fmu"], validate=False)
            if md.defaultExperiment is not None and md.defaultExperiment.stepSize:
                steps.append(float(md.defaultExperiment.stepSize))
        return min(steps) if steps else 1e-3


def _problem(loc: tuple[str, int], msg: str):

    return Problem(loc[0], loc[1], msg)


def scene_tree(path: Path | str, problems: list, *, cache_dir: Path | None = None):
    """The scene tree (:class:`cosim.scenario.YMap`) of the SSP archive ``path``, or None with the
    reasons appended to ``problems`` (see the module docstring for what is refused)."""
    return _Reader(Path(path), problems, cache_dir).read()
