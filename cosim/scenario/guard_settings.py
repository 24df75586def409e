"""Physical guards, their settings and their scene-time checks (the run-time checks of every recorded
row: :mod:`cosim.run.row_guards`).  A run of the robot's scenes is "ok" only if it stayed physical and within limits.

Four guards watch every recorded row of a run (at ``master.output_interval``), on by default:

``stroke``
    a leg length ``leg[i].s`` of a mechanism (or of a setpoint) outside its actuator's stroke
    ``[Lmin, Lmax]`` (docs/explanation/thesis.md §1: 0.10-0.60 m; the block's :class:`~models.block.Rating` of kind
    ``"stroke"``).  There are no modelled end stops: the run is stopped "out of stroke" with the
    leg, the time and the value.
``rated``
    a variable beyond its component's rated values (the block's ratings of kind ``"rated"``: the
    DC motor's voltage ``u`` +-12 V and current ``i`` +-30 A, :mod:`models.blocks.motor`).
``singularity``
    ``|det J|`` of a mechanism's platform pose below ``min_det`` [m] (J of eq. 4.14 in SI units,
    :func:`models.kinematics.dexterity`), or det J changing sign (the pose passed a singular
    configuration between two rows).
``unstable``
    a non-finite value, or a value that grew beyond ``max(max_abs, 1000 |start value|)``, in any
    recorded or connected variable of any slave (external FMUs included; a large constant such
    as an Int64 input of 2**40 is its own scale): status "unstable".

Each guard's action is ``stop`` (default: the run ends with status "out_of_limits" (stroke,
rated, singularity) or "unstable"; not "stopped", which is a component's own request to end, the
rows after the offending one dropped, the reason in the sidecar), ``warn`` (the run goes on; the
first crossing is kept in the statistics' ``guards.warnings``) or ``off``.  A scene sets them under
``guards:`` (``guards: off`` turns all off)::

    guards: {stroke: stop, rated: stop, singularity: stop, unstable: stop, min_det: 0.01, max_abs: 1e6}

At scene check time (:func:`check_scene`), every ``pose_setpoint`` component's commanded path is
sampled over the run (the block's own output function, i.e. inverse kinematics of
:mod:`models.kinematics`): a leg outside its stroke, or a singular pose on the path, is a scene
error (a warning with ``warn``), naming the leg, the time and the stroke.

Which component is the mechanism, where its legs and pose are, and what the ratings are all come
from the catalog blocks of the scene (their model and :attr:`~models.block.Block.ratings`), not
from component names.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from .yamlfile import YMap
from .problems import suggest
from .geometry import manipulator_for
from fmus.index import replay
from models.numeric import vectorize

ACTIONS = ("stop", "warn", "off")
GUARDS = ("stroke", "rated", "singularity", "unstable")
#: Settings and their defaults (actions, then thresholds).
DEFAULTS: dict[str, Any] = {"stroke": "stop", "rated": "stop", "singularity": "stop", "unstable": "stop",
                            "min_det": 0.01, "max_abs": 1e6}
POSE = ("platform.x", "platform.y", "platform.phi")
#: Run statuses of a tripped guard (a run that ends with either is not "ok": exit code 1).
OUT_OF_LIMITS, UNSTABLE = "out_of_limits", "unstable"
_SAMPLES = 2001  # points of a setpoint's path checked at scene time
_REL_TOL = 1e-9  # a value exactly at its rating (a PID limited to 12 V) is inside it
GROWTH = 1e3  # a variable is unstable beyond max(max_abs, GROWTH |its start value|)


@dataclass(frozen=True)
class GuardSettings:
    """The ``guards:`` section of a scene: an action per guard (stop | warn | off), the
    singularity threshold ``min_det`` on |det J| [m] and the instability bound ``max_abs``."""

    stroke: str = DEFAULTS["stroke"]
    rated: str = DEFAULTS["rated"]
    singularity: str = DEFAULTS["singularity"]
    unstable: str = DEFAULTS["unstable"]
    min_det: float = DEFAULTS["min_det"]
    max_abs: float = DEFAULTS["max_abs"]

    @property
    def active(self) -> bool:
        return any(getattr(self, g) != "off" for g in GUARDS)


@dataclass(frozen=True)
class GuardedRating:
    """One rated or stroke-limited variable of a component: ``[low, high]`` in ``unit``."""

    var: str
    low: float
    high: float
    kind: str  # "stroke" or "rated"
    unit: str = ""
    source: str = ""


@dataclass(frozen=True)
class GuardNeeds:
    """What the run-time guards need of one component, as plain data (no CasADi block): its
    catalog identity (``model/fidelity``), its ratings, and for a mechanism the pose variables
    and the geometry vector (:data:`models.geometry.GEOMETRY_FIELDS`).  Made from the block at
    scene load (:func:`guard_needs`), it travels with the component to batch workers and in the
    SSP archive's component annotation (:meth:`as_dict`, :meth:`from_dict`)."""

    identity: str
    ratings: tuple[GuardedRating, ...] = ()
    pose: tuple[str, str, str] | None = None
    geometry: tuple[float, ...] | None = None

    def as_dict(self) -> dict:
        return {"identity": self.identity, "ratings": [asdict(r) for r in self.ratings],
                **({"pose": list(self.pose), "geometry": list(self.geometry)} if self.pose else {})}

    @classmethod
    def from_dict(cls, data: Mapping) -> "GuardNeeds":
        """The needs written by :meth:`as_dict`; ValueError (with the key) when malformed."""
        try:
            ratings = tuple(GuardedRating(str(r["var"]), float(r["low"]), float(r["high"]), str(r["kind"]),
                                          str(r.get("unit", "")), str(r.get("source", "")))
                            for r in data.get("ratings", ()))
            pose = tuple(str(v) for v in data["pose"]) if data.get("pose") else None
            geo = tuple(float(x) for x in data["geometry"]) if pose else None
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"malformed guard data ({type(exc).__name__}: {exc})") from None
        if any(r.kind not in ("stroke", "rated") for r in ratings):
            raise ValueError("a rating's kind must be stroke or rated")
        if pose is not None and (len(pose) != 3 or geo is None or len(geo) != 10):
            raise ValueError("a mechanism's guard data needs 3 pose variables and 10 geometry values")
        return cls(str(data.get("identity", "")), ratings, pose, geo)


def guard_needs(comp) -> GuardNeeds | None:
    """The guards' needs of component ``comp`` (:class:`GuardNeeds`): kept on the component
    (``comp.guard``) once made; made from its catalog block when it has one; None for a component
    without catalog identity (an external FMU: only the unstable guard applies to it)."""
    have = getattr(comp, "guard", None)
    if have is not None:
        return have
    blk = comp.block if comp.kind == "model" else None
    if blk is None:
        return None
    variables = comp.description.variables
    ratings = tuple(GuardedRating(var, float(r.low), float(r.high), r.kind,
                                  variables[var].unit if var in variables else "", r.source)
                    for var, r in blk.ratings.items())
    pose = geo = None
    if comp.model == "mechanism" and getattr(comp, "origin", None) is None and all(v in variables for v in POSE):
        pose, geo = POSE, tuple(float(x) for x in geometry(comp).reshape(-1))
    comp.guard = GuardNeeds(comp.label, ratings, pose, geo)
    return comp.guard


# --- scene time ----------------------------------------------------------------------------------
def parse_settings(node: Any, loc, err) -> GuardSettings:
    """Settings from a scene's ``guards:`` node (None: defaults; ``off``/``false``: all off);
    problems go to ``err(where, message)`` with ``loc(key)`` giving the line of a key."""

    if node is None or node is True:
        return GuardSettings()
    if node is False or node == "off":
        return GuardSettings(**{g: "off" for g in GUARDS})
    if not isinstance(node, Mapping):
        err(loc(None), f"guards must be a mapping (e.g. {{stroke: stop, singularity: warn}}) or off, got {_show(node)}")
        return GuardSettings()
    values: dict[str, Any] = {}
    where = node.loc if isinstance(node, YMap) else loc
    for key, val in node.items():
        if not isinstance(key, str) or key not in DEFAULTS:
            err(where(key), f"unknown key {key!r} in guards{suggest(str(key), DEFAULTS)} "
                            f"(expected: {', '.join(DEFAULTS)})")
        elif key in GUARDS:
            action = {False: "off", True: "stop"}.get(val, val) if isinstance(val, bool) else val
            if action not in ACTIONS:
                err(where(key), f"guards.{key} = {_show(val)}{suggest(str(val), ACTIONS)}; expected stop, warn or off")
            else:
                values[key] = action
        elif not _positive(val):
            err(where(key), f"guards.{key} = {_show(val)} must be a positive number "
                            f"({'[m], |det J| threshold' if key == 'min_det' else 'bound on |value|'})")
        else:
            values[key] = float(val)
    return GuardSettings(**values)


def _show(val: Any, width: int = 60) -> str:
    text = repr(val)
    return text if len(text) <= width else text[:width - 3] + "..."


def _positive(val: Any) -> bool:
    """A finite positive number (a bool is not; an integer too large for a float is not)."""
    if isinstance(val, bool) or not isinstance(val, (int, float)):
        return False
    try:
        return math.isfinite(float(val)) and val > 0
    except OverflowError:
        return False


def check_scene(settings: GuardSettings, comps: Mapping[str, Any], duration: float | None, err, warn) -> None:
    """Refuse (``err``) or flag (``warn``) setpoints that command poses outside the workspace or
    through a singular pose over the run's ``duration`` [s], per ``settings``; ``err``/``warn``
    take (where, message)."""
    if duration is None:
        return
    for comp in comps.values():
        if comp.kind != "model" or comp.model != "pose_setpoint" or comp.origin is not None or comp.block is None:
            continue
        for action, message in setpoint_problems(comp, duration, settings):
            (err if action == "stop" else warn)(comp.where, message)


#: :func:`setpoint_problems` by component and duration: a batch validates many scenes whose
#: setpoints are the same (evaluating a setpoint path costs ~25 ms)
_SETPOINT_MEMO: dict[tuple, list[tuple[str, str]]] = {}


def setpoint_problems(comp, duration: float, settings: GuardSettings) -> list[tuple[str, str]]:
    """(action, message) for every leg of a pose setpoint that leaves its stroke over the
    ``duration`` [s] of a run (its clock from its parameter ``t0`` on), and for a singular pose
    on its path; times in the messages are clock times."""
    if settings.stroke == "off" and settings.singularity == "off":
        return []
    import json

    key = (comp.name, comp.label, json.dumps([comp.options, comp.params], sort_keys=True, default=repr),
           float(duration), settings)
    if key not in _SETPOINT_MEMO:
        if len(_SETPOINT_MEMO) >= 256:
            _SETPOINT_MEMO.clear()
        _SETPOINT_MEMO[key] = _setpoint_problems(comp, duration, settings)
    return list(_SETPOINT_MEMO[key])


def _setpoint_problems(comp, duration: float, settings: GuardSettings) -> list[tuple[str, str]]:
    blk = comp.block
    p = blk.param_vector(**comp.params)
    t = np.linspace(0.0, duration, _SAMPLES)
    t0 = p[blk.index("params", "t0")] if any(q.name == "t0" for q in blk.params) else 0.0
    t = t + t0  # the block's clock
    y = _outputs_over_time(blk, t, p)
    col = {v.name: y[i] for i, v in enumerate(blk.outputs)}
    pose = np.vstack([col[n] for n in POSE]) if all(n in col for n in POSE) else None
    found: list[tuple[str, str]] = []
    if settings.stroke != "off":
        for var, r in blk.ratings.items():
            if r.kind != "stroke" or var not in col:
                continue
            bad = _outside(col[var], r.low, r.high)
            if bad.any():
                k = int(np.argmax(bad))
                at = f" at t = {t[k]:.6g} s" + (f" (pose x = {pose[0, k]:.4g} m, y = {pose[1, k]:.4g} m, "
                                               f"phi = {pose[2, k]:.4g} rad)" if pose is not None else "")
                found.append((settings.stroke, f"component {comp.name!r} ({comp.label}) commands {_leg(var)} to "
                                               f"{col[var][k]:.4g} m{at}, outside the stroke [{r.low:g}, {r.high:g}] m "
                                               f"of the workspace" + _hint(settings.stroke, "stroke", "a pose inside it")))
    if settings.singularity != "off" and pose is not None:
        det = det_j(comp, pose)
        k = _singular(det, settings.min_det)
        if k is not None:
            found.append((settings.singularity, f"component {comp.name!r} ({comp.label}) commands a singular pose"
                                                f"{_singular_text(det, k, t, settings.min_det)}"
                                                + _hint(settings.singularity, "singularity", "a path away from it")))
    return found


def _outputs_over_time(blk, t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The outputs (rows) of a source block whose one state is its clock, at clock times ``t``,
    by the numpy replay of its output function (:mod:`models.numeric`; an indexed block keeps it
    in the FMU cache, so no CasADi is needed)."""
    if hasattr(blk, "replay"):
        fn = blk.replay("out")
    else:

        fn = vectorize(blk.functions()["out"])
    return np.asarray(fn([t], [], list(p))[0], float).reshape(len(blk.outputs), len(t))


def _hint(action: str, guard: str, what: str) -> str:
    return f"; choose {what} (or set guards.{guard}: warn)" if action == "stop" else ""


def _leg(var: str) -> str:
    return f"leg {var[4:-3]}" if var.startswith("leg[") and var.endswith("].s") else var


def _outside(v: np.ndarray, low: float, high: float) -> np.ndarray:
    tol = _REL_TOL * max(abs(low), abs(high), 1.0)
    return (v < low - tol) | (v > high + tol)


def geometry(comp) -> np.ndarray:
    """The geometry vector (:data:`models.geometry.GEOMETRY_FIELDS`) of a mechanism or setpoint
    component: its ``config`` option and geometry parameters, shape (10, 1)."""

    return manipulator_for(comp.options, comp.params).geometry_vector().reshape(-1, 1)


def det_j(comp, pose: np.ndarray, g: np.ndarray | None = None) -> np.ndarray:
    """det J [m] (eq. 4.14, SI units; :func:`models.kinematics.dexterity`) of ``comp``'s
    geometry ``g`` (default :func:`geometry`) at poses ``pose`` of shape (3, N)."""
    det = _det_map()(np.asarray(pose, float), geometry(comp) if g is None else g)
    return np.asarray(det, float).reshape(-1)


@lru_cache(maxsize=1)
def _det_map():
    """The numpy replay of det J (:func:`models.kinematics.numpy_map`), kept in the FMU cache's
    index (:func:`fmus.index.replay`) so that a run needs no CasADi for it."""

    def build():
        from models import kinematics

        return kinematics.numpy_map("det")

    return replay("kinematics.det", build)


def _singular(det: np.ndarray, min_det: float, sign0: float | None = None) -> int | None:
    """First index where |det| < min_det or det's sign differs from ``sign0`` (default: det[0]'s)."""
    if not len(det):
        return None
    s0 = np.sign(det[0]) if sign0 is None else sign0
    bad = (np.abs(det) < min_det) | (np.sign(det) != s0)
    bad &= np.isfinite(det)
    return int(np.argmax(bad)) if bad.any() else None


def _singular_text(det: np.ndarray, k: int, t: np.ndarray, min_det: float) -> str:
    if abs(det[k]) < min_det:
        return f": |det J| = {abs(det[k]):.3g} m at t = {t[k]:.6g} s, below guards.min_det = {min_det:g} m"
    before = f"t = {t[k - 1]:.6g} and " if k > 0 else "before "
    return f": det J changes sign between {before}t = {t[k]:.6g} s (now {det[k]:.3g} m)"




__all__ = ["ACTIONS", "DEFAULTS", "GuardNeeds", "GuardSettings", "GuardedRating", "check_scene", "guard_needs", "det_j", "parse_settings", "setpoint_problems"]
