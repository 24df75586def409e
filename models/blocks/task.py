"""A planned task as a trajectory source: the pose, its rates and accelerations, the leg setpoints
and the inverse-dynamics feedforward (construction options: a task, :mod:`models.task`).

The task is planned when the block is built (:func:`models.task.Task.plan`) and its segments
(:class:`models.trajectory.PiecewiseCubic`) become the block's structural data: on the segment
holding the clock, ``q = P + V tau + A tau^2/2 + J tau^3/6`` with the segment's coefficients
chosen exactly (:func:`piecewise_cubic`), so the FMU evaluates the planned polynomial itself, to
round-off, in C as in numpy; after the last segment the end pose at rest.  A new plan is a new FMU (the cache keys it by content).

Outputs as :func:`models.blocks.setpoint.pose_setpoint` (``platform.*``, ``leg[i].s``, ``.v``,
``.a``), plus per leg the feedforward force ``leg[i].f_ff`` [N] (virtual-work inverse dynamics of
the planned motion plus ``m_act`` times the leg acceleration) and the feedforward voltage
``leg[i].u_ff`` [V] of the drive's line ``alpha f_ff + beta v`` (:class:`models.trajectory.Drive`).
The clock is a state ``clock.t`` starting at ``t0`` (the scene's start time).
"""
from __future__ import annotations

import json
from functools import lru_cache

import casadi as ca
import numpy as np

from ..block import Block, BlockError, Var
from ..kinematics import leg_motion
from ..task import task_from
from ..trajectory import PiecewiseCubic, TrajectoryError
from ..virtual_work import inverse_dynamics_fn
from ._common import ParamSet, geometry_params, inertia_params, stroke_ratings

LEGS = (1, 2, 3)


def piecewise_cubic(traj: PiecewiseCubic, t: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX]:
    """Pose, rate and acceleration (3-vectors) of ``traj`` at the symbolic time ``t``.

    The segment holding ``t`` is picked by indicators ``ind_k = (t >= t_k)(t < t_k+1)`` (1 on
    segment k, 0 elsewhere), and each coefficient is ``sum_k ind_k c_k``: an exact selection, since
    every other term is a product with 0."""
    table = traj.table()
    hold = np.concatenate([[traj.breaks[-1]], traj.end, np.zeros(9)])
    table = np.vstack([table, hold])  # after the end: the end pose at rest
    starts = [float(b) for b in table[1:, 0]]
    ind = ca.vertcat(*([t < starts[0]] + [(t >= a) * (t < b) for a, b in zip(starts[:-1], starts[1:])]
                       + [t >= starts[-1]]))
    coef = ca.mtimes(ca.DM(table).T, ind)  # (13, 1): start time, P, V, A, J of the segment holding t
    tau = ca.fmax(t - coef[0], 0.0)
    P, V, A, J = (coef[1 + 3 * g:4 + 3 * g] for g in range(4))
    q = P + tau * (V + tau * (A / 2 + tau * J / 6))
    qd = V + tau * (A + tau * J / 2)
    qdd = A + tau * J
    return q, qd, qdd


@lru_cache(maxsize=32)
def _planned(spec: str):
    """The task and its motion for a task mapping (as JSON: a scene's loading and its checks build
    the same block several times, and a toppra plan takes a fraction of a second)."""
    try:
        task = task_from(json.loads(spec))
        return task, task.plan()
    except TrajectoryError as exc:
        raise BlockError(f"task_trajectory: {exc}") from None
    except (ValueError, TypeError, ArithmeticError, RuntimeError) as exc:  # a planner refusing odd numbers
        raise BlockError(f"task_trajectory: the task cannot be planned ({type(exc).__name__}: {exc})") from None


def task_trajectory(config: str = "cross_leg", waypoints=None, method: str = "ruckig", times=None,
                    limits=None, margins=None, start: float = 0.0) -> Block:
    """The trajectory source of a planned task (module docstring).  Blocks are immutable in use, so
    one is built per task (the options are mappings, which the scene loader's cache cannot key)."""
    spec = {"config": config, "waypoints": waypoints, "method": method, "limits": limits or {}, "start": start}
    if times is not None:
        spec["times"] = times
    if margins is not None:
        spec["margins"] = margins
    return _block(json.dumps(spec, sort_keys=True, default=repr))


@lru_cache(maxsize=32)
def _block(spec: str) -> Block:
    config = json.loads(spec)["config"]
    task, traj = _planned(spec)
    drive = task.limits.drive
    ps = ParamSet()
    g = geometry_params(ps, config)
    m = inertia_params(ps, config)
    m_act = ps.add("m_act", task.limits.m_act, "kg", "actuator mass lumped on each leg's extension (feedforward)",
                   lower=0.0)
    alpha = ps.add("alpha", drive.alpha, "V/N", f"drive volts per newton ({drive.name}: R rack / kt)")
    beta = ps.add("beta", drive.beta, "V.s/m", f"drive volts per m/s ({drive.name}: back-EMF and friction)")
    t0 = ps.add("t0", 0.0, "s", "start value of the block's clock (the scene's start time)")
    clock = ca.SX.sym("clock")
    q, qd, qdd = piecewise_cubic(traj, clock)
    mot = leg_motion(q, qd, qdd, g, m[0], m[1])
    f_ff = inverse_dynamics_fn()(q, qd, qdd, g, m) + m_act * mot.Ldd
    u_ff = alpha * f_ff + beta * mot.Ld
    names = [("x", "m"), ("y", "m"), ("phi", "rad"), ("vx", "m/s"), ("vy", "m/s"), ("omega", "rad/s"),
             ("ax", "m/s2"), ("ay", "m/s2"), ("alpha", "rad/s2")]
    outputs = ([Var(f"platform.{n}", u, "platform setpoint (global frame)") for n, u in names]
               + [Var(f"leg[{i}].s", "m", f"leg {i} length setpoint (inverse kinematics)") for i in LEGS]
               + [Var(f"leg[{i}].v", "m/s", f"leg {i} rate setpoint") for i in LEGS]
               + [Var(f"leg[{i}].a", "m/s2", f"leg {i} acceleration setpoint") for i in LEGS]
               + [Var(f"leg[{i}].f_ff", "N", f"leg {i} feedforward force (inverse dynamics)") for i in LEGS]
               + [Var(f"leg[{i}].u_ff", "V", f"leg {i} feedforward voltage (drive line)") for i in LEGS])
    return Block.build(
        "task_trajectory", description=f"planned task ({task.method}, {len(task.waypoints)} waypoints, "
                                       f"{traj.duration:.4g} s) with inverse kinematics and feedforward",
        params=ps.params, inputs=[], outputs=outputs, states=[Var("clock.t", "s", "the block's clock")],
        p=ps.vector(), u=ca.SX(0, 1), x=clock, ode=ca.SX(1),
        out=ca.vertcat(q, qd, qdd, mot.L, mot.Ld, mot.Ldd, f_ff, u_ff),
        start=t0, integrator="rk4", fidelity="planned", ratings=stroke_ratings(config))
