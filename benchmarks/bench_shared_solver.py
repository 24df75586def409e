"""One CVODES per model-exchange FMU (ours) against one CVODES shared by the pair (OMSimulator's
way: the monolithic ODE of the coupled pair), on a loop of two lags, at equal solver tolerance:
error against the exact solution (``expm``), right-hand-side evaluations of the FMUs, wall time.

Pair (tests/data/me_lag, model exchange, FMI 3.0): a: der(x) = -k_a x - u, b: der(x) = -k_b x + u,
a.x -> b.u, b.x -> a.u, x(0) = (1, 0), 2 s.  Two cases: mild (k = 1, 2) and stiff-coupled
(k = 1, 1000: b is a fast lag that follows a).  The shared solver is CVODES (CasADi's, BDF) on the
pair's ODE ``x' = A x`` at the same rtol; each of its right-hand sides would evaluate both FMUs.
Ours: each FMU its own CVODES, coupled by the master (gauss_seidel at a fixed step, iterative and
adaptive, which roll back).

    python3 benchmarks/bench_shared_solver.py
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from conftest import REFERENCE_FMUS_SRC, build_lag_fmus  # noqa: E402

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import from_dict  # noqa: E402

STOP, GRID, RTOL = 2.0, 0.01, 1e-6
CASES = {"mild (k = 1, 2)": (1.0, 2.0), "stiff (k = 1, 1000)": (1.0, 1000.0)}


def matrix(ka: float, kb: float) -> np.ndarray:
    return np.array([[-ka, -1.0], [1.0, -kb]])


def exact(A: np.ndarray, t: np.ndarray) -> np.ndarray:
    from scipy.linalg import expm

    return np.array([expm(A * ti) @ [1.0, 0.0] for ti in t])


def error(t: np.ndarray, xa: np.ndarray, xb: np.ndarray, A: np.ndarray) -> float:
    ref = exact(A, t)
    return max(float(np.max(np.abs(xa - ref[:, 0])) / np.ptp(ref[:, 0])),
               float(np.max(np.abs(xb - ref[:, 1])) / np.ptp(ref[:, 1])))


def shared(A: np.ndarray) -> tuple[float, float, int, int]:
    """(wall s, error, FMU right-hand sides (two per solver rhs), solver steps) of one CVODES."""
    import casadi as ca

    x = ca.SX.sym("x", 2)
    grid = np.arange(0.0, STOP + GRID / 2, GRID)
    F = ca.integrator("pair", "cvodes", {"x": x, "ode": ca.mtimes(ca.DM(A), x)}, 0.0, grid[1:],
                      {"abstol": RTOL, "reltol": RTOL})
    t0 = time.perf_counter()
    out = F(x0=[1.0, 0.0])
    wall = time.perf_counter() - t0
    xs = np.hstack([[[1.0], [0.0]], np.array(out["xf"])])
    st = F.stats()
    return wall, error(grid, xs[0], xs[1], A), 2 * int(st.get("nfevals", 0)), int(st.get("nsteps", 0))


def per_fmu(fmu: Path, A: np.ndarray, ka: float, kb: float, master: dict) -> tuple[float, float, int, int, str]:
    """(wall s, error, FMU right-hand sides, solver steps, status) of our run with one CVODES per FMU."""
    scene = from_dict({"name": "pair", "stop_time": STOP, "outputs": ["a.x", "b.x"],
                       "components": {"a": {"fmu": str(fmu), "params": {"k": ka, "g": -1.0}, "start": {"x": 1.0},
                                            "rtol": RTOL},
                                      "b": {"fmu": str(fmu), "params": {"k": kb, "g": 1.0}, "rtol": RTOL}},
                       "connections": ["a.x -> b.u", "b.x -> a.u"],
                       "master": {**master, "output_interval": GRID, "estimate": False}})
    t0 = time.perf_counter()
    res = run(scene)
    wall = time.perf_counter() - t0
    me = res.stats.get("model_exchange", {})
    rhs = sum(v.get("rhs_evaluations", 0) for v in me.values())
    steps = sum(v.get("solver_steps", 0) for v in me.values())
    tr = res.trace
    keep = np.r_[np.diff(tr.time) > 0, True]
    err = error(tr.time[keep], tr["a.x"][keep], tr["b.x"][keep], A) if res.status == "ok" else float("nan")
    return wall, err, rhs, steps, res.status


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        fmu = build_lag_fmus(REFERENCE_FMUS_SRC, Path(tmp))["3"]
        print(f"loop of two model-exchange lags, {STOP:g} s, rtol {RTOL:g} in every solver; error against expm, "
              f"relative to range; rhs: FMU right-hand-side evaluations")
        print(f"{'case':<20} {'solver(s)':<44} {'error':>9} {'rhs':>8} {'steps':>7} {'wall s':>8}")
        for case, (ka, kb) in CASES.items():
            A = matrix(ka, kb)
            w, e, r, s = shared(A)
            print(f"{case:<20} {'one shared CVODES (monolithic pair)':<44} {e:>9.2e} {r:>8d} {s:>7d} {w:>8.4f}")
            for label, master in (("per FMU, gauss_seidel 1e-2 s", {"algorithm": "gauss_seidel", "step": 1e-2}),
                                  ("per FMU, gauss_seidel 1e-3 s", {"algorithm": "gauss_seidel", "step": 1e-3}),
                                  ("per FMU, gauss_seidel 1e-4 s", {"algorithm": "gauss_seidel", "step": 1e-4}),
                                  ("per FMU, iterative 1e-2 s", {"algorithm": "iterative", "step": 1e-2}),
                                  ("per FMU, adaptive (rtol 1e-6)", {"algorithm": "adaptive", "step": 1e-2,
                                                                     "options": {"rtol": 1e-6}})):
                w, e, r, s, status = per_fmu(fmu, A, ka, kb, master)
                tail = "" if status == "ok" else f"  ({status})"
                print(f"{case:<20} {label:<44} {e:>9.2e} {r:>8d} {s:>7d} {w:>8.4f}{tail}")


if __name__ == "__main__":
    main()
