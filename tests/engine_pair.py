"""A scene run on both engines of one algorithm (the Python loop, the compiled kernel), and the
bit-for-bit comparison the event-kernel tests share."""
from __future__ import annotations

import numpy as np

from cosim.run.execute import run
from cosim.scenario import from_dict


def both(scene: dict, **master) -> tuple:
    """The scene's run on the Python loop and on the kernel (``engine: compiled``)."""
    out = []
    for engine in ("oracle", "compiled"):
        res = run(from_dict({**scene, "master": {"step": 0.01, "estimate": False, **master, "engine": engine}}))
        assert res.stats["engine"] == engine
        out.append(res)
    return tuple(out)


def assert_same(py, cc) -> None:
    """Status, reason, times, values (NaN equal), events and each slave's doStep count equal."""
    assert (py.status, py.reason) == (cc.status, cc.reason)
    assert np.array_equal(py.trace.time, cc.trace.time)
    assert np.array_equal(py.trace.data, cc.trace.data, equal_nan=True)
    assert py.stats.get("events") == cc.stats.get("events")
    calls = lambda r: {k: x["do_step_calls"] for k, x in r.stats["slaves"].items()}  # noqa: E731
    assert calls(py) == calls(cc)
