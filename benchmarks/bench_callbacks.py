"""The cost of a callback slave (cosim/master/callbacks.py): a Python slave stepped by the compiled
fixed-step loop through ctypes trampolines, against the same slave in the Python loop.

A ring of N exact linear slaves (:class:`cosim.slaves.linear.LinearSlave`, one state each, no
feedthrough), Jacobi and Gauss-Seidel, the same steps in both engines (their traces are
bit-identical, tests/test_general_kernel.py).  Printed: wall time per macro step per slave [us]
of the stepping loop (best of ``--repeat``), and the ratio.

    python3 benchmarks/bench_callbacks.py [--slaves 4] [--steps 20000] [--repeat 3]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from cosim.master import CoupledSystem, Link, simulate  # noqa: E402
from cosim.slaves.linear import LinearSlave  # noqa: E402
import oracles  # noqa: E402 - the Python twins of the kernels (tests/oracles), as engine 'oracle'

oracles.register()


def ring(n: int) -> CoupledSystem:
    slaves = [LinearSlave(f"s{i}", [[-1.0]], [[1.0]], [[1.0]], x0=[float(i)]) for i in range(n)]
    return CoupledSystem(slaves, [Link(i, "y[1]", (i + 1) % n, "u[1]") for i in range(n)], [(0, "y[1]")])


def per_step_us(alg: str, engine: str, n: int, steps: int, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        system = ring(n)
        t0 = time.perf_counter()
        stats = simulate(system, alg, step_ns=1_000_000, n_steps=steps, engine=engine, record_every=steps)
        best = min(best, time.perf_counter() - t0)
        assert stats.engine == engine and stats.status == "ok", stats.reason
    return best / steps / n * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--slaves", type=int, default=4)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    print(f"ring of {a.slaves} Python LinearSlaves, {a.steps} steps, best of {a.repeat}; "
          f"wall time per macro step per slave [us] (initialisation included)")
    for alg in ("jacobi", "gauss_seidel"):
        py = per_step_us(alg, "oracle", a.slaves, a.steps, a.repeat)
        cc = per_step_us(alg, "compiled", a.slaves, a.steps, a.repeat)
        print(f"  {alg:13s} Python loop {py:8.2f}   compiled loop, callback slaves {cc:8.2f}   ratio {py / cc:5.2f}")


if __name__ == "__main__":
    main()
