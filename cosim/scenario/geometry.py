"""The manipulator of a mechanism or setpoint component: its ``config`` option (a preset of
:mod:`models.geometry`) with the geometry parameters the scene sets (base joints ``A1x`` ...
``A3y`` [m], platform size ``Lmp`` [m], platform joint angles ``a1`` ... ``a3`` [rad])."""
from __future__ import annotations

from models.geometry import GEOMETRY_FIELDS, Manipulator, preset

_GEOMETRY_PARAMS = ("A1x", "A1y", "A2x", "A2y", "A3x", "A3y", "Lmp", "a1", "a2", "a3")


def manipulator_for(options: dict | None = None, params: dict | None = None) -> Manipulator:
    """The geometry of a mechanism component from its ``config`` option and geometry params."""
    m = preset(str((options or {}).get("config", "cross_leg")))
    params = params or {}
    if not any(k in params for k in _GEOMETRY_PARAMS):
        return m
    g = dict(zip(GEOMETRY_FIELDS, m.geometry_vector()))
    base = tuple((float(params.get(f"A{i}x", g[f"A{i}x"])), float(params.get(f"A{i}y", g[f"A{i}y"])))
                 for i in (1, 2, 3))
    angles = tuple(float(params.get(f"a{i}", g[f"a{i}"])) for i in (1, 2, 3))
    return m.with_(base=base, angles=angles, Lmp=float(params.get("Lmp", m.Lmp)), name=f"{m.name}*")
