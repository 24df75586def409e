"""The thesis's scenes end to end, against the thesis (SPEC §5-§6), against a second formulation
(the virtual-work inverse dynamics), against a peer master (ecospy) and FMPy's own master, with
a third-party FMU (pythonfmu) inside a scene, and through the CLI."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cosim.run.execute import build_components, run
from cosim.scenario import load
from cosim.trace.traces import read_trace

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
LEGS = (1, 2, 3)
#: the coupling these tests are about (the scene itself takes the tolerance default, cosim.run.choose)
GS = "master.algorithm=gauss_seidel"
#: these tests measure the coupling at the scene's step against the thesis, not against the
#: tolerance (Gauss-Seidel at 1 ms is 5-18 % of range off in the first ms): no verdict asked
NOV = "master.tolerance=none"

# SPEC §6 / thesis Table 6.12
TARGET_POSE = (-0.2, -0.15, 0.2)
TARGET_LEGS = (0.3415, 0.3641, 0.2613)
START_LEGS = (0.3109, 0.3559, 0.2043)
THESIS_END_POSE = (-0.1995, -0.1500, 0.2032)
THESIS_END_LEGS = (0.3416, 0.3642, 0.2614)
BAND_LEG, BAND_PHI = 0.5e-3, 0.003  # the thesis's end-state agreement, used as the settling band


@pytest.fixture(scope="module")
def pid_rigid(cache):
    """pid_step (Gauss-Seidel at 1 ms, linear inputs), run on to 15 s to see it settle."""
    return run(SCENES / "pid_step.yaml", ["stop_time=15", GS, NOV], cache_dir=cache)


def leg_error(tr) -> np.ndarray:
    return np.max(np.abs(np.vstack([tr[f"mech.leg[{i}].s"] - tr[f"target.leg[{i}].s"] for i in LEGS])), axis=0)


def test_pid_step_starts_and_aims_where_table_6_12_says(pid_rigid):
    tr = pid_rigid.trace
    assert pid_rigid.ok, pid_rigid.reason
    for i in LEGS:
        assert tr[f"mech.leg[{i}].s"][0] == pytest.approx(START_LEGS[i - 1], abs=6e-5)
        assert tr[f"target.leg[{i}].s"][-1] == pytest.approx(TARGET_LEGS[i - 1], abs=6e-5)


def test_pid_step_reproduces_the_shape_of_table_6_10(pid_rigid):
    """phi overshoots to about 0.30 rad near 1.3 s and x dips to about -0.22 m (thesis Table 6.10;
    the rigid model with parallel gains gives the same shape, SPEC §6)."""
    tr = pid_rigid.trace
    t, phi, x = tr.time, tr["mech.platform.phi"], tr["mech.platform.x"]
    k = int(np.argmax(phi))
    assert 0.28 < phi[k] < 0.32 and 1.1 < t[k] < 1.5, (phi[k], t[k])
    assert -0.23 < x.min() < -0.215 and 1.1 < t[np.argmin(x)] < 1.5
    assert 0.35 < tr["mech.leg[1].s"].max() < 0.36
    # one overshoot, then it comes back through the target (an underdamped step)
    assert phi[t > t[k]].min() < TARGET_POSE[2]


def test_pid_step_settles_on_the_target_within_the_thesis_band(pid_rigid):
    """The band is the thesis's (its bond graph's end state agrees with the target to 0.5 mm and
    0.003 rad).  The thesis's plant is inside it at 5 s; this rigid plant with the parallel gains
    is not (SPEC §6: 2-3 mm / 0.01 rad off at 5 s) and enters it later: measured 8.05 s.
    Bounds below are the measured values with their margin stated, not the thesis's band."""
    tr = pid_rigid.trace
    t = tr.time
    out = (leg_error(tr) > BAND_LEG) | (np.abs(tr["mech.platform.phi"] - TARGET_POSE[2]) > BAND_PHI)
    settle = t[np.nonzero(out)[0][-1] + 1]
    assert 7.5 < settle < 8.6, settle  # measured 8.053 s
    # after settling the error keeps shrinking (integral action): at 15 s measured 9.2e-6 m and
    # 7.1e-5 rad, 50 times inside the band
    assert leg_error(tr)[-1] < 3e-5
    assert abs(tr["mech.platform.phi"][-1] - TARGET_POSE[2]) < 2e-4
    # at 5 s (the thesis's horizon), beside Table 6.12's end state: legs 1.15 / 0.49 / 2.63 mm and
    # phi 0.0048 rad away (SPEC §6: the rigid plant ends 2-3 mm / 0.01 rad off at 5 s); bounds
    # 1.3x measured, and phi at SPEC's 0.01 rad
    at5 = {n: tr.at(n, 5.0) for n in tr.names}
    for i, measured in zip(LEGS, (1.15e-3, 0.49e-3, 2.63e-3)):
        assert abs(at5[f"mech.leg[{i}].s"] - THESIS_END_LEGS[i - 1]) < 1.3 * measured, i
    assert abs(at5["mech.platform.phi"] - THESIS_END_POSE[2]) < 0.01


def test_pid_step_multibody_agrees_with_rigid(cache):
    """Stiff parasitic joints (1e8 N/m) deflect by f/k ~ 1e-7 m: the closed loop must not notice.
    Both fidelities run with the scene's coupling (Gauss-Seidel at 1 ms, linear inputs).  Stated
    tolerance: 5e-6 m on the leg lengths and platform position, 2e-5 rad on phi, over the whole
    5 s (measured: legs 2.5e-6 / 1.2e-6 / 1.7e-6 m, x 1.0e-6 m, y 0.8e-6 m, phi 7.1e-6 rad)."""
    a = run(SCENES / "pid_step.yaml", [GS, NOV], cache_dir=cache).trace
    mb = run(SCENES / "pid_step_multibody.yaml", [GS, NOV], cache_dir=cache)
    b = mb.trace
    assert mb.ok, mb.reason
    assert mb.scene.components["mech"].fidelity == "multibody" and len(b.time) == 5001
    n = len(b.time)
    assert np.array_equal(a.time[:n], b.time)
    for name in [f"mech.leg[{i}].s" for i in LEGS] + ["mech.platform.x", "mech.platform.y"]:
        assert np.max(np.abs(a[name][:n] - b[name])) < 5e-6, name
    assert np.max(np.abs(a["mech.platform.phi"][:n] - b["mech.platform.phi"])) < 2e-5


# --- Chapter 7 ---------------------------------------------------------------------------------
def vw_errors(tr, mech: str, t_from: float = 0.05) -> dict[str, float]:
    """Largest error of leg lengths, rates, accelerations and forces of ``mech`` against the
    virtual-work reference 'ref', relative to the reference's largest magnitude, for t >= t_from
    (the joints of the multibody model start relaxed and take up the load in ~1 ms).

    Accelerations: central differences of the leg rates.  Forces: the virtual-work inverse
    dynamics (models.virtual_work) of the motion the mechanism actually made (its platform pose,
    velocity and, by central differences, acceleration) -- the force a rigid mechanism would need
    for that motion -- against the reference force on the path."""
    from models.geometry import preset
    from models.numeric import vectorize
    from models.virtual_work import inverse_dynamics_fn

    t = tr.time
    h = t[1] - t[0]
    win = (t >= t_from) & (t < t[-1])
    win[0] = False
    m = preset("cross_leg")
    q = np.vstack([tr[f"{mech}.platform.{k}"] for k in ("x", "y", "phi")])
    qd = np.vstack([tr[f"{mech}.platform.{k}"] for k in ("vx", "vy", "omega")])
    qdd = np.zeros_like(qd)
    qdd[:, 1:-1] = (qd[:, 2:] - qd[:, :-2]) / (2 * h)
    tau = vectorize(inverse_dynamics_fn())(q, qd, qdd, m.geometry_vector()[:, None], m.inertia.vector()[:, None])[0]
    out = {}
    for kind in ("s", "v", "a", "f"):
        worst = 0.0
        for i in LEGS:
            ref = tr[f"ref.leg[{i}].{kind}"]
            if kind == "a":
                v = tr[f"{mech}.leg[{i}].v"]
                got = np.zeros_like(v)
                got[1:-1] = (v[2:] - v[:-2]) / (2 * h)
            elif kind == "f":
                got = tau[i - 1]
            else:
                got = tr[f"{mech}.leg[{i}].{kind}"]
            worst = max(worst, float(np.max(np.abs(got - ref)[win]) / np.max(np.abs(ref))))
        out[kind] = worst
    return out


VW_GS = ["master.algorithm=gauss_seidel", NOV]


@pytest.fixture(scope="module")
def vw(cache, tmp_path_factory):
    # the models compared at the thesis's coupling (Gauss-Seidel, 1 ms, linear inputs), not at the
    # tolerance default's choice (a fixed step of 50 us for the flat rotation, docs/accuracy.md)
    return run(SCENES / "vw_compare.yaml", VW_GS, cache_dir=cache, out_dir=tmp_path_factory.mktemp("vw_compare"))


def test_vw_compare_every_recorded_force_is_the_reference_force_at_its_time_stamp(vw):
    """Issue 8: each force column of the CSV (the drive's output and the mechanisms' inputs) is
    the virtual-work force of its own row's time, within 1e-5 of the force's range -- no column
    is shifted by part of a step."""
    tr = read_trace(vw.trace_path)
    forces = [c for c in tr.names if c.endswith(".f") and ".leg[" in c and not c.startswith("ref.")]
    assert {f"drive.leg[{i}].f" for i in LEGS} <= set(forces), forces
    for name in forces:
        i = name.split(".leg[")[1][0]
        ref = tr[f"ref.leg[{i}].f"]
        err = np.max(np.abs(tr[name] - ref)) / np.max(np.abs(ref))
        assert err < 1e-5, (name, err)


# Table 7.7 (accelerations) and 7.9 (forces) match the path at the thesis's t = 0.5 s, which is
# t = 1.0 s in this scene (its path is shifted by a quarter period to start at rest).
TABLE_7_7 = (0.678478249, 0.696504281, 0.019889875)
TABLE_7_9 = (2.610272368, 1.440588406, 0.693698204)


def test_vw_reference_reproduces_tables_7_7_and_7_9(vw):
    """The thesis's own agreement bands (SPEC §5): accelerations 0.2 % (legs 1-2; measured 0.04 %
    and 0.19 %), leg 3 "2 %" (measured 2.19 % at this instant, the path's acceleration peak, so
    no nearby instant does better: the bound is 2.2 %, SPEC's one-digit "2 %" to its next
    digit); forces 1 % (measured 0.11 / 0.48 / 0.75 %)."""
    tr = vw.trace
    assert vw.ok, vw.reason
    for i, (a, f) in enumerate(zip(TABLE_7_7, TABLE_7_9), start=1):
        assert tr.at(f"ref.leg[{i}].a", 1.0) == pytest.approx(a, rel=0.022 if i == 3 else 0.002)
        assert tr.at(f"ref.leg[{i}].f", 1.0) == pytest.approx(f, rel=0.01)


@pytest.mark.parametrize("mech", ["rigid", "multibody"])
def test_vw_compare_dynamic_mechanisms_follow_the_virtual_work_reference(vw, mech):
    """Lengths, rates, accelerations and forces over the whole 5 s, at the multibody default
    stiffness, relative to the reference's range (the thesis's bond graph: 0.01-2.85 %).
    Measured: rigid 1.2e-5 (rates; lengths 5.0e-6, forces 1.3e-6), multibody 7.4e-6 (rates;
    forces 1.4e-6); bound 3e-5, 2.5x the worst."""
    errs = vw_errors(vw.trace, mech)
    assert max(errs.values()) < 3e-5, errs


@pytest.fixture(scope="module")
def stiffness_sweep(cache):
    """vw_compare for 1 s with the multibody joints at several stiffnesses (translational and
    rotational together); k_joint is not structural, so one FMU serves all."""
    out = {}
    for k in (1e5, 1e6, 1e7, 1e8, 1e9):
        res = run(SCENES / "vw_compare.yaml", [*VW_GS, "stop_time=1.0", f"components.multibody.params.k_joint={k:g}",
                                               f"components.multibody.params.k_rot={k:g}"], cache_dir=cache)
        assert res.ok, res.reason
        out[k] = vw_errors(res.trace, "multibody")
    return out


@pytest.mark.parametrize("kind", ["s", "v"])
@pytest.mark.parametrize("k", [1e5, 1e6, 1e7])
def test_vw_error_falls_like_the_joint_compliance(stiffness_sweep, kind, k):
    """Joint deflection ~ f/k: ten times stiffer joints, about ten times smaller errors (until the
    co-simulation's own floor, ~1e-6).  From 1e7 to 1e8 N/m the floor is reached: the rigid
    mechanism's own error in the same scene is 2.8e-7 on lengths (forces entering as linear
    inputs; 1.4e-7 with the former mid-step hold), beside the multibody's 4.3e-7 at 1e8 N/m, so
    that decade gains a factor 4 on lengths instead of 10."""
    ratio = stiffness_sweep[k][kind] / stiffness_sweep[10 * k][kind]
    low = 3 if k >= 1e7 else 5
    assert low < ratio < 20, (k, kind, stiffness_sweep)


@pytest.mark.parametrize("kind", ["s", "v", "a", "f"])
def test_vw_error_at_default_and_stiffer_joints(stiffness_sweep, kind):
    """At the thesis's 1e8 N/m (measured over 1 s: s 2.9e-7, v 1.3e-6, a 3.9e-6, f 1.4e-6):
    bound 1e-5, 2.5x the worst; stiffer joints are no worse; softer (1e5) far worse."""
    assert stiffness_sweep[1e8][kind] < 1e-5
    assert stiffness_sweep[1e9][kind] <= stiffness_sweep[1e8][kind] * 1.05
    assert stiffness_sweep[1e8][kind] < stiffness_sweep[1e5][kind] / 50


# --- peers ---------------------------------------------------------------------------------------
def test_pid_step_fmus_in_ecospy_give_our_jacobi_trajectory_bit_for_bit(cache):
    """ecospy (a C++ master) runs the scene's FMUs with fixed-step Jacobi exchange; its state
    trajectory equals ours exactly.  (It reads outputs after setting the next inputs, so only
    outputs without feedthrough are compared.)"""
    try:
        import ecospy  # noqa: F401  (whether it loads; ecospy_trace drives it)
    except (ImportError, OSError) as exc:  # OSError: its C++ library cannot load (Debian libtbb12 missing)
        pytest.skip(f"ecospy (PyPI, with Debian libtbb12) is needed for this peer check: {exc}")
    from cosim.study.precision import ecospy_trace

    sc = load(SCENES / "pid_step.yaml", ["master.algorithm=jacobi", "master.inputs=hold", "master.step=1e-4",
                                         "stop_time=1.0", "master.output_interval=1e-4"])
    paths = build_components(sc, cache_dir=cache)
    names = ["mech.platform.x", "mech.platform.phi", "mech.leg[3].s", "motor1.i"]
    peer, _, _ = ecospy_trace(sc, paths, sc.master.step, names)  # the FMUs wired into ecospy, read every step
    rows = np.vstack([peer[n] for n in names]).T
    ours = run(sc, cache_dir=cache).trace
    assert len(rows) == sc.n_steps + 1
    np.testing.assert_array_equal(rows, np.vstack([ours[n] for n in names]).T)


def test_a_one_component_scene_equals_fmpy_simulate_fmu(cache, tmp_path):
    """FMPy's own master on the same FMU with the same start values: the same outputs (to round-off:
    FMPy passes step sizes computed as differences of communication points)."""
    import fmpy

    scene = tmp_path / "mech.yaml"
    scene.write_text(textwrap.dedent("""\
        name: mech_only
        stop_time: 0.5
        components:
          mech:
            model: mechanism
            fidelity: rigid
            params: {x0: -0.2, m_p: 2.0}
            start:
              leg[1].f: 1.5
              leg[2].f: -0.5
              leg[3].f: 0.25
        connections: []
        master: {algorithm: gauss_seidel, step: 1e-3}
        outputs: [mech.platform.x, mech.platform.phi]
        """))
    res = run(scene, cache_dir=cache)
    ref = fmpy.simulate_fmu(str(res.fmus["mech"]), stop_time=0.5, step_size=1e-3, output_interval=1e-3,
                            start_values={"x0": -0.2, "m_p": 2.0, "leg[1].f": 1.5, "leg[2].f": -0.5,
                                          "leg[3].f": 0.25}, output=["platform.x", "platform.phi"])
    np.testing.assert_allclose(res.trace.time, ref["time"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.trace["mech.platform.x"], ref["platform.x"], rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(res.trace["mech.platform.phi"], ref["platform.phi"], rtol=1e-13, atol=1e-16)
    assert np.max(np.abs(res.trace["mech.platform.phi"])) > 1e-3  # it moved


LEAKY = '''
from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real


class leaky(Fmi2Slave):
    """Leaky integrator y' = (u - y) / T, one forward-Euler step per communication step."""

    author = "rpr-cosim tests"
    description = "leaky integrator (third-party FMU for the master's tests)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.T = 0.05
        self.u = 0.0
        self.y = 0.0
        self.register_variable(Real("T", causality=Fmi2Causality.parameter, variability=Fmi2Variability.tunable))
        self.register_variable(Real("u", causality=Fmi2Causality.input))
        self.register_variable(Real("y", causality=Fmi2Causality.output))

    def do_step(self, current_time, step_size):
        self.y += step_size * (self.u - self.y) / self.T
        return True
'''


def test_a_third_party_pythonfmu_fmu_runs_inside_a_scene(tmp_path, cache):
    """A pythonfmu FMU (not built by us; its modelDescription has an empty InitialUnknowns, which
    FMPy's validation flags) filters the setpoint of leg 1 and feeds one of our PIDs."""
    pytest.importorskip("pythonfmu", reason="pythonfmu (PyPI) builds the third-party FMU")
    src = tmp_path / "leaky.py"
    src.write_text(LEAKY)
    subprocess.run([sys.executable, "-m", "pythonfmu", "build", "-f", str(src), "-d", str(tmp_path)],
                   check=True, capture_output=True, timeout=120)
    assert (tmp_path / "leaky.fmu").is_file()
    scene = tmp_path / "third_party.yaml"
    scene.write_text(textwrap.dedent("""\
        name: third_party
        stop_time: 0.2
        components:
          target: {model: pose_setpoint}
          filt: {fmu: leaky.fmu, params: {T: 0.02}}
          pid1: {model: pid, params: {Kp: 2.0, Ki: 0.0, Kd: 0.0}}
        connections:
          - target.leg[1].s -> filt.u
          - filt.y -> pid1.setpoint
        master: {algorithm: gauss_seidel, step: 1e-3}
        outputs:
          - filt.y
          - pid1.y
          - target.leg[1].s
        """))
    sc = load(scene)
    assert any("pid1.measurement" in w.message for w in sc.warnings)
    res = run(sc, cache_dir=cache)
    assert res.ok, res.reason
    tr = res.trace
    u = tr["target.leg[1].s"][0]
    y = [0.0]
    for _ in range(200):
        y.append(y[-1] + 1e-3 * (u - y[-1]) / 0.02)
    np.testing.assert_allclose(tr["filt.y"], y, rtol=1e-12, atol=1e-15)
    # Gauss-Seidel: the PID takes the filter's fresh output; proportional only: y = Kp (y_f - 0)
    np.testing.assert_allclose(tr["pid1.y"], 2.0 * np.array(y), rtol=1e-12, atol=1e-15)


# --- the CLI -------------------------------------------------------------------------------------
def test_cli_run_writes_trace_sidecar_plot_and_animation(tmp_path, cache):
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "cosim", "run", str(SCENES / "pid_step.yaml"), "--set",
                          "stop_time=0.3", "--set", GS, "--set", NOV, "--out", str(out), "--plot", "--animate", "--cache", str(cache)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "real-time factor" in res.stdout and "mech.platform.phi" in res.stdout
    tr = read_trace(out / "pid_step.csv")
    assert tr.status == "ok" and len(tr.time) == 301 and tr.time[-1] == pytest.approx(0.3)
    assert tr.meta["algorithm"] == "gauss_seidel" and tr.meta["inputs"] == "linear" and tr.meta["scene_hash"] and "fmpy" in tr.meta["versions"]
    assert tr.stats["steps_done"] == 300 and set(tr.stats["slaves"]) >= {"mech", "pid1", "motor3"}
    side = json.loads((out / "pid_step.json").read_text())
    assert side["status"] == "ok" and side["scene_data"]["master"]["step"] == 1e-3
    from PIL import Image

    assert Image.open(out / "pid_step.png").size[0] > 300
    gif = Image.open(out / "pid_step.gif")
    assert gif.n_frames > 3


def test_fmi3_components_give_the_fmi2_trajectory(cache):
    """The same scene with every catalog component exported as FMI 3.0: bit-identical trace."""
    names = ["target", "pid1", "pid2", "pid3", "motor1", "motor2", "motor3", "mech"]
    held = ["stop_time=0.5", "master.inputs=hold", GS, NOV]  # FMI 3.0 has no input derivatives
    v2 = run(SCENES / "pid_step.yaml", held, cache_dir=cache)
    v3 = run(SCENES / "pid_step.yaml", held + [f"components.{n}.fmi=3.0" for n in names], cache_dir=cache)
    # held inputs at 1 ms: both judged "unstable" by their error estimate (2.2x range off), alike
    assert v3.status == v2.status and v3.stats["engine"] == "compiled"
    assert all(str(p).endswith(".fmu") for p in v3.fmus.values()) and v3.fmus["mech"] != v2.fmus["mech"]
    np.testing.assert_array_equal(v2.trace.data, v3.trace.data)
