"""Modelica events (models/modelica.py on the Block event contract, docs/explanation/events.md):
`when` on a relation with `reinit` and `pre` becomes an indicator and its update; the pendulum
against a stop written in Modelica hits the analytic impact times; what is not translated yet is
refused naming file, line and construct."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.special import ellipk

pytest.importorskip("rumoca")

from cosim.run.execute import run  # noqa: E402
from models.block import EITHER, FALLING  # noqa: E402
from models.modelica import ModelicaError, translate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def analytic_impacts(n: int, L=0.5, g=9.81, theta0=1.0, e=0.7) -> np.ndarray:
    """The pendulum's impacts on a stop at its lowest point: a quarter period, then half periods
    (complete elliptic integral K), each amplitude from the energy the previous impact left."""
    w0, amp, t, out = np.sqrt(g / L), theta0, 0.0, []
    for k in range(n):
        K = ellipk(np.sin(amp / 2) ** 2)
        t += (K if k == 0 else 2 * K) / w0
        out.append(t)
        amp = np.arccos(1 - e ** 2 * (1 - np.cos(amp)))
    return np.array(out)


def test_a_when_with_reinit_and_pre_is_an_indicator_and_its_update():
    b = translate((ROOT / "scenarios/user/PendulumStop.mo").read_text(), "PendulumStop", "PendulumStop.mo")
    assert [v.name for v in b.modes] == ["mode.impacts", "mode.t_impact"] and b.directions == [FALLING]
    ev = b.event_functions()
    x, m, p = [-1e-3, -2.0], [3.0, 1.5], b.param_defaults
    z = float(ev["indicators"](1.7, x, [], p, m))
    x_new, m_new = ev["update"](0, 1.7, x, [], p, m)
    assert z == -1e-3
    assert np.array(x_new).ravel().tolist() == [-1e-3, pytest.approx(0.7 * 2.0)]  # omega+ = -e pre(omega)
    assert np.array(m_new).ravel().tolist() == [4.0, 1.7]  # impacts = pre(impacts) + 1; t_impact = time


def test_the_modelica_pendulum_hits_the_analytic_impact_times(tmp_path):
    res = run(ROOT / "scenarios" / "pendulum_stop_modelica.yaml", [], out_dir=tmp_path)
    assert res.ok, res.reason
    times = np.unique(res.trace["pend.t_impact"])[1:]
    assert len(times) == 5
    assert np.max(np.abs(times - analytic_impacts(5))) < 1e-9, times - analytic_impacts(5)


def test_a_relation_read_by_an_if_expression_restarts_the_step_where_it_switches():
    b = translate('model Sat "a saturated integrator"\n  input Real u;\n  Real x(start = 0);\n  output Real y;\n'
                  'equation\n  der(x) = if x > 1 then 0 else u;\n  y = x;\nend Sat;\n', "Sat", "Sat.mo")
    assert b.directions == [EITHER] and float(b.event_functions()["indicators"](0, [1.25], [0.0], [], [])) == 0.25


@pytest.mark.parametrize("body, line, what", [
    ("  when x > 1 then\n    terminate(\"done\");\n  end when;", 7, "terminate"),
    ("  when x > 1 then\n    n = 1;\n  elsewhen initial() then\n    n = 2;\n  end when;", 8,
     "an elsewhen branch's condition"),
    ("  when edge(x > 1) then\n    n = 1;\n  end when;", 6, "edge"),
    ("  when x > 1 and x < 3 then\n    n = 1;\n  end when;", 6, "a when-condition other than one relation"),  # the when's line
    ("  when {x > 1, x < -1} then\n    n = 1;\n  end when;", 6, "a when-condition other than one relation"),
])
def test_what_is_not_translated_yet_names_file_line_and_construct(body, line, what):
    text = f'model E "e"\n  Real x(start = 0);\n  discrete Real n(start = 0);\nequation\n  der(x) = 1;\n{body}\nend E;\n'
    with pytest.raises(ModelicaError) as err:
        translate(text, "E", "E.mo")
    assert str(err.value).startswith(f"E.mo:{line}: {what}"), str(err.value)


def test_a_modelica_ball_without_modes_has_an_event_reference(tmp_path):
    """The issue's bouncing ball (`when h < 0 then reinit(v, -e*pre(v))`, no discrete variable):
    the event reference (`run --reference`) took modes for granted; its impact times against the
    analytic ones (free fall, then flights of 2 v_k / g with v_k = e^k sqrt(2 g h0))."""
    from cosim.run.reference import reference

    (tmp_path / "Ball.mo").write_text(
        "model Ball\n  parameter Real e = 0.8;\n  parameter Real g = 9.81;\n  Real h(start = 1, fixed = true);\n"
        "  Real v(start = 0, fixed = true);\nequation\n  der(h) = v;\n  der(v) = -g;\n"
        "  when h < 0 then\n    reinit(v, -e*pre(v));\n  end when;\nend Ball;\n")
    (tmp_path / "ball.yaml").write_text(
        "name: ball\nstop_time: 2\ncomponents:\n  b: {modelica: Ball.mo, model: Ball}\nconnections: []\n"
        "master: {algorithm: jacobi, step: 1e-2}\noutputs: [b.h, b.v]\n")
    ref = reference(tmp_path / "ball.yaml")
    assert ref.status == "ok", ref.reason
    v0 = np.sqrt(2 * 9.81)
    analytic = np.cumsum([v0 / 9.81] + [2 * 0.8 ** k * v0 / 9.81 for k in (1, 2)])
    times = np.array([e["time"] for e in ref.stats["events"]["list"]])
    assert len(times) == 3 and np.max(np.abs(times - analytic)) < 1e-8, times - analytic
    cosim = run(tmp_path / "ball.yaml", [], out_dir=tmp_path / "out")
    once = np.diff(ref.trace.time, prepend=-1.0) > 0  # one row per instant (the grid's rows are among them)
    on_grid = np.interp(cosim.trace.time, ref.trace.time[once], ref.trace["b.h"][once])
    assert cosim.ok and np.max(np.abs(cosim.trace["b.h"] - on_grid)) < 1e-9


def test_the_reference_of_a_relation_on_time_at_its_start_time_ends(tmp_path):
    """The MSL sources' `if time < startTime` with startTime = 0 (the Oscillator's sines) is an
    undirected indicator at zero at the start: the event reference fired it at t = 0 again and
    again until its wall-time cap.  Against the analytic x = 1 - cos t (y = sin t from t = 0.5 s
    in a second relation, which must fire once there)."""
    from cosim.run.reference import reference

    (tmp_path / "Src.mo").write_text(
        "model Src\n  parameter Real startTime = 0;\n  parameter Real w = 1;\n  parameter Real t1 = 0.5;\n  Real x(start = 0, fixed = true);\n"
        "  Real z(start = 0, fixed = true);\nequation\n  der(x) = if time < startTime then 0 else sin(w * time);\n"
        "  der(z) = if time < t1 then 0 else 1;\nend Src;\n")
    (tmp_path / "src.yaml").write_text(
        "name: src\nstop_time: 1\ncomponents:\n  s: {modelica: Src.mo, model: Src}\nconnections: []\n"
        "master: {algorithm: jacobi, step: 1e-2}\noutputs: [s.x, s.z]\n")
    ref = reference(tmp_path / "src.yaml", max_wall_s=60)
    assert ref.status == "ok", ref.reason
    t = ref.trace.time
    assert np.max(np.abs(ref.trace["s.x"] - (1 - np.cos(t)))) < 1e-6
    assert np.max(np.abs(ref.trace["s.z"] - np.maximum(t - 0.5, 0))) < 1e-6
    assert ref.stats["events"]["count"] <= 2  # t1 once (startTime's, at zero at the start, at most once)


@pytest.mark.parametrize("integrator, tol", [("exact", 1e-11), ("radau", 1e-8), ("rk4", 1e-5)])
def test_a_crossing_inside_one_long_step_fires_once(tmp_path, integrator, tol):
    """x' = 1 - x from 0 crosses 0.5 at ln 2 inside one 0.1 s step (a linear model: exact by default,
    one internal step).  The dense output there is 1e-8 s off the integrator's own crossing; the
    core applied the update on the near side and the when-clause fired a second time (n = 2).  Now
    once, at ln 2 to the method's accuracy, and x stays on 1 - exp(-t)."""
    (tmp_path / "L.mo").write_text(
        "model L\n  Real x(start = 0, fixed = true);\n  discrete Real t1(start = 0);\n  discrete Real n(start = 0);\n"
        "equation\n  der(x) = 1 - x;\n  when x > 0.5 then\n    t1 = time;\n    n = pre(n) + 1;\n  end when;\nend L;\n")
    (tmp_path / "l.yaml").write_text(
        "stop_time: 1\ncomponents:\n  c: {modelica: L.mo, model: L, options: {integrator: %s}}\n"
        "master: {algorithm: jacobi, step: 0.1, estimate: false}\noutputs: [c.x, c.t1, c.n]\n" % integrator)
    res = run(tmp_path / "l.yaml", [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    assert res.trace["c.n"][-1] == 1.0
    assert abs(res.trace["c.t1"][-1] - np.log(2)) < tol
    if integrator == "exact":
        assert np.max(np.abs(res.trace["c.x"] - (1 - np.exp(-res.trace["time"])))) < 1e-12


def test_the_reference_fires_a_when_on_a_rising_state_once(tmp_path):
    """The event reference of the same model: after `when x > 0.5` fired, x goes on rising past the
    indicator's watch (EPS_Z on its far side), which fired it again and again at ln 2 (n = 19390
    when the wall-time cap stopped it).  Once, at ln 2 (1e-9 s), x on 1 - exp(-t)."""
    from cosim.run.reference import reference

    (tmp_path / "L.mo").write_text(
        "model L\n  Real x(start = 0, fixed = true);\n  discrete Real t1(start = 0);\n  discrete Real n(start = 0);\n"
        "equation\n  der(x) = 1 - x;\n  when x > 0.5 then\n    t1 = time;\n    n = pre(n) + 1;\n  end when;\nend L;\n")
    (tmp_path / "l.yaml").write_text("stop_time: 1\ncomponents:\n  c: {modelica: L.mo, model: L}\n"
                                     "master: {algorithm: jacobi, step: 0.1}\noutputs: [c.x, c.t1, c.n]\n")
    ref = reference(tmp_path / "l.yaml", max_wall_s=60)
    assert ref.status == "ok", ref.reason
    assert ref.stats["events"]["count"] == 1 and ref.trace["c.n"][-1] == 1.0
    assert abs(ref.trace["c.t1"][-1] - np.log(2)) < 1e-9
    assert np.max(np.abs(ref.trace["c.x"] - (1 - np.exp(-ref.trace.time)))) < 1e-8


def test_a_zeno_ball_fails_in_the_run_and_in_its_reference_at_the_zeno_time(tmp_path):
    """The bouncing ball (e = 0.8, from 1 m) bounces infinitely often before
    t_z = sqrt(2 h / g) + 2 e sqrt(2 g h) / (g (1 - e)) = 4.0637 s.  The run fails there naming the
    chattering; so must the event reference, which had let the ball fall through the floor and
    ended "ok" (h = -4.3 m at 5 s)."""
    from cosim.run.reference import reference

    (tmp_path / "Ball.mo").write_text(
        "model Ball\n  parameter Real e = 0.8;\n  parameter Real g = 9.81;\n  Real h(start = 1, fixed = true);\n"
        "  Real v(start = 0, fixed = true);\nequation\n  der(h) = v;\n  der(v) = -g;\n"
        "  when h < 0 then\n    reinit(v, -e*pre(v));\n  end when;\nend Ball;\n")
    (tmp_path / "ball.yaml").write_text(
        "name: ball\nstop_time: 5\ncomponents:\n  b: {modelica: Ball.mo, model: Ball}\nconnections: []\n"
        "master: {algorithm: jacobi, step: 1e-2}\noutputs: [b.h, b.v]\n")
    t_z = np.sqrt(2 / 9.81) + 2 * 0.8 * np.sqrt(2 * 9.81) / (9.81 * 0.2)
    cosim = run(tmp_path / "ball.yaml", [], out_dir=tmp_path / "out")
    assert cosim.status == "failed" and "chattering" in cosim.reason and abs(cosim.trace.time[-1] - t_z) < 0.011
    ref = reference(tmp_path / "ball.yaml", max_wall_s=120)
    assert ref.status == "failed" and "Zeno" in ref.reason, ref.reason
    assert abs(ref.trace.time[-1] - t_z) < 1e-6 and ref.stats["simulated_s"] == ref.trace.time[-1]
    assert ref.trace["b.h"].min() > -1e-9  # never through the floor


W = """model W
  parameter Real T0 = 0.55;
  Real x(start = 0, fixed = true);
  Real y(start = 0, fixed = true);
equation
  der(x) = 1;
  der(y) = 1;
  when sample(0, 0.3) then
    reinit(x, 0);
  end when;
  when time > T0 then
    reinit(y, 10);
  end when;
end W;
"""


@pytest.mark.parametrize("T0", [0.55, 0.42])
def test_a_when_on_time_fires_at_its_instant_and_its_parameter_is_settable(tmp_path, T0):
    """`when time > T0 then reinit(y, 10)` (rumoca makes the relation a time event) was refused as
    "a when-condition other than one relation"; now an indicator in time, so T0 stays a settable
    parameter: y = t, then 10 + t - T0.  The event reference of the same scene (a sample every
    0.3 s against a 0.1 s grid: 3 x 0.1 rounds past 0.3, which solve_ivp refused as outside its
    span) agrees, and x restarts from 0 at every sample."""
    from cosim.run.reference import reference

    (tmp_path / "W.mo").write_text(W)
    (tmp_path / "w.yaml").write_text(
        f"stop_time: 1\ncomponents:\n  c: {{modelica: W.mo, model: W, params: {{T0: {T0}}}}}\n"
        "master: {algorithm: jacobi, step: 0.1, estimate: false}\noutputs: [c.x, c.y]\n")
    res = run(tmp_path / "w.yaml", [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    t = res.trace["time"]
    assert np.max(np.abs(res.trace["c.y"] - np.where(t < T0, t, 10 + t - T0))) < 1e-9
    ref = reference(tmp_path / "w.yaml")
    assert ref.status == "ok", ref.reason
    times = [round(e["time"], 9) for e in ref.stats["events"]["list"] if "T0" in e["event"]]
    assert times == [T0]
    once = (np.diff(ref.trace.time, append=2.0) > 0) & (np.abs(ref.trace.time - T0) > 1e-9)  # right limits, off the jump
    tr = ref.trace.time[once]
    assert np.max(np.abs(ref.trace["c.y"][once] - np.where(tr < T0, tr, 10 + tr - T0))) < 1e-9
    assert np.max(np.abs(ref.trace["c.x"][once] - (tr - 0.3 * np.floor(tr / 0.3 + 1e-9)))) < 1e-9
