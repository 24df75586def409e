"""Validation of components: catalog models, external FMUs, hardware, their params and start values."""
from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..errors import UserError
from ..slaves.types import TYPES, display, parse_start
from ..slaves.description import INTERFACES, Variable, describe_block, describe_fmu, resolve_shapes
from fmus.errors import BuildError
from fmus.index import source_digest
from fmus.names import check_names

from .catalog import default_catalog, make_block
from .checker import Checker, _is_number
from .keys import COMPONENT_KEYS, FMI_VERSIONS
from .model import Component
from .problems import Loc, suggest
from .user_blocks import (ENTRY_POINT_GROUP, UserBlockError, UserCatalog, entry_point_catalog, load_module_file,
                          module_depends, module_table)
from .yamlfile import YMap, _display
from ..slaves.archive import check_archive
from models.interface import Flange
from ..slaves import probe
from ..slaves.behaviour import check_in_subprocess
from ..slaves.xmlcheck import check_xml
from hardware.hil_fmu import build_hil_fmu
from hardware.protocol import parse_address
from .modelica_sources import ENV_VAR, SourceError, modelica_class, roots_from_env
from .guard_settings import GuardNeeds
from .recipes import indexed_component, indexed_user_component, recipe_of


class ComponentChecks(Checker):
    """Checks of the ``components:`` section."""

    def component(self, name: str, spec: Any, where: Loc) -> Component | None:
        if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", str(name)):
            self.err(where, f"component name {name!r} must be an identifier (letters, digits, '_'; no dots)")
            return None
        if not isinstance(spec, YMap):
            self.err(where, f"component {name!r}: expected a mapping with 'model:' or 'fmu:', got {spec!r}")
            return None
        self.unknown_keys(spec, COMPONENT_KEYS, f"component {name!r}")
        for key in ("options", "params", "start"):
            if key in spec and not isinstance(spec[key], YMap):
                self.err(spec.loc(key), f"component {name!r}: {key} must be a mapping name: value, got {spec[key]!r}")
                return None
        fmi = spec.get("fmi", "2.0")
        fmi = {2: "2.0", 3: "3.0", 2.0: "2.0", 3.0: "3.0"}.get(fmi, str(fmi)) if not isinstance(fmi, bool) else str(fmi)
        if fmi not in FMI_VERSIONS:
            self.err(spec.loc("fmi"), f"component {name!r}: fmi = {spec.get('fmi')!r}; expected \"2.0\" or \"3.0\"")
            return None
        if "modelica" in spec and ("fmu" in spec or "hardware" in spec):
            self.err(spec.where, f"component {name!r} has both 'modelica:' and "
                                 f"'{'fmu' if 'fmu' in spec else 'hardware'}:'; keep one")
            return None
        if "model" in spec and "fmu" in spec:
            self.err(spec.where, f"component {name!r} has both 'model:' and 'fmu:'; keep one")
            return None
        rollback = spec.get("rollback", True)
        if not isinstance(rollback, bool):
            self.err(spec.loc("rollback"), f"component {name!r}: rollback = {rollback!r}; expected true or false "
                                           f"(false: the master may not save and restore its state, as for hardware)")
            rollback = True  # reported; check the rest of the component as usual
        if "fmu" not in spec:
            for key in ("interface", "rtol"):
                if key in spec:
                    self.err(spec.loc(key), f"component {name!r}: '{key}' applies to an FMU ('fmu:'), not to this "
                                            f"component")
        if "replay" in spec:
            comp = self._replay_component(name, spec)
        elif "hardware" in spec:
            comp = self._hardware_component(name, spec)
        elif "fmu" in spec:
            comp = self._fmu_component(name, spec, fmi)
        elif "modelica" in spec:
            comp = self._modelica_component(name, spec, fmi)
        elif "model" in spec:
            comp = self._model_component(name, spec, fmi)
        else:
            self.err(spec.where, f"component {name!r} needs 'model:' (a catalog model), 'fmu:' (a file), "
                                 f"'modelica:' (a .mo file) or 'replay:' (a recording)")
            return None
        if comp is not None:
            comp.rollback = rollback
        return comp

    def _fmu_component(self, name: str, spec: YMap, fmi: str) -> Component | None:
        where = spec.loc("fmu")
        rel = spec["fmu"]
        if not isinstance(rel, str):
            self.err(where, f"component {name!r}: fmu must be a file path, got {rel!r}")
            return None
        base = Path(where[0]).parent if where[1] else (self.path.parent if self.path else Path.cwd())
        fpath = (base / rel) if not Path(rel).is_absolute() else Path(rel)
        if not fpath.is_file():
            near = suggest(Path(rel).name, [p.name for p in fpath.parent.glob("*.fmu")]) if fpath.parent.is_dir() else ""
            self.err(where, f"component {name!r}: FMU file {rel!r} not found (looked in {_display(fpath.parent)}){near}")
            return None
        for key in ("fidelity", "options"):
            if key in spec:
                self.err(spec.loc(key), f"component {name!r}: '{key}' applies to catalog models, not to an FMU")

        try:  # the archive's members and sizes before anything reads it
            check_archive(fpath)
        except UserError as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        if not self._xml(name, fpath, where):
            return None
        interface = spec.get("interface")
        if interface is not None and interface not in INTERFACES:
            self.err(spec.loc("interface"), f"component {name!r}: interface = {interface!r}; expected "
                                            f"{' or '.join(INTERFACES)}")
            return None
        try:
            desc = describe_fmu(fpath, interface)
        except UserError as exc:
            self.err(spec.loc("interface") if interface is not None else where, f"component {name!r}: {exc}")
            return None
        rtol = self._solver_rtol(name, spec, desc)
        if rtol is not None:
            desc = dataclasses.replace(desc, solver_rtol=rtol)
        comp = Component(name, "fmu", desc, fmu=fpath.resolve(), fmi=desc.fmi_version or fmi, where=spec.where)
        if "guard_data" in spec:  # what the guards know of it (an rpr-cosim SSP's component annotation)

            try:
                comp.guard = GuardNeeds.from_dict(spec["guard_data"])
            except (ValueError, AttributeError) as exc:
                self.err(spec.loc("guard_data"), f"component {name!r}: guard_data: {exc}")
            else:
                missing = [v for v in [r.var for r in comp.guard.ratings] + list(comp.guard.pose or ())
                           if v not in desc.variables]
                if missing:
                    self.err(spec.loc("guard_data"), f"component {name!r}: guard_data names variables the FMU does "
                                                     f"not have: {', '.join(missing)}")
        self._values(comp, spec)
        self._feedthrough(comp, spec)
        self._flanges(comp, spec)
        self._behaviour(comp, spec)
        return comp

    def _solver_rtol(self, name: str, spec: YMap, desc) -> float | None:
        """The scene's ``rtol:`` of a model-exchange component (None: not given or wrong, reported)."""
        if "rtol" not in spec:
            return None
        rtol = spec["rtol"]
        if desc.interface != "model exchange":
            self.err(spec.loc("rtol"), f"component {name!r}: rtol applies to a model-exchange FMU (CVODES's tolerance); "
                                       f"this one runs as {desc.interface}")
            return None
        if isinstance(rtol, bool) or not isinstance(rtol, (int, float)) or not 1e-14 <= rtol < 1:
            self.err(spec.loc("rtol"), f"component {name!r}: rtol = {rtol!r}; expected a number in [1e-14, 1)")
            return None
        return float(rtol)

    def _flanges(self, comp: Component, spec: YMap) -> None:
        """``flanges: {NAME: {effort: VAR, flow: VAR}}``: power ports of an external FMU, each a pair
        of an effort (force, torque) and a flow (velocity) variable, one an input and the other an
        output (which one the FMU computes gives the flange's causality); bonded with
        ``'a.NAME <-> b.NAME'`` like a catalog model's flanges (ecco's energy residual uses them)."""

        node = spec.get("flanges")
        if node is None:
            return
        if not isinstance(node, YMap):
            self.err(spec.loc("flanges"), f"component {comp.name!r}: flanges must be a mapping NAME: {{effort: VAR, "
                                          f"flow: VAR}}, got {node!r}")
            return
        vs, found = comp.description.variables, []
        for fname, fl in node.items():
            where = node.loc(fname)
            if not isinstance(fl, Mapping) or set(fl) != {"effort", "flow"}:
                self.err(where, f"component {comp.name!r}: flange {fname!r} must be {{effort: VAR, flow: VAR}}, "
                                f"got {fl!r}")
                continue
            kinds = []
            for role in ("effort", "flow"):
                var = vs.get(str(fl[role]))
                if var is None or var.causality not in ("input", "output") or not var.fast:
                    what = "does not exist" if var is None else f"is {var.causality} {var.type}"
                    self.err(where, f"component {comp.name!r}: flange {fname!r}: {role} {fl[role]!r} {what}; it must "
                                    f"be a Real input or output{suggest(str(fl[role]), vs) if var is None else ''}")
                    break
                kinds.append(var.causality)
            else:
                if kinds[0] == kinds[1]:
                    self.err(where, f"component {comp.name!r}: flange {fname!r}: effort and flow are both "
                                    f"{kinds[0]}s; one must be the input, the other the output")
                    continue
                if fname in vs:
                    self.err(where, f"component {comp.name!r}: flange {fname!r} has the name of a variable; "
                                    f"name it otherwise")
                    continue
                found.append(Flange(str(fname), str(fl["effort"]), str(fl["flow"]),
                                    "effort_out" if kinds[0] == "output" else "flow_out"))
        comp.description = dataclasses.replace(comp.description, flanges=list(comp.description.flanges) + found)

    def _behaviour(self, comp: Component, spec: YMap) -> None:
        """The behavioural check of an external FMU (:mod:`cosim.slaves.behaviour`, once per FMU hash):
        each departure a warning, each workaround applied to the component and noted."""

        where = spec.loc("fmu")
        try:
            found, _ = probe.cached(comp.fmu, "behaviour", lambda: check_in_subprocess(comp.fmu))
        except UserError as exc:
            self.warn(where, f"component {comp.name!r}: {exc}")
            return
        for line in found["departures"]:
            self.warn(where, f"component {comp.name!r} ({comp.label}): {line}")
        desc, fixes = comp.description, found["workarounds"]
        if fixes.get("always_no_prior"):
            desc = dataclasses.replace(desc, workarounds=desc.workarounds + ("always_no_prior",))
            self.note(where, f"component {comp.name!r}: workaround: every doStep passes "
                             f"noSetFMUStatePriorToCurrentPoint = true (the FMU does not step right with false)")
        if fixes.get("no_rollback") and desc.can_get_set_state:
            desc = dataclasses.replace(desc, can_get_set_state=False,
                                       rollback_reason="its FMU state restore does not restore (behavioural check)")
            self.note(where, f"component {comp.name!r}: workaround: run without rollback (restoring its FMU state "
                             f"does not restore it); adaptive and iterative refuse it")
        if fixes.get("set_in_init"):
            desc = dataclasses.replace(desc, workarounds=desc.workarounds + ("set_in_init",))
            self.note(where, f"component {comp.name!r}: workaround: its parameters and start values are set again in "
                             f"initialisation mode (it forgets values set before)")
        if fixes.get("no_reset"):
            desc = dataclasses.replace(desc, workarounds=desc.workarounds + ("no_reset",))
            self.note(where, f"component {comp.name!r}: workaround: loaded anew for every run of a batch (its reset "
                             f"does not reset it)")
        comp.description = desc

    def _xml(self, name: str, fpath: Path, where: Loc) -> bool:
        """The FMU's modelDescription.xml checked (:mod:`cosim.slaves.xmlcheck`, once per FMU hash):
        errors refuse the component, recommendations are warnings.  False on an error."""

        try:
            found, _ = probe.cached(fpath, "xml", lambda: [list(p) for p in check_xml(fpath)])
        except Exception as exc:  # an archive so broken that the checker itself fails: one line, no traceback
            found = [["error", 0, f"cannot be checked ({type(exc).__name__}: {exc})"]]
        for severity, line, msg in found:
            at = f"modelDescription.xml{f' line {line}' if line else ''}"
            (self.err if severity == "error" else self.warn)(where, f"component {name!r}: {fpath.name}: {at}: {msg}")
        return not any(p[0] == "error" for p in found)

    def _feedthrough(self, comp: Component, spec: YMap) -> None:
        """The component's direct feedthrough: the scene's ``feedthrough:`` (``none``, ``all`` or a
        mapping output -> inputs; unlisted outputs have none) wins; else the FMU's declared
        dependencies; else, for an FMU that declares none, the feedthrough measured on a scratch
        instance (:func:`cosim.slaves.probe.feedthrough`, cached by the FMU's hash), with a note."""

        desc = comp.description
        if "feedthrough" in spec:
            ft = self._declared_feedthrough(comp, spec["feedthrough"], spec.loc("feedthrough"))
            if ft is not None:
                comp.description = dataclasses.replace(desc, feedthrough=ft, feedthrough_source="scene")
            return
        if not probe.undeclared_dependencies(desc):
            return
        try:
            ft, _ = probe.feedthrough(comp.fmu, desc)
        except UserError as exc:
            self.warn(spec.loc("fmu"), f"component {comp.name!r}: its FMU declares no output dependencies and "
                                       f"measuring them failed ({exc}); every output is taken to depend on every "
                                       f"input (declare 'feedthrough:' in the scene)")
            return
        text = "; ".join(f"{y} <- {', '.join(us)}" for y, us in ft.items() if us) or "none"
        self.note(spec.loc("fmu"), f"component {comp.name!r} ({comp.label}) declares no output dependencies; "
                                   f"measured direct feedthrough: {text} (set 'feedthrough:' to override)")
        comp.description = dataclasses.replace(desc, feedthrough=ft, feedthrough_source="measured")

    def _declared_feedthrough(self, comp: Component, node: Any, where: Loc) -> dict[str, list[str]] | None:
        desc = comp.description
        ins, outs = desc.of("input"), desc.of("output")
        if node in ("none", "all"):
            return {y: (list(ins) if node == "all" else []) for y in outs}
        if not isinstance(node, Mapping):
            self.err(where, f"component {comp.name!r}: feedthrough = {node!r}; expected none, all, or a mapping "
                            f"output: [inputs] of the outputs with direct feedthrough")
            return None
        ft: dict[str, list[str]] = {y: [] for y in outs}
        ok = True
        for y, us in node.items():
            loc = node.loc(y) if hasattr(node, "loc") else where
            if y not in outs:
                self.err(loc, f"component {comp.name!r}: feedthrough names {y!r}, which is not an output"
                              f"{suggest(str(y), outs)}")
                ok = False
                continue
            us = [] if us in ("none", None) else list(ins) if us == "all" else [us] if isinstance(us, str) else us
            if not isinstance(us, list) or any(u not in ins for u in us):
                bad = us if not isinstance(us, list) else next(u for u in us if u not in ins)
                self.err(loc, f"component {comp.name!r}: feedthrough {y}: {bad!r} is not an input"
                              f"{suggest(str(bad), ins)} (expected a list of inputs, none or all)")
                ok = False
                continue
            ft[y] = [str(u) for u in us]
        return ft if ok else None

    def _hardware_component(self, name: str, spec: YMap) -> Component | None:
        """``{hardware: {address: HOST:PORT, key: FILE}}``: the hardware FMU (:mod:`hardware.hil_fmu`),
        built and cached with these start values; then an FMU component like any other."""
        node, where = spec["hardware"], spec.loc("hardware")
        if not isinstance(node, Mapping) or any(k not in ("address", "key") for k in node):
            self.err(where, f"component {name!r}: hardware must be a mapping {{address: HOST:PORT, key: FILE}}, "
                            f"got {node!r}")
            return None

        address, key = str(node.get("address", "127.0.0.1:5005")), str(node.get("key", "board.key"))
        try:
            parse_address(address)
        except ValueError as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        base = Path(where[0]).parent if where[1] else (self.path.parent if self.path else Path.cwd())
        try:
            keyfile = base / Path(key).expanduser()
        except RuntimeError as exc:  # '~user' that does not exist, or no home directory
            self.err(where, f"component {name!r}: key file {key!r}: {exc}")
            return None
        if not keyfile.is_file():
            self.err(where, f"component {name!r}: key file {_display(keyfile)} not found; make one with "
                            f"'rpr-cosim board keygen {key}' and copy it to the board")
            return None
        for k in ("model", "fidelity", "options", "fmu"):
            if k in spec:
                self.err(spec.loc(k), f"component {name!r}: '{k}' does not apply to a hardware component")
                return None
        try:
            fpath = build_hil_fmu()  # one build; address and key are string start values
        except (ValueError, OSError) as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        comp = Component(name, "fmu", describe_fmu(fpath), fmu=fpath, where=spec.where)
        self._values(comp, spec)
        comp.params.update(address=address, key_file=str(keyfile.resolve()))
        return comp

    def _model_component(self, name: str, spec: YMap, fmi: str) -> Component | None:
        if self.catalog is None:  # built before: from the FMU cache's recipe index, no block built

            comp = indexed_component(name, spec, fmi, Component)
            sources = self._blocks_sources() if comp is None and isinstance(spec.get("model"), str) else None
            if sources:  # a user's block of the scene's 'blocks:' files, unchanged since it was indexed
                model = spec["model"]
                comp = indexed_user_component(
                    name, spec, fmi, Component, key=model, model=model, fidelity=spec.get("fidelity"),
                    options=dict(spec.get("options", {})), sources=sources, origin=", ".join(sources),
                    rebuild=lambda: self._user_block(model, spec))
            if comp is not None:
                self._values(comp, spec, skip=set(comp.recipe.fixed))
                return comp
        try:
            catalog = self.catalog if self.catalog is not None else default_catalog()
        except UserError as exc:
            self.err(spec.loc("model"), f"component {name!r}: {exc}")
            return None
        cat = catalog.catalog()
        model = spec["model"]
        user = None
        if isinstance(model, str) and model not in cat and self.catalog is None:
            user = self.user_models(cat)
            if user is False:
                return None
            if model in user:
                catalog, cat = user, user.catalog()
            else:
                cat = {**cat, **user.catalog()}
        if not isinstance(model, str) or model not in cat:
            self.err(spec.loc("model"), f"component {name!r}: unknown model {model!r}{suggest(str(model), cat)} "
                                        f"(catalog: {', '.join(sorted(cat))}; your own: a 'blocks:' file of the scene, "
                                        f"an '{ENTRY_POINT_GROUP}' entry point or 'modelica:')")
            return None
        fidelity = spec.get("fidelity", cat[model][0])
        if not isinstance(fidelity, str) or fidelity not in cat[model]:
            self.err(spec.loc("fidelity"), f"component {name!r}: model {model} has no fidelity {fidelity!r}"
                                           f"{suggest(str(fidelity), cat[model])} (expected one of "
                                           f"{', '.join(cat[model])})")
            return None
        options = dict(spec.get("options", {}))
        known_opts = getattr(catalog, "options", None)
        if known_opts is not None:
            allowed = list(known_opts(model, fidelity))
            bad = [k for k in options if k not in allowed]
            for k in bad:
                self.err(spec["options"].loc(k), f"component {name!r}: {model}/{fidelity} has no option {k!r}"
                                                 f"{suggest(str(k), allowed)} (options: {', '.join(allowed) or 'none'})")
            if bad:
                return None
        from models.block import BlockError

        try:
            block = make_block(catalog, model, fidelity, options) if user is None else catalog.make(model, fidelity,
                                                                                                      **options)
        except (BlockError, ValueError, TypeError) as exc:
            self.err(spec.loc("options") if "options" in spec else spec.loc("model"), f"component {name!r}: {exc}")
            return None
        params = spec.get("params", YMap())
        structural = {p.name for p in block.params if p.structural}
        fixed = {k: params[k] for k in params if k in structural}
        if fixed:
            try:
                block = catalog.make(model, fidelity, **options, **fixed) if user is not None else \
                    make_block(catalog, model, fidelity, {**options, **fixed})
            except (BlockError, ValueError, TypeError) as exc:
                self.err(params.loc(next(iter(fixed))), f"component {name!r}: {exc}")
                return None
        if not self._units_readable(name, block, spec):
            return None
        desc = describe_block(block, f"{model}/{fidelity}")
        comp = Component(name, "model", desc, model=model, fidelity=fidelity, options=options, fmi=fmi,
                         block=block, where=spec.where)
        if self.catalog is None:

            if user is None:
                comp.recipe = recipe_of(spec, options, fixed, fmi)
            else:
                comp.origin, comp.depends = user.models[model].origin, user.depends(model)
                sources = self._blocks_sources() if not comp.origin.startswith("entry point") else None
                if sources:  # indexed with its sources; an entry point's block is found by content only
                    comp.recipe = recipe_of(spec, options, fixed, fmi, key=model, fidelity=spec.get("fidelity"),
                                            sources=sources)
        self._values(comp, spec, skip=set(fixed))
        return comp

    def _units_readable(self, name: str, block, spec: YMap) -> bool:
        """Every unit of ``block`` one the FMU exporter can write (:func:`fmus.model_description.
        check_names`): refused here, at the options that made it, not when the FMU is built."""
        try:
            check_names(block)
        except BuildError as exc:
            self.err(spec.loc("options") if "options" in spec else spec.loc("model"), f"component {name!r}: {exc}")
            return False
        return True

    def _base(self, where: Loc) -> Path:
        return Path(where[0]).parent if where[1] else (self.path.parent if self.path else Path.cwd())

    def user_models(self, reserved) -> UserCatalog | bool:
        """The users' Python models: the scene's ``blocks:`` files and the ``rpr_cosim.blocks``
        entry points (loaded once per scene); False after reporting why they cannot be loaded."""
        if getattr(self, "_user", None) is not None:
            return self._user
        node, cat = self.tree.get("blocks", []), None
        files = [node] if isinstance(node, str) else node
        where = self.tree.loc("blocks") if "blocks" in self.tree else self.tree.where
        if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
            self.err(where, f"blocks must be a Python file or a list of them, got {node!r}")
            self._user = False
            return False
        try:
            cat = entry_point_catalog(set(reserved))
            for rel in files:
                path = self._base(where) / rel
                if not path.is_file():
                    raise UserBlockError(f"blocks file {rel!r} not found (looked in {_display(path.parent)})")
                module, digest = load_module_file(path)
                cat.add(module_table(module, path.name), path.name, digest, set(reserved), module_depends(module))
        except UserBlockError as exc:
            self.err(where, str(exc))
            self._user = False
            return False
        self._user = cat
        return cat

    def _blocks_sources(self) -> dict[str, str] | None:
        """``{"blocks:<file>": SHA-256}`` of the scene's ``blocks:`` files (None without any, or
        when one cannot be read: then the full path reports it)."""
        node = self.tree.get("blocks")
        files = [node] if isinstance(node, str) else node
        if not files or not isinstance(files, list):
            return None
        where = self.tree.loc("blocks")
        out = {}
        for rel in files:
            digest = source_digest(self._base(where) / rel) if isinstance(rel, str) else "missing"
            if digest == "missing":
                return None
            out[f"blocks:{rel}"] = digest
        return out

    def _user_block(self, model: str, spec: YMap):
        """The real block of a user's model (when an indexed component needs its equations)."""
        user = self.user_models(default_catalog().catalog())
        if user is False:
            raise UserError("; ".join(p.message for p in self.problems if p.severity == "error"))
        return user.make(model, spec.get("fidelity"), **dict(spec.get("options", {})))

    def _modelica_component(self, name: str, spec: YMap, fmi: str) -> Component | None:
        """``{modelica: FILE.mo, model: CLASS, options: {integrator, substeps, causality}}`` or ``{modelica:
        QUALIFIED.CLASS}`` (a class of the source roots: the scene's ``modelica_path:`` and
        ``MODELICAPATH``): the class translated into a block (:func:`models.modelica.translate`)
        from the files it reads (:mod:`.modelica_sources`), which its recipe key covers."""
        from models.block import BlockError
        from models.modelica import CAUSALITIES, INTEGRATORS, refuse_unsupported, translate


        where, rel, cls = spec.loc("modelica"), spec["modelica"], spec.get("model")
        if not isinstance(rel, str) or not rel.strip():
            self.err(where, f"component {name!r}: modelica must be a .mo file path or a qualified class name, "
                            f"got {rel!r}")
            return None
        file_ref = rel.endswith(".mo")
        if file_ref and (not isinstance(cls, str) or not cls):
            self.err(spec.loc("model") if "model" in spec else where,
                     f"component {name!r}: name the Modelica class to use with 'model:' (e.g. model: Gear)")
            return None
        if not file_ref and cls is not None and cls != rel:
            self.err(spec.loc("model"), f"component {name!r}: modelica: {rel} names the class already; drop "
                                        f"'model: {cls}'")
            return None
        cls = cls if file_ref else rel
        if "fidelity" in spec:
            self.err(spec.loc("fidelity"), f"component {name!r}: 'fidelity' applies to catalog models, not to a "
                                           f"Modelica class")
            return None
        path = self._base(where) / rel
        if file_ref and not path.is_file():
            near = suggest(Path(rel).name, [p.name for p in path.parent.glob("*.mo")]) if path.parent.is_dir() else ""
            self.err(where, f"component {name!r}: Modelica file {rel!r} not found (looked in "
                            f"{_display(path.parent)}){near}")
            return None
        options = dict(spec.get("options", {}))
        known = ["integrator", "substeps", "causality"]
        bad = [k for k in options if k not in known]
        for k in bad:
            self.err(spec["options"].loc(k), f"component {name!r}: a Modelica component has no option {k!r}"
                                             f"{suggest(str(k), known)} (options: {', '.join(known)})")
        causality = options.get("causality", {})
        if not isinstance(causality, dict) or not all(isinstance(k, str) and v in CAUSALITIES
                                                      for k, v in causality.items()):
            self.err(spec["options"].loc("causality"), f"component {name!r}: options.causality {causality!r}; "
                                                       f"expected a mapping flange: {' or '.join(CAUSALITIES)} "
                                                       f"(effort_out: the force from the partner's velocity; "
                                                       f"flow_out: the velocity from the partner's force)")
            return None
        if causality:
            options["causality"] = dict(causality)
        integrator, substeps = options.get("integrator", "auto"), options.get("substeps", 1)
        if integrator not in INTEGRATORS:
            self.err(spec["options"].loc("integrator"), f"component {name!r}: integrator {integrator!r}; expected "
                                                        f"one of {', '.join(INTEGRATORS)}")
            return None
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            self.err(spec["options"].loc("substeps"), f"component {name!r}: substeps {substeps!r}; expected a whole "
                                                      f"number >= 1")
            return None
        if bad:
            return None
        roots = self.modelica_roots()
        if roots is None:
            return None
        try:
            mc = modelica_class(rel, cls, self._base(where), roots)
        except SourceError as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        origin = mc.filename

        def block_of_text():
            if not mc.library:  # the constructs refused by their line before rumoca compiles
                refuse_unsupported(mc.text, mc.filename)
            return translate(mc.text, mc.model, mc.filename, name=mc.model.split(".")[-1].lower(),
                             integrator=integrator, substeps=substeps, compiled=mc.compiled(), scan=False,
                             causality=causality)

        from fmus.index import installed_version

        key = f"modelica:{mc.model}"  # indexed with the digests of every file it reads and the front end's version
        sources = mc.recipe_sources(str(installed_version("rumoca", "rumoca")))
        if self.catalog is None:

            comp = indexed_user_component(name, spec, fmi, Component, key=key, model=mc.model, fidelity="modelica",
                                          options=options, sources=sources, origin=origin, rebuild=block_of_text)
            if comp is not None:
                self._values(comp, spec)
                return comp
        try:
            block = block_of_text()
        except BlockError as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        comp = Component(name, "model", describe_block(block, f"{mc.model}/modelica"), model=mc.model,
                         fidelity="modelica", options=options, fmi=fmi, block=block, where=spec.where, origin=origin)
        if self.catalog is None:

            comp.recipe = recipe_of(spec, options, {}, fmi, key=key, fidelity="modelica", sources=sources)
        self._values(comp, spec)
        return comp

    def modelica_roots(self) -> list[Path] | None:
        """The Modelica source roots: the scene's ``modelica_path:`` (a list of directories or a
        colon-separated string, relative to the scene), then ``MODELICAPATH``; None after
        reporting a root that is not a directory."""
        if getattr(self, "_modelica_roots", None) is not None:
            return self._modelica_roots

        node = self.tree.get("modelica_path", [])
        where = self.tree.loc("modelica_path") if "modelica_path" in self.tree else self.tree.where
        items = node.split(os.pathsep) if isinstance(node, str) else node
        if not isinstance(items, list) or not all(isinstance(p, str) for p in items):
            self.err(where, f"modelica_path must be a list of directories or a '{os.pathsep}'-separated string, "
                            f"got {node!r}")
            return None
        roots = []
        for p in [x for x in items if x.strip()]:
            root = self._base(where) / os.path.expanduser(p)
            if not root.is_dir():
                self.err(where, f"modelica_path: {p!r} is not a directory (looked for {_display(root)})")
                return None
            roots.append(root)
        env = roots_from_env()
        missing = [str(r) for r in env if not r.is_dir()]
        if missing:
            self.warn(where, f"{ENV_VAR}: {missing[0]} is not a directory (skipped)")
        self._modelica_roots = roots + [r for r in env if r.is_dir()]
        return self._modelica_roots

    def _values(self, comp: Component, spec: YMap, skip: set[str] = frozenset()) -> None:
        """Check ``params`` and ``start`` against the component's variables."""
        if comp.kind == "fmu":
            self._fmu_values(comp, spec)
            return
        vs = comp.description.variables
        params = spec.get("params", YMap())
        pnames = [v.name for v in vs.values() if v.causality == "parameter"]
        bounds = {p.name: (p.lower, p.upper, p.unit) for p in comp.block.params} if comp.block is not None else {}
        for k, val in params.items():
            where = params.loc(k)
            if k in skip:
                continue
            if k not in vs or vs[k].causality != "parameter":
                if comp.kind == "model" and k in ("config", "form", "integrator", "substeps", "rotor", "profile",
                                                  "derivative", "anti_windup", "sample_period"):
                    self.err(where, f"component {comp.name!r}: {k!r} is a construction option, not a parameter; "
                                    f"put it under 'options:'")
                elif k in vs:
                    self.err(where, f"component {comp.name!r}: {k!r} is a{'n' if vs[k].causality[0] in 'aeiou' else ''} "
                                    f"{vs[k].causality}, not a parameter; use 'start:' for start values")
                else:
                    self.err(where, f"component {comp.name!r} ({comp.label}) has no parameter {k!r}"
                                    f"{suggest(str(k), pnames)}")
                continue
            if vs[k].type != "Real":
                self.err(where, f"component {comp.name!r}: parameter {k!r} is {vs[k].type}; only Real parameters "
                                f"can be set from a scene")
                continue
            if not _is_number(val) or not math.isfinite(val):
                self.err(where, f"component {comp.name!r}: parameter {k} = {val!r} is not a finite number")
                continue
            if k in bounds:
                lo, hi, unit = bounds[k]
                if not (lo <= val <= hi):
                    self.err(where, f"component {comp.name!r}: parameter {k} = {val} is outside [{lo}, {hi}]"
                                    f"{' ' + unit if unit else ''}")
                    continue
            if vs[k].variability in ("constant",):
                self.err(where, f"component {comp.name!r}: parameter {k!r} is a constant and cannot be set")
                continue
            comp.params[k] = float(val)
        start = spec.get("start", YMap())
        settable = [v.name for v in vs.values() if v.causality in ("input", "local", "output")]
        for k, val in start.items():
            where = start.loc(k)
            if k not in vs:
                self.err(where, f"component {comp.name!r} ({comp.label}) has no variable {k!r}{suggest(str(k), settable)}")
                continue
            var = vs[k]
            if var.causality == "parameter":
                self.err(where, f"component {comp.name!r}: {k!r} is a parameter; set it under 'params:'")
                continue
            if var.causality == "output":
                self.err(where, f"component {comp.name!r}: {k!r} is an output; outputs are computed and have no "
                                f"start value to set")
                continue
            if not _is_number(val) or not math.isfinite(val):
                self.err(where, f"component {comp.name!r}: start value {k} = {val!r} is not a finite number")
                continue
            if var.causality == "local" and comp.block is not None and not _exact_start(comp.block, k):
                self.err(where, f"component {comp.name!r}: state {k!r} starts from the parameters (its start is "
                                f"calculated); set those parameters instead")
                continue
            comp.start[k] = float(val)

    def _fmu_values(self, comp: Component, spec: YMap) -> None:
        """``params`` and ``start`` of an FMU component, any FMI type (see :mod:`cosim.slaves.types`):
        parameters (and FMI 3.0 structural parameters, which size the arrays) under ``params``;
        inputs and variables with initial = exact or approx under ``start``."""
        params, start = spec.get("params", YMap()), spec.get("start", YMap())
        vs = comp.description.variables
        pkinds = ("parameter", "structuralParameter")
        pnames = [v.name for v in vs.values() if v.causality in pkinds and v.variability != "constant"]
        snames = [v.name for v in vs.values() if _start_settable(v)]
        structural: dict[str, int] = {}
        for pass_ in ("structural", "other"):
            for k, val in params.items():
                var = vs.get(k)
                if (var is not None and var.causality == "structuralParameter") != (pass_ == "structural"):
                    continue
                where = params.loc(k)
                if var is None or var.causality not in pkinds:
                    if var is None:
                        self.err(where, f"component {comp.name!r} ({comp.label}) has no parameter {k!r}"
                                        f"{suggest(str(k), pnames)}")
                    elif _start_settable(var):
                        self.err(where, f"component {comp.name!r}: {k!r} is a{'n' if var.causality[0] in 'aeiou' else ''} "
                                        f"{var.causality} (initial = {var.initial}), not a parameter; set its start value "
                                        f"under 'start:'")
                    else:
                        self.err(where, f"component {comp.name!r}: {k!r} is a{'n' if var.causality[0] in 'aeiou' else ''} "
                                        f"{var.causality} computed by the FMU; it cannot be set")
                    continue
                if var.variability == "constant":
                    self.err(where, f"component {comp.name!r}: parameter {k!r} is a constant and cannot be set")
                    continue
                value = self._typed_value(comp, var, val, where, "parameter")
                if value is None:
                    continue
                if pass_ == "structural":
                    structural[k] = int(value[0])
                comp.params[k] = value
            if pass_ == "structural" and structural:
                comp.description = resolve_shapes(comp.description, structural)
                vs = comp.description.variables
        for k, val in start.items():
            where = start.loc(k)
            var = vs.get(k)
            if var is None:
                self.err(where, f"component {comp.name!r} ({comp.label}) has no variable {k!r}{suggest(str(k), snames)}")
                continue
            if var.causality == "structuralParameter":
                self.err(where, f"component {comp.name!r}: {k!r} is a structural parameter (it sizes arrays and is set "
                                f"in configuration mode); set it under 'params:'")
                continue
            if var.causality == "parameter":
                self.err(where, f"component {comp.name!r}: {k!r} is a parameter; set it under 'params:'")
                continue
            if not _start_settable(var):
                what = {"output": "an output", "local": "a local variable", "independent": "the independent variable",
                        "calculatedParameter": "a calculated parameter"}.get(var.causality, var.causality)
                self.err(where, f"component {comp.name!r}: {k!r} is {what} computed by the FMU (initial = "
                                f"{var.initial or 'calculated'}); FMI allows start values only for inputs and "
                                f"variables with initial = exact or approx (here: {', '.join(snames) or 'none'})")
                continue
            value = self._typed_value(comp, var, val, where, "start value")
            if value is not None:
                comp.start[k] = value

    def _typed_value(self, comp: Component, var: Variable, val: Any, where: Loc, what: str):
        """``val`` as the values of ``var`` (a float for a scalar Float64, else a list), or None
        after reporting why it does not fit."""
        ft = TYPES.get(var.type)
        tname = display(var.type, comp.description.fmi_version)
        if ft is None:
            self.err(where, f"component {comp.name!r}: {var.name!r} is a {var.fmi_type} variable; rpr-cosim sets "
                            f"and connects {', '.join(sorted({display(t, comp.description.fmi_version) for t in TYPES}))}")
            return None
        flat = _flatten(val)
        try:
            vals = parse_start(flat, ft, var.size, f"{what} {var.name} ({tname}"
                                                   f"{', shape ' + 'x'.join(map(str, var.shape)) if var.shape else ''})", tname)
        except ValueError as exc:
            self.err(where, f"component {comp.name!r}: {exc}")
            return None
        if var.fast:
            return float(vals[0])
        return [x.item() if hasattr(x, "item") else x for x in vals]

    # connections ----------------------------------------------------------------------------------

def _start_settable(var: Variable) -> bool:
    """FMI allows a start value before initialisation: inputs, and non-parameter variables with
    initial = exact or approx."""
    if var.variability == "constant" or var.causality in ("independent", "parameter", "structuralParameter",
                                                          "calculatedParameter"):
        return False
    return var.causality == "input" or var.initial in ("exact", "approx")


def _flatten(val: Any) -> Any:
    """Nested YAML lists (a matrix) as one row-major list; anything else unchanged."""
    if isinstance(val, (list, tuple)):
        out: list = []
        for x in val:
            out.extend(_flatten(x) if isinstance(x, (list, tuple)) else [x])
        return out
    return val


def _exact_start(block, state: str) -> bool:
    if getattr(block, "exact_start", None) is not None:  # an indexed block (fmus.index) recorded it
        return state in block.exact_start
    import casadi as ca

    i = block.index("states", state)
    return not (block.p.numel() and ca.depends_on(block.start[i], block.p))
