"""Examples of the Modelica Standard Library 4.1.0 run as scene components against the Modelica
Association's reference results (MAP-LIB_ReferenceResults: Dymola, tolerance 1e-6), on their
comparison signals, each recorded by its Modelica name (an FMI local such as ``c.mass1.s``).
Needs ../shared/third_party (skipped with a message without it); the docs' table of every
example is made by benchmarks/msl_examples.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("rumoca")

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import load  # noqa: E402,F401

THIRD = Path(__file__).resolve().parents[1].parent / "shared" / "third_party"
if not THIRD.is_dir():
    THIRD = Path("/work/shared/third_party")
MSL, RESULTS = THIRD / "modelica-standard-library", THIRD / "msl-reference-results"
pytestmark = pytest.mark.skipif(not (MSL / "Modelica" / "package.mo").is_file() or not RESULTS.is_dir(),
                                reason="the MSL sources and reference results are not in ../shared/third_party")

#: Within this fraction of each comparison signal's range (the issue's acceptance).
TOLERANCE = 1e-3


def reference(example: str) -> tuple[pd.DataFrame, list[str], float, float]:
    """The reference trace, its comparison signals, stop time and output interval [s]."""
    d = RESULTS / Path(*example.split("."))
    signals = [s for s in (d / "comparisonSignals.txt").read_text().split() if s != "time"]
    creation = (d / "creation.txt").read_text()
    stop = float(creation.split("StopTime=")[1].split()[0])
    interval = float(creation.split("Interval=")[1].split()[0])
    return pd.read_csv(d / f"{example.split('.')[-1]}.csv"), signals, stop, interval


#: Integrator substeps per communication step (the reference's output interval), where one is
#: not enough: PID_Controller's spring-damper (c = 1e4, d = 100) is stiff, and one Radau step per
#: 0.8 ms leaves 2.9e-3 of range on spring.w_rel as the motion starts (4 substeps: 6.1e-5).
SUBSTEPS = {"Modelica.Blocks.Examples.PID_Controller": 4}


def scene_of(example: str, folder: Path, outputs: str | None = None, name: str = "scene") -> Path:
    """The example as a scene's one component ``c`` at the reference's stop time and interval,
    recording ``outputs`` (a YAML list; by default the comparison signals)."""
    ref, signals, stop, interval = reference(example)
    path = folder / f"{name}.yaml"
    options = f", options: {{substeps: {SUBSTEPS[example]}}}" if example in SUBSTEPS else ""
    path.write_text(f"stop_time: {stop}\nmodelica_path: [{MSL}]\ncomponents:\n  c: {{modelica: {example}{options}}}\n"
                    f"master: {{algorithm: jacobi, step: {interval}}}\n"
                    f"outputs: {outputs or '[' + ', '.join('c.' + s for s in signals) + ']'}\n")
    return path


@pytest.mark.parametrize("example", ["Modelica.Mechanics.Translational.Examples.Oscillator",
                                     "Modelica.Mechanics.Translational.Examples.Damper",
                                     "Modelica.Mechanics.Rotational.Examples.First",
                                     "Modelica.Blocks.Examples.PID_Controller"])
def test_an_msl_example_matches_the_reference_result(example, tmp_path):
    """PID_Controller needs its initial equations (steady state, der(spring.w_rel) = 0, fixed
    accelerations), the time event of its KinematicPTP source, Boolean discrete variables and
    one-element arrays (KinematicPTP's y[1])."""
    res = run(scene_of(example, tmp_path), [], out_dir=tmp_path / "out")
    assert res.ok, res.reason
    ref, signals, _, _ = reference(example)
    for s in signals:
        expected = np.interp(res.trace["time"], ref["time"], ref[s])
        error = np.abs(res.trace[f"c.{s}"] - expected).max() / np.ptp(ref[s])
        assert error < TOLERANCE, (s, error)


MASS_ON_FLANGE = """model MassOnFlange "an MSL mass with a damper to the ground, driven through its flange"
  Modelica.Mechanics.Translational.Interfaces.Flange_a flange "where the drive pushes";
  Modelica.Mechanics.Translational.Components.Mass mass(m = 2, L = 0);
  Modelica.Mechanics.Translational.Components.Damper damper(d = 0.5);
  Modelica.Mechanics.Translational.Components.Fixed fixed;
equation
  connect(flange, mass.flange_a);
  connect(mass.flange_b, damper.flange_a);
  connect(damper.flange_b, fixed.flange);
end MassOnFlange;
"""


def test_an_msl_built_component_bonds_through_the_causality_its_equations_allow(tmp_path):
    """The MSL flange (s, flow f) is acausal; the mass computes its velocity from a force, so the
    flange is flow_out (force in, rate out).  Taking the velocity in instead would need its
    derivative (an index problem), which the translation names rather than hides.  The equations
    against the mass-damper written by hand: m dv/dt = f - d v, the flange's position s."""
    from cosim.scenario.modelica_sources import modelica_class
    from models.modelica import translate

    (tmp_path / "MassOnFlange.mo").write_text(MASS_ON_FLANGE)
    mc = modelica_class("MassOnFlange.mo", "MassOnFlange", tmp_path, [MSL])
    b = translate(mc.text, "MassOnFlange", "MassOnFlange.mo", compiled=mc.compiled())
    assert [(f.effort, f.flow, f.causality) for f in b.flanges] == [("flange.f", "flange.v", "flow_out")]
    assert [v.name for v in b.inputs] == ["flange.f"]
    fn = b.functions()
    names = [v.name for v in b.states]
    x = np.array([0.1 if n == "state.mass.v" else 0.3 for n in names])
    v, s_rel = 0.1, 0.3
    dx = dict(zip(names, np.array(fn["ode"](x, [1.5], b.param_defaults)).ravel()))
    assert dx["state.mass.v"] == pytest.approx((1.5 - 0.5 * v) / 2, rel=1e-14)
    y = dict(zip([o.name for o in b.outputs], np.array(fn["out"](x, [1.5], b.param_defaults)).ravel()))
    assert y["flange.v"] == pytest.approx(v) and y["mass.s"] == pytest.approx(-s_rel)  # fixed at 0, s_rel = 0 - s


def test_an_outputs_pattern_reaches_a_modelica_components_inner_variables(tmp_path):
    """``c.mass1.*`` records what listing mass1's variables by hand records (its Modelica names,
    FMI locals), with equal values; ``c.spring?.f`` reaches both springs' forces.  The positions
    against the Modelica Association's reference result besides."""
    example = "Modelica.Mechanics.Translational.Examples.Oscillator"
    by_hand = ["c.mass1.s", "c.mass1.flange_a.s", "c.mass1.flange_a.f", "c.mass1.flange_b.s",
               "c.mass1.flange_b.f", "c.mass1.v", "c.mass1.a", "c.spring1.f", "c.spring2.f"]
    runs = {}
    for name, outputs in (("pattern", "[c.mass1.*, \"c.spring?.f\"]"), ("hand", f"[{', '.join(by_hand)}]")):
        runs[name] = run(scene_of(example, tmp_path, outputs, name), [], out_dir=tmp_path / name)
        assert runs[name].ok, runs[name].reason
    recorded = [c for c in runs["pattern"].trace.columns if c != "time"]
    assert sorted(recorded) == sorted(by_hand)
    for c in by_hand:
        np.testing.assert_array_equal(runs["pattern"].trace[c], runs["hand"].trace[c])
    ref, _, _, _ = reference(example)
    expected = np.interp(runs["pattern"].trace["time"], ref["time"], ref["mass1.s"])
    assert np.abs(runs["pattern"].trace["c.mass1.s"] - expected).max() < TOLERANCE * np.ptp(ref["mass1.s"])
