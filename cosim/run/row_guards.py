"""The run-time guards: every recorded row of a run checked against the ratings, strokes and singularity of its
catalog blocks (settings, defaults and scene-time checks: :mod:`cosim.scenario.guard_settings`)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
import numpy as np

from ..scenario.guard_settings import (GROWTH, GUARDS, OUT_OF_LIMITS, UNSTABLE, _REL_TOL, GuardSettings, _singular,
                               _singular_text, det_j, guard_needs)


@dataclass
class _Limit:
    name: str  # component.variable
    low: float
    high: float
    kind: str  # "stroke" or "rated"
    unit: str
    source: str


@dataclass
class _Mechanism:
    name: str  # the component
    names: tuple[str, str, str]  # the pose columns
    g: np.ndarray  # geometry vector (10, 1)
    sign0: float | None = None


@dataclass
class Guard:
    """The run-time guards of one scene (build with :func:`scene_guard`).

    :attr:`watch` lists the (component, variable) pairs to sample with the recorded ones;
    :meth:`bind` takes the sampled column names (recorded, then watched), :meth:`check` a block of
    rows (time first) and returns the number of rows to keep when a ``stop`` guard trips (None
    otherwise); then :attr:`status` and :attr:`reason` say why."""

    settings: GuardSettings
    limits: list[_Limit]
    mechanisms: list[_Mechanism]
    watch: list[tuple[str, str]]
    #: components without catalog identity (external FMUs): only the unstable guard watches them
    unknown: list[str] = field(default_factory=list)
    status: str = ""
    reason: str = ""
    warnings: list[str] = field(default_factory=list)
    _col: dict[str, int] = field(default_factory=dict)
    _warned: set = field(default_factory=set)
    _bound: list = field(default_factory=list)
    _lim: tuple = (np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0))
    _bound_abs: np.ndarray | None = None  # per column: max(max_abs, GROWTH |start value|)
    rows_checked: int = 0

    @property
    def tripped(self) -> bool:
        return bool(self.status)

    def bind(self, names: list[str]) -> None:
        """``names``: the sampled variables in row order after the time column."""
        self._col = {n: j + 1 for j, n in enumerate(names)}
        self._bound = [lim for lim in self.limits
                       if lim.name in self._col and getattr(self.settings, lim.kind) != "off"]
        idx = np.array([self._col[lim.name] for lim in self._bound], dtype=np.int64)
        tol = np.array([_REL_TOL * max(abs(lim.low), abs(lim.high), 1.0) for lim in self._bound])
        low = np.array([lim.low for lim in self._bound]) - tol
        high = np.array([lim.high for lim in self._bound]) + tol
        self._lim = (idx, low, high)

    def check(self, rows: np.ndarray) -> int | None:
        if not len(rows) or self.tripped:
            return None
        self.rows_checked += len(rows)
        found = self._unstable(rows) + self._limits(rows) + self._singular(rows)
        stops = [(k, i) for i, (k, action, _, _, _) in enumerate(found) if action == "stop"]
        cut = min(stops)[0] if stops else None
        for k, action, _, text, key in found:
            if action == "warn" and (cut is None or k <= cut) and key not in self._warned:
                self._warned.add(key)
                self.warnings.append(text)
        if cut is None:
            return None
        _, _, self.status, self.reason, _ = found[min(stops)[1]]
        self.rows_checked -= len(rows) - cut - 1  # the rows after the offending one are dropped unseen
        return cut + 1

    def applied(self) -> dict[str, str]:
        """Per guard: its action (``stop``/``warn``) where it looked at every row, ``off``, or
        ``not applied: <why>``; a guard that could not look at some components says which (the
        sidecar's ``guards.applied``)."""
        unknown = ", ".join(self.unknown)
        missing = f"no catalog identity for {unknown} (external FMUs)" if unknown else ""
        out = {}
        for g in GUARDS:
            action = getattr(self.settings, g)
            if action == "off":
                out[g] = "off"
                continue
            if g == "unstable":
                found, what = bool(self._col), "no recorded or connected variable"
            elif g == "singularity":
                found = any(all(n in self._col for n in m.names) for m in self.mechanisms)
                what = "no mechanism pose among the sampled variables"
            else:
                found, what = any(lim.kind == g for lim in self._bound), f"no {g} variable among the sampled ones"
            if not found:
                out[g] = f"not applied: {what}" + (f"; {missing}" if missing and g != "unstable" else "")
            else:
                out[g] = action + (f" (not applied to {unknown}: no catalog identity)" if unknown and g != "unstable"
                                   else "")
        return out

    def summary(self) -> dict:
        return {"settings": asdict(self.settings), "applied": self.applied(), "rows_checked": self.rows_checked,
                "warnings": list(self.warnings), "tripped": self.reason}

    # the checks: each returns [(first bad row, action, status, message, key)] ---------------------
    def _unstable(self, rows: np.ndarray) -> list:
        action = self.settings.unstable
        if action == "off" or rows.shape[1] < 2:
            return []
        vals = rows[:, 1:]
        if self._bound_abs is None:  # the first row seen is the start
            start = np.abs(vals[0])
            self._bound_abs = np.maximum(self.settings.max_abs, GROWTH * np.where(np.isfinite(start), start, 0.0))
        bad = ~np.isfinite(vals) | (np.abs(vals) > self._bound_abs)  # NaN compares False: no warning
        if not bad.any():
            return []
        k = int(np.argmax(bad.any(axis=1)))
        j = int(np.argmax(bad[k]))
        name = next((n for n, c in self._col.items() if c == j + 1), f"column {j + 1}")
        v = vals[k, j]
        bound = self._bound_abs[j]
        why = ("not finite" if not np.isfinite(v) else f"|value| beyond guards.max_abs = {bound:g}"
               if bound == self.settings.max_abs else f"|value| beyond {bound:g}, {GROWTH:g} times its start value")
        return [(k, action, UNSTABLE, f"unstable: {name} = {v:.6g} at t = {rows[k, 0]:.6g} s ({why})", name)]

    def _limits(self, rows: np.ndarray) -> list:
        idx, low, high = self._lim
        if not len(idx):
            return []
        vals = rows[:, idx]
        bad = (vals < low) | (vals > high)
        if not bad.any():
            return []
        out = []
        for m in np.flatnonzero(bad.any(axis=0)):
            lim, j = self._bound[m], int(idx[m])
            action = getattr(self.settings, lim.kind)
            k = int(np.argmax(bad[:, m]))
            v, t = rows[k, j], rows[k, 0]
            if lim.kind == "stroke":
                text = (f"out of stroke: {lim.name} = {v:.4g} m at t = {t:.6g} s, outside the stroke "
                        f"[{lim.low:g}, {lim.high:g}] m (guards.stroke)")
            else:
                text = (f"beyond rating: {lim.name} = {v:.4g} {lim.unit} at t = {t:.6g} s, outside the rated "
                        f"[{lim.low:g}, {lim.high:g}] {lim.unit} ({lim.source}; guards.rated)")
            out.append((k, action, OUT_OF_LIMITS, text, lim.name))
        return out

    def _singular(self, rows: np.ndarray) -> list:
        action = self.settings.singularity
        if action == "off":
            return []
        out = []
        for mech in self.mechanisms:
            cols = [self._col.get(n) for n in mech.names]
            if None in cols:
                continue
            det = det_j(None, rows[:, cols].T, mech.g)
            if mech.sign0 is None and len(det) and np.isfinite(det[0]) and det[0] != 0:
                mech.sign0 = float(np.sign(det[0]))
            k = _singular(det, self.settings.min_det, mech.sign0)
            if k is not None:
                text = (f"singularity: {mech.name}{_singular_text(det, k, rows[:, 0], self.settings.min_det)} "
                        f"(guards.singularity)")
                out.append((k, action, OUT_OF_LIMITS, text, mech.name))
        return out


def scene_guard(scene) -> Guard | None:
    """The guards of ``scene`` (None when all are off): the rated and stroke variables of its
    catalog components, the pose of each mechanism, and every connected output.  What a
    component contributes comes from its :class:`cosim.scenario.guard_settings.GuardNeeds` (plain data,
    made from its block, or carried to a batch worker or through an SSP archive without one);
    components without it (external FMUs) are watched by the unstable guard only, and the guards
    that then look at nothing say so (:meth:`Guard.applied`)."""
    settings: GuardSettings = getattr(scene, "guards", None) or GuardSettings()
    if not settings.active:
        return None
    limits, mechanisms, watch, unknown = [], [], [], []
    for name, comp in scene.components.items():
        needs = guard_needs(comp)
        if needs is None:
            unknown.append(name)
            continue
        for r in needs.ratings:
            limits.append(_Limit(f"{name}.{r.var}", r.low, r.high, r.kind, r.unit, r.source))
            watch.append((name, r.var))
        if needs.pose:
            mechanisms.append(_Mechanism(name, tuple(f"{name}.{v}" for v in needs.pose),
                                         np.asarray(needs.geometry, float).reshape(-1, 1)))
            watch += [(name, v) for v in needs.pose]
    watch += [(c.src, c.src_var) for c in scene.connections]
    return Guard(settings, limits, mechanisms, list(dict.fromkeys(watch)), unknown)


__all__ = ["Guard", "scene_guard"]

