"""A recording as a scene component: ``{replay: FILE}``.

The file is a trace: a CSV with a header (a column named ``time`` [s], strictly increasing, then one
column per signal) or a Parquet file of the same shape, written by ``rpr-cosim run``, by the rig (or
the virtual board, :mod:`hardware.record`) or by hand.  Each column becomes an output of the
component, named as the column, in the unit the trace's metadata (its ``# units:`` line or JSON
sidecar) gives, or the scene states (``units: {COLUMN: UNIT}``, which wins).  ``interpolation``:
``linear`` (default; samples of a continuous signal) or ``hold`` (a command held until the next
sample).  The component is an FMU with the table compiled in (:mod:`fmus.replay`).

Refused, in one line naming the file: no ``time`` column, a time that does not increase strictly, a
value that is not a number, a column named twice; and, once the scene is known
(:meth:`ReplayChecks.replay_scene`), a scene that runs outside the recording's span, and a connection
from a column whose unit is unknown or differs from its destination's.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError
from .checker import Checker
from .model import Component, Connection
from .problems import suggest
from .yamlfile import YMap, _display
from ..trace.traces import read_trace
from fmus.errors import BuildError
from fmus.replay import build_replay_fmu
from ..slaves.description import describe_fmu

#: Keys of a replay component.
REPLAY_KEYS = ("replay", "interpolation", "units", "description")
INTERPOLATIONS = ("linear", "hold")
#: Slack [s] of the span check: a master's time equal to the last instant but for rounding is inside.
SPAN_SLACK = 1e-9


@dataclass
class Recording:
    """A trace read for replay: ``time`` [s], ``data`` (one column per name), ``units`` by name."""

    path: Path
    time: np.ndarray
    names: list[str]
    data: np.ndarray
    units: dict[str, str] = field(default_factory=dict)
    interpolation: str = "linear"

    def column(self, name: str) -> np.ndarray:
        return self.data[:, self.names.index(name)]


def read_recording(path: Path | str, units: dict[str, str] | None = None, interpolation: str = "linear") -> Recording:
    """Read and check a recording (module docstring); raises :class:`UserError` naming the file."""

    path = Path(path)
    where = _display(path)
    if interpolation not in INTERPOLATIONS:
        raise UserError(f"{where}: interpolation {interpolation!r}; expected one of {', '.join(INTERPOLATIONS)}")
    try:
        trace = read_trace(path)
    except UserError as exc:
        raise UserError(f"not a trace: {exc}") from None
    cols = [c.strip() for c in trace.columns]
    dup = sorted({c for c in cols if cols.count(c) > 1})
    if dup:
        raise UserError(f"{where}: column {dup[0]!r} appears twice in the header")
    if "time" not in cols:
        raise UserError(f"{where}: not a trace: no 'time' column (the header names {', '.join(cols[:4])}"
                        f"{', ...' if len(cols) > 4 else ''}; the time in seconds must be a column named time)")
    if len(trace.data) < 2:
        raise UserError(f"{where}: not a trace: {len(trace.data)} row(s); a replay needs at least two instants")
    k = cols.index("time")
    t = trace.data[:, k]
    bad = np.flatnonzero(~np.isfinite(trace.data).all(axis=1))
    if len(bad):
        j = int(np.flatnonzero(~np.isfinite(trace.data[bad[0]]))[0])
        raise UserError(f"{where}: row {bad[0] + 1} of the data: {cols[j]} is not a finite number")
    back = np.flatnonzero(np.diff(t) <= 0)
    if len(back):
        i = int(back[0])
        raise UserError(f"{where}: not a trace: time does not increase at row {i + 2} of the data "
                        f"({t[i]!r} s, then {t[i + 1]!r} s)")
    names = [c for c in cols if c != "time"]
    known = {str(n): str(u) for n, u in (trace.meta.get("units") or {}).items() if u}
    for n, u in (units or {}).items():
        if n not in names:
            raise UserError(f"{where}: units names column {n!r}, which the file does not have{suggest(n, names)}")
        known[n] = str(u)
    data = np.column_stack([trace.data[:, cols.index(n)] for n in names]) if names else np.zeros((len(t), 0))
    if not names:
        raise UserError(f"{where}: not a trace: no column besides time")
    return Recording(path, t.copy(), names, data, {n: known[n] for n in names if n in known}, interpolation)


class ReplayChecks(Checker):
    """The checks of replay components (a mixin of the scene checker)."""

    def _replay_component(self, name: str, spec: YMap) -> Component | None:


        for k in spec:
            if k not in REPLAY_KEYS:
                self.err(spec.loc(k), f"component {name!r}: '{k}' does not apply to a replay (keys: "
                                      f"{', '.join(REPLAY_KEYS)})")
                return None
        where, rel = spec.loc("replay"), spec["replay"]
        if not isinstance(rel, str):
            self.err(where, f"component {name!r}: replay must be a file path (CSV or Parquet), got {rel!r}")
            return None
        units = spec.get("units") or YMap()
        if not isinstance(units, YMap) or not all(isinstance(v, str) for v in units.values()):
            self.err(spec.loc("units"), f"component {name!r}: units must be a mapping COLUMN: UNIT (text), "
                                        f"got {units!r}")
            return None
        interp = spec.get("interpolation", "linear")
        if interp not in INTERPOLATIONS:
            self.err(spec.loc("interpolation"), f"component {name!r}: interpolation {interp!r}; expected "
                                                f"{' or '.join(INTERPOLATIONS)}")
            return None
        base = Path(where[0]).parent if where[1] else (self.path.parent if self.path else Path.cwd())
        fpath = Path(rel).expanduser()
        fpath = Path(os.path.normpath(fpath if fpath.is_absolute() else base / fpath))
        if not fpath.is_file():
            self.err(where, f"component {name!r}: recording {_display(fpath)} not found (a relative path is "
                            f"relative to the scene file)")
            return None
        try:
            rec = read_recording(fpath, {str(k): v for k, v in units.items()}, str(interp))
            fmu = build_replay_fmu(rec.time, rec.data, rec.names, units=rec.units, interpolation=rec.interpolation,
                                   source=fpath.name)
        except (UserError, BuildError) as exc:
            self.err(where, f"component {name!r}: {exc}")
            return None
        comp = Component(name, "fmu", describe_fmu(fmu), fmu=fmu, where=spec.where)
        comp.replay = rec
        return comp

    def replay_scene(self, comps: dict[str, Component], conns: list[Connection], start: float | None,
                     stop: float | None) -> None:
        """What a replay needs of the scene: its span inside the recording, and each connection
        from a column in a known unit that is its destination's."""
        for c in comps.values():
            rec = getattr(c, "replay", None)
            if rec is None:
                continue
            t0, t1 = float(rec.time[0]), float(rec.time[-1])
            if start is not None and stop is not None and (start < t0 - SPAN_SLACK or stop > t1 + SPAN_SLACK):
                self.err(c.where, f"component {c.name!r}: recording {_display(rec.path)} covers {t0:g}..{t1:g} s, "
                                  f"shorter than the scene's {start:g}..{stop:g} s")
        for cn in conns:
            rec = getattr(comps.get(cn.src), "replay", None)
            if rec is None:
                continue
            dst = comps[cn.dst].description.variables.get(cn.dst_var)
            want = dst.unit if dst is not None else ""
            have = rec.units.get(cn.src_var, "")
            if want and not have:
                self.err(cn.where, f"connection {cn}: the unit of column {cn.src_var!r} of {_display(rec.path)} is "
                                   f"unknown and {cn.dst}.{cn.dst_var} is in {want}; state it in the scene "
                                   f"(units: {{{cn.src_var}: {want}}})")
            elif want and have != want and cn.factor == 1.0:
                self.err(cn.where, f"connection {cn}: column {cn.src_var!r} of {_display(rec.path)} is in {have}, "
                                   f"{cn.dst}.{cn.dst_var} expects {want} (convert with '* FACTOR')")


__all__ = ["INTERPOLATIONS", "REPLAY_KEYS", "Recording", "ReplayChecks", "read_recording"]
