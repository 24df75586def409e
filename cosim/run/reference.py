"""The monolithic reference of a scene: its catalog blocks wired into one ODE
(:func:`models.compose.compose`) and integrated by CVODES at tight tolerances; a scene with an
algebraic loop becomes a semi-explicit DAE (the loop's cut inputs as algebraic variables),
integrated by IDAS, its start made consistent by a Newton solve.

Where the co-simulation holds each input over a communication step, the reference feeds every
input continuously, so the difference between the two traces is the error of the master
algorithm and its step (plus the reference's tolerance).  The reference records the same
variables at the same instants as the scene and writes the same trace format.

Only components with equations can join (catalog blocks, Modelica classes): an external FMU is a
black box and a sampled (discrete) block has no ODE; both are refused with the component's name.
A scene whose blocks have events goes to :mod:`.event_reference` (SciPy, event to event).
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from models.block import Block, BlockError
from models.compose import Composite, compose

from ..errors import UserError
from .execute import RunResult, scene_meta, scene_observers
from .row_guards import scene_guard
from .reference_files import output_instants as _output_instants
from ..trace.traces import TraceWriteError
from ..scenario import Scene, load
from fmus.index import real_block
from ..interrupts import signals_as_interrupts
from ..outputs import OutputLock, check_out_dir
from .event_reference import EventReferenceError, Tolerances, integrate

#: CVODES tolerances of the reference (relative, absolute).
RTOL, ATOL = 1e-10, 1e-12
#: Output instants per CVODES call (progress is reported between calls); a quarter as many after a
#: call that took more than :data:`SLOW_CALL_STEPS` CVODES steps (signals and caps are seen between
#: calls).  Each call restarts the integrator (BDF from order 1): on pid_step 500 instants per call
#: take 4,284 CVODES steps where 100 took 6,147 (a third less CPU), the results 2e-9 of range
#: apart.  The chunks follow the step count, never the wall time, so that a reference is the same,
#: to the bit, however loaded the machine.
CHUNK = 500
SLOW_CALL_STEPS = 5_000
#: Default caps of one reference: wall time [s] and CVODES internal steps (in total; also at most
#: :data:`MAX_STEPS_PER_INTERVAL` between two output instants).
MAX_WALL_S = 300.0
MAX_STEPS = 5_000_000
MAX_STEPS_PER_INTERVAL = 100_000


class _WallCap(Exception):
    """Raised by the SIGALRM handler when the reference's wall-time cap is reached."""


class _Collapsed:
    """Counts what the solver prints (Python and C level, stdout and stderr) instead of letting
    it through: :attr:`lines` and the :attr:`first` line.  The C level goes to an unlinked
    temporary file while :meth:`capture` is on and is counted when it ends (no reader thread to
    start per solver call, no pipe to fill)."""

    def __init__(self) -> None:
        self.lines, self.first = 0, ""
        self._file = None

    def feed(self, text: str) -> None:
        if not self.first and text.strip():
            self.first = text.strip().splitlines()[0][:200]
        self.lines += text.count("\n")

    def write(self, text: str) -> int:  # file-like for sys.stdout / sys.stderr
        self.feed(text)
        return len(text)

    def flush(self) -> None:
        pass

    @contextlib.contextmanager
    def capture(self):
        """File descriptors 1 and 2 and ``sys.stdout``/``sys.stderr`` go to this counter."""
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        if self._file is None:
            self._file = tempfile.TemporaryFile()
        fd = self._file.fileno()
        saved = [os.dup(1), os.dup(2)]
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        try:
            with contextlib.redirect_stdout(self), contextlib.redirect_stderr(self):
                yield self
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for saved_fd in saved:
                os.close(saved_fd)
            self._count(fd)

    def _count(self, fd: int) -> None:
        """Count what the C level wrote to the file, then empty it."""
        size, at = os.fstat(fd).st_size, 0
        while at < size:
            block = os.pread(fd, min(1 << 20, size - at), at)
            if not block:
                break
            self.feed(block.decode(errors="replace"))
            at += len(block)
        if size:
            os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def composite(scene: Scene, *, symbols: Mapping[tuple[str, str], ca.SX] | None = None,
              sources: Mapping[str, tuple[Block, ca.SX]] | None = None) -> Composite:
    """The scene's components and connections as one ODE (raises :class:`UserError` naming the
    component that cannot join).  ``symbols[(component, parameter)]`` stands for that parameter's
    value (the unknowns of a fit: the ODE is then symbolic in them); ``sources[component]`` is a
    block and its symbolic parameter vector standing for a component without equations (a
    replay's columns, whose values the caller feeds)."""
    sources = sources or {}
    for name, comp in scene.components.items():
        if comp.kind != "model" and name not in sources:
            raise UserError(f"component {name!r} is an external FMU ({comp.label}); a monolithic reference "
                            f"needs the equations of every component (catalog models only)")

    blocks = {n: sources[n][0] if n in sources else real_block(c.block) for n, c in scene.components.items()}
    params = {n: sources[n][1] if n in sources else _param_vector(blocks[n], c.params, n, symbols or {})
              for n, c in scene.components.items()}
    state_names = {n: {v.name for v in b.states} for n, b in blocks.items()}
    input_names = {n: {v.name for v in b.inputs} for n, b in blocks.items()}
    starts = {n: {k: v for k, v in c.start.items() if k in state_names[n]} for n, c in scene.components.items()}
    inputs = {n: {k: v for k, v in c.start.items() if k in input_names[n]} for n, c in scene.components.items()}
    for c in scene.connections:
        if c.factor != 1.0 or c.offset != 0.0:
            raise UserError(f"connection {c}: the monolithic reference joins signals as they are; a linear "
                            f"transformation is not supported there")
    wires = [(c.src, c.src_var, c.dst, c.dst_var) for c in scene.connections]
    try:
        return compose(blocks, params, wires, starts=starts, inputs=inputs, loops=True)
    except BlockError as exc:
        raise UserError(f"scene {scene.name}: no monolithic reference: {exc}") from None


def _param_vector(block: Block, values: Mapping[str, float], name: str,
                  symbols: Mapping[tuple[str, str], ca.SX]) -> np.ndarray | ca.SX:
    """The block's parameter values as the scene sets them, symbols where ``symbols`` has them."""
    vec = block.param_vector(**values)
    mine = {p: sym for (comp, p), sym in symbols.items() if comp == name}
    if not mine:
        return vec
    index = {p.name: i for i, p in enumerate(block.params)}
    out = ca.SX(ca.DM(vec))
    for p, sym in mine.items():
        if p not in index:
            raise UserError(f"component {name!r} has no parameter {p!r}")
        out[index[p]] = sym
    return out


@dataclass(frozen=True)
class ReferenceRequest:
    """What a reference is asked for besides the scene (see :func:`reference` for each field)."""

    out_dir: Path | None = None
    rtol: float = RTOL
    atol: float = ATOL
    progress: Callable[[int, int], None] | None = None
    max_wall_s: float = MAX_WALL_S
    max_steps: int = MAX_STEPS
    log: Callable[[str], None] | None = None
    times: Sequence[float] | None = None
    trace_format: str = "csv"
    guarded: bool = True


def reference(scene: Scene | str | Path, overrides=None, **options: Any) -> RunResult:
    """Integrate the scene's monolithic ODE over ``[0, stop_time]`` and record the scene's outputs
    at its output instants, or at ``times`` [s] when given (increasing, from 0: e.g. the irregular
    instants of a variable-step run, so that comparing with it needs no interpolation); the trace goes to ``out_dir/<name>_reference.csv`` (``.parquet`` with
    ``trace_format="parquet"``) when ``out_dir`` is given.  A solver failure is a status (``failed``) with the partial trace kept; so is reaching
    ``max_wall_s`` seconds of wall time or ``max_steps`` CVODES steps.  What the solver prints is
    counted, not shown: ``log`` gets one line with the count and the first line, and the
    statistics keep the count (``solver_messages``).  The scene's guards hold the reference to
    the same limits as its runs (a runaway truth ends ``out_of_limits``/``unstable``, cut at the
    offending row); ``guarded=False`` integrates the maths alone, for a study's ruler, whose
    runs are guarded themselves.  The keyword ``options`` are the fields of
    :class:`ReferenceRequest` (``out_dir``, ``rtol``, ``atol``, ``progress``, ``max_wall_s``,
    ``max_steps``, ``log``, ``times``, ``trace_format``, ``guarded``)."""

    req = ReferenceRequest(**options)
    if not isinstance(scene, Scene):
        scene = load(scene, overrides)
    if req.out_dir is None:
        with signals_as_interrupts():
            return _reference(scene, req)
    check_out_dir(req.out_dir)
    with signals_as_interrupts(), OutputLock(req.out_dir, log=req.log):
        return _reference(scene, req)


def _reference(scene: Scene, req: ReferenceRequest) -> RunResult:
    comp = composite(scene)
    if comp.has_events:
        return _event_reference(scene, comp, req)
    out_dir, rtol, atol, progress, log, times = req.out_dir, req.rtol, req.atol, req.progress, req.log, req.times
    max_wall_s, max_steps, trace_format, guarded = req.max_wall_s, req.max_steps, req.trace_format, req.guarded
    dt = scene.master.record_every * scene.master.step
    grid, regular = _output_instants(scene, times)
    n_out = len(grid) - 1
    names = [tuple(o.split(".", 1)) for o in scene.outputs]
    guard = scene_guard(scene) if guarded else None  # the truth is held to the same limits as the runs it judges
    watch = [w for w in (guard.watch if guard else ()) if w not in names]
    signals = comp.signal_function(names + watch)
    if guard:
        guard.bind(list(scene.outputs) + [f"{c}.{v}" for c, v in watch])
    n_rec = 1 + len(names)
    columns = ["time", *scene.outputs]
    memory, observers, trace_path = scene_observers(scene, out_dir, "_reference", trace_format)
    dae = comp.z.numel() > 0  # an algebraic loop: the loop's cut inputs are algebraic variables (IDAS)
    meta = {**scene_meta(scene), "method": "monolithic DAE, IDAS (BDF)" if dae else "monolithic ODE, CVODES (BDF)",
            "rtol": rtol, "atol": atol, "states": int(comp.x.numel()),
            **({"algebraic": [f"{b}.{i}" for b, i in comp.cuts]} if dae else {})}
    for ob in observers:
        ob.start(columns, meta)
    t0 = time.perf_counter()
    status, reason, done = "ok", "", 0
    x, z = comp.x0.copy(), comp.z0.copy()
    if dae:  # a consistent start: the loop solved at the start state (IDAS would do it too)
        z = np.array(ca.rootfinder("start", "newton", ca.Function("g", [comp.z, comp.x], [comp.alg]))(z, x)).ravel()

    def record(ts: np.ndarray, xs: np.ndarray, zs: np.ndarray | None = None) -> bool:
        """Record the rows the guard lets through; False when it tripped."""
        vals = signals.map(len(ts))(xs, zs) if dae else signals.map(len(ts))(xs)
        rows = np.column_stack([ts, np.array(vals).T])
        keep = guard.check(rows) if guard else None
        if keep is not None:
            rows = rows[:keep]
        for ob in observers:
            ob.record(rows[:, :n_rec])
        return keep is None

    running = record(np.zeros(1), x.reshape(-1, 1), z.reshape(-1, 1))
    integrators: dict[int, ca.Function] = {}
    chunk, solver_steps, printed = CHUNK, 0, _Collapsed()
    per_interval = max(1, min(MAX_STEPS_PER_INTERVAL, int(max_steps)))
    alarm = threading.current_thread() is threading.main_thread() and max_wall_s > 0
    interrupt, fired = None, []

    def on_alarm(signum, frame):
        fired.append(signum)
        raise _WallCap()

    previous = signal.signal(signal.SIGALRM, on_alarm) if alarm else None
    try:
        if alarm:
            signal.setitimer(signal.ITIMER_REAL, max_wall_s)
        while done < n_out and running:
            if time.perf_counter() - t0 > max_wall_s:
                raise _WallCap()
            if solver_steps >= max_steps:
                status, reason = "failed", (f"the reference reached its cap of {max_steps:,} CVODES steps at "
                                            f"t = {grid[done]:g} s (a diverging or very stiff scene?)")
                break
            m = min(chunk, n_out - done)
            rel = grid[done + 1:done + m + 1] - grid[done]
            # the ODE is autonomous: each chunk starts at 0, and a chunk on the regular grid (all of a
            # fixed-step run's, those of a variable-step run between events) reuses its integrator
            # (building one costs ~10 ms: one per chunk was 3/4 of an irregular reference)
            on_grid = regular or bool(np.all(np.abs(rel - dt * np.arange(1, m + 1)) <= 1e-9 * dt))
            if not on_grid or m not in integrators:
                problem = {"x": comp.x, "ode": comp.ode, **({"z": comp.z, "alg": comp.alg} if dae else {})}
                made = ca.integrator("reference", "idas" if dae else "cvodes", problem, 0.0,
                                     dt * np.arange(1, m + 1) if on_grid else rel,
                                     {"reltol": rtol, "abstol": atol, "max_num_steps": per_interval})
                if on_grid:
                    integrators[m] = made
            solve = integrators[m] if on_grid else made
            steps = 0
            try:
                with printed.capture():
                    sol = solve(x0=x, z0=z) if dae else solve(x0=x)
                    xs = np.array(sol["xf"])
                    zs = np.array(sol["zf"]) if dae else None
            except RuntimeError as exc:
                if m > 1 and "TOO_MUCH_WORK" in str(exc) and not fired:
                    chunk = max(1, m // 4)  # the rows before the stall, one chunk at a time: the guards see them
                    continue
                raise
            finally:
                steps = int(solve.stats().get("nsteps", 0) or 0)
                solver_steps += steps
            running = record(grid[done + 1:done + m + 1], xs, zs)
            x = xs[:, -1]
            if dae:
                z = zs[:, -1]
            done += m
            if progress:
                progress(done, n_out)
            if steps > SLOW_CALL_STEPS and chunk > 1:
                chunk = max(1, chunk // 4)  # long calls: return to Python (signals, caps) more often
    except _WallCap:
        status, reason = "failed", (f"the reference reached its wall-time cap of {max_wall_s:g} s at "
                                    f"t = {grid[done]:g} s (a diverging or very stiff scene?)")
    except TraceWriteError as exc:
        status, reason = "failed", f"TraceWriteError: {exc}"
    except RuntimeError as exc:
        from ..interrupts import last_signal

        text = str(exc).splitlines()[-1] if str(exc) else type(exc).__name__
        if fired:
            status, reason = "failed", (f"the reference reached its wall-time cap of {max_wall_s:g} s at "
                                        f"t = {grid[done]:g} s (a diverging or very stiff scene?)")
        elif last_signal() or "KeyboardInterrupt" in printed.first or "KeyboardInterrupt" in str(exc):
            interrupt = last_signal()
            status, reason = "interrupted", f"interrupted by {interrupt or 'the user (KeyboardInterrupt)'} at t = {grid[done]:g} s"
        elif "TOO_MUCH_WORK" in text:
            status, reason = "failed", (f"the reference reached its cap of {per_interval:,} CVODES steps between two "
                                        f"output instants after t = {grid[done]:g} s (a diverging or very stiff scene?)")
        else:
            status, reason = "failed", f"CVODES failed after t = {grid[done]:g} s: {text}"
    except KeyboardInterrupt as exc:
        status, reason = "interrupted", f"interrupted by {str(exc) or 'the user (KeyboardInterrupt)'} at t = {grid[done]:g} s"
        interrupt = exc
    finally:
        printed.close()
        if alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
    wall = time.perf_counter() - t0
    if guard and guard.tripped and status == "ok":
        status, reason = guard.status, guard.reason
    if printed.lines and log:
        log(f"the solver printed {printed.lines:,} lines, not shown (first: {printed.first})")
    stats = {"algorithm": "monolithic", "engine": "cvodes", "step": dt, "steps_planned": n_out,
             "steps_done": done, "status": status, "reason": reason, "wall_s": wall,
             "simulated_s": float(grid[done]), "real_time_factor": float(grid[done]) / wall if wall > 0 else float("inf"),
             "solver_steps": solver_steps, "solver_messages": printed.lines, "slaves": {},
             **({"guards": guard.summary()} if guard else {})}
    for ob in observers:
        ob.finish(status, reason, stats)
    for ob in observers:
        if getattr(ob, "note", "") and log:
            log(ob.note)
    if interrupt is not None:
        raise interrupt if isinstance(interrupt, BaseException) else KeyboardInterrupt(str(interrupt))
    return RunResult(scene, status, reason, memory.trace, stats, {}, trace_path, 0.0)


def _event_reference(scene: Scene, comp: Composite, req: ReferenceRequest) -> RunResult:
    """The reference of a scene whose blocks have events (:mod:`.event_reference`): the output grid
    plus two rows at each event; the sidecar's ``events`` lists them (time and block.event)."""

    out_dir, rtol, atol, max_wall_s, log = req.out_dir, req.rtol, req.atol, req.max_wall_s, req.log
    times, trace_format, guarded = req.times, req.trace_format, req.guarded
    grid, _ = _output_instants(scene, times)
    names = [tuple(o.split(".", 1)) for o in scene.outputs]
    guard = scene_guard(scene) if guarded else None
    watch = [w for w in (guard.watch if guard else ()) if w not in names]
    signals = comp.signal_function(names + watch)
    if guard:
        guard.bind(list(scene.outputs) + [f"{c}.{v}" for c, v in watch])
    n_rec = 1 + len(names)
    memory, observers, trace_path = scene_observers(scene, out_dir, "_reference", trace_format)
    meta = {**scene_meta(scene), "method": "monolithic ODE with events, SciPy solve_ivp (LSODA), event to event",
            "rtol": rtol, "atol": atol, "states": int(comp.x.numel()), "modes": int(comp.m.numel())}
    for ob in observers:
        ob.start(["time", *scene.outputs], meta)

    last = [0.0]  # the time of the last row recorded [s]: where a failed reference got to

    def record(rows: np.ndarray) -> bool:
        keep = guard.check(rows) if guard else None
        if keep is not None:
            rows = rows[:keep]
        for ob in observers:
            ob.record(rows[:, :n_rec])
        if len(rows):
            last[0] = float(rows[-1, 0])
        return keep is None

    t0 = time.perf_counter()
    status, reason, reached, events = "ok", "", 0.0, None
    try:
        events, reached = integrate(comp, signals, grid, Tolerances(rtol, atol), record, t0 + max_wall_s)
    except TimeoutError as exc:
        status, reason = "failed", f"the reference reached its wall-time cap of {max_wall_s:g} s at {exc}"
    except EventReferenceError as exc:
        status, reason, reached = "failed", str(exc), last[0]
    except TraceWriteError as exc:
        status, reason = "failed", f"TraceWriteError: {exc}"
    wall = time.perf_counter() - t0
    if guard and guard.tripped and status == "ok":
        status, reason = guard.status, guard.reason
    stats = {"algorithm": "monolithic", "engine": "scipy-lsoda", "step": scene.master.record_every * scene.master.step,
             "status": status, "reason": reason, "wall_s": wall, "simulated_s": float(reached),
             "real_time_factor": float(reached) / wall if wall > 0 else float("inf"), "slaves": {},
             "events": {"count": events.total if events else 0,
                        "list": [{"time": t, "event": n} for t, n in (events.items if events else [])]},
             **({"guards": guard.summary()} if guard else {})}
    for ob in observers:
        ob.finish(status, reason, stats)
    if log and events:
        log(f"reference: {events.total} events")
    return RunResult(scene, status, reason, memory.trace, stats, {}, trace_path, 0.0)


__all__ = ["composite", "reference", "ReferenceRequest", "RTOL", "ATOL"]
