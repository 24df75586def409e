"""A run is a pure function of (scene, overrides): load and validate the scene, build (or fetch
from the cache) the FMUs of its catalog components, couple the slaves, step them with the
scene's master algorithm and return a :class:`RunResult`.  Everything it takes is plain data
(a path and a mapping), so a worker process can execute it."""
from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import UserError
from .guards import scene_guard
from .master import CoupledSystem, Link, simulate
from .scenario import Scene, load
from .slaves import FmuSlave, Slave
from .trace import CsvTrace, MemoryTrace, Trace


@dataclass
class RunResult:
    """Outcome of :func:`run`: ``status`` is ``"ok"``, ``"failed"``, ``"stopped"`` (a component
    asked to end), ``"out_of_limits"`` or ``"unstable"`` (a guard, :mod:`cosim.guards`) or
    ``"interrupted"``; ``reason`` says why a run
    ended early; ``trace`` holds what was recorded
    (also the partial trace of a failed run); ``stats`` the run statistics
    (:class:`cosim.master.RunStats` as a dict)."""

    scene: Scene
    status: str
    reason: str
    trace: Trace
    stats: dict
    fmus: dict[str, Path] = field(default_factory=dict)
    trace_path: Path | None = None
    build_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def build_components(scene: Scene, *, cache_dir: Path | None = None,
                     progress: Callable[[str], None] | None = None) -> dict[str, Path]:
    """The FMU of every component: the external file, or the catalog block built by
    :func:`fmus.build_fmu` (cached by content, so a second run compiles nothing)."""
    paths: dict[str, Path] = {}
    for name, comp in scene.components.items():
        if comp.kind == "fmu":
            paths[name] = comp.fmu
            continue
        import fmus

        paths[name] = fmus.build_fmu(comp.block, fmi_version=comp.fmi, cache_dir=cache_dir,
                                     progress=(lambda msg, n=name: progress(f"{n}: {msg}")) if progress else None)
    return paths


def couple(scene: Scene, slaves: Sequence[Slave], watch: Sequence[tuple[str, str]] = ()) -> CoupledSystem:
    """The coupled system of ``scene`` over ``slaves`` (one per component, in scene order);
    ``watch``: (component, variable) pairs sampled with the recorded ones but not traced."""
    index = {s.name: i for i, s in enumerate(slaves)}
    links = [Link(index[c.src], c.src_var, index[c.dst], c.dst_var, c.factor, c.offset) for c in scene.connections]
    record = []
    for name in scene.outputs:
        comp, _, var = name.partition(".")
        record.append((index[comp], var))
    return CoupledSystem(slaves, links, record, [(index[c], v) for c, v in watch])


def scene_observers(scene: Scene, out_dir: Path | None, suffix: str = "") -> tuple[MemoryTrace, list, Path | None]:
    """The observers of a run of ``scene``: a :class:`MemoryTrace` and, with ``out_dir``, a
    :class:`CsvTrace` streaming to ``out_dir/<name><suffix>.csv`` (returned as the trace path)."""
    memory = MemoryTrace()
    if out_dir is None:
        return memory, [memory], None
    path = Path(out_dir) / f"{scene.name}{suffix}.csv"
    return memory, [memory, CsvTrace(path, extra={"scene_data": scene.data})], path


def scene_meta(scene: Scene) -> dict:
    """Trace metadata identifying the scene a run comes from."""
    from .charts import units_of

    units = units_of(scene)
    return {"scene": scene.name, "scene_file": str(scene.path) if scene.path else None, "scene_hash": scene.hash,
            "start_time": scene.start_time, "stop_time": scene.stop_time,
            "output_interval": scene.master.record_every * scene.master.step,
            "units": {name: units.get(name, "") for name in scene.outputs}}


def run(scene: Scene | str | Path, overrides: Mapping[str, Any] | Sequence[str] | None = None, *,
        out_dir: Path | None = None, catalog=None, cache_dir: Path | None = None,
        progress: Callable[[int, int], None] | None = None, log: Callable[[str], None] | None = None,
        engine: str | None = None, slaves: Sequence[Slave] | None = None) -> RunResult:
    """Run a scene.

    Parameters
    ----------
    scene : a validated :class:`Scene` or the path of a scene file.
    overrides : ``--set`` style overrides (mapping path -> value, or ``"path=value"`` strings);
        with a :class:`Scene` they are applied by reloading its file.
    out_dir : write ``<name>.csv`` (streamed) and ``<name>.json`` (sidecar) there.
    catalog : the model catalog (default :mod:`models.blocks`).
    cache_dir : FMU cache directory (default ``$RPR_COSIM_CACHE`` or ``~/.cache/rpr-cosim/fmus``).
    progress : called as ``progress(steps_done, steps_total)`` during the run.
    log : one-line messages about building FMUs.
    engine : overrides ``master.engine`` (auto | compiled | python).
    slaves : ready slaves in scene order instead of FMUs built from the scene (non-FMU slaves).

    Returns a :class:`RunResult`; a numerical failure is a status, not an exception.  A
    KeyboardInterrupt propagates after the trace files were finalised with the reason.
    """
    if not isinstance(scene, Scene):
        scene = load(scene, overrides, catalog=catalog)
    elif overrides:
        if scene.path is None or not Path(scene.path).is_file():
            raise UserError("overrides need the scene's file; pass the path instead of a Scene")
        scene = load(scene.path, overrides, catalog=catalog)
    t0 = time.perf_counter()
    if slaves is None:
        paths = build_components(scene, cache_dir=cache_dir, progress=log)
        slaves = [FmuSlave(name, paths[name], c.description if c.kind == "fmu" else None)
                  for name, c in scene.components.items()]
    else:
        paths = {}
        if [s.name for s in slaves] != list(scene.components):
            raise UserError(f"slaves must match the scene's components in order: {list(scene.components)}")
    build_s = time.perf_counter() - t0
    guard = scene_guard(scene)
    system = couple(scene, slaves, guard.watch if guard else ())
    if guard:
        guard.bind(system.record_names + system.watch_names)
    memory, observers, trace_path = scene_observers(scene, out_dir)
    meta = {**scene_meta(scene), "inputs": scene.master.inputs,
            "components": {n: c.label for n, c in scene.components.items()},
            "connections": [str(c) for c in scene.connections],
            "overrides": list(overrides.items()) if isinstance(overrides, Mapping) else list(overrides or [])}
    index = {n: i for i, n in enumerate(scene.components)}
    order = [index[n] for n in scene.master.order] if scene.master.order else None
    stats = simulate(system, scene.master.algorithm, step_ns=scene.master.step_ns, n_steps=scene.n_steps,
                     record_every=scene.master.record_every, observers=observers,
                     start_values=[c.start_values() for c in scene.components.values()],
                     engine=engine or scene.master.engine, order=order, progress=progress, meta=meta,
                     inputs=scene.master.inputs, start_ns=scene.start_ns,
                     tolerances=[c.description.default_experiment.get("tolerance")
                                 for c in scene.components.values()], guard=guard)
    return RunResult(scene, stats.status, stats.reason, memory.trace, stats.as_dict(), paths, trace_path, build_s)


def progress_bar(stream=sys.stderr, *, min_s: float = 0.5) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback drawing a bar on ``stream`` for runs longer than
    ``min_s`` seconds (short runs print nothing).  The clock starts at the first call, i.e. when
    the stepping starts, so FMU builds before it do not distort the time left."""
    state = {"shown": False, "last": 0.0, "t0": None}

    def update(done: int, total: int) -> None:
        now = time.perf_counter()
        if state["t0"] is None:
            state["t0"] = now
        t0 = state["t0"]
        if now - t0 < min_s and done < total:
            return
        if done < total and now - state["last"] < 0.1:
            return
        if not state["shown"] and done >= total:
            return
        state["shown"], state["last"] = True, now
        frac = done / total if total else 1.0
        bar = "#" * int(30 * frac)
        eta = (now - t0) * (1 - frac) / frac if frac > 0 else 0.0
        stream.write(f"\r[run] |{bar:<30}| {100 * frac:5.1f}%  {now - t0:6.1f} s  eta {eta:5.1f} s")
        if done >= total:
            stream.write("\n")
        stream.flush()

    return update
