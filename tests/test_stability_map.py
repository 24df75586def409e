"""Stability of fixed-step master algorithms: the measured map of the linear two-mass scene against
the analytic spectral radius of the macro-step map (models.coupling), and the map itself against
hand-derived cases."""
from __future__ import annotations

import math
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from cosim.cli import main
from cosim.study.stability import DEFAULT_VARIANTS, growth_per_step, stability_map
from models.block import Block, Var
from models.blocks._common import ParamSet
from models.coupling import Link, linearize, macro_map, monolithic_map, ramp_discretization, spectral_radius

SCENE = Path(__file__).resolve().parents[1] / "scenarios" / "two_mass.yaml"


def _lag(a: float) -> Block:
    """dx/dt = -a x + u, y = x."""
    ps = ParamSet()
    pa = ps.add("a", a)
    x, u = ca.SX.sym("x"), ca.SX.sym("u")
    return Block.build("lag", params=ps.params, inputs=[Var("u")], outputs=[Var("y")], states=[Var("state.x")],
                       p=ps.vector(), u=u, x=x, ode=-pa * x + u, out=x, start=ca.SX(0.0))


@pytest.mark.parametrize("h", [0.01, 0.3, 2.0])
def test_jacobi_hold_map_of_two_lags_is_the_hand_derived_one(h):
    """x1' = -a x1 + x2, x2' = -a x2 + x1 under Jacobi with held inputs: x_i+ = phi x_i + g x_j with
    phi = exp(-a h), g = (1 - phi) / a, so the eigenvalues are phi +- g."""
    a = 1.5
    s = linearize(_lag(a))
    M = macro_map([s, s], [Link(0, 0, 1, 0), Link(1, 0, 0, 0)], h, "jacobi", "hold")
    phi, g = math.exp(-a * h), (1 - math.exp(-a * h)) / a
    np.testing.assert_allclose(M[:2, :2], [[phi, g], [g, phi]], rtol=1e-12, atol=1e-14)
    assert spectral_radius(M) == pytest.approx(abs(phi) + abs(g), rel=1e-12)


@pytest.mark.parametrize("h", [0.01, 0.3, 2.0])
def test_gauss_seidel_hold_map_of_two_lags_is_the_hand_derived_one(h):
    """Gauss-Seidel (slave 0 first): x0+ = phi x0 + g x1, x1+ = phi x1 + g x0+."""
    a = 1.5
    s = linearize(_lag(a))
    M = macro_map([s, s], [Link(0, 0, 1, 0), Link(1, 0, 0, 0)], h, "gauss_seidel", "hold", order=[0, 1])
    phi, g = math.exp(-a * h), (1 - math.exp(-a * h)) / a
    np.testing.assert_allclose(M[:2, :2], [[phi, g], [g * phi, phi + g * g]], rtol=1e-12, atol=1e-14)


def test_ramp_discretization_matches_quadrature():
    """G0 = int_0^h e^{A(h-s)} B ds and G1 = int_0^h e^{A(h-s)} B s ds, by Simpson's rule."""
    from scipy.integrate import simpson
    from scipy.linalg import expm

    A, B, h = np.array([[0.0, 1.0], [-4.0, -0.3]]), np.array([[0.0], [1.0]]), 0.7
    Phi, G0, G1 = ramp_discretization(A, B, h)
    s = np.linspace(0, h, 2001)
    ker = np.array([expm(A * (h - si)) @ B for si in s])[:, :, 0]
    np.testing.assert_allclose(Phi, expm(A * h), rtol=1e-13)
    np.testing.assert_allclose(G0[:, 0], simpson(ker, x=s, axis=0), rtol=1e-9)
    np.testing.assert_allclose(G1[:, 0], simpson(ker * s[:, None], x=s, axis=0), rtol=1e-9)


@pytest.mark.parametrize("variant", DEFAULT_VARIANTS)
def test_coupling_maps_tend_to_the_monolithic_map(variant):
    """As h -> 0 every consistent algorithm's macro step approaches the exact flow: fed a history
    that lies on the exact solution (y_k-1 from the flow run backwards), one macro step differs from
    expm(A h) by O(h^2) (local error of a first-order coupling) or less."""
    from models.blocks import make

    s1 = linearize(make("oscillator", coupling="none"))
    s2 = linearize(make("oscillator", coupling="spring"), {"kc": 100.0})
    links = [Link(1, 0, 0, 0), Link(0, 0, 1, 0), Link(0, 1, 1, 1)]
    C = np.zeros((len(links), 4))
    for c, ln in enumerate(links):
        C[c, 2 * ln.src:2 * ln.src + 2] = [s1, s2][ln.src].C[ln.out]
    errs = []
    for h in (1e-3, 5e-4):
        exact = monolithic_map([s1, s2], links, h)
        M = macro_map([s1, s2], links, h, *variant, order=[0, 1])
        step = M[:4, :4] + M[:4, 4:] @ C @ np.linalg.inv(exact)  # y_k-1 = C x(t_k - h)
        errs.append(np.abs(step - exact).max())
    assert errs[1] < errs[0] / 3.5  # local error at least O(h^2)


def test_linearize_refuses_a_nonlinear_block():
    from models.blocks import make

    with pytest.raises(ValueError, match="not linear"):
        linearize(make("mechanism", "rigid"))


def test_growth_measure_on_known_sequences():
    """A geometric oscillation r^k cos(k w) gives back r per step."""
    k = np.arange(4000)
    for r in (0.999, 1.0005):
        data = np.column_stack([r ** k * np.cos(0.05 * k), r ** k * np.sin(0.05 * k)])
        assert growth_per_step(data, 1.0) == pytest.approx(r, abs=2e-5)
    assert growth_per_step(np.array([[1.0], [np.nan]] * 8), 1.0) == math.inf


@pytest.fixture(scope="module")
def two_mass_map():
    # 7 x 7 per variant: steps 2 ms .. 0.3 s, coupling stiffness 1 .. 1e4 N/m.
    return stability_map(SCENE, "components.mass2.params.kc", (1.0, 1e4), (2e-3, 0.3), n_values=7, n_steps=7)


def _boundary_adjacent(analytic_stable: np.ndarray, i: int, j: int) -> bool:
    n, m = analytic_stable.shape
    return any(0 <= a < n and 0 <= b < m and analytic_stable[a, b] != analytic_stable[i, j]
               for a, b in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)))


@pytest.mark.parametrize("variant", DEFAULT_VARIANTS, ids=lambda v: "/".join(v))
def test_measured_boundary_matches_the_analytic_one_within_a_cell(two_mass_map, variant):
    """Every cell whose measured outcome disagrees with rho <= 1 lies next to the analytic boundary,
    and both outcomes occur (the grid straddles the boundary)."""
    outcome = two_mass_map.grid(*variant)
    rho = two_mass_map.grid(*variant, what="rho")
    analytic_stable = rho <= 1.0
    measured_stable = outcome == "stable"
    assert analytic_stable.any() and (~analytic_stable).any()
    assert not (outcome == "failed").any()
    wrong = [(i, j) for i, j in zip(*np.nonzero(measured_stable != analytic_stable))]
    assert all(_boundary_adjacent(analytic_stable, i, j) for i, j in wrong), (variant, wrong)
    assert len(wrong) <= 2, (variant, wrong)


def test_jacobi_hold_is_less_stable_than_gauss_seidel_hold(two_mass_map):
    """The textbook ordering: Gauss-Seidel's map is stable wherever Jacobi's is, not the reverse."""
    j = two_mass_map.grid("jacobi", "hold") == "stable"
    g = two_mass_map.grid("gauss_seidel", "hold") == "stable"
    assert (g | ~j).all() and g.sum() > j.sum()


def test_cli_writes_table_and_chart(tmp_path, capsys):
    rc = main(["study", "stability", str(SCENE), "--vary", "components.mass2.params.kc=10:1000", "--n", "3",
               "--steps", "0.005:0.2", "--variant", "gauss_seidel/hold", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "gauss_seidel/hold" in out and "/9" in out
    rows = (tmp_path / "two_mass_stability.csv").read_text().splitlines()
    assert len(rows) == 1 + 9 and rows[0].startswith("algorithm,inputs,step,components.mass2.params.kc,outcome")
    assert (tmp_path / "two_mass_stability.png").stat().st_size > 10_000


@pytest.mark.parametrize("argv, message", [
    (["--vary", "components.mass2.params.kc"], "expected PATH=LO:HI"),
    (["--vary", "components.mass2.params.kc=10:1"], "0 < LO < HI"),
    (["--vary", "components.mass2.params.kq=1:10"], "no value at 'kq'"),
    (["--vary", "components.mass2.params.kc=1:10", "--variant", "newton/hold"], "expected ALG/INPUTS"),
])
def test_cli_bad_arguments_are_one_line(argv, message, capsys):
    rc = main(["study", "stability", str(SCENE), *argv])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1


# --- work-precision ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_mass_precision():
    from cosim.study.precision import precision_study

    return precision_study(SCENE, DEFAULT_VARIANTS, [4e-3, 2e-3, 1e-3, 5e-4], stop_time=4.0)


@pytest.mark.parametrize("variant, order", [(("jacobi", "hold"), 1), (("gauss_seidel", "hold"), 1),
                                            (("jacobi", "linear"), 2), (("gauss_seidel", "linear"), 2)],
                         ids=lambda v: "/".join(v) if isinstance(v, tuple) else str(v))
def test_precision_study_observes_the_theoretical_coupling_order(two_mass_precision, variant, order):
    """Holding inputs is a first-order coupling, linear extrapolation/interpolation second order
    (the coupling error dominates: each slave's RK4 with 40 substeps is far more accurate)."""
    assert two_mass_precision.order(variant) == pytest.approx(order, abs=0.3)
    rows = [r for r in two_mass_precision.rows if (r.algorithm, r.inputs) == variant]
    assert all(a.worst > b.worst for a, b in zip(rows, rows[1:]))
    # every step ran its whole span; a row is "inaccurate" exactly where its error against the
    # reference is over 10x the scene's tolerance (1e-3), the verdict a run's own estimate gives
    assert all(r.status == ("inaccurate" if r.worst > 10 * 1e-3 else "ok") for r in rows), \
        [(r.step, r.status, r.worst) for r in rows]


def test_precision_study_cheapest_within_tolerance(two_mass_precision):
    best = two_mass_precision.cheapest_within(5e-3)
    assert best is not None and best.worst <= 5e-3 and best.inputs == "linear"
    assert two_mass_precision.cheapest_within(1e-12) is None


def test_cli_precision_writes_table_and_chart(tmp_path, capsys):
    rc = main(["study", "precision", str(SCENE), "--steps", "4e-3,2e-3", "--variant", "gauss_seidel/linear",
               "--stop", "1", "--no-peer", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "observed order gauss_seidel/linear" in out and "cheapest within 0.001" in out
    assert len((tmp_path / "two_mass_precision.csv").read_text().splitlines()) == 3
    assert (tmp_path / "two_mass_precision.png").stat().st_size > 10_000


@pytest.mark.parametrize("argv, message", [
    (["--steps", "4e-3,3e-3"], "does not divide"),
    (["--steps", "a,b"], "comma-separated"),
    (["--stop", "-1"], "positive simulated time"),
])
def test_cli_precision_bad_arguments_are_one_line(argv, message, capsys):
    rc = main(["study", "precision", str(SCENE), *argv])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1


# --- fidelity ---------------------------------------------------------------------------------
PID_STEP = SCENE.with_name("pid_step.yaml")


def _auto_scene(tmp_path: Path, tol: float) -> Path:
    path = tmp_path / f"auto_{tol:g}.yaml"
    path.write_text(f"include: {PID_STEP}\nstop_time: 0.5\nfidelity_tolerance: {tol}\n"
                    "fidelity_signals: [mech.platform.x, mech.platform.phi]\n"
                    "components:\n  mech: {fidelity: auto}\n")
    return path


@pytest.mark.parametrize("tol, picked", [(1e-4, "rigid"), (1e-6, "multibody")])
def test_fidelity_auto_picks_by_measured_difference(tmp_path, monkeypatch, tol, picked):
    """Rigid and multibody pid_step differ by ~2e-5 of range in x and phi (measured, the start
    transient of the parasitic joints): at 1e-4 the rigid mechanism is good enough and cheaper, at
    1e-6 only the multibody one is.  The choice is cached with the scene's hash."""
    from cosim.scenario import load
    from cosim.study.fidelity import resolve_auto

    monkeypatch.setenv("RPR_COSIM_FIDELITY_CACHE", str(tmp_path / "fidelity"))
    scene = load(_auto_scene(tmp_path, tol), auto_fidelity=resolve_auto)
    assert scene.components["mech"].fidelity == picked
    notes = [str(w) for w in scene.warnings if w.severity == "note"]
    assert len(notes) == 1 and f"mechanism={picked}" in notes[0] and "fidelity auto" in notes[0]
    assert list((tmp_path / "fidelity").glob("*.json"))
    again = load(_auto_scene(tmp_path, tol), auto_fidelity=resolve_auto)  # from the cache: no runs
    assert again.components["mech"].fidelity == picked



def test_cli_fidelity_table(capsys):
    rc = main(["study", "fidelity", str(SCENE.with_name("two_mass.yaml")), "--set", "stop_time=1"])
    assert rc == 2  # the oscillator has one level only: a one-line refusal
    assert "no catalog component has more than one fidelity level" in capsys.readouterr().err
