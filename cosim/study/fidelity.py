"""Fidelity study: "model no more than the scene needs", measured.

Components of the same catalog model share one fidelity level; the study runs the scene for every
combination of levels (models whose components are marked ``fidelity: auto``, or every model with
more than one level), measures each run against the combination of the highest levels (largest
error relative to the reference signal's range, over the signals both recorded) and its cost
(wall time of the stepping loop), and picks the cheapest combination within a tolerance.
Combinations that do not make a valid scene (an interface that no longer matches the
connections) are reported with the reason and skipped.

``fidelity: auto`` in a scene: :func:`resolve_auto` runs this study once for the scene (with the
scene's ``fidelity_tolerance``, default 1e-3, over its ``fidelity_signals`` globs, default every
recorded signal), caches the choice under the hash of the scene's
data, and substitutes the chosen levels before validation.
"""
from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import os
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..analysis.trace_diff import common_names, compare
from ..errors import UserError
from ..scenario import Problem, SceneError, apply_overrides, default_catalog, load_raw, validate
from fmus.cache import cache_root
from ..scenario.overrides import plain

#: Default relative tolerance of ``fidelity: auto``.
AUTO_TOLERANCE = 1e-3


@dataclass
class FidelityRow:
    """One combination: levels per model, outcome, worst relative error against the highest
    combination (and the signal), wall time [s]."""

    levels: dict[str, str]
    status: str
    reason: str = ""
    worst: float = math.nan
    worst_signal: str = ""
    wall_s: float = math.nan
    dropped: list[str] = field(default_factory=list)  # output patterns that match nothing at these levels
    unestimated: str = ""  # why the run has no error estimate of its own (e.g. a sampled block), else ""

    @property
    def label(self) -> str:
        return ", ".join(f"{m}={f}" for m, f in self.levels.items())


@dataclass
class FidelityStudy:
    scene: str
    models: dict[str, list[str]]  # model -> levels studied, highest first
    rows: list[FidelityRow] = field(default_factory=list)
    run_tolerance: float | None = None  # the master.tolerance each combination ran at (None: the scene's)

    def cheapest_within(self, tol: float) -> FidelityRow | None:
        ok = [r for r in self.rows if r.status == "ok" and r.worst <= tol]
        return min(ok, key=lambda r: r.wall_s) if ok else None


def detail_order(catalog, model: str) -> list[str]:
    """The model's fidelity levels, most detailed first (the catalog's ``detail_order`` if it has
    one, else its declaration order)."""
    order = getattr(catalog, "detail_order", None)
    levels = list(catalog.catalog()[model])
    if order is None:
        return levels
    ranked = [f for f in order(model) if f in levels]
    return ranked + [f for f in levels if f not in ranked]


def _tree(path: Path) -> Any:

    problems: list[Problem] = []
    tree = load_raw(Path(path), problems)
    if tree is None:
        raise SceneError(problems)
    return tree


def _studied_models(tree: Mapping, catalog, only_auto: bool) -> dict[str, list[str]]:
    comps = tree.get("components") or {}
    models: dict[str, list[str]] = {}
    for spec in comps.values():
        if not isinstance(spec, Mapping) or "model" not in spec:
            continue
        model = str(spec["model"])
        if model not in catalog.catalog():
            continue
        if only_auto and spec.get("fidelity") != "auto":
            continue
        models[model] = detail_order(catalog, model)
    return {m: lv for m, lv in models.items() if len(lv) > 1 or only_auto}


def _with_levels(tree: Any, levels: Mapping[str, str], only_auto: bool) -> Any:
    out = copy.deepcopy(tree)
    for spec in (out.get("components") or {}).values():
        if isinstance(spec, Mapping) and spec.get("model") in levels and (not only_auto or spec.get("fidelity") == "auto"):
            spec["fidelity"] = levels[spec["model"]]
    return out


#: A combination's runs are asked to be this much more accurate than the study's tolerance, so
#: that the co-simulation's own error does not decide which fidelity is within it.
RUN_MARGIN = 10.0
#: A scene problem a combination may drop and still be compared: an ``outputs:`` pattern that
#: matches nothing at these levels (``motor*.i`` of an ideal motor, which has no current).
_UNMATCHED_OUTPUT = re.compile(r"^output pattern '(.+?)' matches no input or output")


def _validated(tree: Any, path: Path):
    """The scene of a combination's ``tree`` and the output patterns dropped for it (patterns
    that match nothing at its levels); :class:`SceneError` for any other problem."""

    dropped: list[str] = []
    for _ in range(2):
        try:
            return validate(tree, path), dropped
        except SceneError as exc:
            errors = [p for p in exc.problems if p.severity == "error"]
            unmatched = [m.group(1) for p in errors if (m := _UNMATCHED_OUTPUT.match(p.message))]
            if not unmatched or len(unmatched) != len(errors) or not isinstance(tree.get("outputs"), list):
                raise
            tree = copy.deepcopy(tree)
            tree["outputs"] = [o for o in tree["outputs"] if o not in unmatched]
            dropped += unmatched
    return validate(tree, path), dropped


def fidelity_study(scene_path: Path | str, overrides: Mapping[str, Any] | Sequence[str] | None = None, *,
                   only_auto: bool = False, only: Sequence[str] | None = None, cache_dir: Path | None = None,
                   progress: Callable[[str], None] | None = None, tolerance: float | None = None) -> FidelityStudy:
    """Run every combination (module docstring); the first row is the highest combination.
    ``only`` restricts the compared signals (globs; default every recorded signal).  With
    ``tolerance``, a scene whose master chooses runs each combination at a tolerance
    :data:`RUN_MARGIN` times tighter (the co-simulation's error then cannot decide the answer).
    A combination that cannot make a valid scene or cannot run is "invalid" with the reason; an
    output pattern that matches nothing at its levels is dropped (the row says so) and the
    combination is compared over the signals both recorded."""
    from ..run.execute import run

    path = Path(scene_path)
    catalog = default_catalog()
    tree = apply_overrides(_tree(path), overrides)
    models = _studied_models(tree, catalog, only_auto)
    if not models:
        raise UserError(f"{path}: no catalog component has more than one fidelity level to study")
    study = FidelityStudy(str(tree.get("name") or path.stem), models)
    master = tree.get("master") if isinstance(tree.get("master"), Mapping) else {}
    if tolerance is not None and "algorithm" not in master:
        tight = min(float(master.get("tolerance", AUTO_TOLERANCE)), tolerance / RUN_MARGIN)
        tree = apply_overrides(tree, {"master.tolerance": tight})
        study.run_tolerance = tight
    reference = None
    for combo in itertools.product(*models.values()):
        levels = dict(zip(models, combo))
        row = FidelityRow(levels, "invalid")
        try:
            scene, dropped = _validated(_with_levels(tree, levels, only_auto), path)
        except SceneError as exc:
            first = next((p for p in exc.problems if p.severity == "error"), None)
            row.reason = first.message if first else str(exc)
            study.rows.append(row)
            if reference is None:
                raise UserError(f"{path}: the most detailed combination ({row.label}) is not a valid scene: "
                                f"{row.reason}") from None
            if progress:
                progress(f"{row.label:<60} invalid: {row.reason}")
            continue
        try:
            res = run(scene, cache_dir=cache_dir)
        except UserError as exc:  # a clash found when the run starts (the master's choice, a build)
            row.reason = str(exc)
            study.rows.append(row)
            if reference is None:
                raise UserError(f"{path}: the most detailed combination ({row.label}) cannot run: {exc}") from None
            if progress:
                progress(f"{row.label:<60} invalid: {row.reason}")
            continue
        row.dropped = dropped
        row.status, row.reason, row.wall_s = res.status, res.reason, float(res.stats.get("wall_s", math.nan))
        est = res.stats.get("estimate") or {}
        if res.ok and est and est.get("worst") is None:
            row.unestimated = str(est.get("method") or "no companion run")
        if reference is None:
            if not res.ok:
                raise UserError(f"{path}: the most detailed combination ({row.label}) did not run: {res.reason}")
            reference, row.worst = res.trace, 0.0
            if only:  # a misspelt pattern is one line now, not after every other combination ran
                common_names(reference, reference, only)
        elif res.ok:
            diffs = compare(res.trace, reference, only)
            worst = max(diffs, key=lambda d: d.relative)
            row.worst, row.worst_signal = worst.relative, worst.name
        study.rows.append(row)
        if progress:
            progress(f"{row.label:<60} {row.status:<8} worst {row.worst:10.3e} {row.worst_signal:<20} "
                     f"{row.wall_s:8.3f} s" + (f" (without {', '.join(dropped)})" if dropped else ""))
    return study


# --- fidelity: auto ---------------------------------------------------------------------------
def _auto_cache(cache_dir: Path | None) -> Path:
    """``$RPR_COSIM_FIDELITY_CACHE``, else ``fidelity/`` beside the FMU cache."""

    env = os.environ.get("RPR_COSIM_FIDELITY_CACHE")
    root = Path(env) if env else (Path(cache_dir) if cache_dir else cache_root()).parent / "fidelity"
    root.mkdir(parents=True, exist_ok=True)
    return root


def resolve_auto(tree: Any, path: Path, *, cache_dir: Path | None = None,
                 log: Callable[[str], None] | None = None) -> tuple[Any, str]:
    """Replace ``fidelity: auto`` by the cheapest levels within the scene's
    ``fidelity_tolerance`` (default :data:`AUTO_TOLERANCE`); returns the new tree and a one-line
    note of the choice.  The choice is cached by the hash of the scene's data."""

    tol = tree.get("fidelity_tolerance", AUTO_TOLERANCE)
    try:
        tol = float(tol)
    except (TypeError, ValueError):
        tol = math.nan
    if not tol > 0:
        raise UserError(f"{path}: fidelity_tolerance = {tree.get('fidelity_tolerance')!r}: expected a positive "
                        f"relative tolerance, e.g. 1e-4")
    key = hashlib.sha256(json.dumps(plain(tree), sort_keys=True, default=str).encode()).hexdigest()[:24]
    cached = _auto_cache(cache_dir) / f"{key}.json"
    choice = None
    if cached.is_file():
        try:
            choice = json.loads(cached.read_text())
        except ValueError:
            choice = None
    if choice is None:
        if log:
            log(f"[fidelity] {path.name}: studying fidelity levels for 'auto' (tolerance {tol:g}); cached afterwards")
        study = _study_tree(tree, path, cache_dir)  # the scene's own master tolerance (a 10x tighter one cannot be met at 1e-6)
        best = study.cheapest_within(tol)
        if best is None:
            best = study.rows[0]
        choice = {"levels": best.levels, "worst": best.worst, "tolerance": tol, "wall_s": best.wall_s,
                  "highest_wall_s": study.rows[0].wall_s, "created": time.time()}
        tmp = cached.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(choice, indent=1))
        os.replace(tmp, cached)
    levels = choice["levels"]
    note = (f"fidelity auto: picked {', '.join(f'{m}={f}' for m, f in levels.items())} (error {choice['worst']:.2e} "
            f"relative against the most detailed levels, tolerance {choice['tolerance']:g})")
    return _with_levels(tree, levels, True), note


def _study_tree(tree: Any, path: Path, cache_dir: Path | None, tolerance: float | None = None) -> FidelityStudy:
    """:func:`fidelity_study` over an in-memory tree (the one being loaded)."""
    import tempfile

    import yaml


    with tempfile.TemporaryDirectory(prefix="rpr-fidelity-") as tmp:
        # written beside nothing: includes were already merged; FMU paths are made absolute
        data = plain(tree)
        data.pop("include", None)
        for spec in (data.get("components") or {}).values():
            if isinstance(spec, dict) and "fmu" in spec and not Path(str(spec["fmu"])).is_absolute():
                spec["fmu"] = str((path.parent / str(spec["fmu"])).resolve())
        scene_file = Path(tmp) / path.name
        scene_file.write_text(yaml.safe_dump(data, sort_keys=False))
        signals = data.get("fidelity_signals")
        if signals is not None and (not isinstance(signals, list) or not all(isinstance(x, str) for x in signals)):
            raise UserError(f"{path}: fidelity_signals: expected a list of signal names or globs, e.g. "
                            f"[mech.platform.x, 'mech.leg[*].s']")
        return fidelity_study(scene_file, only_auto=True, only=signals, cache_dir=cache_dir, tolerance=tolerance)
