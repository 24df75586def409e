"""The monolithic reference of a scene: its catalog blocks wired into one ODE
(:func:`models.compose.compose`) and integrated by CVODES at tight tolerances.

Where the co-simulation holds each input over a communication step, the reference feeds every
input continuously, so the difference between the two traces is the error of the master
algorithm and its step (plus the reference's tolerance).  The reference records the same
variables at the same instants as the scene and writes the same trace format.

Only catalog components with continuous dynamics can join: an external FMU is a black box and a
sampled (discrete) block has no ODE; both are refused with the component's name.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import casadi as ca
import numpy as np

from models.block import BlockError
from models.compose import Composite, compose

from .errors import UserError
from .run import RunResult, scene_meta, scene_observers
from .scenario import Scene, load

#: CVODES tolerances of the reference (relative, absolute).
RTOL, ATOL = 1e-10, 1e-12
#: Output instants per CVODES call (progress is reported between calls).
CHUNK = 100


def composite(scene: Scene) -> Composite:
    """The scene's components and connections as one ODE (raises :class:`UserError` naming the
    component that cannot join)."""
    for name, comp in scene.components.items():
        if comp.kind != "model":
            raise UserError(f"component {name!r} is an external FMU ({comp.label}); a monolithic reference "
                            f"needs the equations of every component (catalog models only)")
    blocks = {n: c.block for n, c in scene.components.items()}
    params = {n: c.block.param_vector(**c.params) for n, c in scene.components.items()}
    state_names = {n: {v.name for v in c.block.states} for n, c in scene.components.items()}
    input_names = {n: {v.name for v in c.block.inputs} for n, c in scene.components.items()}
    starts = {n: {k: v for k, v in c.start.items() if k in state_names[n]} for n, c in scene.components.items()}
    inputs = {n: {k: v for k, v in c.start.items() if k in input_names[n]} for n, c in scene.components.items()}
    for c in scene.connections:
        if c.factor != 1.0 or c.offset != 0.0:
            raise UserError(f"connection {c}: the monolithic reference joins signals as they are; a linear "
                            f"transformation is not supported there")
    wires = [(c.src, c.src_var, c.dst, c.dst_var) for c in scene.connections]
    try:
        return compose(blocks, params, wires, starts=starts, inputs=inputs)
    except BlockError as exc:
        raise UserError(f"scene {scene.name}: no monolithic reference: {exc}") from None


def reference(scene: Scene | str | Path, overrides=None, *, out_dir: Path | None = None,
              rtol: float = RTOL, atol: float = ATOL,
              progress: Callable[[int, int], None] | None = None) -> RunResult:
    """Integrate the scene's monolithic ODE over ``[0, stop_time]`` and record the scene's outputs
    at its output instants; the trace goes to ``out_dir/<name>_reference.csv`` when ``out_dir`` is
    given.  A solver failure is a status (``failed``) with the partial trace kept."""
    if not isinstance(scene, Scene):
        scene = load(scene, overrides)
    comp = composite(scene)
    dt = scene.master.record_every * scene.master.step
    n_out = scene.n_steps // scene.master.record_every
    names = [tuple(o.split(".", 1)) for o in scene.outputs]
    signals = comp.signal_function(names)
    columns = ["time", *scene.outputs]
    memory, observers, trace_path = scene_observers(scene, out_dir, "_reference")
    meta = {**scene_meta(scene), "method": "monolithic ODE, CVODES (BDF)", "rtol": rtol, "atol": atol,
            "states": int(comp.x.numel())}
    for ob in observers:
        ob.start(columns, meta)
    t0 = time.perf_counter()
    status, reason, done = "ok", "", 0
    x = comp.x0.copy()

    def record(ts: np.ndarray, xs: np.ndarray) -> None:
        rows = np.column_stack([ts, np.array(signals.map(len(ts))(xs)).T])
        for ob in observers:
            ob.record(rows)

    record(np.zeros(1), x.reshape(-1, 1))
    integrators: dict[int, ca.Function] = {}
    try:
        while done < n_out:
            m = min(CHUNK, n_out - done)
            if m not in integrators:
                integrators[m] = ca.integrator("reference", "cvodes", {"x": comp.x, "ode": comp.ode}, 0.0,
                                               dt * np.arange(1, m + 1),
                                               {"reltol": rtol, "abstol": atol, "max_num_steps": 10 ** 7})
            xs = np.array(integrators[m](x0=x)["xf"])
            record(dt * np.arange(done + 1, done + m + 1), xs)
            x = xs[:, -1]
            done += m
            if progress:
                progress(done, n_out)
    except RuntimeError as exc:
        status, reason = "failed", f"CVODES failed after t = {done * dt:g} s: {str(exc).splitlines()[-1]}"
    except KeyboardInterrupt:
        status, reason = "interrupted", f"interrupted at t = {done * dt:g} s"
        for ob in observers:
            ob.finish(status, reason, {})
        raise
    wall = time.perf_counter() - t0
    stats = {"algorithm": "monolithic", "engine": "cvodes", "step": dt, "steps_planned": n_out,
             "steps_done": done, "status": status, "reason": reason, "wall_s": wall,
             "simulated_s": done * dt, "real_time_factor": done * dt / wall if wall > 0 else float("inf"),
             "slaves": {}}
    for ob in observers:
        ob.finish(status, reason, stats)
    return RunResult(scene, status, reason, memory.trace, stats, {}, trace_path, 0.0)


__all__ = ["composite", "reference", "RTOL", "ATOL"]
