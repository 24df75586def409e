"""Manipulator descriptions: presets match SPEC §1 and invalid designs are refused clearly."""
from __future__ import annotations

import numpy as np
import pytest

from models import geometry as G


def test_table_6_8_fixed_joints():
    np.testing.assert_allclose(np.asarray(G.preset().base), [[-0.15, 0.0866], [0.15, 0.0866], [0.0, -0.1732]],
                               atol=5e-5)


@pytest.mark.parametrize("name, side", [("config1", 0.9), ("config2", 0.6), ("config3", 0.3), ("config4", 0.3)])
def test_preset_base_sides(name, side):
    a = np.asarray(G.preset(name).base)
    np.testing.assert_allclose([np.hypot(*(a[i] - a[(i + 1) % 3])) for i in range(3)], side, rtol=1e-12)


@pytest.mark.parametrize("changes, message", [
    ({"base": ((0.0, 0.0), (0.0, 0.0), (0.1, 0.2))}, "A1 and A2 coincide"),
    ({"base": ((0.0, 0.0), (0.1, 0.1), (0.2, 0.2))}, "collinear"),
    ({"Lmin": 0.6, "Lmax": 0.6}, "Lmin < Lmax"),
    ({"Lmp": -0.1}, "Lmp must be a positive"),
    ({"angles": (0.1, 0.1, 2.0)}, "B1 and B2 coincide"),
    ({"inertia": G.Inertia(m_rod=0.0)}, "inertia.m_rod must be positive"),
    ({"inertia": G.Inertia(I_p=-1.0)}, "inertia.I_p must be positive"),
])
def test_invalid_geometry_refused(changes, message):
    with pytest.raises(G.GeometryError, match=message):
        G.preset().with_(**changes)


def test_unknown_preset_lists_names():
    with pytest.raises(G.GeometryError, match="unknown configuration 'config9'.*cross_leg"):
        G.preset("config9")
