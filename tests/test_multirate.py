"""Multirate stepping (``components.X.rate``) against an independent account of it.

The scene is ``scenarios/two_mass.yaml`` (two linear oscillators cut at a spring) with the slaves'
embedded RK4 at one substep per doStep, so that a slave's sub-steps change its result.  The
independent account is :func:`models.coupling.macro_map` with the RK4 map of each slave under its
held or ramped input (:func:`models.coupling.rk4_ramp_discretization`), written from the
conventions of :mod:`cosim.master.multirate` and sharing no code with the master: the trajectory of
``Z_k+1 = M Z_k`` must equal the co-simulation's trace to rounding, in both engines, bit for bit
between them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.errors import UserError
from cosim.run.execute import run
from cosim.scenario import SceneError, load
from models.coupling import Link, linearize, macro_map, rk4_ramp_discretization

SCENE = Path(__file__).resolve().parents[1] / "scenarios" / "two_mass.yaml"
STEP, STOP = 0.05, 3.0  # 60 macro steps; kc = 100 N/m: omega h ~ 0.7, RK4 stable, its error visible
BASE = {"components.mass1.options.substeps": 1, "components.mass2.options.substeps": 1,
        "master.step": STEP, "master.output_interval": STEP, "stop_time": STOP}


def overrides(alg: str, inputs: str, rates: dict[str, int]) -> dict:
    return {**BASE, "master.algorithm": alg, "master.inputs": inputs,
            **{f"components.{n}.rate": r for n, r in rates.items()}}


def analytic(alg: str, inputs: str, rates: dict[str, int]) -> tuple[list[str], np.ndarray]:
    """The recorded columns and their values at t_0..t_n from the RK4 macro-step map."""
    scene = load(SCENE, overrides(alg, inputs, rates))
    names = list(scene.components)
    comps = list(scene.components.values())
    slaves, x0 = [], []
    for c in comps:
        params = {k: v for k, v in c.params.items() if k in {p.name for p in c.block.params}}
        slaves.append(linearize(c.block, params))
        x0.append(np.array(c.block.functions()["start"](c.block.param_vector(**params))).ravel())
    links = [Link(names.index(c.src), scene.components[c.src].block.index("outputs", c.src_var),
                  names.index(c.dst), scene.components[c.dst].block.index("inputs", c.dst_var))
             for c in scene.connections]
    # the master's Gauss-Seidel order for this scene: mass2 (the spring's carrier) feeds mass1 ...
    from cosim.master import gauss_seidel_order

    order = gauss_seidel_order(len(names), [(ln.src, ln.dst) for ln in links])
    M = macro_map(slaves, links, STEP, alg, inputs, order, rates=[rates.get(n, 1) for n in names],
                  discretization=rk4_ramp_discretization)
    x = np.concatenate(x0)
    offs = np.cumsum([0] + [len(v) for v in x0])
    y_of = lambda z, ln: slaves[ln.src].C[ln.out] @ z[offs[ln.src]:offs[ln.src + 1]]  # noqa: E731
    z = np.concatenate([x, [y_of(x, ln) for ln in links]])  # y_-1 = y_0: no slope in the first step
    rows = []
    for _ in range(round(STOP / STEP) + 1):
        row = []
        for col in scene.outputs:
            cname, _, var = col.partition(".")
            i = names.index(cname)
            row.append(slaves[i].C[slaves[i].outputs.index(var)] @ z[offs[i]:offs[i + 1]])
        rows.append(row)
        z = M @ z
    return scene.outputs, np.array(rows)


VARIANTS = [(a, i) for a in ("jacobi", "gauss_seidel") for i in ("hold", "linear")]
RATES = [{"mass2": 4}, {"mass1": 5, "mass2": 2}]


@pytest.mark.parametrize("rates", RATES, ids=lambda r: ",".join(f"{k}x{v}" for k, v in r.items()))
@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: "/".join(v))
def test_multirate_trace_is_the_substepped_macro_map(variant, rates):
    """Python and compiled loops equal each other bit for bit and the RK4 macro-step map with
    sub-steps to rounding; the sub-steps matter (the single-rate map is far off)."""
    alg, inputs = variant
    cols, want = analytic(alg, inputs, rates)
    traces = {}
    for engine in ("oracle", "compiled"):
        res = run(SCENE, overrides(alg, inputs, rates), engine=engine)
        # the whole span ran; at 50 ms on kc = 100 N/m the coupling is far off the coupled solution,
        # which the run's own error estimate may say ("unstable"): this test is about the map
        assert res.stats["status"] == "ok" or res.stats["reason"].startswith("the estimated error of ")
        assert res.stats["engine"] == engine and res.stats["steps_done"] == round(STOP / STEP)
        for name, r in rates.items():
            assert res.stats["slaves"][name]["do_step_calls"] == r * round(STOP / STEP)
            assert res.stats["slaves"][name]["rate"] == r
        traces[engine] = res.trace
    assert np.array_equal(traces["oracle"].data, traces["compiled"].data)
    got = np.column_stack([traces["compiled"][c] for c in cols])
    scale = np.abs(want).max(axis=0)
    np.testing.assert_allclose(got / scale, want / scale, rtol=0, atol=1e-12)
    _, single = analytic(alg, inputs, {})
    assert np.abs((single - want) / scale).max() > 1e-4


def test_sub_steps_are_taken_at_exact_nanosecond_instants(monkeypatch):
    """The fast slave steps at t_k + j h/r computed from integer nanoseconds, with h/r each."""
    from cosim import slaves as slaves_mod

    seen: list[tuple[str, float, float]] = []
    orig = slaves_mod.FmuSlave.do_step

    def spy(self, t, h):
        seen.append((self.name, t, h))
        return orig(self, t, h)

    monkeypatch.setenv("RPR_COSIM_SUPERVISE", "0")  # the calls are seen in this process
    monkeypatch.setattr(slaves_mod.FmuSlave, "do_step", spy)
    ov = {**overrides("gauss_seidel", "linear", {"mass2": 4}), "master.step": 0.1, "master.output_interval": 0.1,
          "stop_time": 3.0}
    run(SCENE, ov, engine="oracle")
    # the run's own calls are the last ones (its error estimate's companion at half the step ran first)
    fast = [(t, h) for n, t, h in seen if n == "mass2"][-120:]
    assert [t for t, _ in fast] == [k * 25_000_000 / 1e9 for k in range(120)]
    assert {h for _, h in fast} == {0.025}
    assert [t for n, t, _ in seen if n == "mass1"][-30:] == [k * 100_000_000 / 1e9 for k in range(30)]
    companion = [(t, h) for n, t, h in seen if n == "mass2"][:-120]
    assert len(companion) == 240 and {h for _, h in companion} == {0.0125}


@pytest.mark.parametrize("rate, message", [
    (2.5, "rate = 2.5 must be a whole number >= 1"),
    (0, "rate = 0 must be a whole number >= 1"),
    ("four", "rate = 'four' must be a whole number >= 1"),
    (3, "rate = 3 does not divide master.step = 0.05 s into whole nanoseconds (50000000 ns / 3); rates that "
        "divide it: 2, 4, 5, 8, 10"),
])
def test_a_bad_rate_is_one_line_at_its_line(rate, message):
    with pytest.raises(SceneError) as err:
        load(SCENE, {**BASE, "components.mass2.rate": rate})
    text = str(err.value)
    assert len(text.splitlines()) == 1 and message in text and "component 'mass2'" in text


def test_a_variable_step_algorithm_refuses_a_rate():
    with pytest.raises(SceneError, match="multirate needs gauss_seidel or jacobi"):
        load(SCENE, {**BASE, "components.mass2.rate": 2, "master.algorithm": "adaptive"})


def test_the_master_refuses_rates_an_algorithm_cannot_take():
    from cosim.master import CoupledSystem, simulate
    from cosim.slaves.linear import LinearSlave

    sl = LinearSlave("a", [[-1.0]], [[1.0]], [[1.0]])
    with pytest.raises(UserError, match="does not divide master.step"):
        simulate(CoupledSystem([sl], [], [(0, "y[1]")]), "jacobi", step_ns=1_000_001, n_steps=3, rates=[2])
    with pytest.raises(UserError, match="does not step slaves at several rates"):
        simulate(CoupledSystem([sl], [], [(0, "y[1]")]), "adaptive", step_ns=1_000_000, n_steps=3, rates=[2])


def test_rk4_ramp_map_is_rk4():
    """The RK4 map of models.coupling against a plain RK4 loop on a ramp input (the helper the
    analytic account above relies on)."""
    A, B = np.array([[0.0, 1.0], [-4.0, -0.3]]), np.array([[0.0], [1.0]])
    x, u0, u1, h = np.array([0.3, -0.2]), 0.7, -1.5, 0.1
    Phi, G0, G1 = rk4_ramp_discretization(A, B, h, substeps=3)
    f = lambda x, t: A @ x + B[:, 0] * (u0 + u1 * t)  # noqa: E731
    y, hs = x.copy(), h / 3
    for j in range(3):
        t = j * hs
        k1 = f(y, t)
        k2 = f(y + hs / 2 * k1, t + hs / 2)
        k3 = f(y + hs / 2 * k2, t + hs / 2)
        k4 = f(y + hs * k3, t + hs)
        y = y + hs / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(Phi @ x + G0[:, 0] * u0 + G1[:, 0] * u1, y, rtol=0, atol=1e-15)




@pytest.mark.parametrize("variant", [("jacobi", "hold"), ("gauss_seidel", "linear")], ids=lambda v: "/".join(v))
def test_exact_slaves_at_several_rates_give_the_single_rate_trace(variant):
    """With exact kernels a slave's sub-steps along its held input or its macro-step line compose
    to the one exact step, and its outputs are exchanged at the macro instants only: the trace is
    the single-rate one to rounding (what multirate changes is the slave's own integration)."""
    alg, inputs = variant
    exact = {"components.mass1.options.integrator": "exact", "components.mass2.options.integrator": "exact"}
    one = run(SCENE, {**overrides(alg, inputs, {}), **exact}, engine="compiled").trace
    many = run(SCENE, {**overrides(alg, inputs, {"mass2": 4, "mass1": 2}), **exact}, engine="compiled").trace
    scale = np.abs(one.data[:, 1:]).max(axis=0)
    np.testing.assert_allclose(many.data[:, 1:] / scale, one.data[:, 1:] / scale, rtol=0, atol=1e-12)


def test_precision_study_applies_its_overrides_to_every_run():
    """``study precision --set components.mass2.rate=4``: every run steps mass2 four times per step."""
    from cosim.study.precision import precision_study

    st = precision_study(SCENE, [("gauss_seidel", "linear")], [0.02, 0.01], stop_time=1.0,
                         overrides=["components.mass2.rate=4", "master.tolerance=none"])
    assert [r.status for r in st.rows] == ["ok", "ok"]
    assert [r.do_steps for r in st.rows] == [50 * (1 + 4), 100 * (1 + 4)]
