"""Every block of the model catalog (models.blocks) exports to an FMU that validates, runs in
FMPy, equals its own CasADi step map and rolls back exactly."""
from __future__ import annotations

import numpy as np
import pytest
import fmpy
from fmpy.validation import validate_fmu

import fmus
import models.blocks as blocks
from models import integrators as I
from test_fmus import Slave

CATALOG = [(m, f) for m, fs in sorted(blocks.catalog().items()) for f in fs]
IDS = [f"{m}-{f}" for m, f in CATALOG]


def _step(blk) -> float:
    return float(blk.sample_period) if blk.integrator == "discrete" else 1e-3


@pytest.mark.parametrize("model,fidelity", CATALOG, ids=IDS)
def test_catalog_block_exports_validates_and_runs(model, fidelity, cache):
    blk = blocks.make(model, fidelity)
    path = fmus.build_fmu(blk, cache_dir=cache)
    assert validate_fmu(str(path)) == []
    h = _step(blk)
    res = fmpy.simulate_fmu(str(path), stop_time=20 * h, step_size=h, output_interval=h)
    assert res["time"][-1] == pytest.approx(20 * h)
    for v in blk.outputs:
        assert np.all(np.isfinite(res[v.name])), v.name


class _MemoryStep:
    """The step map the FMU runs when its kernel keeps memory between steps (Radau's factors and
    last stages, :func:`models.integrators.radau_memory_kernel`), carried here as ``rpr_core.c``
    carries it: new factors kept when refreshed, the stages kept after an accepted step."""

    def __init__(self, st: I.Stepper):
        self.kernel, nx = st.memory_kernel, st.block.x.numel()
        self.F, self.hF = np.zeros(I.radau_memory_size(st.block)), 0.0
        self.Z, self.hZ = np.zeros(3 * nx), 0.0

    def __call__(self, x, u, p, h):
        xn, ok, _err, F_new, Z, info = self.kernel(x, u, p, h, np.zeros(len(u)), self.F, self.hF, self.Z, self.hZ)
        info = np.asarray(info, dtype=float).ravel()
        if info[0] == 1.0:
            self.F = np.asarray(F_new, dtype=float).ravel()
        self.hF = float(info[1])
        ok = float(ok) == 1.0
        self.Z, self.hZ = (np.asarray(Z, dtype=float).ravel(), h) if ok else (self.Z, 0.0)
        return np.asarray(xn, dtype=float).ravel(), ok


@pytest.mark.parametrize("model,fidelity", CATALOG, ids=IDS)
def test_catalog_fmu_equals_its_casadi_step_map_and_rolls_back(model, fidelity, cache):
    """The FMU against the step map it was generated from, then rollback.  A block with events
    steps through its core's event handling, which no CasADi step map holds (tests/test_events.py
    checks those against analytic solutions): for it the rollback alone."""
    blk = blocks.make(model, fidelity)
    plain = not blk.has_events
    sl = Slave(fmus.build_fmu(blk, cache_dir=cache))
    st = I.Stepper(blk)
    p = st.block.param_defaults  # (a block with events: its modes follow as parameters)
    x = np.asarray(st.start(p), dtype=float).ravel()
    h = _step(blk)
    memory = _MemoryStep(st) if st.memory_kernel is not None else None
    names = [v.name for v in blk.outputs]
    rng = np.random.default_rng(11)
    saved = None
    for k in range(10):
        u = 0.1 * rng.normal(size=len(blk.inputs))
        if len(u):
            sl.setn({v.name: float(val) for v, val in zip(blk.inputs, u)})
        if plain:
            y_ref = np.asarray(st.out(x, u, p), dtype=float).ravel()
            np.testing.assert_allclose(sl.get(*names), y_ref, rtol=1e-10, atol=1e-13)
        if k == 5:
            saved, t_saved = sl.get_state(), sl.t
            first = []
        sl.step(h)
        if plain:
            x, ok = memory(x, u, p, h) if memory else st.step(x, u, p, h)
            assert ok
        if saved is not None:
            first.append(sl.get(*names))
    sl.set_state(saved)
    sl.t = t_saved
    rng = np.random.default_rng(11)
    us = [0.1 * rng.normal(size=len(blk.inputs)) for _ in range(10)]
    again = []
    for k in range(5, 10):
        if len(us[k]):
            sl.setn({v.name: float(val) for v, val in zip(blk.inputs, us[k])})
        sl.step(h)
        again.append(sl.get(*names))
    assert np.array_equal(np.array(first), np.array(again))
    sl.free()


@pytest.mark.parametrize("model,fidelity", [CATALOG[0], CATALOG[-1]], ids=[IDS[0], IDS[-1]])
def test_catalog_block_fmi3_validates_and_runs(model, fidelity, cache):
    blk = blocks.make(model, fidelity)
    path = fmus.build_fmu(blk, fmi_version="3.0", cache_dir=cache)
    assert validate_fmu(str(path)) == []
    h = _step(blk)
    res = fmpy.simulate_fmu(str(path), stop_time=10 * h, step_size=h, output_interval=h)
    assert res["time"][-1] == pytest.approx(10 * h)
