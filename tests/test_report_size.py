"""Issue 32, item 10, on the issue's own case: pid_step's whole 5 s run with its monolithic
reference, reported (``run --reference --report``), is under 2 MB (it was 8-13 MB), and the page
still holds every recorded row: decoded as the page's script decodes it, each signal equals the
run's CSV (an independent reader of the same run) to the float32 precision the page promises
(range / 1.7e7), the time column exactly."""
from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np

from cosim.cli import main
from cosim.trace.traces import read_trace

SCENE = Path(__file__).resolve().parents[1] / "scenarios" / "pid_step.yaml"


def _page_data(html: str) -> dict:
    found = re.search(r"var D = (\{.*?\}), gd = document\.getElementById\('signals'\)", html, re.S)
    assert found, "the report's full-resolution data is missing"
    return json.loads(found.group(1))


def _decode(s: str, dtype: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(s), dtype=dtype).astype(float)


def test_pid_steps_report_is_under_2_mb_with_every_row(tmp_path):
    assert main(["run", str(SCENE), "--reference", "--report", "--out", str(tmp_path)]) == 0
    page = tmp_path / "pid_step.html"
    assert page.stat().st_size < 2e6, page.stat().st_size
    csv = read_trace(tmp_path / "pid_step.csv")
    assert len(csv.time) == 5001
    data = _page_data(page.read_text())
    assert np.array_equal(_decode(data["t"], "<f8"), csv.time)
    assert sorted(data["names"]) == sorted(csv.names)
    for k, name in enumerate(data["names"]):
        y = _decode(data["v"][k], "<f4") + data["mid"][k]
        span = max(np.ptp(csv[name]), 1e-300)
        assert np.max(np.abs(y - csv[name])) <= span / 1.6e7, name
    assert set(data["err"]) == set(csv.names)  # the error against the reference, every signal
