"""The monolithic reference's output instants and files, without CasADi: ``run --reference``
integrates the reference in a child forked as the run starts (:mod:`.reference`), and the
command's own process, which never imports CasADi for it, checks that it is the reference the
run asks for (:func:`same_request`) and writes its files (:func:`write_reference`)."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..scenario import Scene
from ..trace.traces import Trace, TraceWriteError
from .execute import RunResult, scene_meta, scene_observers
from ..outputs import OutputLock, check_out_dir


def output_instants(scene: Scene, times: Sequence[float] | None) -> tuple[np.ndarray, bool]:
    """The reference's output instants [s] (from 0) and whether they are the scene's regular grid:
    counted in whole nanoseconds as the master counts its steps (``k * step_ns / 1e9``), so that
    they are a run's instants to the bit."""
    if times is None:
        every_ns = scene.master.record_every * scene.master.step_ns
        return np.arange(scene.n_steps // scene.master.record_every + 1) * every_ns / 1e9, True
    grid = np.asarray(times, dtype=float)
    if grid.ndim != 1 or not len(grid) or grid[0] != 0.0 or np.any(np.diff(grid) <= 0) or not np.isfinite(grid).all():
        raise UserError("reference output instants must increase strictly from 0 s")
    return grid, False


def same_request(computed: Scene, scene: Scene, times: Sequence[float] | None = None) -> bool:
    """Whether the reference of ``computed`` on its own output grid is the one asked of ``scene``
    (e.g. the scene as a run ran it, the master's choice made) at ``times``: the same trace
    metadata (scene hash, outputs, units, output interval) and the same output instants, to
    1e-9 of the output interval (a variable-step run lands on the grid up to rounding, 1e-16 s)."""
    if scene_meta(computed) != scene_meta(scene):
        return False
    ours, _ = output_instants(computed, None)
    asked, _ = output_instants(scene, times)
    dt = computed.master.record_every * computed.master.step
    return len(ours) == len(asked) and bool(np.all(np.abs(ours - asked) <= 1e-9 * dt))


def write_reference(scene: Scene, trace: Trace, out_dir: Path, *, trace_format: str = "csv",
                    log: Callable[[str], None] | None = None) -> RunResult:
    """Write a reference computed without ``out_dir`` (``trace``, as :func:`reference` returned
    it: rows, metadata, status, statistics) into ``out_dir``: the files :func:`reference` writes
    there itself, under the same safety (:func:`cosim.outputs.place`)."""

    check_out_dir(out_dir)
    with OutputLock(out_dir, log=log):
        memory, observers, trace_path = scene_observers(scene, out_dir, "_reference", trace_format)
        status, reason, stats = trace.status, trace.reason, trace.stats
        for ob in observers:
            ob.start(trace.columns, trace.meta)
        try:
            for ob in observers:
                ob.record(trace.data)
        except TraceWriteError as exc:
            status, reason = "failed", f"TraceWriteError: {exc}"
            stats = dict(stats, status=status, reason=reason)
        for ob in observers:
            ob.finish(status, reason, stats)
        for ob in observers:
            if getattr(ob, "note", "") and log:
                log(ob.note)
    return RunResult(scene, status, reason, memory.trace, stats, {}, trace_path, 0.0)


__all__ = ["output_instants", "same_request", "write_reference"]
