"""Event-synchronised coupling (FMI 3.0 event mode: a step ends at the event for the whole
coupling, event iteration, the other component rolled back to the event) against the
unsynchronised one (the ball's event mode not used: events stay inside its doStep and reach the other
component at the next communication point), at equal error, in one run.

Scene: the Reference FMU BouncingBall (FMI 3.0 co-simulation, event mode) drives a first-order lag
(tests/data/me_lag, model exchange, der(x) = -x + v) with its velocity, Jacobi, 1.2 s (two
bounces).  Error: the lag's state against the synchronised run at a 5e-5 s step, relative to its
range (one value per instant: the right limit where an event wrote two).  Each coupling is swept
over the communication step; the cheapest step within each target is listed.

    python3 benchmarks/bench_event_sync.py
"""
from __future__ import annotations

import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from conftest import REFERENCE_FMUS_SRC, _source_key, build_lag_fmus, build_reference_fmus  # noqa: E402

from cosim.master.simulate import simulate  # noqa: E402
from cosim.master.system import CoupledSystem, Link  # noqa: E402
from cosim.slaves import FmuSlave, describe_fmu  # noqa: E402
from cosim.trace.observer import Observer  # noqa: E402
from fmus.cache import cache_root  # noqa: E402

STOP = 1.2
STEPS = (1e-2, 5e-3, 2e-3, 1e-3, 5e-4)
REF_STEP = 5e-5


class _Rows(Observer):
    """The recorded rows of a run, kept in memory."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []

    def start(self, columns, meta) -> None:
        pass

    def record(self, rows) -> None:
        self.rows.append(np.array(rows, dtype=float))

    def finish(self, status, reason, stats) -> None:
        pass


def coupled(ball: Path, lag: Path, step: float, synchronised: bool):
    """(wall time [s] from instantiation to the end, time, the lag's state); unsynchronised: the
    ball's event mode not used (its events stay inside its doStep, as for an FMU without one)."""
    desc = dataclasses.replace(describe_fmu(ball), has_event_mode=synchronised)
    system = CoupledSystem([FmuSlave("ball", ball, desc), FmuSlave("lag", lag)], [Link(0, "v", 1, "u")], [(1, "x")])
    rows = _Rows()
    n = round(STOP / step)
    stats = simulate(system, "jacobi", step_ns=round(step * 1e9), n_steps=n, observers=[rows], engine="compiled",
                     start_values=[{}, {"k": 1.0}])
    assert stats.status == "ok", stats.reason
    data = np.concatenate(rows.rows)
    return stats.wall_s + stats.init_s, data[:, 0], data[:, 1]


def error(t: np.ndarray, x: np.ndarray, ref_t: np.ndarray, ref_x: np.ndarray) -> float:
    """Worst difference relative to the reference's range at the run's instants (one value per
    instant: the right limit where an event wrote two)."""
    keep = np.r_[np.diff(t) > 0, True]
    rt_keep = np.r_[np.diff(ref_t) > 0, True]
    return float(np.max(np.abs(x[keep] - np.interp(t[keep], ref_t[rt_keep], ref_x[rt_keep]))) / np.ptp(ref_x))


def main() -> None:
    fmus = build_reference_fmus(REFERENCE_FMUS_SRC, cache_root().parent / "reference-fmus" / _source_key(REFERENCE_FMUS_SRC))
    ball = fmus["3.0/BouncingBall"]
    with tempfile.TemporaryDirectory() as tmp:
        lag = build_lag_fmus(REFERENCE_FMUS_SRC, Path(tmp))["3"]
        t0 = time.perf_counter()
        _, ref_t, ref_x = coupled(ball, lag, REF_STEP, True)
        print(f"reference: synchronised at {REF_STEP:g} s ({time.perf_counter() - t0:.1f} s)")
        rows = []
        for sync in (True, False):
            for step in STEPS:
                wall, t, x = coupled(ball, lag, step, sync)
                rows.append(("synchronised (event mode)" if sync else "unsynchronised (events inside doStep)", step,
                             error(t, x, ref_t, ref_x), wall))
    print(f"BouncingBall (FMI 3.0 CS) -> lag (ME), Jacobi, {STOP:g} s; error of the lag's state relative to its "
          f"range; wall [s] from instantiation")
    print(f"{'coupling':<40} {'step s':>8} {'error':>9} {'wall s':>8}")
    for name, step, err, wall in rows:
        print(f"{name:<40} {step:>8g} {err:>9.2e} {wall:>8.3f}")
    for target in (1e-2, 1e-3):
        print(f"cheapest within {target:g} of range:")
        for name in dict.fromkeys(r[0] for r in rows):
            ok = [r for r in rows if r[0] == name and r[2] <= target]
            pick = min(ok, key=lambda r: r[3]) if ok else None
            print(f"  {name:<40} " + (f"step {pick[1]:g} s, {pick[3]:.3f} s" if pick else "none of the steps"))


if __name__ == "__main__":
    main()
