"""Units on every connection, Modelica-style (issue 32, item 4): incompatible units refused at
``run --check`` with file:line and both units; units the FMU exporter cannot read refused at the
check, not at the build; every unit of the catalog readable by the exporter.  The dimensions are
checked against SI's definitions (N = kg.m/s2, V = kg.m2/(s3.A)), written out here."""
from __future__ import annotations

import textwrap
from fractions import Fraction
from pathlib import Path

import pytest

from cosim.cli import main
from fmus.names import check_names, parse_unit
from models import blocks
from models.block import BlockError
from models.units import compose, scaled

DAMPER = '''\
from models.user import BlockBuilder


def damper():
    b = BlockBuilder("damper", "mass with viscous friction driven by a force")
    m = b.param("m", 2.0, "kg", "mass", lower=0.0)
    c = b.param("c", 0.5, "N.s/m", "viscous friction coefficient", lower=0.0)
    f = b.input("f", "N", "applied force")
    v = b.state("v", 0.0, "m/s", "velocity")
    b.der(v, (f - c * v) / m)
    b.output("v_out", v, "m/s", "velocity")
    return b.build()


BLOCKS = {"damper": damper}
'''


def _scene(tmp_path: Path, connections: list[str], push: str = "{model: pid}") -> Path:
    (tmp_path / "damper_block.py").write_text(DAMPER)
    lines = "\n".join(f"  - {c}" for c in connections)
    path = tmp_path / "push.yaml"
    path.write_text(textwrap.dedent("""\
        name: push
        stop_time: 0.1
        blocks: [damper_block.py]
        components:
          d: {model: damper}
          push: %s
        connections:
        %s
        master: {algorithm: gauss_seidel, step: 1e-3}
        """) % (push, lines))
    return path


def _check(path: Path, capsys) -> tuple[int, str]:
    code = main(["run", str(path), "--check"])
    return code, capsys.readouterr().err


def test_the_issues_connections_are_refused_with_file_line_and_both_units(tmp_path, capsys):
    path = _scene(tmp_path, ["d.v_out -> push.measurement", "push.y -> d.f"])
    code, err = _check(path, capsys)
    assert code == 2
    assert (f"{path}:8: error: incompatible units: d.v_out [m/s] -> push.measurement [m] (m.s-1 is not m)"
            in err), err
    assert f"{path}:9: error: incompatible units: push.y [V] -> d.f [N] (kg.m2.s-3.A-1 is not kg.m.s-2)" in err


def test_matching_units_pass_and_a_factor_converts(tmp_path, capsys):
    path = _scene(tmp_path, ["d.v_out -> push.measurement", "push.y -> d.f * 2.0"],
                  push="{model: pid, options: {unit_in: m/s, unit_out: N}}")
    code, err = _check(path, capsys)
    assert code == 0, err


def test_a_scale_difference_names_the_factor(tmp_path, capsys):
    path = _scene(tmp_path, ["d.v_out -> push.measurement", "push.y -> d.f"],
                  push="{model: pid, options: {unit_in: mm/s, unit_out: N}}")
    code, err = _check(path, capsys)
    assert code == 2 and f"{path}:8: error: units differ in scale: d.v_out [m/s] -> push.measurement [mm/s]" in err
    assert "write 'd.v_out -> push.measurement * 1000'" in err


def test_a_unit_the_exporter_cannot_read_is_refused_at_the_check(tmp_path, capsys):
    path = _scene(tmp_path, ["d.v_out -> push.measurement"], push="{model: pid, options: {unit_in: furlong}}")
    code, err = _check(path, capsys)
    assert code == 2 and f"{path}:6: error: component 'push': block pid: parameter 'Kp' has unit" in err
    assert "exporter cannot read (unknown unit symbol 'furlong')" in err


def test_the_pid_gains_of_a_velocity_loop_are_readable_units():
    """The issue's PID with ``unit_in: m/s`` (its gain units were 'N/m/s', which the exporter refused)."""
    blk = blocks.make("pid", "continuous", unit_in="m/s", unit_out="N")
    check_names(blk)
    units = {p.name: p.unit for p in blk.params}
    assert units["Kp"] == "N.s/m" and units["Ki"] == "N/m" and units["Kd"] == "N.s2/m"
    # SI: N = kg.m/s2, so N.s/m = kg/s, N/m = kg/s2, N.s2/m = kg
    assert parse_unit(units["Kp"]) == (1.0, {"kg": 1, "s": -1})
    assert parse_unit(units["Ki"]) == (1.0, {"kg": 1, "s": -2})
    assert parse_unit(units["Kd"]) == (1.0, {"kg": 1})


def test_compose_and_scaled_follow_si():
    assert compose(("V", 1), ("m", -1), ("s", -1)) == "V/(m.s)" and compose(("m/s", 1), ("s", 1)) == "m"
    f, dims = scaled("km/h")
    assert f == pytest.approx(1000 / 3600) and dims[1:3] == (Fraction(1), Fraction(-1))
    assert scaled("furlong") is None and scaled("") is None


def test_every_unit_of_the_catalog_is_readable_by_the_exporter():
    """Every model and fidelity, and each choice of each option that has choices."""
    seen = 0
    for model, fids in blocks.catalog().items():
        for fid in fids:
            variants = [{}] + [{o.name: c} for o in blocks.options(model, fid).values() for c in (o.choices or ())]
            for opts in variants:
                try:
                    blk = blocks.make(model, fid, **opts)
                except BlockError as exc:  # a choice that needs other options too (task_trajectory's spline)
                    assert "give" in str(exc) or "needs" in str(exc), exc
                    continue
                check_names(blk)  # BuildError naming the variable otherwise
                for v in [*blk.params, *blk.inputs, *blk.outputs, *blk.states]:
                    if v.unit:
                        parse_unit(v.unit)
                        seen += 1
    assert seen > 200


def test_a_sum_carries_the_unit_of_what_it_sums(capsys):
    """pick_and_place adds a PID's volts and the feedforward's volts in a ``sum`` block, whose
    declared "1" is no dimension (Modelica's Add declares none): not refused."""
    scene = Path(__file__).resolve().parents[1] / "scenarios" / "pick_and_place.yaml"
    code = main(["run", str(scene), "--check"])
    assert code == 0, capsys.readouterr().err
