"""Mechanism start rates (vx0, vy0, omega0): the rigid and the multibody fidelities started with
the same moving platform agree, and the multibody bodies start with the velocities of the rigid
motion (every joint relaxed and not stretching), checked against finite differences of the
bodies' start positions."""
from __future__ import annotations

import numpy as np
import pytest

import models.blocks as B
from test_blocks import simulate

START = {"x0": -0.2, "y0": -0.12, "phi0": 0.15}
RATES = [{"vx0": 0.05, "vy0": -0.03, "omega0": 0.4}, {"vx0": -0.08, "vy0": 0.0, "omega0": 0.0},
         {"vx0": 0.0, "vy0": 0.0, "omega0": -0.6}]


def _start_out(blk):
    F = blk.functions()
    x0 = F["start"](blk.param_defaults)
    return np.array(F["out"](x0, np.zeros(3), blk.param_defaults)).ravel(), np.array(x0).ravel()


@pytest.mark.parametrize("fidelity", ["rigid", "multibody"])
def test_start_rates_are_parameters(fidelity):
    names = [p.name for p in B.make("mechanism", fidelity).params]
    assert {"vx0", "vy0", "omega0"} <= set(names)


@pytest.mark.parametrize("rates", RATES, ids=["general", "vx", "omega"])
def test_multibody_start_velocities_are_those_of_the_rigid_motion(rates):
    """Outputs at the start (pose, platform rates, leg lengths and rates) equal the rigid ones,
    and each body's start velocity equals the finite difference of its start position along the
    platform's motion (the multibody start placed at q0 +- eps qd0)."""
    rigid = B.make("mechanism", "rigid", **START, **rates)
    mb = B.make("mechanism", "multibody", **START, **rates)
    y_r, _ = _start_out(rigid)
    y_m, x_m = _start_out(mb)
    np.testing.assert_allclose(y_m, y_r, atol=1e-13)
    eps = 1e-6
    qd = np.array([rates["vx0"], rates["vy0"], rates["omega0"]])
    shifted = []
    for sgn in (1, -1):
        q = np.array([START["x0"], START["y0"], START["phi0"]]) + sgn * eps * qd
        shifted.append(_start_out(B.make("mechanism", "multibody", x0=q[0], y0=q[1], phi0=q[2]))[1].reshape(7, 6))
    fd = (shifted[0] - shifted[1]) / (2 * eps)  # global mass-centre velocity and angular rate
    body = x_m.reshape(7, 6)
    for j in range(7):
        c, s = np.cos(body[j, 2]), np.sin(body[j, 2])
        v_global = np.array([[c, -s], [s, c]]) @ body[j, 3:5]
        np.testing.assert_allclose(v_global, fd[j, :2], atol=1e-8)
        assert body[j, 5] == pytest.approx(fd[j, 2], abs=1e-8)
    xdot = np.array(mb.functions()["ode"](x_m, np.zeros(3), mb.param_defaults)).ravel().reshape(7, 6)
    assert np.abs(xdot[:, 3:]).max() < 5.0  # no joint force spike (a stretched 1e8 N/m joint gives >> 1e3)


def test_multibody_and_rigid_agree_in_free_motion_from_the_same_rates():
    """Issue 8 acceptance: started with the same non-zero rates and no force, the two fidelities'
    poses agree to 1e-6 m (and rad) over 0.5 s (both integrated by CVODES at 1e-10)."""
    rates = RATES[0]
    ts = np.linspace(0.0, 0.5, 51)
    y_r, _ = simulate(B.make("mechanism", "rigid", **START, **rates), ts)
    y_m, _ = simulate(B.make("mechanism", "multibody", **START, **rates), ts)
    assert np.abs(y_r[-1, :3] - y_r[0, :3]).max() > 0.01  # it really moved
    assert np.abs(y_m[:, :3] - y_r[:, :3]).max() < 1e-6
