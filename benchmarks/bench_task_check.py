"""Motion-check benchmark: a 10 s motion checked at 1 kHz (10 001 samples) with root finding, as
``rpr-cosim task check`` and ``run --check`` do (:func:`models.motion_check.check_motion`: every
margin of the check over all samples at once, CasADi expressions replayed with numpy, then the
first crossing of each broken margin located to 1e-12 s by vectorised multisection).

Target: under 0.1 s.  Peer, measured in the same run: a plain Python loop evaluating the same
quantities at the same samples with the CasADi Functions called once per sample (det J and the
DSI, the leg kinematics, the inverse dynamics), without any root finding; its values are checked
against the vectorised check's margins.

Two motions: the pick and place of ``scenarios/tasks/pick_and_place.yaml`` repeated and slowed to
10 s (passes: no root to find), and a 10 s straight move across the cross-leg design's singular
line x = 0 (refused: the det J crossing, the |det J| margin and the DSI margins are located).

Usage: ``python3 benchmarks/bench_task_check.py [--repeat R]``
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from models import kinematics as K  # noqa: E402
from models.analysis import THESIS_LENGTH_SCALE  # noqa: E402
from models.geometry import preset  # noqa: E402
from models.motion_check import check_motion  # noqa: E402
from models.task import task_from  # noqa: E402
from models.virtual_work import inverse_dynamics_fn  # noqa: E402

PICK = [[-0.15, -0.15, 0.0], [-0.20, -0.12, 0.10], [-0.25, -0.15, 0.20], [-0.20, -0.20, 0.0]]


def motions():
    m = preset("cross_leg")
    pick = task_from({"waypoints": PICK * 3 + [PICK[0]], "limits": {"m_act": 0.058}})
    traj = pick.plan()
    pick_traj = traj.scaled(10.0 / traj.duration)
    cross = task_from({"waypoints": [[-0.1, -0.15, 0.0], [0.1, -0.15, 0.0]], "limits": {"m_act": 0.058}})
    traj = cross.plan()
    cross_traj = traj.scaled(10.0 / traj.duration)
    return m, [("pick and place x3 (passes)", pick, pick_traj), ("across x = 0 (refused)", cross, cross_traj)]


def python_loop(m, task, traj, t):
    """The same quantities, one CasADi call per sample and quantity."""
    g, e, inertia = m.geometry_vector(), [m.inertia.e1, m.inertia.e2], m.inertia.vector()
    dex, motion, dyn = K.dexterity_fn(THESIS_LENGTH_SCALE), K.leg_motion_fn(), inverse_dynamics_fn()
    drive = task.limits.drive
    worst = np.full(5, np.inf)  # smallest |det|, largest leg speed, acceleration, force, voltage margin
    dets = np.empty(len(t))
    for k, s in enumerate(t):
        q, qd, qdd = (a[:, 0] for a in traj.evaluate(np.array([s])))
        det, dsi, L = dex(q, g)
        mot = motion(q, qd, qdd, g, e)
        Ld, Ldd = np.array(mot[1]).ravel(), np.array(mot[2]).ravel()
        F = np.array(dyn(q, qd, qdd, g, inertia)).ravel() + task.limits.m_act * Ldd
        u = drive.alpha * F + drive.beta * Ld
        dets[k] = float(det)
        worst = np.minimum(worst, [abs(float(det)), task.limits.leg_speed - np.max(np.abs(Ld)),
                                   task.limits.leg_accel - np.max(np.abs(Ldd)), drive.F_max - np.max(np.abs(F)),
                                   task.limits.u_max - np.max(np.abs(u))])
    return dets, worst


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    m, cases = motions()
    print(f"motion check of a 10 s motion at 1 kHz (10 001 samples), best of {args.repeat}")
    print(f"{'motion':<28} {'check (s)':>10} {'roots':>6} {'python loop (s)':>16} {'ratio':>7}")
    for label, task, traj in cases:
        t0, t1 = float(traj.breaks[0]), float(traj.breaks[-1])
        res = check_motion(m, traj.evaluate, t0, t1, task.limits, task.margins)  # warm up
        best = np.inf
        for _ in range(args.repeat):
            start = time.perf_counter()
            res = check_motion(m, traj.evaluate, t0, t1, task.limits, task.margins)
            best = min(best, time.perf_counter() - start)
        start = time.perf_counter()
        dets, worst = python_loop(m, task, traj, res.t)
        loop = time.perf_counter() - start
        det_v = res.margins["det J = 0"] * res.det_sign
        assert np.allclose(dets, det_v, rtol=1e-9, atol=1e-12), "the loop disagrees"
        print(f"{label:<28} {best:>10.4f} {len(res.violations):>6} {loop:>16.3f} {loop / best:>6.0f}x")
        if res.refusal:
            print(f"  {res.refusal.line()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
