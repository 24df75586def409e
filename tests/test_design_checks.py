"""Chapter 8's design checks (models.mechanical_design, ``rpr-cosim design``) against the numbers
the thesis prints (Section 8.1.2, Eq. 8.1-8.5, Table 8.1, Section 8.1.5; SPEC §8), each to the
digits printed, and the verb's exit status on a load that breaks a margin."""
from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from cosim import cli
from models import mechanical_design as D

#: (value, decimals printed) as the thesis prints them.
PRINTED = {"F1": (504.92, 2), "F2": (404.92, 2), "M_max": (26.32, 2), "M_e": (26.36, 2), "d_min_mm": (10.9, 1),
           "clamp": (166.67, 2)}


def test_the_thesis_numbers_from_its_inputs():
    c = D.check_shaft()  # the thesis's inputs: 100 N at 63 + 92.5 mm, 17.27 N m, 65 mm, 2 N m, 210 MPa
    got = {"F1": c.F1, "F2": c.F2, "M_max": c.M_max, "M_e": c.M_e, "d_min_mm": c.d_min * 1e3, "clamp": c.clamp}
    for key, (value, digits) in PRINTED.items():
        assert round(got[key], digits) == value, (key, got[key])
    # Eq. 8.4 from limits that give the printed 210 MPa (either bound can be the active one)
    assert D.permissible_stress(350e6, 700e6) == pytest.approx(210e6)
    assert D.permissible_stress(400e6, 583.33e6) == pytest.approx(0.36 * 583.33e6)
    # Table 8.1's two moments are the weight line's ends; the chosen 15 mm shaft: 38 % over 10.85 mm
    assert D.weight_moment(0.1, 0.1, 0.6) == 17.27 and D.weight_moment(0.6, 0.1, 0.6) == 5.24
    assert c.diameter_margin == pytest.approx(15 / 10.853 - 1, rel=1e-3)


def test_equations_by_hand():
    """Eq. 8.1-8.3 written out for another load: moments about each bearing balance."""
    loads = D.ShaftLoads(F_h=40.0, M_w=9.0, T=1.0)
    f1, f2 = D.bearing_forces(loads)
    geo = D.ShaftGeometry()
    # statics of the shaft: forces F1 - F2 = F_h, moments about the load point
    assert f1 - f2 == pytest.approx(40.0)
    assert f2 * (geo.a + geo.b) - f1 * (geo.a + geo.b - geo.s) == pytest.approx(9.0)
    m = D.largest_bending_moment(loads)
    assert D.equivalent_moment(m, 1.0) == pytest.approx(0.5 * (m + math.sqrt(m * m + 1.0)))
    d = D.minimum_diameter(D.equivalent_moment(m, 1.0), 210e6)
    assert D.bending_stress(D.equivalent_moment(m, 1.0), d) == pytest.approx(210e6)


def test_design_verb_prints_the_table_and_exits_zero(tmp_path, capsys):
    rc = cli.main(["design", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    assert "504.92" in out and "404.92" in out and "26.32" in out and "166.67" in out
    rows = {r["quantity"]: r for r in csv.DictReader(open(tmp_path / "design.csv"))}
    assert float(rows["minimum diameter d (Eq. 8.5)"]["thesis_inputs"]) == pytest.approx(10.853, abs=5e-4)


def test_a_trace_that_breaks_the_shaft_exits_nonzero(tmp_path, capsys):
    """A recorded leg force of 800 N (an end-stop impact) needs more than the 15 mm shaft."""
    t = np.linspace(0, 1, 11)
    path = tmp_path / "impact.csv"
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time"] + [f"mech.leg[{i}].{k}" for i in (1, 2, 3) for k in ("f", "s")])
        for k, s in enumerate(t):
            f = 800.0 if k == 5 else 1.0
            w.writerow([s] + [v for i in (1, 2, 3) for v in (f, 0.3)])
    rc = cli.main(["design", "--trace", str(path), "--out", str(tmp_path / "out"), "--plot"])
    out = capsys.readouterr().out
    assert rc == 1
    assert "negative margin: trace impact: margin: diameter" in out
    # by hand: F_h = 800 N, M_w at L = 0.3 m on the Table 8.1 line
    m_w = 17.27 + (5.24 - 17.27) * (0.3 - 0.1) / 0.5
    m = 800.0 * (0.063 + 0.0925 - 0.065) + m_w
    d = (32 * 0.5 * (m + math.hypot(m, 2.0)) / (math.pi * 210e6)) ** (1 / 3)
    rows = {r["quantity"]: r for r in csv.DictReader(open(tmp_path / "out" / "design.csv"))}
    assert float(rows["minimum diameter d (Eq. 8.5)"]["trace_impact"]) == pytest.approx(d * 1e3, rel=1e-12)
    assert (tmp_path / "out" / "trace_impact_loads.png").stat().st_size > 1000


def test_a_task_column(tmp_path, capsys):
    task = tmp_path / "move.yaml"
    task.write_text("waypoints: [[-0.15, -0.15, 0.0], [-0.2, -0.15, 0.2]]\nlimits: {m_act: 0.058}\n")
    rc = cli.main(["design", "--task", str(task), "--out", str(tmp_path / "o")])
    out = capsys.readouterr().out
    assert rc == 0 and "task move" in out


def test_bad_input_is_one_line(tmp_path, capsys):
    rc = cli.main(["design", "--drive", "nope", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and "--drive 'nope'" in err and len(err.strip().splitlines()) == 1
