"""Charts a user reads without the legend hunt: units from the FMUs' declarations (checked against
FMPy's reading of each modelDescription), setpoints on the axes of the signal they command, the
co-simulation over its reference with the error axis in the variable's unit."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosim.analysis import charts
from cosim.cli import main
from cosim.analysis.trace_diff import compare
from cosim.run.execute import build_components
from cosim.scenario import load
from cosim.scenario.units import units_of
from cosim.trace.traces import Trace

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"


@pytest.fixture(scope="module")
def pid_scene():
    return load(SCENES / "pid_step.yaml")


@pytest.fixture(scope="module")
def pid_units(pid_scene, cache):
    return units_of(pid_scene, build_components(pid_scene, cache_dir=cache))


@pytest.mark.parametrize("name", ["mech.leg[1].s", "mech.platform.phi", "pid2.y", "motor3.i", "motor1.torque",
                                  "target.leg[2].s"])
def test_units_come_from_the_fmus(name, pid_scene, pid_units, cache):
    import fmpy

    comp, _, var = name.partition(".")
    path = build_components(pid_scene, cache_dir=cache)[comp]
    declared = {v.name: v.unit for v in fmpy.read_model_description(str(path)).modelVariables}
    assert pid_units[name] == declared[var] and declared[var]


def test_setpoints_pair_with_the_signals_they_command(pid_scene):
    assert charts.setpoint_pairs(pid_scene) == {f"target.leg[{i}].s": f"mech.leg[{i}].s" for i in (1, 2, 3)}


def test_run_panels_have_units_and_setpoints_beside_their_signals(pid_scene, pid_units):
    panels = charts.run_panels(pid_scene.outputs, pid_units, charts.setpoint_pairs(pid_scene))
    assert all(p.ylabel.startswith("[") and p.ylabel != "[1]" for p in panels)
    legs = next(p for p in panels if p.title == "mech.leg[*].s")
    assert legs.ylabel == "[m]"
    assert [n for n, dashed in legs.lines if dashed] == [f"target.leg[{i}].s" for i in (1, 2, 3)]
    assert not any(p.title.startswith("target.leg") for p in panels)  # no separate setpoint axes
    assert next(p for p in panels if p.title == "pid*.y").ylabel == "[V]"


def _trace(names, t, cols):
    return Trace(["time", *names], np.column_stack([t, *cols]))


def test_comparison_overlays_both_and_labels_the_error_in_the_unit():
    t = np.linspace(0.0, 1.0, 101)
    test = _trace(["mech.leg[1].s", "motor1.i"], t, [0.3 + 0.01 * t, 2.0 * t])
    ref = _trace(["mech.leg[1].s", "motor1.i"], t, [0.3 + 0.0101 * t, 2.0 * t + 0.1])
    diffs = compare(test, ref)
    fig = charts.comparison_figure(test, ref, diffs, labels=("jacobi", "reference"),
                                   units={"mech.leg[1].s": "m", "motor1.i": "A"})
    axes = fig.axes
    titles = [a.get_title() for a in axes[0::2]]
    by_name = dict(zip(titles, range(len(titles))))
    i = by_name["mech.leg[1].s"]
    assert axes[2 * i].get_ylabel() == "[m]" and axes[2 * i + 1].get_ylabel() == "error [m]"
    assert len(axes[2 * i].lines) == 2  # co-simulation and reference on the same axes
    err = axes[2 * i + 1].lines[0].get_ydata()
    assert np.allclose(err, -0.0001 * t, atol=1e-15)
    j = by_name["motor1.i"]
    assert axes[2 * j + 1].get_ylabel() == "error [A]"


def test_cli_run_plot_writes_the_chart(tmp_path, cache):
    out = tmp_path / "run"
    assert main(["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=0.02", "--plot", "--out", str(out),
                 "--cache", str(cache)]) == 0
    assert (out / "pid_step.png").stat().st_size > 10_000


def test_traces_carry_units_for_compare(tmp_path, cache):
    from cosim.trace.traces import read_trace

    out = tmp_path / "run"
    assert main(["run", str(SCENES / "pid_step.yaml"), "--set", "stop_time=0.01", "--out", str(out),
                 "--cache", str(cache)]) == 0
    tr = read_trace(out / "pid_step.csv")
    assert tr.meta["units"]["mech.leg[1].s"] == "m" and tr.meta["units"]["motor2.i"] == "A"
    assert set(tr.meta["units"]) == set(tr.names)
