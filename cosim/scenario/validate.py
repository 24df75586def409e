"""Validation of a merged scene tree into a :class:`Scene`: every check, every problem collected."""
from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path

from fmus.cache import file_digest

from .check_components import ComponentChecks
from .check_connections import ConnectionChecks
from .check_master import MasterChecks
from .keys import TOP_KEYS
from .model import Component, Scene
from .replay import ReplayChecks
from .overrides import plain
from .problems import Problem, SceneError
from .yamlfile import YMap
from .guard_settings import check_scene, parse_settings
from ..outputs import name_problem, stem_name


class _Checker(ComponentChecks, ConnectionChecks, MasterChecks, ReplayChecks):
    """Every check of a scene."""


def _hash(data: dict, comps: Mapping[str, Component]) -> str:
    h = hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode())
    for name in sorted(comps):
        c = comps[name]
        if c.fmu is not None:
            h.update(name.encode() + bytes.fromhex(file_digest(c.fmu)))
        sources = getattr(getattr(c, "recipe", None), "sources", None)
        if sources:  # a user's block: the files that define it (a Modelica class: every file it reads)
            h.update(name.encode() + json.dumps(sources, sort_keys=True).encode())
    return h.hexdigest()


def validate(tree: YMap, path: Path | None = None, *, catalog=None, problems: list[Problem] | None = None) -> Scene:
    """Check a merged scene tree; raises :class:`SceneError` with every problem found."""
    ck = _Checker(tree, path, catalog)
    ck.problems.extend(problems or [])
    ck.unknown_keys(tree, [k for k in TOP_KEYS if k != "include"], "the scene")
    node = tree.get("components")
    comps: dict[str, Component] = {}
    if not isinstance(node, YMap) or not node:
        ck.err(tree.loc("components") if "components" in tree else tree.where,
               "the scene needs 'components:', a mapping of name -> {model: ...} or {fmu: ...}")
    else:
        for name, spec in node.items():
            errors = sum(p.severity == "error" for p in ck.problems)
            c = ck.component(str(name), spec, node.loc(name))
            if c is not None:
                comps[c.name] = c
            elif sum(p.severity == "error" for p in ck.problems) > errors:  # refused, and said so
                ck.refused.add(str(name))
    broken = isinstance(node, YMap) and len(comps) != len(node)
    conns, bonds = ck.connections(comps) if comps else ([], [])
    master = ck.master(comps)
    stop, n_steps, start, start_ns = ck.times(master, comps)
    outputs = ck.outputs(comps) if comps else []
    ck.replay_scene(comps, conns, start, stop)
    if comps and not broken:
        ck.unconnected(comps, conns)
    if conns:
        # a scene naming no algorithm may have a loop: the run then chooses iterative (cosim.run.choose)
        ck.algebraic_loops(comps, conns, "iterative" if master is not None and master.auto else
                           master.algorithm if master is not None else None)

    guards = parse_settings(tree.get("guards"), lambda _key: tree.loc("guards"), ck.err)
    if comps and not broken:
        check_scene(guards, comps, stop - start if stop is not None else None, ck.err, ck.warn)
    errors = [p for p in ck.problems if p.severity == "error"]
    if errors:
        raise SceneError(ck.problems)

    name = tree.get("name") or stem_name(path.stem if path else "scene")
    if name_problem(name):
        ck.err(tree.loc("name"), name_problem(name))
        raise SceneError(ck.problems)
    data = plain(tree)
    return Scene(str(name), path, str(tree.get("description", "")), stop, n_steps, comps, conns, bonds, master,
                 outputs, data, _hash(data, comps), [p for p in ck.problems if p.severity != "error"], start, start_ns,
                 guards)
