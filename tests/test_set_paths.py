"""One vocabulary across verbs: ``run --set`` takes the paths a batch axis takes, wildcards over
component names included, and resolves them to the same scene."""
from __future__ import annotations

from pathlib import Path

import pytest

from cosim.batch import load_batch, plan
from cosim.cli import main
from cosim.scenario import load

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenarios" / "pid_step.yaml"


def test_a_wildcard_set_equals_the_explicit_sets_of_every_match():
    wild = load(SCENE, ["components.pid*.params.Kp=40", "components.motor[12].params.R=0.6"])
    explicit = load(SCENE, [f"components.pid{i}.params.Kp=40" for i in (1, 2, 3)]
                    + ["components.motor1.params.R=0.6", "components.motor2.params.R=0.6"])
    assert wild.hash == explicit.hash != load(SCENE).hash
    assert [wild.components[f"pid{i}"].params["Kp"] for i in (1, 2, 3)] == [40, 40, 40]
    assert "R" not in load(SCENE, ["components.motor[12].params.R=0.6"]).components["motor3"].params


def test_set_and_a_batch_axis_resolve_the_same_path_to_the_same_scene(tmp_path):
    batch = tmp_path / "b.yaml"
    batch.write_text(f"name: b\nscene: {SCENE}\nset: {{stop_time: 0.5}}\n"
                     "grid:\n  Kp: {path: \"components.pid*.params.Kp\", values: [40, 55]}\n")
    runs, _ = plan(load_batch(batch))
    for r, kp in zip(runs, (40, 55)):
        assert r.scene.hash == load(SCENE, ["stop_time=0.5", f"components.pid*.params.Kp={kp}"]).hash


def test_a_wildcard_matching_nothing_is_one_line(capsys):
    assert main(["run", str(SCENE), "--set", "components.pod*.params.Kp=40", "--check"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'pod*' in 'components.pod*.params.Kp' matches no component" in err[0]
