"""Work-precision study: error against cost of master algorithm variants on one scene.

``precision_study`` integrates the scene's monolithic reference once (:mod:`cosim.run.reference`,
CVODES at tight tolerances), then runs the co-simulation for every variant (algorithm, inputs):

* a fixed-step algorithm (jacobi, gauss_seidel, iterative) at every communication step of
  ``steps``; everything is recorded every ``record`` seconds, a multiple of every step, so its
  error is measured at instants the reference shares exactly (no interpolation);
* a variable-step algorithm (adaptive, ecco) at every tolerance of ``rtols`` (its option
  ``master.options.rtol``; each class declares its bounds).  Such a run records at its own
  accepted steps, irregular instants: the reference is integrated once more with output at exactly
  those instants (:func:`cosim.run.reference.reference` with ``times``), so no interpolation error
  enters there either.

A run's error, per recorded signal, is its largest deviation from the reference relative to that
signal's range in the reference (max - min over the run, at least
:data:`cosim.master.estimate.FLAT`, as ``master.tolerance`` and the estimate measure it); the row keeps every signal's, the worst one and the RMS over signals.
In a scene with state events (its components' recorded modes, :func:`cosim.run.execute.event_modes`)
the error is the run's own estimate's two numbers (docs/explanation/events.md): the event-time
error of the k-th change of each mode against the reference's k-th (``event_time`` [s]), and the
value error between events (outside a window of that difference plus one recorded interval around
each), where a max-norm would read a switch a hair apart as an error the jump's size; a mode that
changes a different number of times is a missing event.  Such a row is judged as a run is: inaccurate
beyond 10x the tolerance, or beyond 10x the event time tolerance, or with a missing event.  Its cost is the
wall time of the stepping loop (the run's own statistics: FMU builds, instantiation and the batch's
overhead excluded, as the reference's excludes building its integrator), the doStep calls, and for
the algorithms that have them the accepted and rejected steps and rollbacks.

The runs go through the batch runner (:func:`cosim.batch.run_batch` on a
:func:`cosim.batch.points_batch`): ``workers`` processes at once, each run's trace and sidecar in
``<out>/runs/<run id>/``, and a study interrupted or repeated in the same ``out`` runs only what is
missing (the run id is the resolved scene's hash).  Running several at once on a machine with fewer
free cores inflates the wall times measured; the default is one worker.  A variant the scene
refuses (at load, or when the run starts: e.g. ``ecco`` on a scene without power bonds, ``adaptive``
with a slave that cannot roll back) is a row with status ``failed`` and the reason.

The peer master ``ecospy`` (PyPI, C++ libecos; optional) runs the scene's FMUs with fixed-step
Jacobi exchange and held inputs at the study's step nearest the scene's, in the study's process (it is not our run
loop, so not a batch run).  It sets every input before reading the outputs of the same instant, so
an output with direct feedthrough reads one exchange later than ours: only the recorded outputs
without direct feedthrough are compared for it (for those its trajectory is our jacobi/hold's to
the bit); its wall time is the stepping loop including reading those outputs at every recording
instant.  Where ecospy does not import, one line says so and the study goes on.

The observed order of a fixed-step variant is the slope of log(error) against log(step) over its
ok runs; for a variable-step variant the same slope against log(rtol) (1: the error follows the
tolerance proportionally).
"""
from __future__ import annotations

import csv
import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..analysis.trace_diff import Difference, compare_modes
from ..errors import RUN_ERRORS, UserError
from ..master.estimate import FLAT, INACCURATE, event_time_tolerance
from ..run.execute import event_modes
from ..scenario import load
from .fidelity import resolve_auto
from ..trace.traces import Trace
from ..master import ALGORITHMS
from ..scenario import SceneError, parse_set
from ..batch import points_batch, run_batch
from ..batch.executors import LocalExecutor
from ..outputs import safe_name, staged
from ..trace.traces import read_trace
from ..batch.overview import run_trace_path
from ..slaves.description import describe_fmu
from ..run.execute import build_components
from ..analysis.charts import save_figure
from ..readers import read_json

ECOSPY = "ecospy"
#: how the reason of a run judged by its estimate begins (cosim.master.estimate.judge)
ESTIMATED = "the estimated error of "
#: how the reason of a row the study judged by its measured error begins (:func:`judge_rows`)
MEASURED = "the measured error of "
#: the statuses of rows whose errors were measured over the whole run
MEASURED_STATUSES = ("ok", "inaccurate")


@dataclass
class PrecisionRow:
    """One co-simulation: variant, step [s] (the master step; for a variable-step run the first
    step tried), outcome, worst relative error and the signal it is on, RMS of the relative errors
    over the signals, wall time [s] of the stepping loop and doStep calls; ``errors`` per signal;
    ``tolerance`` the rtol of a variable-step run (nan otherwise); accepted and rejected macro
    steps and rollbacks where the algorithm counts them."""

    algorithm: str
    inputs: str
    step: float
    status: str
    reason: str
    worst: float = math.nan
    worst_signal: str = ""
    rms: float = math.nan
    wall_s: float = math.nan
    do_steps: int = 0
    errors: dict[str, float] = field(default_factory=dict)
    tolerance: float = math.nan
    accepted: int = 0
    rejected: int = 0
    rollbacks: int = 0
    run_id: str = ""
    chosen: str = ""  # the tolerance default's choice (cosim.run.choose): what it picked, else ""
    event_time: float = math.nan  # the largest event-time error [s] of the matched events (event scenes)
    missing_events: str = ""  # the modes whose event counts differ from the reference's: "mode (run n, ref m)"

    @property
    def variable(self) -> bool:
        """A variable-step run (swept over its tolerance)."""
        return math.isfinite(self.tolerance)

    @property
    def label(self) -> str:
        """The run's setting: ``rtol 1e-03`` or ``1 ms``."""
        if self.chosen:
            return "choice"
        return f"rtol {self.tolerance:.0e}" if self.variable else f"{self.step * 1e3:g} ms"


@dataclass
class PrecisionStudy:
    scene: str
    stop_time: float
    record: float
    reference_wall_s: float
    rows: list[PrecisionRow] = field(default_factory=list)
    out: Path | None = None  # where the runs' traces are (None: they were temporary)

    def variants(self) -> list[tuple[str, str]]:
        return list(dict.fromkeys((r.algorithm, r.inputs) for r in self.rows))

    def order(self, variant: tuple[str, str]) -> float:
        """Observed order of ``variant``: slope of log(error) over log(step), or over log(rtol)
        for a variable-step variant (nan with fewer than two ok runs)."""
        pts = [(r.tolerance if r.variable else r.step, r.worst) for r in self.rows
               if (r.algorithm, r.inputs) == variant and r.status in MEASURED_STATUSES and 0 < r.worst < math.inf]
        if len(pts) < 2 or len({p[0] for p in pts}) < 2:
            return math.nan
        h, e = np.log(np.array(pts)).T
        return float(np.polyfit(h, e, 1)[0])

    def cheapest_within(self, tol: float) -> PrecisionRow | None:
        """The fastest ok run whose worst relative error is at most ``tol`` (and, in an event scene,
        whose event-time error is within the event time tolerance at ``tol``)."""
        ok = [r for r in self.rows if r.status == "ok" and r.worst <= tol and not r.chosen
              and not r.event_time > event_time_tolerance(tol)]
        return min(ok, key=lambda r: r.wall_s) if ok else None

    def choice(self) -> PrecisionRow | None:
        """The row of the tolerance default's choice, when the study ran it."""
        return next((r for r in self.rows if r.chosen), None)

    def write_csv(self, path: Path) -> None:

        signals = list(dict.fromkeys(s for r in self.rows for s in r.errors))
        with staged(path) as part, open(part, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["algorithm", "inputs", "step", "tolerance", "status", "worst_relative", "worst_signal",
                        "rms_relative", "wall_s", "do_steps", "accepted_steps", "rejected_steps", "rollbacks",
                        "run_id", "reason", "chosen", "event_time_error_s", "missing_events",
                        *(f"rel:{s}" for s in signals)])
            for r in self.rows:
                w.writerow([r.algorithm, r.inputs, repr(r.step), "" if not r.variable else repr(r.tolerance),
                            r.status, f"{r.worst:.6g}", r.worst_signal, f"{r.rms:.6g}", f"{r.wall_s:.6g}",
                            r.do_steps, r.accepted, r.rejected, r.rollbacks, r.run_id, r.reason, r.chosen,
                            "" if math.isnan(r.event_time) else f"{r.event_time:.6g}", r.missing_events,
                            *(f"{r.errors[s]:.6g}" if s in r.errors else "" for s in signals)])


def default_steps(step: float) -> list[float]:
    """Four times the scene's step down to an eighth of it, by halves."""
    return [step * f for f in (4, 2, 1, 0.5, 0.25, 0.125)]


#: Tolerances a variable-step algorithm is swept over by default (decades).
DEFAULT_RTOLS = (1e-2, 1e-3, 1e-4, 1e-5)


def is_variable_step(algorithm: str) -> bool:
    """True for an algorithm that chooses its own steps (``variable_step`` in the registry)."""

    return bool(getattr(ALGORITHMS.get(algorithm), "variable_step", False))


def check_rtols(algorithm: str, rtols: Sequence[float]) -> None:
    """Each of ``rtols`` must be within the bounds ``algorithm`` declares for its ``rtol`` option
    (one-line :class:`UserError` otherwise)."""

    declared = {o.name: o for o in getattr(ALGORITHMS[algorithm], "options", ())}
    if "rtol" not in declared:
        raise UserError(f"master algorithm {algorithm} has no rtol option to sweep")
    for r in rtols:
        try:
            declared["rtol"].check(r)
        except ValueError as exc:
            raise UserError(f"--rtols: {algorithm}: {exc}") from None


def _record_interval(steps: Sequence[float], scene_interval: float) -> float:
    big = max(steps)
    k = scene_interval / big
    return scene_interval if k >= 1 and abs(k - round(k)) < 1e-9 else big


def _checked_steps(steps: Sequence[float]) -> list[float]:
    steps = sorted({round(float(h) * 1e9) / 1e9 for h in steps}, reverse=True)
    if not steps or any(not h > 0 for h in steps):
        raise UserError(f"steps must be positive, got {steps}")
    for h in steps:
        k = steps[0] / h
        if abs(k - round(k)) > 1e-9:
            raise UserError(f"step {h:g} s does not divide the largest step {steps[0]:g} s: choose steps that halve")
    return steps


def _plan(variants: Sequence[tuple[str, str]], steps: Sequence[float], rtols: Sequence[float], record: float
          ) -> list[tuple[dict, dict]]:
    """The runs as (table values, scene overrides)."""
    points = []
    for alg, inputs in variants:
        if is_variable_step(alg):
            for r in rtols:
                points.append(({"algorithm": alg, "inputs": inputs, "step": record, "tolerance": float(r)},
                               {"master.algorithm": alg, "master.inputs": inputs, "master.step": record,
                                "master.output_interval": record, "master.options.rtol": float(r)}))
        else:
            for h in steps:
                points.append(({"algorithm": alg, "inputs": inputs, "step": h, "tolerance": None},
                               {"master.algorithm": alg, "master.inputs": inputs, "master.step": h,
                                "master.output_interval": record}))
    return points


def _refused(scene_path: Path | str, over: dict) -> str:
    """Why the scene with ``over`` does not load ("" when it does)."""

    try:
        load(scene_path, over, auto_fidelity=resolve_auto)
    except (SceneError, *RUN_ERRORS) as exc:
        text = str(exc).strip().splitlines()
        return text[0] if text else type(exc).__name__
    return ""


def reference_scale(ref: Trace, names: Sequence[str]) -> dict[str, float]:
    """Each signal's range in the reference (max - min), at least
    :data:`cosim.master.estimate.FLAT` in its SI unit, the scale relative errors are measured
    against: the measure of ``master.tolerance`` and of every run's estimate (a platform angle
    that the path keeps at 0 moves 3e-8 rad in the reference, and an error of 1e-8 rad on it is
    not a third of its range)."""
    out = {}
    for n in names:
        v = ref[n]
        out[n] = max(float(v.max() - v.min()), FLAT)
    return out


def relative_errors(diffs: Sequence[Difference], scale: dict[str, float]) -> dict[str, float]:
    """Largest deviation of each signal over ``scale`` (its range in the whole reference)."""
    out = {}
    for d in diffs:
        s = scale.get(d.name, d.scale)
        out[d.name] = d.max_abs / s if s > 0 else (0.0 if d.max_abs == 0 else math.inf)
    return out


def judged(reason: str) -> bool:
    """Did the run end "unstable" or "inaccurate" by its own error estimate (having run its whole
    span, so that its errors can be measured like an ok run's)?"""
    return reason.startswith(ESTIMATED)


def judge_row(row: PrecisionRow, tolerance: float | None) -> None:
    """Give an "ok" ``row`` the verdict of its error measured against the reference: "inaccurate"
    when its worst is more than :data:`cosim.master.estimate.INACCURATE` times ``tolerance``,
    as a run's own estimate judges it (None: the scene wants no verdict, the reason says so)."""
    if row.status != "ok" or not math.isfinite(row.worst):
        return
    if tolerance is None:
        row.reason = "no verdict: the scene's master.tolerance is none"
    elif row.missing_events:
        row.status = "inaccurate"
        row.reason = f"{MEASURED}events against the reference: missing events: {row.missing_events}"
    elif row.worst > INACCURATE * tolerance:
        row.status = "inaccurate"
        row.reason = (f"{MEASURED}{row.worst_signal} against the reference is {row.worst:.3g} of its range, more "
                      f"than {INACCURATE:g}x the tolerance {tolerance:g}")
    elif row.event_time > INACCURATE * event_time_tolerance(tolerance):
        row.status = "inaccurate"
        row.reason = (f"{MEASURED}event times against the reference is {row.event_time:.3g} s, more than "
                      f"{INACCURATE:g}x the event time tolerance {event_time_tolerance(tolerance):g} s")


def measure(row: PrecisionRow, trace: Trace, against: Trace, only: Sequence[str] | None, scale: dict[str, float],
            modes: Sequence[str] = ()) -> None:
    """Fill ``row``'s errors of ``trace`` against the reference ``against``: the max-norm per
    signal, or, where ``modes`` (recorded event modes) change, the event-time error and the value
    error between events (module docstring, :func:`cosim.analysis.trace_diff.compare_modes`)."""
    diffs, ev = compare_modes(trace, against, modes, only)
    _fill_errors(row, relative_errors(diffs, scale))
    if ev is not None:
        row.event_time = ev.time_error if ev.time_error is not None else math.nan
        row.missing_events = ", ".join(f"{n} (run {a}, reference {b})" for n, (a, b) in ev.missing.items())


def _fill_errors(row: PrecisionRow, errors: dict[str, float]) -> None:
    row.errors = errors
    if errors:
        row.worst_signal = max(errors, key=errors.get)
        row.worst = errors[row.worst_signal]
        row.rms = float(np.sqrt(np.mean([e ** 2 for e in errors.values()])))


def _costs(row: PrecisionRow, stats: dict) -> None:
    row.do_steps = int(sum(s.get("do_step_calls", 0) for s in (stats.get("slaves") or {}).values()))
    row.accepted = int(stats.get("accepted_steps") or 0)
    row.rejected = int(stats.get("rejected_steps") or 0)
    row.rollbacks = int(stats.get("rollbacks") or 0)
    if stats.get("wall_s") is not None:
        row.wall_s = float(stats["wall_s"])


def precision_study(scene_path: Path | str, variants: Sequence[tuple[str, str]], steps: Sequence[float] | None = None,
                    *, rtols: Sequence[float] | None = None, stop_time: float | None = None,
                    only: Sequence[str] | None = None, cache_dir: Path | None = None,
                    progress: Callable[[str], None] | None = None, overrides: Sequence[str] | None = None,
                    out: Path | None = None, workers: int | None = 1, executor=None, batch_progress=None,
                    peer: bool = False, log: Callable[[str], None] | None = None,
                    tolerance: float | None = None) -> PrecisionStudy:
    """Run the study (module docstring).  ``steps`` default to :func:`default_steps` of the
    scene's step, ``rtols`` to :data:`DEFAULT_RTOLS`; ``stop_time`` overrides the scene's (rounded
    to a whole number of recording intervals); ``only`` restricts the signals compared (globs);
    ``overrides`` (``--set`` items) apply to every run and to the reference (e.g.
    ``components.mech.rate=4``).  The runs go to ``out`` (a temporary directory when None) on
    ``executor`` (default: ``workers`` local processes); ``batch_progress`` is a
    :class:`cosim.batch.overview.Progress`.  ``peer`` adds the ecospy row (``log`` gets the line
    saying why not, when ecospy does not import).  ``tolerance`` adds the row of the master's
    own choice for ``master.tolerance`` at that value (:func:`choice_row`)."""
    from ..run.reference import reference

    sets = dict(parse_set(s) for s in overrides or ())
    base = load(scene_path, sets, auto_fidelity=resolve_auto)
    steps = _checked_steps(steps or default_steps(base.master.step))
    rtols = [float(r) for r in (DEFAULT_RTOLS if rtols is None else rtols)]
    for alg in dict.fromkeys(a for a, _ in variants):
        if is_variable_step(alg):
            check_rtols(alg, rtols)
    record = _record_interval(steps, base.master.record_every * base.master.step)
    stop = stop_time if stop_time is not None else base.stop_time
    stop = max(1, round(stop / record)) * record
    common = {**sets, "stop_time": stop}
    # the ruler is maths, not a run: unguarded (the study's runs are guarded themselves)
    ref = reference(scene_path, {**common, "master.step": record, "master.output_interval": record}, guarded=False)
    if not ref.ok:
        raise UserError(f"{base.name}: the monolithic reference failed ({ref.reason}); no study without it")
    study = PrecisionStudy(base.name, stop, record, float(ref.stats.get("wall_s", math.nan)))
    # every row judged as a run's estimate judges it: the study's tolerance, else the scene's
    verdict_tol = tolerance if tolerance is not None and base.master.tolerance is not None else base.master.tolerance
    scale = reference_scale(ref.trace, ref.trace.names)
    modes = event_modes(base)
    points = _plan(variants, steps, rtols, record)
    refused = {i: _refused(scene_path, {**common, **over}) for i, (_, over) in enumerate(points)}
    todo = [p for i, p in enumerate(points) if not refused[i]]
    with tempfile.TemporaryDirectory(prefix="rpr-precision-") as tmp:
        where = Path(out) if out is not None else Path(tmp)
        done = _run_points(scene_path, todo, common, where, study.scene, cache_dir, workers, executor,
                           batch_progress, log).rows if todo else []
        rows_by_values = {_key(r): r for r in done}
        for i, (values, over) in enumerate(points):
            row = PrecisionRow(values["algorithm"], values["inputs"], values["step"], "failed", refused[i],
                               tolerance=math.nan if values["tolerance"] is None else values["tolerance"])
            if not refused[i]:
                _measure(row, rows_by_values.get(_key(values)), where, base.name, scene_path,
                         {**common, **over}, ref.trace, scale, only, modes)
                judge_row(row, verdict_tol)
            study.rows.append(row)
            if progress:
                progress(_line(row))
    if peer:
        near = min(steps, key=lambda h: abs(math.log(h / base.master.step)))  # the scene's step, if studied
        row = ecospy_row(scene_path, common, near, record, ref.trace, scale, only, cache_dir, log, modes)
        if row is not None:
            judge_row(row, verdict_tol)
            study.rows.append(row)
            if progress:
                progress(_line(row))
    row = choice_row(scene_path, common, tolerance, ref.trace, scale, only, cache_dir, modes) \
        if tolerance is not None else None
    if row is not None:
        judge_row(row, verdict_tol)
        study.rows.append(row)
        if progress:
            progress(_line(row))
    study.out = Path(out) if out is not None else None
    return study


def choice_row(scene_path, common: dict, tolerance: float, ref: Trace, scale: dict[str, float],
               only: Sequence[str] | None, cache_dir, modes: Sequence[str] = ()) -> PrecisionRow | None:
    """The row of the scene run the way its tolerance default runs it (None when the scene names
    its algorithm: there is no choice), ``master.tolerance`` = ``tolerance``;
    the master chooses (:mod:`cosim.run.choose`) and the run is measured like every other row
    (its wall time: the stepping loop of the final run, the pilots not counted)."""
    from ..run.execute import run
    from ..run.reference import reference
    over = {**common, "master.tolerance": tolerance}
    row = PrecisionRow("choice", "", math.nan, "failed", "", chosen="?")
    if not load(scene_path, over, auto_fidelity=resolve_auto).master.auto:
        return None
    res = run(scene_path, over, cache_dir=cache_dir, auto_fidelity=resolve_auto)
    ch = res.stats.get("choice") or {}
    sets = ch.get("settings", {})
    row.algorithm, row.inputs = ch.get("algorithm", "?"), sets.get("inputs", "")
    row.step = sets.get("step", res.scene.master.step)
    row.tolerance = sets["rtol"] if "rtol" in sets else math.nan
    row.chosen = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in sets.items())
    row.status, row.reason = res.status, res.reason
    _costs(row, res.stats)
    if res.status != "ok" and not judged(res.reason):
        return row
    against = ref
    if res.stats.get("smallest_step") is not None:
        at = reference(res.scene, times=res.trace.time, guarded=False)
        if not at.ok:
            row.status, row.reason = "failed", f"the reference at the run's instants failed: {at.reason}"
            return row
        against = at.trace
    measure(row, res.trace, against, only, scale, modes)
    return row


def _key(values: dict) -> tuple:
    tol = values.get("tolerance")
    return (values["algorithm"], values["inputs"], round(float(values["step"]) * 1e9),
            None if tol is None or (isinstance(tol, float) and math.isnan(tol)) else float(tol))


def _line(row: PrecisionRow) -> str:
    return (f"{row.algorithm:<13} {row.inputs:<7} {row.label:<11} {row.status:<10} worst {row.worst:10.3e} "
            f"({row.worst_signal or row.reason[:60]})  {row.wall_s:7.3f} s")


def _run_points(scene_path, points, common, out: Path, name: str, cache_dir, workers, executor, batch_progress, log):

    batch = points_batch(scene_path, points, name=f"{name}_precision", fixed=common, auto_fidelity=resolve_auto,
                         description="rpr-cosim study precision")
    return run_batch(batch, out=out, executor=executor or LocalExecutor(workers), cache_dir=cache_dir,
                     progress=batch_progress, log=log)


def _measure(row: PrecisionRow, result: dict | None, out: Path, name: str, scene_path, over: dict, ref: Trace,
             scale: dict[str, float], only: Sequence[str] | None, modes: Sequence[str] = ()) -> None:
    """Fill ``row`` from its batch result and trace (module docstring)."""
    from ..run.reference import reference

    if result is None:
        row.reason = "the batch has no result for this run"
        return
    row.status, row.reason, row.run_id = result["outcome"], result["reason"] or "", result["run_id"]

    path = run_trace_path(out, row.run_id) or out / "runs" / row.run_id / f"{safe_name(name)}.npy"
    stats = {}
    sidecar = path.with_suffix(".json")
    if sidecar.is_file():

        side = read_json(sidecar, "sidecar")
        stats = side.get("statistics") if isinstance(side, dict) and isinstance(side.get("statistics"), dict) else {}
    _costs(row, stats)
    if row.status != "ok" and not judged(row.reason):
        return
    try:
        trace = read_trace(path)
    except UserError as exc:  # a resumed study whose run directory was removed
        row.status, row.reason = "failed", f"{exc} (remove its row from {out / 'results.csv'} to run it again)"
        return
    against = ref
    if row.variable:  # irregular instants: the reference integrated to exactly those
        at = reference(scene_path, over, times=trace.time)
        if not at.ok:
            row.status, row.reason = "failed", f"the reference at the run's instants failed: {at.reason}"
            return
        against = at.trace
    measure(row, trace, against, only, scale, modes)


# --- the peer master ---------------------------------------------------------------------------------
def ecospy_trace(scene, paths: dict[str, Path], record: float, names: Sequence[str]) -> tuple[Trace, float, int]:
    """Run ``scene``'s FMUs (``paths``) in ecospy at its master step with Jacobi exchange and
    record ``names`` every ``record`` seconds: the trace, the wall time [s] of the stepping loop
    (reads included) and the doStep calls.  ImportError or OSError when ecospy cannot load."""
    import ecospy

    if any(c.factor != 1 or c.offset != 0 or c.as_type for c in scene.connections):
        raise UserError("a connection has a factor, offset or type conversion, which ecospy connections cannot carry")
    ss = ecospy.EcosSimulationStructure()
    for n, p in paths.items():
        ss.add_model(n, str(p))
    for c in scene.connections:
        ss.make_real_connection(f"{c.src}::{c.src_var}", f"{c.dst}::{c.dst_var}")
    ss.add_parameter_set("scene", {f"{n}::{k}": float(v) for n, c in scene.components.items()
                                   for k, v in c.start_values().items()})
    sim = ecospy.EcosSimulation(structure=ss, step_size=scene.master.step)
    sim.init(parameter_set="scene")
    keys = [n.replace(".", "::", 1) for n in names]
    per = round(record / scene.master.step)
    n_out = round(scene.stop_time / record)
    rows = np.empty((n_out + 1, len(names) + 1))
    rows[0] = [0.0, *(sim.get_real(k) for k in keys)]
    t0 = time.perf_counter()
    for j in range(1, n_out + 1):
        sim.step(per)
        rows[j, 0] = j * record
        rows[j, 1:] = [sim.get_real(k) for k in keys]
    wall = time.perf_counter() - t0
    sim.terminate()
    return Trace(["time", *names], rows), wall, per * n_out * len(paths)


def without_feedthrough(scene, paths: dict[str, Path]) -> list[str]:
    """The scene's recorded signals that are outputs of their component without direct feedthrough
    (what ecospy reproduces: see the module docstring)."""

    desc = {n: describe_fmu(p) for n, p in paths.items()}
    out = []
    for sig in scene.outputs:
        comp, _, var = sig.partition(".")
        d = desc.get(comp)
        if d is not None and var in d.variables and d.variables[var].causality == "output" \
                and not d.feedthrough.get(var):
            out.append(sig)
    return out


def ecospy_row(scene_path, common: dict, step: float, record: float, ref: Trace, scale: dict[str, float],
               only: Sequence[str] | None, cache_dir, log: Callable[[str], None] | None,
               modes: Sequence[str] = ()) -> PrecisionRow | None:
    """The ecospy point (module docstring), or None with one line to ``log`` where it does not import."""
    try:
        import ecospy  # noqa: F401
    except (ImportError, OSError) as exc:  # OSError: its C++ library cannot load (Debian libtbb12 missing)
        if log:
            log(f"ecospy not available ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); "
                f"no peer point (pip install ecospy, apt install libtbb12)")
        return None

    row = PrecisionRow(ECOSPY, "hold", step, "failed", "")
    try:
        scene = load(scene_path, {**common, "master.algorithm": "jacobi", "master.inputs": "hold", "master.step": step},
                     auto_fidelity=resolve_auto)
        paths = build_components(scene, cache_dir=cache_dir)
        names = without_feedthrough(scene, paths)
        if not names:
            raise UserError("every recorded signal has direct feedthrough; ecospy reads those one exchange late")
        trace, row.wall_s, row.do_steps = ecospy_trace(scene, paths, record, names)
        row.accepted = round(scene.stop_time / step)
        row.status = "ok"
        measure(row, trace, ref, only, scale, modes)
        row.reason = f"compared: {len(row.errors)} outputs without direct feedthrough"
    except RUN_ERRORS as exc:
        row.reason = str(exc)
    except Exception as exc:  # the peer's failure is its row, never the study's
        row.reason = f"{type(exc).__name__}: {exc}"
    return row


# --- the chart ---------------------------------------------------------------------------------------
def plot_study(study: PrecisionStudy, path: Path) -> Path:
    """Work-precision chart: worst relative error against wall time, one curve per variant, each
    point labelled with its step (fixed-step) or tolerance (variable-step); the ecospy point as a
    star; the monolithic reference's wall time as a vertical line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10.5, 5.5), layout="constrained")
    for variant in study.variants():
        pts = [r for r in study.rows if (r.algorithm, r.inputs) == variant and r.status in MEASURED_STATUSES
               and r.worst > 0
               and not r.chosen]
        if not pts:
            continue
        if variant[0] == ECOSPY:
            for r in pts:
                ax.loglog([r.wall_s], [r.worst], marker="*", ms=14, ls="none", color="k",
                          label=f"ecospy (Jacobi, hold, {r.step * 1e3:g} ms; outputs without feedthrough)")
            continue
        p = study.order(variant)
        what = "slope vs rtol" if pts[0].variable else "order"
        name = variant[0] if pts[0].variable else f"{variant[0]}, {variant[1]}"
        line, = ax.loglog([r.wall_s for r in pts], [r.worst for r in pts], marker="s" if pts[0].variable else "o",
                          ls="--" if pts[0].variable else "-",
                          label=f"{name} ({what} {p:.2f})" if math.isfinite(p) else name)
        for r in pts:
            ax.annotate(r.label, (r.wall_s, r.worst), fontsize=7, textcoords="offset points", xytext=(4, 3),
                        color=line.get_color())
    ch = study.choice()
    if ch is not None and ch.status == "ok" and ch.worst > 0:
        ax.loglog([ch.wall_s], [ch.worst], marker="X", ms=13, ls="none", color="crimson",
                  label=f"tolerance default's choice: {ch.algorithm} ({ch.chosen})")
        ax.annotate("choice", (ch.wall_s, ch.worst), fontsize=8, textcoords="offset points", xytext=(6, -10),
                    color="crimson")
    if math.isfinite(study.reference_wall_s):
        ax.axvline(study.reference_wall_s, color="k", ls=":", lw=1, label="monolithic reference (CVODES)")
    ax.set_xlabel("wall time of the stepping loop [s]")
    ax.set_ylabel("worst error relative to the signal's range [1]")
    ax.set_title(f"{study.scene}: work-precision over {study.stop_time:g} s")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))

    return save_figure(fig, Path(path), dpi=110)
