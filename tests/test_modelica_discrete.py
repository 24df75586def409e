"""Modelica as users write it, translated into the event-aware Block (models/modelica.py,
docs/explanation/modelica.md): initial equations, Boolean and Integer discrete variables,
relations on time as time events, relations on states as state events, noEvent, one-element
arrays and for-equations over them, sample() as periodic time events, Boolean and Integer
variables assigned in when-clauses, edge() and change() of a Boolean given by a
relation, when initial().  Each small model runs as a scene component and is compared
with its analytic solution; what is not translated yet is refused naming file, line and construct."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rumoca")

from cosim.run.execute import run  # noqa: E402
from cosim.run.reference import reference  # noqa: E402
from models.modelica import ModelicaError, translate  # noqa: E402


def simulate(tmp_path, text: str, model: str, stop: float, step: float, outputs: list[str]):
    (tmp_path / f"{model}.mo").write_text(text)
    scene = tmp_path / "scene.yaml"
    scene.write_text(f"stop_time: {stop}\ncomponents:\n  c: {{modelica: {model}.mo, model: {model}}}\n"
                     f"connections: []\nmaster: {{algorithm: jacobi, step: {step}, estimate: false}}\n"
                     f"outputs: [{', '.join(repr('c.' + o) for o in outputs)}]\n")
    res = run(scene, [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    return res.trace


LAG = """model Lag "first-order lags started by initial equations"
  parameter Real T = 0.5;
  parameter Real k = 2;
  Real x;
  Real y;
initial equation
  x = 2 * k;
  der(y) = 0;
equation
  T * der(x) = k - x;
  der(y) = k - 4 * y;
end Lag;
"""


def test_initial_equations_set_the_start_values(tmp_path):
    """x(0) = 2k from an equation, y(0) = k/4 from der(y) = 0 (a steady state): x(t) = k + k
    exp(-t/T), y stays at k/4."""
    b = translate(LAG, "Lag", "Lag.mo")
    import casadi as ca

    start = np.array(ca.Function("s", [b.p], [b.start])(b.param_defaults)).ravel()
    assert start.tolist() == [4.0, 0.5]
    tr = simulate(tmp_path, LAG, "Lag", 2.0, 0.01, ["x", "y"])
    t = np.asarray(tr["time"])
    assert np.max(np.abs(tr["c.x"] - (2 + 2 * np.exp(-t / 0.5)))) < 1e-6
    assert np.max(np.abs(tr["c.y"] - 0.5)) < 1e-12


SWITCH = """model Switch "a Boolean on time (a time event) and an Integer on a state (a state event)"
  Boolean on = time >= 0.5;
  Integer n = if x > 0.9 then 3 else 1;
  Real x(start = 0);
  Real s(start = 0);
equation
  der(x) = if on then n else 0;
  der(s) = if noEvent(s > 10) then 0 else 1;
end Switch;
"""


def test_boolean_and_integer_discrete_variables_switch_at_their_events(tmp_path):
    """x = 0 until the time event at 0.5 s, then rate 1 until x = 0.9 (t = 1.4 s, a state event
    located inside a communication step of 0.04 s), then rate 3: x = 0.9 + 3 (t - 1.4).  The Boolean and
    the Integer are modes, recorded as 0/1 and 1/3."""
    b = translate(SWITCH, "Switch", "Switch.mo")
    assert [v.name for v in b.modes] == ["mode.on", "mode.n"]
    assert [s.offset for s in b.sample_times] == [0.0, 0.5]  # the initial event, the time event
    assert b.event_names == ["state.x > 0.9"]  # noEvent(s > 10) is no indicator (without it: a second one)
    assert translate(SWITCH.replace("noEvent(s > 10)", "s > 10"), "Switch", "Switch.mo").event_names[1] == "state.s > 10"
    tr = simulate(tmp_path, SWITCH, "Switch", 2.0, 0.04, ["x", "on", "n", "s"])
    t = np.asarray(tr["time"])
    exact = np.where(t < 0.5, 0.0, np.where(t < 1.4, t - 0.5, 0.9 + 3 * (t - 1.4)))
    assert np.max(np.abs(tr["c.x"] - exact)) < 1e-9
    assert set(np.asarray(tr["c.on"])[t > 0.52]) == {1.0} and set(np.asarray(tr["c.on"])[t < 0.48]) == {0.0}
    assert set(np.asarray(tr["c.n"])[t > 1.42]) == {3.0} and set(np.asarray(tr["c.n"])[t < 1.38]) == {1.0}
    assert np.max(np.abs(tr["c.s"] - t)) < 1e-12  # noEvent: no indicator, a smooth ramp here


CHAIN = """model Chain "a one-element array and a for-equation over it"
  parameter Real tau[1] = {0.25};
  Real a[1](each start = 1);
equation
  for i in 1:1 loop
    der(a[i]) = -a[i] / tau[i];
  end for;
end Chain;
"""


def test_a_for_equation_over_a_one_element_array(tmp_path):
    tr = simulate(tmp_path, CHAIN, "Chain", 1.0, 0.01, ["a"])
    t = np.asarray(tr["time"])
    assert np.max(np.abs(tr["c.a"] - np.exp(-t / 0.25))) < 1e-6


HOLD = """model Hold "sample and hold of sin(2 pi t)"
  parameter Real f = 1;
  discrete Real y(start = 0);
equation
  when sample(0, 0.1) then
    y = sin(2 * 3.141592653589793 * f * time);
  end when;
end Hold;
"""


def test_sample_holds_the_value_at_each_sample_instant(tmp_path):
    """y(t) = sin(2 pi t_k) with t_k = 0.1 floor(t / 0.1): the held value is the sine exactly at
    the instants, which the communication steps of 0.03 s do not meet (ties left out)."""
    b = translate(HOLD, "Hold", "Hold.mo")
    assert [(s.period, s.offset) for s in b.sample_times] == [(0.1, 0.0)]
    tr = simulate(tmp_path, HOLD, "Hold", 0.99, 0.03, ["y"])
    t = np.asarray(tr["time"])
    k = np.floor(t / 0.1 + 1e-9)
    away = np.abs(t / 0.1 - np.round(t / 0.1)) > 1e-6
    assert away.sum() > 25
    assert np.max(np.abs(tr["c.y"][away] - np.sin(2 * np.pi * 0.1 * k[away]))) < 1e-12


def test_a_parameter_read_by_sample_is_fixed_not_settable():
    """rumoca fixes the interval at the parameter's value, so the parameter is not exported as
    settable (a scene could not change the period); one computed from others is refused."""
    text = HOLD.replace("parameter Real f = 1;", "parameter Real f = 1;\n  parameter Real T = 0.1;")
    b = translate(text.replace("sample(0, 0.1)", "sample(0, T)"), "Hold", "Hold.mo")
    assert [v.name for v in b.params] == ["f"] and [s.period for s in b.sample_times] == [0.1]
    computed = text.replace("T = 0.1", "T = 0.1 * f").replace("sample(0, 0.1)", "sample(0, T)")
    with pytest.raises(ModelicaError, match=r"^Hold\.mo:3: T: a parameter read by sample\(\) must have a literal"):
        translate(computed, "Hold", "Hold.mo")


COUNT = """model Count "an Integer counter on sample(), a Boolean latched by a state event"
  Real x(start = 0);
  Integer n(start = 0);
  Boolean hit(start = false);
equation
  der(x) = 1;
  when sample(0.05, 0.1) then
    n = pre(n) + 1;
  end when;
  when x > 0.33 then
    hit = true;
  end when;
end Count;
"""


def test_integer_and_boolean_assigned_in_when_clauses(tmp_path):
    """n counts the instants 0.05 + 0.1 k passed (k = 0, 1, ...); hit turns true where x = t
    crosses 0.33 and stays true (the grid of 0.04 s meets neither)."""
    tr = simulate(tmp_path, COUNT, "Count", 0.96, 0.04, ["n", "hit"])
    t = np.asarray(tr["time"])
    assert np.array_equal(np.asarray(tr["c.n"]), np.where(t < 0.05, 0, np.floor((t - 0.05) / 0.1) + 1))
    assert np.array_equal(np.asarray(tr["c.hit"]), (t > 0.33).astype(float))


EDGES = """model Edges "a counter of the rising crossings of sin(x), by edge()"
  Real x(start = -1.05);
  Boolean pos;
  Integer n(start = 0);
equation
  der(x) = 1;
  pos = sin(x) > 0;
  when edge(pos) then
    n = pre(n) + 1;
  end when;
end Edges;
"""


def test_edge_counts_the_positive_crossings(tmp_path):
    """sin(t - 1.05) turns positive at t = 1.05 + 2 pi k: n counts those passed."""
    tr = simulate(tmp_path, EDGES, "Edges", 20.0, 0.1, ["n"])
    t = np.asarray(tr["time"])
    exact = np.where(t < 1.05, 0, np.floor((t - 1.05) / (2 * np.pi)) + 1)
    assert exact[-1] == 4 and np.array_equal(np.asarray(tr["c.n"]), exact)


AT_START = """model AtStart "when initial(): the modes set once, at the start"
  parameter Real a = 3;
  Real x(start = 0);
  discrete Real m(start = 0);
  Integer n(start = 0);
equation
  der(x) = m;
  when initial() then
    m = 2 * a;
    n = 5;
  end when;
end AtStart;
"""


def test_when_initial_sets_the_modes_at_the_start(tmp_path):
    """m = 2a = 6 from t = 0 (not its start value 0), so x = 6 t; n = 5 throughout."""
    b = translate(AT_START, "AtStart", "AtStart.mo")
    assert [(s.offset, s.name) for s in b.sample_times] == [(0.0, "when initial()")]
    tr = simulate(tmp_path, AT_START, "AtStart", 1.0, 0.1, ["x", "m", "n"])
    t = np.asarray(tr["time"])
    assert np.max(np.abs(tr["c.x"] - 6 * t)) < 1e-12
    assert set(np.asarray(tr["c.m"])) == {6.0} and set(np.asarray(tr["c.n"])) == {5.0}


def test_change_counts_the_crossings_both_ways(tmp_path):
    """change(pos) with pos = sin(t - 1.05) > 0 fires at t = 1.05 + pi k: n counts those passed."""
    text = EDGES.replace("edge(pos)", "change(pos)")
    tr = simulate(tmp_path, text, "Edges", 20.0, 0.1, ["n"])
    t = np.asarray(tr["time"])
    exact = np.where(t < 1.05, 0, np.floor((t - 1.05) / np.pi) + 1)
    assert exact[-1] == 7 and np.array_equal(np.asarray(tr["c.n"]), exact)


CHAIN3 = """model Chain3 "a when/elsewhen chain of three relations on x = 1.5 sin(t)"
  Real x(start = 0);
  Real v(start = 1.5);
  Integer hist(start = 0) "the branches fired, one digit each";
  discrete Real t_last(start = -1);
equation
  der(x) = v;
  der(v) = -x;
  when x > 1 then
    hist = 10 * pre(hist) + 1;
    t_last = time;
  elsewhen abs(x) > 1 then
    hist = 10 * pre(hist) + 2;
    t_last = time;
  elsewhen x > 0.5 then
    hist = 10 * pre(hist) + 3;
    t_last = time;
  end when;
end Chain3;
"""


def test_elsewhen_the_first_branch_whose_condition_becomes_true_wins(tmp_path):
    """x = 1.5 sin t.  Hand-computed, with a = asin(2/3), b = asin(1/3): branch 3 (x > 0.5) at
    b; at a both x > 1 and |x| > 1 become true at the same instant, and branch 1 wins (branch 3's
    condition, true already, does not block it); at pi + a only |x| > 1 becomes true (x < -1):
    branch 2; then 3 at 2 pi + b, 1 at 2 pi + a, 2 at 3 pi + a.  ``hist`` appends each fired
    branch's digit, ``t_last`` holds the last firing's time (the error is the integration error
    of x, 6e-8, over |dx/dt| >= 0.5)."""
    b = translate(CHAIN3, "Chain3", "Chain3.mo")
    assert [v.name for v in b.modes][-3:] == ["mode.when1.c1", "mode.when1.c2", "mode.when1.c3"]
    tr = simulate(tmp_path, CHAIN3, "Chain3", 10.5, 0.1, ["x", "hist", "t_last"])
    t = np.asarray(tr["time"])
    a, s = np.arcsin(2 / 3), np.arcsin(1 / 3)
    events = [(s, 3), (a, 1), (np.pi + a, 2), (2 * np.pi + s, 3), (2 * np.pi + a, 1), (3 * np.pi + a, 2)]
    hist, t_last = np.zeros_like(t), np.full_like(t, -1.0)
    for te, digit in events:
        later = t > te
        hist[later] = 10 * hist[later] + digit
        t_last[later] = te
    near = np.min(np.abs(t[:, None] - np.array([te for te, _ in events])[None, :]), axis=1) < 1e-6
    assert hist[-1] == 312312
    assert np.array_equal(np.asarray(tr["c.hist"])[~near], hist[~near])
    assert np.max(np.abs(np.asarray(tr["c.t_last"])[~near] - t_last[~near])) < 1e-6


ON_THE_THRESHOLD = """model OnTheThreshold "x = t - 2 meets each threshold at an instant exact in binary"
  Real x(start = -2);
  Integer hist(start = 0) "the branches fired, one digit each";
  discrete Real t_last(start = -1);
  Integer k(start = 0);
  Integer n = if x > -0.625 then 3 else 1;
equation
  der(x) = 1;
  when x > -1.125 then
    hist = 10 * pre(hist) + 1;
    t_last = time;
  elsewhen x * x > 1 then
    hist = 10 * pre(hist) + 2;
    t_last = time;
  elsewhen x > 1 then
    hist = 10 * pre(hist) + 3;
    t_last = time;
  elsewhen x > 1.75 then
    hist = 10 * pre(hist) + 4;
    t_last = time;
  end when;
  when sample(0, 0.25) then
    k = pre(k) + 1;
  end when;
end OnTheThreshold;
"""


@pytest.mark.parametrize("options", ["{}", "{integrator: rk4, substeps: 4}", "{integrator: radau, substeps: 2}"])
def test_a_branch_whose_crossing_lands_on_its_threshold_applies_there(tmp_path, options):
    """Each crossing's event state has its indicator exactly zero (exact) or a rounding either side
    (radau): branch 1 at 0.875 (x = -1.125 inside a step, a substep boundary for rk4); at 3, a
    communication point, x * x > 1 and x > 1 become true together and branch 2 wins (x * x > 1
    fell false at 1, itself a communication point and a sample instant); branch 4 at 3.75, a
    sample instant; n, always active, switches to 3 at 1.375.  Hand-computed; before, the relation read at a zero indicator kept its old
    value and each branch applied at the chain's next event or never (hist 1 then 12 at 3.75,
    and under radau the crossing at 3, 2e-16 after a sample, was lost; n stayed 1)."""
    text = ON_THE_THRESHOLD
    (tmp_path / "OnTheThreshold.mo").write_text(text)
    scene = tmp_path / "scene.yaml"
    scene.write_text(f"stop_time: 4.5\ncomponents:\n  c: {{modelica: OnTheThreshold.mo, model: OnTheThreshold, "
                     f"options: {options}}}\nconnections: []\n"
                     f"master: {{algorithm: jacobi, step: 0.5, estimate: false}}\noutputs: [c.hist, c.t_last, c.k, c.n]\n")
    res = run(scene, [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    t = np.asarray(res.trace["time"])
    events = [(0.875, 1), (3.0, 2), (3.75, 4)]
    hist, t_last = np.zeros_like(t), np.full_like(t, -1.0)
    for te, digit in events:
        later = t > te
        hist[later] = 10 * hist[later] + digit
        t_last[later] = te
    assert np.array_equal(np.asarray(res.trace["c.hist"])[t != 3.0], hist[t != 3.0])
    assert np.max(np.abs(np.asarray(res.trace["c.t_last"])[t != 3.0] - t_last[t != 3.0])) < 1e-9
    assert np.array_equal(np.asarray(res.trace["c.n"]), np.where(t > 1.375, 3.0, 1.0))
    assert res.trace["c.k"][-1] == 18  # the samples at 0, 0.25, ..., 4.25 all taken
    if options == "{}":  # the event reference too (it lost the crossings at the sample instants 3 and 3.75)
        ref = reference(scene, [])
        assert ref.ok, ref.reason
        rt = np.asarray(ref.trace["time"])
        later = rt > 3.75 + 1e-9
        assert np.all(np.asarray(ref.trace["c.hist"])[later] == 124)
        assert np.max(np.abs(np.asarray(ref.trace["c.t_last"])[later] - 3.75)) < 1e-9


@pytest.mark.parametrize("body, line, what", [
    ("  when change(y) then\n    y = 1;\n  end when;", 6, "change()"),
    ("  when x > 1 then\n    y = 1;\n  elsewhen sample(0, 0.1) then\n    y = 2;\n  end when;", 8,
     "an elsewhen branch's condition other than one relation"),
    ("  when edge(x > 1) then\n    y = 1;\n  end when;", 6, "edge()"),
    ("  when {x > 1, x > 2} then\n    y = 1;\n  end when;", 6, "a when-condition other than one relation"),
])
def test_what_is_not_translated_yet_names_file_line_and_construct(body, line, what):
    text = f'model E "e"\n  Real x(start = 0);\n  discrete Real y(start = 0);\nequation\n  der(x) = 1;\n{body}\nend E;\n'
    with pytest.raises(ModelicaError) as err:
        translate(text, "E", "E.mo")
    assert str(err.value).startswith(f"E.mo:{line}:") and what in str(err.value), str(err.value)


DECAY3 = """model Decay3 "three decays: a for-equation over arrays, a matrix product"
  parameter Real k[3] = {1, 2, 3};
  parameter Real A[2, 3] = [1, 2, 3; 4, 5, 6];
  Real x[3](each start = 1);
  Real y[2];
  Real total;
equation
  for i in 1:3 loop
    der(x[i]) = -k[i] * x[i];
  end for;
  y = A * x;
  total = sum(x);
end Decay3;
"""


def test_arrays_and_for_equations_over_them(tmp_path):
    """x[i] = exp(-k[i] t) (k = 1, 2, 3), y = A x, total = sum(x): each element recorded by its
    Modelica name (``x[2]``, ``y[1]``) and compared with the analytic solution; the array
    parameters' elements are settable parameters (``k[2]``)."""
    b = translate(DECAY3, "Decay3", "Decay3.mo")
    assert [v.name for v in b.params] == ["k[1]", "k[2]", "k[3]", "A[1,1]", "A[1,2]", "A[1,3]", "A[2,1]",
                                          "A[2,2]", "A[2,3]"]
    assert [v.name for v in b.states] == ["state.x[1]", "state.x[2]", "state.x[3]"]
    tr = simulate(tmp_path, DECAY3, "Decay3", 2.0, 0.01, ["x[1]", "x[2]", "x[3]", "y[1]", "y[2]", "total"])
    t = np.asarray(tr["time"])
    x = np.exp(-np.outer(t, [1.0, 2.0, 3.0]))
    for i in range(3):
        assert np.max(np.abs(tr[f"c.x[{i + 1}]"] - x[:, i])) < 1e-6
    A = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    for r in range(2):
        assert np.max(np.abs(tr[f"c.y[{r + 1}]"] - x @ A[r])) < 1e-5
    assert np.max(np.abs(tr["c.total"] - x.sum(axis=1))) < 1e-5


def test_an_array_of_three_dimensions_is_refused_naming_it():
    text = 'model A "a"\n  Real a[2, 2, 2](each start = 1);\nequation\n  der(a) = -a;\nend A;\n'
    with pytest.raises(ModelicaError) as err:
        translate(text, "A", "A.mo")
    assert str(err.value).startswith("A.mo:2: a: an array of dimensions [2, 2, 2] is not supported"), str(err.value)


FUNCTIONS = """model Fn "functions with algorithm sections: reassignment, a for-loop, if-statements"
  function g
    input Real u;
    output Real y;
  protected
    Real a;
  algorithm
    a := u;
    a := a * 2;
    y := a + 1;
    if u > 10 then
      y := 0;
    end if;
  end g;
  function f
    input Real u;
    output Real y;
  protected
    Real acc;
  algorithm
    acc := 0;
    for i in 1:3 loop
      acc := acc + i * u;
    end for;
    if u > 0 then
      y := acc;
    else
      y := -acc;
    end if;
  end f;
  Real x(start = 1);
  Real w;
  Real z;
equation
  der(x) = -f(x);
  w = g(x);
  z = g(20 + x);
end Fn;
"""


def test_functions_with_algorithm_sections(tmp_path):
    """f(u) = |1 u + 2 u + 3 u| (the for-loop, the if-statement), so x = exp(-6 t); g(u) = 2 u + 1
    for u <= 10 (two assignments to a, then y), 0 above: w = 2 x + 1, z = g(20 + x) = 0."""
    tr = simulate(tmp_path, FUNCTIONS, "Fn", 1.0, 0.01, ["x", "w", "z"])
    t = np.asarray(tr["time"])
    x = np.exp(-6 * t)
    assert np.max(np.abs(tr["c.x"] - x)) < 1e-6
    assert np.max(np.abs(tr["c.w"] - (2 * x + 1))) < 2e-6
    assert np.max(np.abs(tr["c.z"])) == 0.0


def test_records_and_extends_across_files(tmp_path):
    """A model extending a class of a sibling file and holding a record of a third: x = 3 exp(-k
    g.a g.b t) with k = 2 from the base, g.b = 0.5 modified (the record's default 4)."""
    (tmp_path / "Base.mo").write_text('partial model Base "a base"\n  parameter Real k = 2;\n'
                                      '  Real x(start = 3);\nend Base;\n')
    (tmp_path / "Gains.mo").write_text('record Gains "two gains"\n  Real a = 1.5;\n  Real b = 4;\nend Gains;\n')
    text = ('model Use "uses both"\n  extends Base;\n  parameter Gains g(b = 0.5);\nequation\n'
            '  der(x) = -k * g.a * g.b * x;\nend Use;\n')
    tr = simulate(tmp_path, text, "Use", 1.0, 0.01, ["x"])
    t = np.asarray(tr["time"])
    assert np.max(np.abs(tr["c.x"] - 3 * np.exp(-1.5 * t))) < 1e-6


def test_an_algorithm_section_of_a_model(tmp_path):
    """rumoca lowers a model's algorithm with one output into an equation: y = 2 x + 1 with
    x = exp(-t); one of several outputs it refuses, named by the section's line."""
    text = ('model Alg "an algorithm section"\n  Real x(start = 1);\n  Real y;\nalgorithm\n  y := 2 * x;\n'
            '  y := y + 1;\nequation\n  der(x) = -x;\nend Alg;\n')
    tr = simulate(tmp_path, text, "Alg", 1.0, 0.01, ["y"])
    t = np.asarray(tr["time"])
    assert np.max(np.abs(tr["c.y"] - (2 * np.exp(-t) + 1))) < 1e-6
    two = text.replace("  Real y;\n", "  Real y;\n  Real z;\n").replace("  y := y + 1;\n", "  y := y + 1;\n  z := y;\n")
    with pytest.raises(ModelicaError, match=r"^Alg\.mo:5: algorithm: .*multi-output algorithm"):
        translate(two, "Alg", "Alg.mo")


ASSERTS = """model As "assertions on a variable, x = exp(-t)"
  Real x(start = 1);
equation
  der(x) = -x;
  assert(x > 0.5, "x fell below 0.5");
  assert(x > 0.8, "x below 0.8", AssertionLevel.warning);
end As;
"""


def _run_asserts(tmp_path, stop: float):
    (tmp_path / "As.mo").write_text(ASSERTS)
    scene = tmp_path / "scene.yaml"
    scene.write_text(f"stop_time: {stop}\ncomponents:\n  c: {{modelica: As.mo, model: As}}\nconnections: []\n"
                     f"master: {{algorithm: jacobi, step: 0.01, estimate: false}}\n"
                     f"outputs: ['c.x', 'c.assert.line5', 'c.assert.line6']\n")
    return run(scene, [], out_dir=tmp_path / f"out{stop}")


def test_assertions_on_variables_are_checked_during_the_run(tmp_path):
    """The warning (x > 0.8) fails at t = ln 1.25 = 0.223 s: recorded as its latch from the first
    row after (0.23 s), the run goes on and ends ok at 0.6 s; the error (x > 0.5) fails at
    t = ln 2 = 0.693 s: the run ends out_of_limits at the first row after (0.70 s), quoting the
    assertion's file, line and message."""
    res = _run_asserts(tmp_path, 0.6)
    assert res.ok, res.reason
    t = np.asarray(res.trace["time"])
    assert np.array_equal(np.asarray(res.trace["c.assert.line6"]), (t > np.log(1.25)).astype(float))
    assert set(np.asarray(res.trace["c.assert.line5"])) == {0.0}
    res = _run_asserts(tmp_path, 1.0)
    assert res.status == "out_of_limits"
    assert 'assert at As.mo:5: "x fell below 0.5"' in res.reason and "t = 0.7 s" in res.reason, res.reason


def test_an_initial_algorithm_sets_discrete_start_values(tmp_path):
    """t0 := 2 a in an initial algorithm (a = 3), then the initial equation x = t0: x = 6 exp(-t)."""
    text = ('model Ia "an initial algorithm"\n  parameter Real a = 3;\n  Real x;\n  discrete Real t0;\n'
            'initial algorithm\n  t0 := 2 * a;\nequation\n  der(x) = -x;\ninitial equation\n  x = t0;\nend Ia;\n')
    tr = simulate(tmp_path, text, "Ia", 1.0, 0.01, ["x", "t0"])
    t = np.asarray(tr["time"])
    assert np.max(np.abs(tr["c.x"] - 6 * np.exp(-t))) < 1e-5
    assert set(np.asarray(tr["c.t0"])) == {6.0}


SWITCHING = "model Switching\n  Real x(start = 0);\nequation\n  der(x) = if x > 0.9 then 2 else 1;\nend Switching;\n"


def simulate_with(tmp_path, text: str, model: str, stop: float, step: float, options: str):
    (tmp_path / f"{model}.mo").write_text(text)
    scene = tmp_path / "scene.yaml"
    scene.write_text(f"stop_time: {stop}\ncomponents:\n  c: {{modelica: {model}.mo, model: {model}, options: {options}}}\n"
                     f"connections: []\nmaster: {{algorithm: jacobi, step: {step}, estimate: false}}\noutputs: ['c.x']\n")
    res = run(scene, [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    return np.asarray(res.trace["time"]), np.asarray(res.trace["c.x"])


@pytest.mark.parametrize("options", ["{integrator: exact}", "{integrator: rk4}", "{integrator: radau}", "{}"])
def test_a_relation_on_a_state_is_a_state_event(tmp_path, options):
    """``der(x) = if x > 0.9 then 2 else 1`` (Modelica: the relation's truth is frozen between
    crossings): x = t until 0.9, then 0.9 + 2 (t - 0.9), x(2) = 3.1.  The relation is a mode
    flipped at its located crossing, so every integrator is exact between events (Radau across
    the switch used to cost h / 9: 1.1e-3 at h = 0.01); the switch time, read back from x after
    it (t - (x - 0.9) / 2), within 1e-9 s."""
    block = translate(SWITCHING, "Switching", "Switching.mo")
    assert block.integrator == "exact" and block.m.numel() == 1  # linear between events: its mode
    assert block.indicators.numel() == 1
    t, x = simulate_with(tmp_path, SWITCHING, "Switching", 2.0, 0.01, options)
    assert abs(x[-1] - 3.1) < 1e-9
    assert np.max(np.abs(x - np.where(t <= 0.9, t, 0.9 + 2 * (t - 0.9)))) < 1e-9
    after = t > 0.95
    assert np.max(np.abs(t[after] - (x[after] - 0.9) / 2 - 0.9)) < 1e-9


@pytest.mark.parametrize("options", ["{integrator: rk4}", "{}"])
def test_a_relation_on_a_solved_variable_is_a_state_event(tmp_path, options):
    """The same switch read through an algebraic variable (``y = 2 x``, ``y > 1.8``): its indicator
    and mode are in the state (the solved variable substituted; before, the indicator named ``y``
    and the block was refused, as MSL's ``Rotational.Examples.Backlash`` was)."""
    text = SWITCHING.replace("  Real x(start = 0);", "  Real x(start = 0);\n  Real y;").replace(
        "x > 0.9", "y > 1.8").replace("equation\n", "equation\n  y = 2 * x;\n")
    block = translate(text, "Switching", "Switching.mo")
    assert block.integrator == "exact" and block.m.numel() == 1
    t, x = simulate_with(tmp_path, text, "Switching", 2.0, 0.01, options)
    assert abs(x[-1] - 3.1) < 1e-9
    assert np.max(np.abs(x - np.where(t <= 0.9, t, 0.9 + 2 * (t - 0.9)))) < 1e-9
    after = t > 0.95
    assert np.max(np.abs(t[after] - (x[after] - 0.9) / 2 - 0.9)) < 1e-9


def test_a_relation_in_noevent_stays_live(tmp_path):
    """``noEvent(x > 0.9)`` is no event: no indicator, no mode, and the block is not taken for a
    linear one (Radau, which costs about h / 9 at the switching step)."""
    text = SWITCHING.replace("x > 0.9", "noEvent(x > 0.9)")
    block = translate(text, "Switching", "Switching.mo")
    assert block.integrator == "radau" and block.indicators.numel() == 0 and block.m.numel() == 0
    t, x = simulate_with(tmp_path, text, "Switching", 2.0, 0.01, "{}")
    assert 1e-9 < abs(x[-1] - 3.1) < 2e-3
