"""The trace text: the block CSV formatter writes exactly what Python's ``repr`` writes for every
float64 (the peer: ``",".join(map(repr, row))``), and every value reads back bit for bit."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosim.trace import text as tracetext


@pytest.fixture(autouse=True, params=["c", "python"])
def rewrite(request, monkeypatch):
    """Every test runs with the compiled rewrite of orjson's text and with the Python one."""
    if request.param == "python":
        monkeypatch.setattr(tracetext, "_c_rows", lambda: None)
    elif tracetext._c_rows() is None:
        pytest.fail("no compiled rewrite although the project's set-up provides gcc")
    return request.param


def _peer(a: np.ndarray) -> bytes:
    return "".join(",".join(repr(float(x)) for x in row) + "\n" for row in a).encode()


def _block(decade: int, seed: int) -> np.ndarray:
    """400 values near 10**decade: 1 to 17 significant digits, both signs."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(1.0, 10.0, 400)
    digits = rng.integers(1, 18, 400)
    m = np.array([round(x, int(d) - 1) for x, d in zip(m, digits)])
    with np.errstate(over="ignore", under="ignore"):
        x = m * 10.0 ** decade if decade > -300 else m * 1e-300 * 10.0 ** (decade + 300)
    x[::2] *= -1
    x = x[np.isfinite(x) & (x != 0)]  # the ends of the range overflow or underflow
    return x[:len(x) // 4 * 4].reshape(-1, 4)


@pytest.mark.parametrize("decade", list(range(-324, 309, 7)) + list(range(-12, 20)))
def test_block_text_is_repr(decade):
    a = _block(decade, seed=decade + 1000)
    text = tracetext.rows_text(a)
    assert text == _peer(a)
    back = np.array([[float(v) for v in ln.split(",")] for ln in text.decode().splitlines()])
    assert back.tobytes() == a.tobytes()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_mixed_block_is_repr(seed):
    """A trace-like block: most rows plain, a few with magnitudes below 1e-4 here and there."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((2000, 9))
    rows, cols = rng.integers(0, 2000, 60), rng.integers(0, 9, 60)
    a[rows, cols] *= 10.0 ** rng.integers(-12, -3, 60)
    a[:, 0] = np.arange(2000) * 1e-3
    assert tracetext.rows_text(a) == _peer(a)


SPECIAL = [0.0, -0.0, 1e-4, 9.999999999999999e-05, 1e-05, 0.00001234, 1.5e-06, 1e-10, 5e-324, -2.2250738585072014e-308,
           1e15, 1e16, 123456789012345678.0, 1.7976931348623157e308, 0.1, 0.30000000000000004, 100.0, 2.0 ** 60,
           1e22, -1e-100, 6.000000000000001e-05]


@pytest.mark.parametrize("value", SPECIAL)
def test_special_values(value):
    a = np.array([[value, -value, 1.0]])
    assert tracetext.rows_text(a) == _peer(a)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_blocks_are_repr(bad):
    a = np.array([[0.0, 1e-5], [bad, 2.5]])
    assert tracetext.rows_text(a) == _peer(a)


@pytest.mark.parametrize("shape", [(0, 3), (1, 1), (3, 1), (2, 7)])
def test_shapes(shape):
    a = np.arange(np.prod(shape), dtype=float).reshape(shape) * 1e-5
    assert tracetext.rows_text(a) == _peer(a)


def test_without_orjson_same_bytes(monkeypatch):
    a = _block(-6, seed=3)
    fast = tracetext.rows_text(a)
    monkeypatch.setattr(tracetext, "orjson", None)
    assert tracetext.rows_text(a) == fast == _peer(a)


def _default(o):
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o).__name__)


JSON_CASES = [
    {"scene": "pid_step", "stats": {"steps": 5000, "wall_s": 0.0821, "slaves": [{"name": "mech", "calls": 5000}]},
     "columns": ["time", "mech.platform.x"], "empty": {}, "none": None, "flag": True, "nested": [[1, 2], []]},
    {"path": Path("/tmp/x.csv"), "tuple": (1.5, 2.5), "small": 1e-05, "tiny": 1.234e-07, "big": 1e300},
    {"text": "é, ü and ∞", "int_keys": {1: "a", 2: "b"}},
    {"numpy": np.float64(0.1), "int": np.int64(3), "array": np.array([1.0, 2.5])},
    {"nan": math.nan, "inf": [math.inf, -math.inf], "ok": 1.0},
]


@pytest.mark.parametrize("obj", JSON_CASES, ids=["plain", "path_small", "unicode_keys", "numpy", "non_finite"])
def test_json_text_reads_back_like_json(obj):
    """The peer: Python's json module (values, and the layout of indent=2)."""
    import json

    fast = tracetext.json_text(obj, default=_default)
    ref = json.dumps(obj, indent=2, default=_default)
    assert json.dumps(json.loads(fast), sort_keys=True) == json.dumps(json.loads(ref), sort_keys=True)
    assert len(fast.splitlines()) == len(ref.splitlines())


def test_json_text_non_finite_is_json_module_text():
    import json

    obj = JSON_CASES[-1]
    assert tracetext.json_text(obj) == json.dumps(obj, indent=2)
