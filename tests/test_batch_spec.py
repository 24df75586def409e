"""Batch files: malformed ones fail before any run with one line naming the file and line; axes
expand as documented; random samples are reproducible from the seed alone."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosim.batch import BatchError, load_batch
from cosim.batch.axes import draw, expand
from cosim.cli import main

SCENE = Path(__file__).resolve().parents[1] / "scenarios" / "pid_step.yaml"

GOOD = f"""\
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, stop_time: 0.2}}
grid:
  Kp: {{path: "components.pid*.params.Kp", values: [20, 30]}}
  components.pid1.params.Kd: {{from: 10, to: 40, num: 3, scale: log}}
zip:
  master.step: [1.0e-3, 5.0e-4]
  master.output_interval: [1.0e-3, 1.0e-3]
metrics:
  mech.platform.phi: {{target: 0.2, measure: [overshoot, {{at: [0.1]}}]}}
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "b.yaml"
    p.write_text(text)
    return p


def test_axes_expand_as_documented(tmp_path):
    batch = load_batch(write(tmp_path, GOOD))
    points = expand(batch)
    assert batch.n_runs == len(points) == 2 * 3 * 2
    assert batch.grid[0].paths == tuple(f"components.pid{i}.params.Kp" for i in (1, 2, 3))
    assert batch.grid[1].values == pytest.approx((10.0, 20.0, 40.0))  # geometric 10..40 in 3
    p = points[5]  # Kp=20, Kd=40, second zip item
    assert p.values == {"Kp": 20, "components.pid1.params.Kd": pytest.approx(40.0), "master.step": 5e-4,
                        "master.output_interval": 1e-3}
    assert p.overrides["components.pid3.params.Kp"] == 20 and p.overrides["stop_time"] == 0.2
    assert batch.metric_columns == ["mech.platform.phi:overshoot", "mech.platform.phi:at(0.1)"]


def random_batch(seed, n) -> str:
    return f"""\
scene: {SCENE}
set: {{master.algorithm: gauss_seidel, stop_time: 0.2}}
random:
  seed: {seed}
  samples: {n}
  axes:
    m_p: {{path: components.mech.params.m_p, dist: normal, mean: 1.7, std: 0.17}}
    b: {{path: "components.motor*.params.b", dist: log_uniform, low: 4.0e-5, high: 2.0e-4}}
    R: {{path: components.motor1.params.R, dist: uniform, low: 0.5, high: 0.65}}
"""


def test_samples_come_from_the_seed_and_the_sample_number_alone(tmp_path):
    """Sample j is numpy's generator seeded by SeedSequence(seed, spawn_key=(j, axis key)):
    the same in a batch of 4 or 9 samples, different for another seed."""
    b4 = load_batch(write(tmp_path, random_batch(7, 4)))
    v4 = [p.values for p in expand(b4)]
    v9 = [p.values for p in expand(load_batch(write(tmp_path, random_batch(7, 9))))]
    other = [p.values for p in expand(load_batch(write(tmp_path, random_batch(8, 4))))]
    assert v9[:4] == v4 and other != v4
    ax = {a.name: a for a in b4.random}
    for j, v in enumerate(v4):
        rng = np.random.default_rng(np.random.SeedSequence(7, spawn_key=(j, ax["R"].key())))
        assert v["R"] == rng.uniform(0.5, 0.65)
        rng = np.random.default_rng(np.random.SeedSequence(7, spawn_key=(j, ax["b"].key())))
        assert v["b"] == math.exp(rng.uniform(math.log(4e-5), math.log(2e-4)))
        assert 4e-5 <= v["b"] <= 2e-4 and draw(ax["m_p"], 7, j) == v["m_p"]


def test_normal_samples_have_the_stated_moments(tmp_path):
    b = load_batch(write(tmp_path, random_batch(1, 2)))
    m = np.array([draw(b.random[0], 1, j) for j in range(4000)])
    assert abs(m.mean() - 1.7) < 4 * 0.17 / math.sqrt(4000) and abs(m.std() - 0.17) < 0.01


BAD = {
    "unknown parameter": ("grid:\n  components.pid1.params.Kq: [1, 2]\n", 3, "no parameter 'Kq'; did you mean 'Kp'?"),
    "unknown component": ("grid:\n  components.pdi1.params.Kp: [1, 2]\n", 3, "unknown component 'pdi1'"),
    "glob matching nothing": ("grid:\n  components.pd*.params.Kp: [1, 2]\n", 3, "matches no component"),
    "misspelt master key": ("grid:\n  master.stepp: [1.0e-3]\n", 3, "did you mean 'step'?"),
    "misspelt top key": ("gird:\n  master.step: [1.0e-3]\n", 2, "did you mean 'grid'?"),
    "bad value": ("grid:\n  master.step:\n    - 1.0e-3\n    - -1.0\n", 5, "must be positive"),
    "empty axis": ("grid:\n  Kp: {path: components.pid1.params.Kp, values: []}\n", 3, "is empty"),
    "empty range": ("grid:\n  master.step: {from: 1, to: 2, num: 0}\n", 3, "is empty"),
    "zip lengths differ": ("zip:\n  master.step: [1.0e-3, 5.0e-4]\n  master.output_interval: [1.0e-3]\n", 2,
                           "equal lengths: 'master.step' has 2 (line 3), 'master.output_interval' has 1 (line 4)"),
    "uniform low above high": ("random:\n  seed: 1\n  samples: 3\n  axes:\n    R: {path: components.motor1.params.R, "
                               "dist: uniform, low: 2, high: 1}\n", 6, "needs low < high"),
    "log-uniform from zero": ("random:\n  seed: 1\n  samples: 3\n  axes:\n    b: {path: components.motor1.params.b, "
                              "dist: log_uniform, low: 0, high: 1}\n", 6, "needs low > 0"),
    "normal without spread": ("random:\n  seed: 1\n  samples: 3\n  axes:\n    m: {path: components.mech.params.m_p, "
                              "dist: normal, mean: 1, std: 0}\n", 6, "std = 0 must be positive"),
    "unknown distribution": ("random:\n  seed: 1\n  samples: 3\n  axes:\n    m: {path: components.mech.params.m_p, "
                             "dist: gaussian, mean: 1, std: 1}\n", 6, "unknown distribution 'gaussian'"),
    "fractional seed": ("random:\n  seed: 1.5\n  samples: 3\n  axes:\n    m: {path: components.mech.params.m_p, "
                        "dist: normal, mean: 1, std: 0.1}\n", 3, "random.seed = 1.5 must be a whole number"),
    "word seed": ("random:\n  seed: abc\n  samples: 3\n  axes:\n    m: {path: components.mech.params.m_p, "
                  "dist: normal, mean: 1, std: 0.1}\n", 3, "random.seed = 'abc' must be a whole number"),
    "misspelt measure": ("grid:\n  master.step: [1.0e-3]\nmetrics:\n  mech.platform.phi: {target: 0.2, measure: "
                         "[overshot]}\n", 5, "did you mean 'overshoot'?"),
    "unrecorded signal": ("grid:\n  master.step: [1.0e-3]\nmetrics:\n  mech.platform.phy: [max]\n", 5,
                          "did you mean 'mech.platform.phi'?"),
    "error measure without target": ("grid:\n  master.step: [1.0e-3]\nmetrics:\n  mech.platform.phi: [end_error]\n",
                                     5, "end_error needs a target"),
}


@pytest.mark.parametrize("body, line, phrase", BAD.values(), ids=BAD.keys())
def test_malformed_batch_fails_with_one_line(tmp_path, body, line, phrase):
    path = write(tmp_path, f"scene: {SCENE}\n{body}")
    with pytest.raises(BatchError) as err:
        load_batch(path)
    errors = [p for p in err.value.problems if p.severity == "error"]
    assert len(errors) == 1, [str(p) for p in errors]
    text = str(err.value)
    assert "\n" not in text and phrase in text
    assert errors[0].line == line and errors[0].file.endswith("b.yaml")


def test_cli_refuses_a_malformed_batch_before_any_run(tmp_path, capsys):
    path = write(tmp_path, f"scene: {SCENE}\ngrid:\n  components.pid1.params.Kq: [1, 2]\n")
    out = tmp_path / "out"
    assert main(["batch", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "b.yaml:3: error:" in err[0] and "nothing was run" in err[1]
    assert not out.exists()
