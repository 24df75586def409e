"""``rpr-cosim run``: run a scene and report.

    rpr-cosim run SCENE.yaml [--set PATH=VALUE ...] [--out DIR] [--plot] [--animate] [--check]
                             [--format csv|commented-csv|parquet|npy] [--report]

The trace streams to ``DIR/<scene>.csv`` (default ``DIR`` = ``runs/<scene>``; a plain CSV, or
``<scene>.parquet``) with a sidecar ``<scene>.json``; ``--report`` writes ``<scene>.html``; a progress bar goes to stderr for long runs and a summary table (per-slave
steps and time, real-time factor, final values) to stdout.  A scene with problems prints one
line per problem (``file:line: error: ...``) and exits with code 2; ``--plot`` and ``--animate``
draw in processes of their own (:mod:`cosim.analysis.drawing`), started with the command, and a
figure that fails is one line and exit code 1, the run's files kept; ``--reference`` integrates
in a child forked as the run starts, its files written after the run's; a run that fails or is
interrupted keeps its partial trace and exits with code 1; a run that a component asked to stop
(FMI terminate request) ends with its last point recorded, "stopped by C at t", and code 0.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..outputs import confined
from .verb import interrupted, load_scene, refuse, say, tagged
from fmus.cache import ENV_VAR
from ..scenario import SceneError
from ..outputs import OutputLock, amend_status, check_out_dir, check_set, safe_name
from ..run.execute import check_trace_size, estimate, event_modes
from ..errors import UserError
from ..run.progress import progress_bar
from ..trace.traces import trace_suffix
from ..analysis.animate import animate, pose_component
from ..analysis.charts import setpoint_pairs
from ..analysis.html_report import run_report
from ..scenario.geometry import manipulator_for
from ..scenario.units import units_of
from ..run.reference_files import same_request, write_reference
from ..slaves.plan import component_line
from ..run.choose import kind
from ..master.algorithm import algorithm
from ..master.engine import check_engine
from ..master.estimate import INACCURATE
from ..analysis.tables import text_table
from ..analysis.drawing import DrawError, Drawer, Forked, SharedProgress
from ..interrupts import signals_as_interrupts


def _run(args: argparse.Namespace) -> int:
    import os

    if args.engine is not None:
        check_engine(args.engine)  # python is gone: said before the scene loads
    before = os.environ.get(ENV_VAR)
    if args.cache:  # the scene's catalog components are looked up in this cache's recipe index too
        os.environ[ENV_VAR] = str(args.cache)
    drawer = None
    if (args.plot or args.animate) and not args.check:

        drawer = Drawer()  # imports matplotlib in a process of its own while the scene loads and runs
    try:
        return _load_and_run(args, drawer)
    finally:  # in-process callers (tests, scripts) keep their environment
        if drawer is not None:
            drawer.close()
        if before is None:
            os.environ.pop(ENV_VAR, None)
        else:
            os.environ[ENV_VAR] = before


def _load_and_run(args: argparse.Namespace, drawer=None) -> int:

    try:
        scene = load_scene(args)
    except SceneError as exc:
        return refuse(exc, "run", args.scene)
    for w in scene.warnings:
        say(str(w))


    if args.check:
        _describe(scene)
        refused = _motion_checks(scene, args)
        try:
            _describe_choice(scene)
        except UserError as exc:
            say(f"rpr-cosim run: {exc}")
            return 2
        print(f"  expected: {estimate(scene)}")
        try:
            check_trace_size(scene, args.max_trace)
        except UserError as exc:
            say(f"rpr-cosim run: {exc}")
            return 2
        return 1 if refused else 0
    if _motion_checks(scene, args):
        say("rpr-cosim run: nothing was run")
        return 1
    check_trace_size(scene, args.max_trace)
    out = args.out or Path("runs") / safe_name(scene.name)
    check_out_dir(out)
    check_set(out, safe_name(scene.name))  # before the pilots: a name the run cannot take is one line, nothing run
    early = _EarlyReference(scene) if args.reference else None
    try:
        with OutputLock(out, log=tagged("run")):
            return _run_locked(args, scene, out, drawer, early)
    finally:
        if early is not None:
            early.stop()


class _EarlyReference:
    """The scene's monolithic reference, integrated in a child forked as the run starts (the
    scene loaded, its blocks shared), on the scene's output grid, while the run steps; the run's
    own reference once the run ended if it asks for the same (:func:`cosim.run.reference_files.
    same_request`: a variable-step run lands on the grid, the master's choice keeps it)."""

    def __init__(self, scene):

        self.scene, self.progress = scene, SharedProgress()
        self.job = Forked(_reference_beside, scene, self.progress)

    def result(self, scene, times):
        """The reference asked of ``scene`` (as run) at ``times``, in memory (not yet written),
        or None when the early one is another (it is then computed after the run, as asked) or
        failed (computed again, which says why)."""

        if not same_request(self.scene, scene, times):
            self.stop()
            return None
        bar = progress_bar()

        def waiting() -> None:
            done, total = self.progress.read()
            if total:
                bar(done, total)

        try:
            trace, said = self.job.result(waiting)
        except DrawError:
            return None
        log = tagged("reference")
        for line in said:
            log(line)
        return trace

    def stop(self) -> None:
        self.job.stop()


def _reference_beside(scene, progress) -> tuple:
    """In the early reference's child: the reference in memory and what it logged."""
    from ..run.reference import reference

    said: list[str] = []
    return reference(scene, progress=progress, log=said.append).trace, said


def _run_locked(args: argparse.Namespace, scene, out: Path, drawer=None, early: _EarlyReference | None = None) -> int:
    from ..run.execute import run

    try:
        res = run(scene, out_dir=out, cache_dir=args.cache, engine=args.engine, progress=progress_bar(),
                  log=lambda m: say(f"[run] {m}" if m.startswith(scene.name + ":") or "trace" in m else f"[fmu] {m}"),
                  max_trace_bytes=args.max_trace, trace_format=args.trace_format, call_timeout=args.call_timeout)
    except KeyboardInterrupt as exc:
        say(f"rpr-cosim run: {interrupted(exc)}; the partial trace and the reason "
            f"are in {out / (scene.name + trace_suffix(args.trace_format))}")
        raise
    _summary(res)
    figures = _Figures(drawer, scene, res)
    with figures.interruptible():
        _products(args, scene, res, out, figures)
        ref = _reference(res, out, args.plot, args.trace_format, figures, early) if args.reference else None
        failed = figures.collect()
    if args.report:
        say(f"report: {_report(scene, res, ref, out)}")
    if res.status == "stopped":  # a component asked to end the simulation: a normal end (FMI)
        say(f"rpr-cosim run: {res.reason}")
        return failed
    if not res.ok:
        say(f"rpr-cosim run: {res.status}: {res.reason}")
        return 1
    return failed


class _Figures:
    """The run's figures, drawn beside what follows the run by a :class:`cosim.analysis.drawing.
    Drawer` (in this process without one): each asked for by :meth:`add`, then all collected by
    :meth:`collect`, which names each file once written, or says in one line why it is not."""

    def __init__(self, drawer, scene, res):
        self.drawer, self.scene, self.res = drawer, scene, res
        self._units: dict[str, str] | None = None
        # (label, what, jobs, join, why refused): the figure is join(results of jobs), or jobs[0]'s result
        self.asked: list[tuple[str, str, list[int], Callable | None, str]] = []

    @property
    def units(self) -> dict[str, str]:
        """The run's units (:func:`cosim.scenario.units.units_of` its FMUs), read once for all figures."""
        if self._units is None:

            self._units = units_of(self.res.scene, self.res.fmus)
        return self._units

    @property
    def parallel(self) -> bool:
        """Whether the figures are drawn in processes of their own."""
        return self.drawer is not None and self.drawer.parallel

    def add(self, label: str, what: str, fn, *args, **kwargs) -> None:
        """Ask for a figure (``label`` "plot" or "animation", ``what`` "the plot x.png") drawn by
        ``fn(*args, **kwargs)``, which returns its path."""
        self.add_parts(label, what, None, [(fn, args, kwargs)])

    def add_parts(self, label: str, what: str, join: Callable | None, parts: list[tuple]) -> None:
        """Ask for a figure drawn in parts, each ``(fn, args, kwargs)``, at the same time;
        ``join(results)`` writes it and returns its path."""
        if self.drawer is None:

            self.drawer = Drawer(parallel=False)
        self.asked.append((label, what, [self.drawer.submit(fn, *a, **kw) for fn, a, kw in parts], join, ""))

    def drawing(self) -> bool:
        """Whether a figure asked for is still being drawn (the drawing processes are busy)."""
        return any(not self.drawer.finished(j) for _, _, jobs, _, _ in self.asked for j in jobs)

    def refuse(self, what: str, why: str) -> None:
        """A figure that cannot be drawn from this run (found before drawing), said by :meth:`collect`."""
        self.asked.append(("", what, [], None, why))

    def collect(self) -> int:
        """Wait for every figure and print where it is, or one line saying why it is not (the
        run's trace and sidecar stay as they are); returns 2 when a figure was refused for its
        input, 1 when one failed, else 0."""

        code = 0
        for label, what, jobs, join, why in self.asked:
            try:
                if not jobs:
                    code = max(code, 2)
                    raise DrawError(why)
                results = [self.drawer.result(j) for j in jobs]
                say(f"{label}: {join(results) if join else results[0]}")
            except (DrawError, OSError) as exc:
                code = max(code, 1)
                kept = f"; the run's trace {self.res.trace_path.name} is complete" if self.res.trace_path else ""
                say(f"rpr-cosim run: {what} was not written: {exc}{kept}")
        self.asked.clear()
        return code

    @contextmanager
    def interruptible(self) -> Iterator[None]:
        """A signal while figures are being drawn stops them (an earlier complete file stays as it
        was) and gives the run's sidecar the status "interrupted", naming the figures."""

        try:
            with signals_as_interrupts():
                yield
        except KeyboardInterrupt as exc:
            drawing = [what for _, what, jobs, _, _ in self.asked if not all(self.drawer.finished(j) for j in jobs)]
            if self.drawer is not None:
                self.drawer.stop()
            if drawing:
                doing, res = " and ".join(drawing), self.res
                if res.trace_path is not None:
                    amend_status(res.trace_path, "interrupted",
                                 f"interrupted by {exc or 'the user'} while writing {doing} (the run itself ended "
                                 f"{res.status}; the earlier good run's files, complete, are kept as "
                                 f"{self.scene.name}.prev.*)")
                say(f"rpr-cosim run: {interrupted(exc)} while writing {doing}; "
                    f"{res.trace_path.with_suffix('.json') if res.trace_path else 'the run'} says so")
            raise


def _products(args: argparse.Namespace, scene, res, out: Path, figures: _Figures) -> None:
    """Ask for the plot and the animation of a run (each written under a temporary name and moved
    into place when complete, :func:`cosim.outputs.staged`)."""

    if args.plot and len(res.trace.data):
        from ..analysis.charts import plot_run, setpoint_pairs

        final = confined(out, f"{scene.name}.png")
        figures.add("plot", f"the plot {final.name}", plot_run, res.trace, final, scene.name,
                    units=figures.units, pairs=setpoint_pairs(scene))
    if args.animate and len(res.trace.data):

        final = confined(out, f"{scene.name}.gif")
        try:
            comp = pose_component(res.trace)
            c = scene.components.get(comp)
            m = manipulator_for(c.options, c.params) if c is not None else None
        except UserError as exc:
            figures.refuse(f"the animation {final.name}", str(exc))
            return
        figures.add("animation", f"the animation {final.name}", animate, res.trace, final, manipulator=m,
                    component=comp, title=scene.name)


def _report(scene, res, ref, out: Path) -> Path | str:
    """The run's interactive HTML report (:mod:`cosim.analysis.html_report`), beside its trace."""

    if not len(res.trace.data):
        return "none (the run recorded no rows)"
    m = None
    try:
        c = scene.components.get(pose_component(res.trace))
        m = manipulator_for(c.options, c.params) if c is not None else None
    except UserError:
        pass
    return run_report(res.trace, confined(out, f"{scene.name}.html"), title=f"run {scene.name}",
                      units=units_of(scene, res.fmus), pairs=setpoint_pairs(scene),
                      reference=ref.trace if ref is not None else None, manipulator=m)


def _reference(res, out: Path, plot: bool, trace_format: str, figures: _Figures,
               early: _EarlyReference | None = None):
    """The monolithic reference (the early one when it is the one asked for, else run now), and
    the co-simulation's error against it printed (and its plot asked of ``figures``)."""
    from ..analysis.trace_diff import compare, compare_modes, format_table

    scene = res.scene  # as it ran (the master's choice)
    irregular = res.stats.get("smallest_step") is not None  # variable steps: the reference at the same instants
    times = res.trace.time if irregular and len(res.trace.data) > 1 else None
    early_trace = early.result(scene, times) if early is not None else None
    if early_trace is None:
        from ..run.reference import reference  # CasADi: in this process only without the early reference

        ref = reference(scene, out_dir=out, progress=progress_bar(), log=tagged("reference"), times=times,
                        trace_format=trace_format)
    else:
        ref = write_reference(scene, early_trace, out, trace_format=trace_format, log=tagged("reference"))
    st = ref.stats
    n_events = (st.get("events") or {}).get("count", 0)
    diffs, ev = None, None
    if len(ref.trace.data) and len(res.trace.data):
        diffs, ev = (compare_modes(res.trace, ref.trace, event_modes(scene)) if n_events
                     else (compare(res.trace, ref.trace), None))
        if plot:  # asked for first: drawn while the table is printed
            _plot_comparison(figures, confined(out, f"{scene.name}_vs_reference.png"), res, ref.trace, diffs)
    print(f"monolithic reference ({ref.trace.meta.get('method', 'CVODES')}, {ref.trace.meta.get('states')} states): "
          f"{ref.status}{' (' + ref.reason + ')' if ref.reason else ''}, {st['wall_s']:.2f} s; trace: {ref.trace_path}")
    if diffs is not None:
        for label, r in (("co-simulation", res), ("reference", ref)):
            if r.status != "ok":
                print(f"note: the {label} ended {r.status!r} at t = {r.trace.time[-1]:g} s ({r.reason}); the errors "
                      f"below cover the common span only")
        if ev is not None:
            missing = "; missing: " + ", ".join(f"{n} (co-simulation {a}, reference {b})" for n, (a, b) in
                                                ev.missing.items()) if ev.missing else ""
            worst = (f", largest time error {ev.time_error:.3g} s ({ev.signal}; a counter's or a flag's beyond "
                     f"one recorded interval)") if ev.time_error is not None else ""
            print(f"events: {ev.matched} mode change{'s' if ev.matched != 1 else ''} matched{worst}{missing}")
        print("co-simulation against the reference" + (" (values between events):" if ev is not None else ":"))
        print(format_table(diffs, most=12, estimates=(res.stats.get("estimate") or {}).get("errors")))
        if n_events and ev is None:
            print(f"note: the reference has {n_events} events; the errors above are max-norms across them (a jump "
                  f"placed a hair apart reads as an error its size): `rpr-cosim compare TEST REFERENCE --events "
                  f"SIGNAL` measures the event times and the values between events (docs/explanation/events.md)")
    return ref


def _plot_comparison(figures: _Figures, path: Path, res, ref, diffs) -> None:
    """Ask for the plot of the run against its reference; in two halves drawn at the same time
    when the figures have processes of their own and none is busy (the reference came after the
    other figures were drawn: this one is the last to wait for).  With the chart and the GIF
    still being drawn (the reference integrated beside the run) it is drawn whole: the cores are
    taken, and halves save no CPU (their PNG is encoded here, when they are joined)."""
    from functools import partial

    from ..analysis import charts

    what, kw = f"the plot {path.name}", {"labels": (res.scene.master.algorithm, "reference"), "units": figures.units}
    rows = charts.comparison_rows(diffs)
    if not figures.parallel or rows < 2 or figures.drawing():
        figures.add("plot", what, charts.plot_comparison, res.trace, ref, diffs, path, **kw)
        return
    halves = (range(0, rows // 2), range(rows // 2, rows))
    figures.add_parts("plot", what, partial(charts.join_comparison, path=path),
                      [(charts.comparison_part, (res.trace, ref, diffs, h), kw) for h in halves])


def _motion_checks(scene, args: argparse.Namespace) -> bool:
    """Check every planned task of the scene before it runs (:mod:`models.motion_check`); print
    the result of each, and each refusal as one line.  True when a motion is refused."""
    if not any(c.model == "task_trajectory" for c in scene.components.values()):
        return False  # no planned task: the planners (CasADi, toppra) stay unimported
    from ..analysis.task_report import scene_motion_checks

    refused = False
    for name, _task, traj, result in scene_motion_checks(scene):
        if result.refusal:
            refused = True
            say(f"rpr-cosim run: {args.scene}: component {name!r}: {result.refusal.line()}")
        elif args.check:
            print(f"  motion of {name}: {traj.duration:.6g} s, passes every check ({len(result.t)} samples)")
    return refused


def _describe(scene) -> None:

    def count(n: int, word: str) -> str:
        return f"{n} {word}" + ("" if n == 1 else "s")

    print(f"scene {scene.name}: {count(len(scene.components), 'component')}, "
          f"{count(len(scene.connections), 'connection')} ({count(len(scene.bonds), 'bond')}), "
          + (f"step {scene.master.step:g} s (algorithm chosen below)" if scene.master.auto else
             f"{scene.master.algorithm} at {scene.master.step:g} s") + ", "
          f"stop {scene.stop_time:g} s ({scene.n_steps} steps)")
    for name, c in scene.components.items():
        extra = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in c.start_values().items())
        print(f"  {name:<12} {c.label:<28} {extra}")
        how = component_line(c.description)
        if how:
            print(f"  {'':<12} {how}")
    for c in scene.connections:
        print(f"  {c}" + (f"   [bond {c.bond}]" if c.bond else ""))
    print(f"  outputs: {len(scene.outputs)} ({', '.join(scene.outputs[:6])}{', ...' if len(scene.outputs) > 6 else ''})")
    if scene.guards is not None:
        g = scene.guards
        print(f"  guards: stroke {g.stroke}, rated {g.rated}, singularity {g.singularity} (|det J| < {g.min_det:g} m), "
              f"unstable {g.unstable} (|value| > {g.max_abs:g})")


def _describe_choice(scene) -> None:
    """What the master will run: the scene's algorithm, or the choice from its tolerance."""
    m = scene.master
    if not m.auto:
        tol = (f", tolerance {m.tolerance:g}{'' if m.tolerance_given else ' (the default)'}: a run estimated over "
               f"10x it ends inaccurate" if m.tolerance else ", tolerance none: no verdict on the run's estimate")
        print(f"  master: {m.algorithm}, named by the scene{tol}")
        _describe_events(scene, m.algorithm)
        return

    alg, why = kind(scene)
    what = "rtol" if alg in ("adaptive", "ecco") else "fixed step"
    print(f"  master: tolerance {m.tolerance:g} -> {alg}: {why}; its {what} from pilot runs' error estimates")
    _describe_events(scene, alg)


def _describe_events(scene, name: str) -> None:
    """What the algorithm ``name`` does with the components' events (said when a component has any)."""

    descs = [c.description for c in scene.components.values()]
    if any(d.has_events for d in descs):
        print(f"  events: {algorithm(name).event_policy}")


def verdict(tolerance: float | None, worst: float, status: str) -> str:
    """What the run's estimate ``worst`` says against the scene's ``tolerance`` (one phrase)."""

    if status == "unstable":
        return "unstable (the estimate reaches half a signal's range)"
    if tolerance is None:
        return "none (master.tolerance: none)"
    if worst <= tolerance:
        return f"within the tolerance {tolerance:g}"
    if worst <= INACCURATE * tolerance:
        return (f"{worst / tolerance:.2g}x the tolerance {tolerance:g}, below the {INACCURATE:g}x that makes a run "
                f"inaccurate")
    return f"inaccurate ({worst / tolerance:.2g}x the tolerance {tolerance:g})"


def _summary(res) -> None:
    st = res.stats
    if res.status in ("crashed", "hung"):  # the child process died: no statistics, the rows it wrote
        print(f"scene {res.scene.name} [{res.scene.hash[:12]}]: {res.status} ({res.reason})")
        print(f"  {len(res.trace.data)} whole rows kept" + (f"; trace: {res.trace_path}" if res.trace_path else ""))
        return
    n = max(1, st["steps_done"])
    print(f"scene {res.scene.name} [{res.scene.hash[:12]}]: {res.status}"
          + (f" ({res.reason})" if res.reason else ""))
    choice = st.get("choice")
    if choice:
        sets = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in choice["settings"].items())
        print(f"  master chose {choice['algorithm']} ({sets}) for tolerance {choice['tolerance']:g}: {choice['why']}"
              + (f" [{len(choice['pilots'])} pilot run{'s' if len(choice['pilots']) != 1 else ''}]"
                 if choice.get("pilots") else ""))
    print(f"  {st['algorithm']} ({st['engine']} loop), step {st['step']:g} s, {st['steps_done']}/{st['steps_planned']} "
          f"steps, simulated {st['simulated_s']:.6g} s in {st['wall_s']:.3f} s "
          f"(real-time factor {st['real_time_factor']:.1f}); build {res.build_s:.2f} s, init {st['init_s']:.3f} s")
    est = st.get("estimate")
    if est:
        if est.get("worst") is None:
            print(f"  no error estimate: {est.get('method')}")
        else:
            print(f"  estimated worst error {est['worst']:.2g} of range, {est['signal']} (at t = {est['at']:.6g} s; "
                  f"{est['method']})")
            print(f"  verdict: {verdict(res.scene.master.tolerance, est['worst'], res.status)}")

    total = st["wall_s"] or 1.0
    cells = []
    for name, s in st["slaves"].items():
        comp = res.scene.components.get(name)
        cells.append([name, comp.label if comp else "", str(s["do_step_calls"]), f"{1e3 * s['wall_s']:.2f}",
                      f"{1e6 * s['wall_s'] / n:.2f}", f"{100 * s['wall_s'] / total:.1f}%"])
    cells.append(["master", "", "", f"{1e3 * st['master_s']:.2f}", f"{1e6 * st['master_s'] / n:.2f}",
                  f"{100 * st['master_s'] / total:.1f}%"])
    print(text_table(["slave", "FMU", "doStep", "time ms", "us/step", "share"], cells,
                     right=[False, False, True, True, True, True]))
    if st.get("smallest_step") is not None:
        print(f"  variable step: {st['smallest_step']:.3g} .. {st['largest_step']:.3g} s, "
              f"{st.get('rejected_steps', 0)} rejected")
    for name, b in st.get("bonds", {}).items():  # ecco
        print(f"  bond {name}: largest scaled energy residual {b['max_scaled_residual']:.3g}, "
              f"{b['steps_over_tolerance']} steps over tolerance, net {b['energy_residual_sum_J']:+.3g} J "
              f"of {b['energy_J']:.3g} J carried")
    rt = st.get("realtime")
    if rt:
        print(f"  real time: lateness p50 {1e6 * rt['lateness_p50_s']:.0f} us, p99 {1e6 * rt['lateness_p99_s']:.0f} us, "
              f"max {1e6 * rt['lateness_max_s']:.0f} us; {rt['missed_deadlines']} missed deadlines of "
              f"{rt['paced_steps']} paced steps" + (f"; scheduling priority: {rt['priority']}" if rt.get("priority")
                                                     else ""))
        for name, fig in rt.get("slaves", {}).items():
            shown = ", ".join(f"{k} {1e6 * v:.0f} us" if k.startswith(("tick", "cpu")) else f"{k} {v:g}"
                              for k, v in fig.items())
            print(f"  real time of {name}: {shown}")
    events = st.get("events") or {}
    for note in (events.get("notes") or [])[:5]:
        print(f"  note: {note}")
    if len(events.get("late") or []) > 5:
        print(f"  note: {len(events['late']) - 5} more events reached a component late (the sidecar's events.late)")
    for w in st.get("guards", {}).get("warnings", []):
        print(f"  guard warning: {w}")
    for g, how in st.get("guards", {}).get("applied", {}).items():
        if "catalog identity" in how:  # external FMUs the guards know nothing of
            print(f"  guard {g}: {how}")
    final = res.trace.final()
    if final:
        t_end = res.trace.time[-1]
        print(f"  final values at t = {t_end:.6g} s:")
        width = max(len(k) for k in final)
        for k, v in final.items():
            print(f"    {k:<{width}} {v: .6g}")
    if res.trace_path:
        print(f"  trace: {res.trace_path}")
