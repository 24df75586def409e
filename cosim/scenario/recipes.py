"""Catalog components through the FMU cache's recipe index (:mod:`fmus.index`): a scene whose
components were built before is validated and run from the index, without building any block
(no CasADi, no code generation); everything else takes the full path and fills the index."""
from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any
from fmus.index import IndexedBlock, Recipe, cached_fmu, lookup, real_block, record
from ..slaves.description import SlaveDescription, Variable, describe_block, describe_fmu
import fmus
from models.interface import Flange


def indexed_component(name: str, spec: Mapping, fmi: str, make_component: Callable[..., Any]) -> Any | None:
    """The component of ``spec`` (a catalog ``model:`` spec) from the index, made by
    ``make_component(name, kind, description, **fields)``; None on a miss or on anything the full
    validation has to report (a malformed spec)."""

    model, fidelity = spec.get("model"), spec.get("fidelity")
    options, params = spec.get("options", {}), spec.get("params", {})
    if not isinstance(model, str) or not (fidelity is None or isinstance(fidelity, str)):
        return None
    if not isinstance(options, Mapping) or not isinstance(params, Mapping):
        return None
    hit = lookup(model, fidelity, dict(options), dict(params), fmi)
    if hit is None:
        return None
    block, recipe = hit
    fid = block.catalog_fidelity
    return make_component(name, "model", _description(block, f"{model}/{fid}"), model=model, fidelity=fid,
                          options=dict(options), fmi=fmi, block=block, where=spec.where, recipe=recipe)


def indexed_user_component(name: str, spec: Mapping, fmi: str, make_component: Callable[..., Any], *, key: str,
                           model: str, fidelity: str | None, options: dict, sources: dict,
                           rebuild: Callable[[], Any], origin: str) -> Any | None:
    """A user's block (``model``, indexed under the recipe model ``key``, ``fidelity`` as
    written, ``sources``) from
    the index, made by ``make_component``; None on a miss.  ``rebuild`` builds the real block
    when a run needs its equations."""

    params = spec.get("params", {})
    if not isinstance(options, Mapping) or not isinstance(params, Mapping):
        return None
    hit = lookup(key, fidelity, dict(options), dict(params), fmi, sources=sources, rebuild=rebuild)
    if hit is None:
        return None
    block, recipe = hit
    fid = block.catalog_fidelity
    return make_component(name, "model", _description(block, f"{model}/{fid}"), model=model, fidelity=fid,
                          options=dict(options), fmi=fmi, block=block, where=spec.where, recipe=recipe, origin=origin)


def _description(block, source: str):
    """:func:`cosim.slaves.describe_block` of an indexed block, made once per block and source
    (the index hands out one block per entry; descriptions are not modified after they are made)."""

    memo = block.__dict__.setdefault("_descriptions", {})
    if source not in memo:
        memo[source] = describe_block(block, source)
    return memo[source]


def recipe_of(spec: Mapping, options: dict, fixed: dict, fmi: str, *, key: str | None = None,
              fidelity: str | None = None, sources: dict | None = None):
    """The :class:`fmus.index.Recipe` of a catalog component validated the full way (a user's
    block: its recipe model ``key``, ``fidelity`` and ``sources``)."""

    return Recipe(key or spec["model"], fidelity if key else spec.get("fidelity"), dict(options), dict(fixed), fmi,
                  dict(sources or {}))


def component_fmu(comp, *, cache_dir: Path | None = None, progress: Callable[[str], None] | None = None) -> Path:
    """The FMU of catalog component ``comp``: the indexed one when it is intact, else built (or
    found by content) through :func:`fmus.build_fmu`, which says why it rebuilds a damaged FMU;
    a component of the default catalog is then (re)indexed."""

    say = progress or (lambda m: None)
    if isinstance(comp.block, IndexedBlock):
        path, why = cached_fmu(comp.block, cache_dir)
        if path is not None:
            say(f"{path.stem}: FMI {comp.fmi} FMU up to date ({path}), from the recipe index")
            return path

    block = real_block(comp.block)
    path = fmus.build_fmu(block, fmi_version=comp.fmi, cache_dir=cache_dir, progress=progress)
    if getattr(comp, "recipe", None) is not None:

        record(comp.recipe, comp.fidelity, block, path, cache_dir, description=description_data(describe_fmu(path)),
               depends=getattr(comp, "depends", None))
    return path


def slave_description(comp, fmu: Path):
    """The description of ``comp``'s FMU ``fmu`` without reading its modelDescription.xml: the
    indexed one when ``fmu`` is the FMU of the index entry (verified before), else None."""

    if isinstance(comp.block, IndexedBlock) and Path(fmu) == comp.block.fmu and comp.block.fmu_description:
        return description_from_data(comp.block.fmu_description)
    return None


def description_data(desc) -> dict:
    """A :class:`cosim.slaves.SlaveDescription` as plain data (see :func:`description_from_data`)."""
    import dataclasses

    plain = {f.name: getattr(desc, f.name) for f in dataclasses.fields(desc) if f.name not in ("variables", "flanges")}
    return {**plain, "variables": [dataclasses.asdict(v) for v in desc.variables.values()],
            "flanges": [dataclasses.asdict(f) for f in desc.flanges]}


def description_from_data(data: dict):
    """The :class:`cosim.slaves.SlaveDescription` written by :func:`description_data`."""


    vs = {}
    for v in data["variables"]:
        v = dict(v, shape=tuple(v.get("shape") or ()), dims=tuple(v.get("dims") or ()))
        vs[v["name"]] = Variable(**v)
    rest = {k: v for k, v in data.items() if k not in ("variables", "flanges")}
    rest["interfaces"] = tuple(rest.get("interfaces") or ())
    rest["workarounds"] = tuple(rest.get("workarounds") or ())
    rest["discrete_states"] = tuple(rest.get("discrete_states") or ())
    return SlaveDescription(variables=vs, flanges=[Flange(**f) for f in data["flanges"]], **rest)
