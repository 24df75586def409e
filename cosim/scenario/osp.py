"""libcosim's system format: ``OspSystemStructure.xml`` read as a scene source (beside
:mod:`cosim.scenario.ssp_archive`), so ``rpr-cosim run OspSystemStructure.xml`` and ``include:`` of one
validate and run it like any scene.

What becomes what:

``Simulator name source stepSize``  a component ``fmu: source`` (relative to the file); its
    ``InitialValues`` (Real, Integer, Boolean, String) become ``params:`` or ``start:`` by the FMU
    variable's causality.  Step sizes: the master step is the largest simulator step (else
    ``BaseStepSize``), and a simulator with a smaller step runs at ``rate`` = master step / its step
    (:mod:`cosim.master.multirate`) when that ratio is whole; otherwise a one-line refusal with the
    numbers.  (libcosim exchanges a slower slave's values at its own step; we exchange at the
    master step: the same when all steps are equal.)
``VariableConnection``   a signal from whichever of the two variables is the FMU's output; with
    ``powerBond="NAME"`` the two connections of one name between two simulators become a power
    bond (a flange on each side: :meth:`ComponentChecks._flanges`), which ``ecco`` controls.
``VariableGroupConnection``  resolved through ``<source stem>_OspModelDescription.xml`` next to the
    FMU: ``Generic`` groups connect variable by variable in order; mechanical and electrical ports
    (``LinearMechanicalPort``, ``AngularMechanicalPort``, ... : an effort group and a flow group)
    become power bonds, one per variable pair.
``SignalConnection`` through ``Functions``  a ``LinearTransformation`` (``in`` -> ``out``) folds into
    the connection's factor and offset; a ``Sum`` (``inputCount``: signals ``in[0]`` ..
    ``in[inputCount-1]`` and ``out``, 0-based as libcosim's) and a ``VectorSum`` (``inputCount`` and
    ``dimension``; connected by ``SignalGroupConnection`` to variable groups of ``dimension``
    variables, element by element in the group's order) become a component of the function's name,
    ``model: sum`` (:mod:`models.blocks.sums`: a memoryless block, which fixed-step Jacobi evaluates
    within the exchange, so it adds no delay: libcosim's convention).  Every signal of a function
    must be connected, once.
``Algorithm``   ``fixedStep`` -> ``jacobi`` (libcosim's fixed-step algorithm exchanges at t_k, then steps
    every slave), ``ecco`` -> ``ecco`` with ``EccoConfiguration`` mapped onto its options by
    :func:`ecco_options`: the steps, step ratios and PI gains exactly, the safety factor and the
    tolerances converted (stated in the function and, per run, in notes in its output and sidecar),
    with what still differs said in a note.
``StartTime``, ``EndTime``, ``BaseStepSize``  the scene's start time, stop time and step.

Bad input gets one line naming the file, the line and what is expected.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .problems import Problem
from ..errors import UserError
from ..readers import open_regular
from .yamlfile import YList, YMap, _display
from ..master.algorithms.ecco import OPTIONS
from ..slaves.description import describe_fmu
from .problems import suggest

ROOT_TAG = "OspSystemStructure"
ALGORITHMS = {"fixedStep": "jacobi", "ecco": "ecco"}
#: EccoConfiguration elements (libcosim's ``ecco_algorithm_params``) that are our ecco options exactly
#: (:mod:`cosim.master.algorithms.ecco`): the first step, the step bounds, the bounds of the step ratio and
#: the PI controller's exponents (libcosim: ratio = SafetyFactor * eps^-(k_i + k_p) * eps_prev^k_p, ours
#: (safety / eps)^k_i * (eps_prev / eps)^k_p: the same exponents)
ECCO_EXACT = {"StepSize": "h_init", "MinimumStepSize": "h_min", "MaximumStepSize": "h_max",
              "MinimumChangeRate": "fac_min", "MaximumChangeRate": "fac_max", "ProportionalGain": "k_p",
              "IntegralGain": "k_i"}
#: the ones converted (see :func:`ecco_options`)
ECCO_CONVERTED = ("SafetyFactor", "RelativeTolerance", "AbsoluteTolerance")
ECCO_ELEMENTS = tuple(ECCO_EXACT) + ECCO_CONVERTED
#: what differs whatever the options: said once per run that maps an EccoConfiguration
ECCO_DIFFERENCES = ("ecco: libcosim's residual of a bond is |P_a - P_b| at the step's end times the step, combined "
                    "over the bonds as a root mean square; ours integrates P_a - P_b over the step (trapezoidal rule) "
                    "and takes the largest over the bonds (the same for one bond but for the rule)")


def ecco_options(given: dict[str, float], k_i_default: float) -> tuple[dict[str, float], list[tuple[str, str]]]:
    """Our ``ecco`` options for libcosim's ECCO parameters ``given`` (element name -> value) and the
    notes saying each conversion and what does not map, as (element, one line).

    Exact: :data:`ECCO_EXACT`.  Converted:

    * ``SafetyFactor`` s: libcosim multiplies the step ratio by s, ours aims the scaled residual at
      ``safety`` inside the integral term, ``(safety / eps)^k_i``: the same ratio for
      ``safety = s^(1/k_i)`` (with k_i = IntegralGain, else our default); not with k_i = 0.
    * ``AbsoluteTolerance`` a and ``RelativeTolerance`` r: libcosim scales the energy residual dE of a
      step [J] (largest over the bonds) by ``a + r * dE``, so its relative term is relative to the
      residual itself and ``eps <= 1`` means ``dE <= a / (1 - r)``: an absolute bound.  Ours scales by
      ``atol + rtol * E`` (E the energy the bond carried): ``atol = a / (1 - r)`` and ``rtol`` its
      smallest value (1e-12: no relative term) give the same bound; not with r >= 1.
    * ``MinimumStepSize``: the same floor; libcosim goes on at it over tolerance, which ours does with
      ``floor_steps = 0`` (its default ends the run as unstable after 100 such steps in a row).
    """
    opts = {ECCO_EXACT[k]: v for k, v in given.items() if k in ECCO_EXACT}
    notes: list[tuple[str, str]] = []
    if "SafetyFactor" in given:
        sf, k_i = given["SafetyFactor"], opts.get("k_i", k_i_default)
        if k_i > 0 and sf > 0:
            opts["safety"] = sf ** (1.0 / k_i)
            notes.append(("SafetyFactor", f"EccoConfiguration SafetyFactor {sf:g} -> ecco safety {opts['safety']:.6g} "
                                          f"(= SafetyFactor^(1/k_i), k_i = {k_i:g}: libcosim multiplies the step ratio "
                                          f"by it, ours aims the scaled residual at safety; the same step ratio)"))
        else:
            notes.append(("SafetyFactor", f"EccoConfiguration SafetyFactor {sf:g} is not mapped: with k_i = {k_i:g} "
                                          f"our controller has no factor to match it; ecco keeps its safety"))
    if "AbsoluteTolerance" in given or "RelativeTolerance" in given:
        a, r = given.get("AbsoluteTolerance"), given.get("RelativeTolerance", 0.0)
        if a is None:
            notes.append(("RelativeTolerance", "EccoConfiguration RelativeTolerance is not mapped without "
                                               "AbsoluteTolerance; ecco keeps its rtol and atol"))
        elif r >= 1.0 or r < 0.0:
            notes.append(("RelativeTolerance", f"EccoConfiguration RelativeTolerance {r:g} is not mapped (libcosim's "
                                               f"residual is then never over tolerance); ecco keeps its rtol and atol"))
        else:
            opts["atol"], opts["rtol"] = a / (1.0 - r), 1e-12
            notes.append(("AbsoluteTolerance", f"EccoConfiguration AbsoluteTolerance {a:g}, RelativeTolerance {r:g} -> "
                                               f"ecco atol {opts['atol']:.9g} J, rtol 1e-12 (libcosim's relative term is "
                                               f"relative to the residual itself: eps <= 1 is dE <= atol/(1 - rtol), an "
                                               f"absolute bound on a step's energy residual)"))
    if "MinimumStepSize" in given:
        opts["floor_steps"] = 0
        notes.append(("MinimumStepSize", f"EccoConfiguration MinimumStepSize {given['MinimumStepSize']:g} s -> ecco h_min "
                                         f"and floor_steps 0: as libcosim, the run goes on at h_min over tolerance (such "
                                         f"steps are counted in the statistics, 'over tolerance'; without floor_steps 0 "
                                         f"ecco ends a run as unstable after 100 of them in a row)"))
    if given:
        notes.append(("", ECCO_DIFFERENCES))
    return opts, notes


#: OSP port groups: (effort group, flow group)
PORTS = {"LinearMechanicalPort": ("Force", "LinearVelocity"),
         "AngularMechanicalPort": ("Torque", "AngularVelocity"),
         "ElectromagneticPort": ("Voltage", "Current"),
         "HydraulicPort": ("Pressure", "VolumeFlowRate"),
         "LinearMechanicalQuasiPort": ("Force", "LinearDisplacement"),
         "AngularMechanicalQuasiPort": ("Torque", "AngularDisplacement")}


def _local(el) -> str:
    return el.tag.split("}")[-1] if isinstance(el.tag, str) else ""


def _kids(el, name: str | None = None) -> list:
    return [c for c in el if isinstance(c.tag, str) and (name is None or _local(c) == name)]


def _kid(el, name: str):
    found = _kids(el, name)
    return found[0] if found else None


def is_osp(path: Path) -> bool:
    """Whether ``path`` is an XML file whose root element is ``OspSystemStructure``."""
    return root_tag(path) == ROOT_TAG


def root_tag(path: Path) -> str | None:
    """The local name of the root element of the XML file ``path`` (any encoding XML allows:
    UTF-8, UTF-16 with its byte order mark, a declared one; any length of prolog, comments and
    processing instructions before it), read up to that element only; None when ``path`` is not
    a ``.xml`` regular file within the size limit (:mod:`cosim.readers`) or not XML."""
    if Path(path).suffix.lower() != ".xml":
        return None
    from lxml import etree


    try:
        with open_regular(path, "XML file") as fh:
            for _, el in etree.iterparse(fh, events=("start",), resolve_entities=False, no_network=True,
                                         huge_tree=False, load_dtd=False):
                return etree.QName(el).localname
    except (UserError, etree.XMLSyntaxError, OSError, ValueError):
        return None
    return None


class _Reader:
    def __init__(self, path: Path, problems: list[Problem]):

        self.path, self.problems = Path(path), problems
        self.label = _display(self.path)
        self.comps: dict[str, tuple] = {}  # name -> (element, spec YMap, description, fmu path)
        self.broken_functions: set[str] = set()  # functions refused at their definition

    def err(self, el, msg: str) -> None:
        self.problems.append(Problem(self.label, getattr(el, "sourceline", 0) or 0, msg))

    def loc(self, el) -> tuple[str, int]:
        return (self.label, getattr(el, "sourceline", 0) or 0)

    def number(self, el, text: str | None, what: str) -> float | None:
        try:
            x = float(text)
        except (TypeError, ValueError):
            self.err(el, f"{what} = {text!r}; expected a number")
            return None
        if x != x or x in (float("inf"), float("-inf")):
            self.err(el, f"{what} = {text!r}; expected a finite number")
            return None
        return x

    def read(self):
        from lxml import etree

        try:
            root = etree.parse(str(self.path)).getroot()
        except etree.XMLSyntaxError as exc:
            self.problems.append(Problem(self.label, exc.lineno or 0, f"XML syntax: {exc.msg}"))
            return None
        except OSError as exc:
            self.problems.append(Problem(self.label, 0, f"cannot read the file ({exc})"))
            return None
        if _local(root) != ROOT_TAG:
            self.err(root, f"root element {_local(root)!r}; an OSP system structure has <{ROOT_TAG}>")
            return None
        return self.tree(root)

    # ------------------------------------------------------------------------------------------
    def tree(self, root):

        known = {"StartTime", "EndTime", "BaseStepSize", "Algorithm", "Simulators", "Functions", "Connections",
                 "EccoConfiguration"}
        for el in _kids(root):
            if _local(el) not in known:
                self.err(el, f"element <{_local(el)}> is not part of OspSystemStructure (expected "
                             f"{', '.join(sorted(known))})")
        base = self.time(root, "BaseStepSize")
        start, stop = self.time(root, "StartTime"), self.time(root, "EndTime")
        alg_el = _kid(root, "Algorithm")
        alg = (alg_el.text or "").strip() if alg_el is not None else "fixedStep"
        if alg not in ALGORITHMS:
            self.err(alg_el, f"Algorithm {alg!r}; expected one of {', '.join(ALGORITHMS)}")
            return None
        sims = _kid(root, "Simulators")
        if sims is None or not _kids(sims, "Simulator"):
            self.err(root, "no <Simulators>/<Simulator>; a system needs at least one simulator")
            return None
        steps: dict[str, float] = {}
        for el in _kids(sims, "Simulator"):
            self.simulator(el, steps)
        if any(p.severity == "error" for p in self.problems):
            return None
        master_step = max(list(steps.values()) + ([base] if base else []), default=None)
        if master_step is None:
            self.err(root, "no BaseStepSize and no simulator stepSize; give <BaseStepSize> in seconds")
            return None
        for name, (el, spec, _desc, _f) in self.comps.items():
            h = steps.get(name, base or master_step)
            ratio = master_step / h
            if abs(ratio - round(ratio)) > 1e-9 * ratio:
                self.err(el, f"simulator {name!r}: stepSize {h:g} s does not divide the master step {master_step:g} s "
                             f"(the largest step; ratio {ratio:.6g}); rpr-cosim steps a faster slave a whole number "
                             f"of times per master step")
            elif round(ratio) != 1:
                spec["rate"] = int(round(ratio))
                spec.locs["rate"] = self.loc(el)
        functions = self.functions(_kid(root, "Functions"))
        conns = YList()
        conns.where = self.loc(root)
        node = _kid(root, "Connections")
        for el in _kids(node) if node is not None else []:
            kind = _local(el)
            if kind == "VariableConnection":
                self.variable_connection(el, conns)
            elif kind == "VariableGroupConnection":
                self.group_connection(el, conns)
            elif kind in ("SignalConnection", "SignalGroupConnection"):
                self.signal_connection(el, functions, conns, group=kind == "SignalGroupConnection")
            else:
                self.err(el, f"<{kind}> connections are not supported (VariableConnection, VariableGroupConnection, "
                             f"SignalConnection and SignalGroupConnection are)")
        self.finish_functions(functions)
        if any(p.severity == "error" for p in self.problems):
            return None
        tree = YMap()
        tree.where = self.loc(root)
        tree["name"] = self.path.stem if self.path.stem != ROOT_TAG else self.path.parent.name
        tree.locs["name"] = self.loc(root)
        if stop is not None:
            tree["stop_time"] = stop
            tree.locs["stop_time"] = self.loc(_kid(root, "EndTime"))
        if start:
            tree["start_time"] = start
            tree.locs["start_time"] = self.loc(_kid(root, "StartTime"))
        cmap = YMap()
        cmap.where = self.loc(sims)
        for name, (el, spec, _d, _f) in self.comps.items():
            cmap[name] = spec
            cmap.locs[name] = self.loc(el)
        for name, spec in self.function_components(functions):
            cmap[name] = spec
            cmap.locs[name] = spec.where
        tree["components"] = cmap
        tree.locs["components"] = self.loc(sims)
        tree["connections"] = conns
        tree.locs["connections"] = conns.where
        master = YMap({"algorithm": ALGORITHMS[alg], "step": master_step})
        master.where = self.loc(alg_el if alg_el is not None else root)
        master.locs = {"algorithm": master.where, "step": master.where}
        opts = self.ecco(_kid(root, "EccoConfiguration"))
        if opts and ALGORITHMS[alg] == "ecco":
            master["options"] = opts
            master.locs["options"] = opts.where
        tree["master"] = master
        tree.locs["master"] = master.where
        return None if any(p.severity == "error" for p in self.problems) else tree

    def time(self, root, tag: str) -> float | None:
        el = _kid(root, tag)
        if el is None:
            return None
        x = self.number(el, (el.text or "").strip(), tag)
        if x is not None and (x < 0 or (tag == "BaseStepSize" and x <= 0)):
            self.err(el, f"{tag} = {x:g}; expected a {'positive' if tag == 'BaseStepSize' else 'non-negative'} "
                         f"time in seconds")
            return None
        return x

    def ecco(self, el):
        """The EccoConfiguration as ecco options (:func:`ecco_options`), its notes added."""

        if el is None:
            return None
        given, where = {}, {}
        for c in _kids(el):
            if _local(c) not in ECCO_ELEMENTS:
                self.err(c, f"EccoConfiguration: <{_local(c)}> is unknown (expected {', '.join(ECCO_ELEMENTS)})")
                continue
            x = self.number(c, (c.text or "").strip(), _local(c))
            if x is not None:
                given[_local(c)], where[_local(c)] = x, c
        k_i = next(o.default for o in OPTIONS if o.name == "k_i")
        values, notes = ecco_options(given, k_i)
        for elem, text in notes:
            self.problems.append(Problem(self.label, getattr(where.get(elem, el), "sourceline", 0) or 0, text, "note"))
        back = {v: k for k, v in ECCO_EXACT.items()} | {"safety": "SafetyFactor", "atol": "AbsoluteTolerance",
                                                         "rtol": "AbsoluteTolerance", "floor_steps": "MinimumStepSize"}
        opts = YMap()
        opts.where = self.loc(el)
        for key, x in values.items():
            opts[key] = x
            opts.locs[key] = self.loc(where.get(back[key], el))
        return opts

    # simulators ---------------------------------------------------------------------------------
    def simulator(self, el, steps: dict[str, float]) -> None:

        name, src = el.get("name"), el.get("source")
        if not name or not src:
            self.err(el, "a <Simulator> needs name= and source= (the FMU, relative to this file)")
            return
        if name in self.comps:
            self.err(el, f"simulator {name!r} is defined twice")
            return
        if "://" in src and not src.startswith("file://"):
            self.err(el, f"simulator {name!r}: source {src!r}: only local FMU files are supported (no proxy or "
                         f"remote URIs)")
            return
        fmu = (self.path.parent / src.removeprefix("file://")).resolve()
        if not fmu.is_file():
            self.err(el, f"simulator {name!r}: FMU {src!r} not found (looked in {fmu.parent})")
            return
        try:
            desc = describe_fmu(fmu)
        except UserError as exc:
            self.err(el, f"simulator {name!r}: {exc}")
            return
        if el.get("stepSize") is not None:
            h = self.number(el, el.get("stepSize"), f"simulator {name!r}: stepSize")
            if h is not None and h <= 0:
                self.err(el, f"simulator {name!r}: stepSize = {h:g}; expected a positive step in seconds")
            elif h is not None:
                steps[name] = h
        spec = YMap({"fmu": str(fmu)})
        spec.where = self.loc(el)
        spec.locs = {"fmu": self.loc(el)}
        ivs = _kid(el, "InitialValues")
        for iv in _kids(ivs, "InitialValue") if ivs is not None else []:
            self.initial_value(iv, name, spec, desc)
        self.comps[name] = (el, spec, desc, fmu)

    def initial_value(self, iv, comp: str, spec, desc) -> None:

        var = iv.get("variable")
        v = desc.variables.get(var or "")
        if v is None:
            self.err(iv, f"simulator {comp!r}: no variable {var!r}{suggest(str(var), desc.variables)}")
            return
        typed = _kids(iv)
        if len(typed) != 1 or _local(typed[0]) not in ("Real", "Integer", "Boolean", "String"):
            self.err(iv, f"simulator {comp!r}: InitialValue {var!r} needs one <Real|Integer|Boolean|String value=.../>")
            return
        kind, text = _local(typed[0]), typed[0].get("value")
        if text is None:
            self.err(typed[0], f"simulator {comp!r}: InitialValue {var!r}: <{kind}> has no value=")
            return
        expect = {"Real": ("Real", "Float64", "Float32"), "Integer": ("Integer", "Int32", "Enumeration"),
                  "Boolean": ("Boolean",), "String": ("String",)}[kind]
        if v.fmi_type not in expect and v.type not in expect:
            self.err(typed[0], f"simulator {comp!r}: InitialValue {var!r} is given as {kind} but the variable is "
                               f"{v.fmi_type or v.type}")
            return
        if kind == "Real":
            value = self.number(typed[0], text, f"simulator {comp!r}: {var}")
        elif kind == "Integer":
            try:
                value = int(text)
            except ValueError:
                self.err(typed[0], f"simulator {comp!r}: {var} = {text!r}; expected an integer")
                return
        elif kind == "Boolean":
            if text.strip().lower() not in ("true", "false", "1", "0"):
                self.err(typed[0], f"simulator {comp!r}: {var} = {text!r}; expected true, false, 1 or 0")
                return
            value = text.strip().lower() in ("true", "1")
        else:
            value = text
        if value is None:
            return
        key = "params" if v.causality in ("parameter", "structuralParameter") else "start"
        if key not in spec:
            spec[key] = YMap()
            spec[key].where = self.loc(iv)
            spec.locs[key] = self.loc(iv)
        spec[key][var] = value
        spec[key].locs[var] = self.loc(iv)

    # connections ----------------------------------------------------------------------------------
    def endpoint(self, el) -> tuple[str, str, str] | None:
        """(simulator, variable, causality) of a <Variable simulator= name=/>."""

        sim, var = el.get("simulator"), el.get("name")
        if sim not in self.comps:
            self.err(el, f"unknown simulator {sim!r}{suggest(str(sim), self.comps)}")
            return None
        desc = self.comps[sim][2]
        v = desc.variables.get(var or "")
        if v is None:
            self.err(el, f"simulator {sim!r} has no variable {var!r}{suggest(str(var), desc.variables)}")
            return None
        return sim, var, v.causality

    def pair(self, el, a, b) -> tuple | None:
        """(source, destination) endpoints of two variables: the output feeds the input."""
        if a[2] == "output" and b[2] in ("input", "parameter"):
            return a, b
        if b[2] == "output" and a[2] in ("input", "parameter"):
            return b, a
        self.err(el, f"connection {a[0]}.{a[1]} ({a[2]}) - {b[0]}.{b[1]} ({b[2]}): one side must be an output, the "
                     f"other an input")
        return None

    def add(self, conns, text: str, el) -> None:
        conns.append(text)
        conns.locs.append(self.loc(el))

    def variable_connection(self, el, conns) -> None:
        vs = _kids(el, "Variable")
        if len(vs) != 2:
            self.err(el, f"a VariableConnection joins two <Variable> elements, got {len(vs)}")
            return
        a, b = self.endpoint(vs[0]), self.endpoint(vs[1])
        if a is None or b is None:
            return
        p = self.pair(el, a, b)
        if p is None:
            return
        bond = el.get("powerBond")
        if bond:
            self.bond_half(el, bond, p, conns)
        else:
            self.add(conns, f"{p[0][0]}.{p[0][1]} -> {p[1][0]}.{p[1][1]}", el)

    def bond_half(self, el, bond: str, p, conns) -> None:
        """One of the two connections of ``powerBond``: the second makes the flanges and the bond."""
        pending = getattr(self, "_bonds", None)
        if pending is None:
            pending = self._bonds = {}
        (sa, va, _), (sb, vb, _) = p
        key = (bond, frozenset((sa, sb)))
        if key not in pending:
            pending[key] = (el, p)
            return
        el0, p0 = pending.pop(key)
        bond = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in bond)
        (s0, v0, _), (d0, w0, _) = p0
        if (s0, d0) != (sb, sa):
            self.err(el, f"powerBond {bond!r}: its two connections must run in opposite directions between two "
                         f"simulators (line {el0.sourceline}: {s0} -> {d0}; here: {sa} -> {sb})")
            return
        # p0: s0.v0 -> d0.w0, p: d0.va -> s0.vb.  The side whose output is the first variable of the
        # force/velocity pair is not named in OSP: effort = the one libcosim's ECCO multiplies; for a
        # bond the power is the product on each side, so which of the two we call effort does not matter
        # as long as both sides agree: side s0 outputs v0 and takes vb; side d0 takes w0 and outputs va.
        self.flange(s0, bond, effort=v0, flow=vb, el=el0)
        self.flange(d0, bond, effort=w0, flow=va, el=el)
        self.add(conns, f"{s0}.{bond} <-> {d0}.{bond}", el0)

    def flange(self, comp: str, name: str, effort: str, flow: str, el) -> None:

        spec = self.comps[comp][1]
        if "flanges" not in spec:
            spec["flanges"] = YMap()
            spec["flanges"].where = self.loc(el)
            spec.locs["flanges"] = self.loc(el)
        node = YMap({"effort": effort, "flow": flow})
        node.where = self.loc(el)
        spec["flanges"][name] = node
        spec["flanges"].locs[name] = self.loc(el)

    def finish_bonds(self) -> None:
        for (bond, _), (el, _p) in getattr(self, "_bonds", {}).items():
            self.err(el, f"powerBond {bond!r} has one connection; a power bond takes two (effort one way, flow the "
                         f"other)")

    def model_description(self, comp: str, el):
        """The simulator's ``<FMU stem>_OspModelDescription.xml`` (parsed), or None after an error."""
        from lxml import etree

        fmu = self.comps[comp][3]
        cands = [fmu.with_name(f"{fmu.stem}_OspModelDescription.xml"),
                 fmu.with_name(f"{comp}_OspModelDescription.xml")]
        cands += [p for p in fmu.parent.glob("*_OspModelDescription.xml")
                  if p.name.lower() in {c.name.lower() for c in cands}]
        file = next((p for p in cands if p.is_file()), None)
        if file is None:
            self.err(el, f"simulator {comp!r}: variable groups need {cands[0].name} next to its FMU (not found in "
                         f"{fmu.parent})")
            return None
        try:
            return etree.parse(str(file)).getroot(), file
        except etree.XMLSyntaxError as exc:
            self.problems.append(Problem(str(file), exc.lineno or 0, f"XML syntax: {exc.msg}"))
            return None

    def group(self, comp: str, name: str, el):
        """(kind, [variable lists per sub-group]) of variable group ``name`` of ``comp``."""
        found = self.model_description(comp, el)
        if found is None:
            return None
        root, file = found
        groups = _kid(root, "VariableGroups")
        for g in root.iter():
            if isinstance(g.tag, str) and g.get("name") == name and g is not root and groups is not None:
                kind = _local(g)
                if kind in PORTS:
                    effort, flow = PORTS[kind]
                    parts = []
                    for sub in (effort, flow):
                        s = _kid(g, sub)
                        parts.append([v.get("ref") for v in _kids(s, "Variable")] if s is not None else [])
                    return kind, parts
                if kind == "Generic":
                    return kind, [[v.get("ref") for v in _kids(g, "Variable")]]
                return kind, [[v.get("ref") for v in g.iter() if isinstance(v.tag, str) and _local(v) == "Variable"]]
        self.err(el, f"simulator {comp!r}: no variable group {name!r} in {file.name}")
        return None

    def group_connection(self, el, conns) -> None:
        gs = _kids(el, "VariableGroup")
        if len(gs) != 2:
            self.err(el, f"a VariableGroupConnection joins two <VariableGroup> elements, got {len(gs)}")
            return
        sides = []
        for g in gs:
            sim = g.get("simulator")
            if sim not in self.comps:
                self.err(g, f"unknown simulator {sim!r}")
                return
            found = self.group(sim, g.get("name"), g)
            if found is None:
                return
            sides.append((sim, *found))
        (sa, ka, pa), (sb, kb, pb) = sides
        if ka != kb or [len(x) for x in pa] != [len(x) for x in pb]:
            self.err(el, f"variable groups {sa}.{gs[0].get('name')} ({ka}, {[len(x) for x in pa]} variables) and "
                         f"{sb}.{gs[1].get('name')} ({kb}, {[len(x) for x in pb]}) do not match")
            return
        for g, (sim, _k, parts) in zip(gs, sides):
            desc = self.comps[sim][2]
            for ref in (r for part in parts for r in part):
                if ref not in desc.variables:
                    self.err(g, f"variable group {g.get('name')!r} of {sim!r} names {ref!r}, which its FMU does not "
                                f"have")
                    return
        if ka in PORTS:
            (ea, fa), (eb, fb) = pa, pb
            for i in range(len(ea)):
                va = [(sa, ea[i]), (sa, fa[i])]
                vb = [(sb, eb[i]), (sb, fb[i])]
                caus = {v: self.comps[v[0]][2].variables[v[1]].causality for v in va + vb}
                name = f"{gs[0].get('name')}_{i + 1}".replace(" ", "_") if len(ea) > 1 else \
                    gs[0].get("name").replace(" ", "_")
                name = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in name)
                # effort of a meets effort of b: one computes it, the other takes it
                if caus[va[0]] == caus[vb[0]] or caus[va[1]] == caus[vb[1]]:
                    self.err(el, f"port {name}: {sa}.{ea[i]} / {sb}.{eb[i]} or {sa}.{fa[i]} / {sb}.{fb[i]} are both "
                                 f"{caus[va[0]]}s; one side must compute what the other takes")
                    return
                self.flange(sa, name, effort=ea[i], flow=fa[i], el=el)
                self.flange(sb, name, effort=eb[i], flow=fb[i], el=el)
                self.add(conns, f"{sa}.{name} <-> {sb}.{name}", el)
            return
        for ra, rb in zip(pa[0], pb[0]):
            a = (sa, ra, self.comps[sa][2].variables[ra].causality)
            b = (sb, rb, self.comps[sb][2].variables[rb].causality)
            p = self.pair(el, a, b)
            if p is not None:
                self.add(conns, f"{p[0][0]}.{p[0][1]} -> {p[1][0]}.{p[1][1]}", el)

    # functions ----------------------------------------------------------------------------------
    def functions(self, node) -> dict[str, _Function]:
        """The ``<Functions>``: each LinearTransformation folds into its connection; each Sum and
        VectorSum becomes a component ``model: sum`` (:mod:`models.blocks.sums`) of its name."""
        out: dict[str, _Function] = {}
        for el in _kids(node) if node is not None else []:
            kind, name = _local(el), el.get("name")
            if kind not in ("LinearTransformation", "Sum", "VectorSum"):
                self.err(el, f"function <{kind}> is unknown (OSP defines LinearTransformation, Sum and VectorSum)")
                continue
            if not name:
                self.err(el, f"a <{kind}> needs name=")
                continue
            if name in out:
                self.err(el, f"function {name!r} is defined twice (line {out[name].el.sourceline})")
                continue
            if kind == "LinearTransformation":
                k = self.number(el, el.get("factor", "1"), f"LinearTransformation {name!r}: factor")
                c = self.number(el, el.get("offset", "0"), f"LinearTransformation {name!r}: offset")
                if k is not None and c is not None:
                    out[name] = _Function(kind, el, name, factor=k, offset=c)
                continue
            count = self.count(el, kind, name, "inputCount")
            dim = self.count(el, kind, name, "dimension") if kind == "VectorSum" else 1
            if count is None or dim is None:
                self.broken_functions.add(name)  # said once here, not again at each of its connections
                continue
            comp = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in name)
            if not comp or comp[0].isdigit():
                comp = f"f_{comp}"
            if comp in self.comps or any(f.comp == comp for f in out.values()):
                self.err(el, f"{kind} {name!r}: its component name {comp!r} is already a simulator's or another "
                             f"function's; rename the function")
                continue
            out[name] = _Function(kind, el, name, count=count, dim=dim, comp=comp)
        return out

    def count(self, el, kind: str, name: str, attr: str) -> int | None:
        text = el.get(attr)
        if text is None:
            self.err(el, f"{kind} {name!r} needs {attr}= (a whole number >= 1)")
            return None
        try:
            n = int(text.strip())
        except ValueError:
            n = 0
        if n < 1:
            self.err(el, f"{kind} {name!r}: {attr} = {text!r}; expected a whole number >= 1")
            return None
        return n

    def function_components(self, functions: dict[str, _Function]) -> list[tuple[str, object]]:
        """(name, spec) of the Sum and VectorSum components."""

        comps = []
        for f in functions.values():
            if f.broken:
                continue
            if f.kind == "LinearTransformation":
                continue
            opts = YMap({"inputs": f.count, "dimension": f.dim})
            opts.where = self.loc(f.el)
            opts.locs = {"inputs": opts.where, "dimension": opts.where}
            spec = YMap({"model": "sum", "options": opts})
            spec.where = self.loc(f.el)
            spec.locs = {"model": spec.where, "options": spec.where}
            comps.append((f.comp, spec))
        return comps

    def signal_port(self, f: _Function, port: str, sig, group: bool) -> tuple[str, list[str]] | None:
        """(direction, the function's variables) of signal ``port`` of ``f``: direction "in" or
        "out"; the variables as the ``sum`` block names them (one, or ``dimension`` for a group)."""
        import re

        if f.kind == "LinearTransformation":
            names = {"in": ["in"], "out": ["out"]}
        elif f.kind == "Sum":
            names = {f"in[{i}]": [f"in[{i}]"] for i in range(f.count)} | {"out": ["out"]}
        else:
            names = {f"in[{i}]": [f"in[{i},{j}]" for j in range(f.dim)] for i in range(f.count)}
            names["out"] = [f"out[{j}]" for j in range(f.dim)]
        if group != (f.kind == "VectorSum"):
            self.err(sig, f"{f.kind} {f.name!r} is connected by "
                          f"{'<SignalGroupConnection> (a group of ' + str(f.dim) + ')' if f.kind == 'VectorSum' else '<SignalConnection>'}, "
                          f"not {'<SignalGroupConnection>' if group else '<SignalConnection>'}")
            return None
        if port not in names:
            m = re.fullmatch(r"in\[(-?\d+)\]", port or "")
            if m and f.kind != "LinearTransformation":
                self.err(sig, f"{f.kind} {f.name!r}: signal {port!r} is out of range; inputCount = {f.count} gives "
                              f"in[0] .. in[{f.count - 1}] (0-based, as libcosim)")
            else:
                self.err(sig, f"{f.kind} {f.name!r} has signals {', '.join(names)}, not {port!r}")
            return None
        if port in f.ends:
            self.err(sig, f"{f.kind} {f.name!r}: signal {port!r} is connected twice (line {f.ends[port][1].sourceline})")
            return None
        return ("out" if port == "out" else "in"), names[port]

    def signal_connection(self, el, functions, conns, group: bool = False) -> None:
        tag, vtag = ("SignalGroup", "VariableGroup") if group else ("Signal", "Variable")
        sig, var = _kid(el, tag), _kid(el, vtag)
        if sig is None or var is None:
            self.err(el, f"a {'SignalGroupConnection' if group else 'SignalConnection'} joins one <{tag} function= "
                         f"name=/> and one <{vtag} simulator= name=/>")
            return
        fname, port = sig.get("function"), sig.get("name")
        if fname in self.broken_functions:
            return
        if fname not in functions:

            self.err(sig, f"unknown function {fname!r}{suggest(str(fname), functions)} (functions: "
                          f"{', '.join(functions) or 'none'})")
            return
        f = functions[fname]
        before = len(self.problems)
        try:
            self.signal_end(el, f, port, sig, var, group, conns)
        finally:
            f.broken = f.broken or len(self.problems) > before  # its missing signals are not said again

    def signal_end(self, el, f: _Function, port: str, sig, var, group: bool, conns) -> None:
        fname = f.name
        found = self.signal_port(f, port, sig, group)
        if found is None:
            return
        direction, fvars = found
        if group:
            sim = var.get("simulator")
            if sim not in self.comps:
                self.err(var, f"unknown simulator {sim!r}")
                return
            g = self.group(sim, var.get("name"), var)
            if g is None:
                return
            refs = [r for part in g[1] for r in part]
            if len(refs) != f.dim:
                self.err(var, f"VectorSum {fname!r} has dimension {f.dim} but variable group {var.get('name')!r} of "
                              f"{sim!r} has {len(refs)} variable{'s' if len(refs) != 1 else ''}")
                return
            ends = []
            for ref in refs:
                v = self.comps[sim][2].variables.get(ref)
                if v is None:
                    self.err(var, f"variable group {var.get('name')!r} of {sim!r} names {ref!r}, which its FMU does "
                                  f"not have")
                    return
                ends.append((sim, ref, v.causality))
        else:
            v = self.endpoint(var)
            if v is None:
                return
            ends = [v]
        want = "output" if direction == "in" else "input"
        for (sim, name, caus) in ends:
            ok = caus == "output" if direction == "in" else caus in ("input", "parameter")
            if not ok:
                self.err(var, f"{f.kind} {fname!r}: signal {port!r} {'takes an output' if direction == 'in' else 'feeds an input'}"
                              f"; {sim}.{name} is {caus} (expected {want})")
                return
            ftype = self.comps[sim][2].variables[name]
            if (ftype.fmi_type or ftype.type) not in ("Real", "Float64", "Float32"):
                self.err(var, f"{f.kind} {fname!r}: {sim}.{name} is {ftype.fmi_type or ftype.type}; OSP's functions "
                              f"take Real signals")
                return
        f.ends[port] = (ends, sig)
        if f.kind != "LinearTransformation":
            for (sim, name, _), fv in zip(ends, fvars):
                text = f"{sim}.{name} -> {f.comp}.{fv}" if direction == "in" else f"{f.comp}.{fv} -> {sim}.{name}"
                self.add(conns, text, el)
            return
        if len(f.ends) == 2:
            (src,), _ = f.ends["in"]
            (dst,), _ = f.ends["out"]
            text = f"{src[0]}.{src[1]} -> {dst[0]}.{dst[1]}"
            if f.factor != 1.0:
                text += f" * {f.factor!r}"
            if f.offset != 0.0:
                text += f" {'-' if f.offset < 0 else '+'} {abs(f.offset)!r}"
            self.add(conns, text, f.ends["out"][1])

    def finish_functions(self, functions: dict[str, _Function]) -> None:
        """Every signal of every function connected (libcosim refuses a function with one missing)."""
        for f in functions.values():
            if f.broken:
                continue
            if f.kind == "LinearTransformation":
                ports = ["in", "out"]
            elif f.kind == "Sum":
                ports = [f"in[{i}]" for i in range(f.count)] + ["out"]
            else:
                ports = [f"in[{i}]" for i in range(f.count)] + ["out"]
            missing = [p for p in ports if p not in f.ends]
            if missing:
                self.err(f.el, f"{f.kind} {f.name!r}: signal{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
                               f"{'are' if len(missing) > 1 else 'is'} not connected (every signal of a function must be)")


@dataclass
class _Function:
    """One ``<Functions>`` entry: a LinearTransformation (``factor``, ``offset``) or a Sum /
    VectorSum (``count`` inputs of ``dim`` elements, the component ``comp``); ``ends``: signal ->
    (its variables, the <Signal> element)."""

    kind: str
    el: object
    name: str
    factor: float = 1.0
    offset: float = 0.0
    count: int = 1
    dim: int = 1
    comp: str = ""
    ends: dict = field(default_factory=dict)
    broken: bool = False  # one of its connections was refused


def scene_tree(path: Path | str, problems: list[Problem]):
    """The scene tree of the OSP system structure ``path`` (see the module docstring), or None with
    the reasons appended to ``problems``."""
    r = _Reader(Path(path), problems)
    tree = r.read()
    if tree is not None:
        r.finish_bonds()
        if any(p.severity == "error" for p in problems):
            return None
    return tree
