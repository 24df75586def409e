"""Validation of the ``master:`` settings (algorithm, step, options, real time), the start and stop
times and the recorded ``outputs``."""
from __future__ import annotations

import fnmatch
import math
import re
from collections.abc import Mapping
from functools import lru_cache

from ..slaves.types import TYPES
from ..master import ALGORITHMS
from .checker import Checker, _is_number
from .keys import DEFAULT_TOLERANCE, ENGINES, INPUT_MODES, MASTER_KEYS, RECORD_MODES
from .model import Component, MasterSettings
from .problems import suggest
from .yamlfile import YList, YMap
from ..master.multirate import rate_problem
from ..master.realtime import RealtimeSettings
from ..master.algorithm import option_values
from ..master.engine import PYTHON_GONE, engine_names


@lru_cache(maxsize=256)
def _output_pattern(pat: str) -> re.Pattern:
    """The regular expression of an ``outputs:`` glob; ``[`` and ``]`` are literal (``leg[*].s``)."""
    return re.compile(fnmatch.translate(pat.replace("[", "\0").replace("]", "\1"))
                      .replace("\0", r"\[").replace("\1", r"\]"))


def _inner(comps: dict[str, Component], pat: str) -> list[str]:
    """The locals of Modelica components (every variable by its Modelica name) an ``outputs:``
    glob reaches: its component part (up to the first dot) matches the component's name and the
    rest the variable's, so ``osc.mass1.*`` and ``osc.*`` reach them and ``motor*.i`` does not
    reach ``motor1.state.i`` (a ``*`` does not cross the component's dot here)."""
    head, dot, tail = pat.partition(".")
    if not dot:
        return []
    comp_rx, var_rx = _output_pattern(head), _output_pattern(tail)
    return [f"{c.name}.{v}" for c in comps.values() if c.fidelity == "modelica" and comp_rx.match(c.name)
            for v in c.description.of("local") if c.description.variables[v].type in TYPES and var_rx.match(v)]


class MasterChecks(Checker):
    """Checks of ``master:``, the times and ``outputs:``."""

    def master(self, comps: dict[str, Component]) -> MasterSettings | None:
        node = self.tree.get("master", YMap())
        if not isinstance(node, YMap):
            self.err(self.tree.loc("master"), f"master must be a mapping (algorithm, step, ...), got {node!r}")
            return None
        self.unknown_keys(node, MASTER_KEYS, "master")
        auto = "algorithm" not in node
        alg = node.get("algorithm", "gauss_seidel")  # auto: the fixed-step default until the run chooses
        ok = True
        tolerance = self.tolerance(node, auto)
        if tolerance is False:
            ok, tolerance = False, None
        tolerance_given = "tolerance" in node and tolerance is not None
        if auto and "options" in node:
            self.err(node.loc("options"), "master.options are an algorithm's options; name master.algorithm too, "
                                          "or drop them and let master.tolerance choose the algorithm")
            ok = False
        if not isinstance(alg, str) or alg not in ALGORITHMS:
            self.err(node.loc("algorithm"), f"unknown master algorithm {alg!r}{suggest(str(alg), ALGORITHMS)} "
                                            f"(known: {', '.join(sorted(ALGORITHMS))})")
            ok = False
        if not node.where[0]:
            node.where = self.tree.where
        default_step = self.fmu_default(comps, "step", "master.step") if "step" not in node else None
        if auto and default_step is None and "step" not in node:  # the first step the choice tries
            default_step = self.number(node, "output_interval", "master.output_interval") or 1e-3
        step = default_step or self.number(node, "step", "master.step", required=True)
        step_ns = None
        if step is not None:
            if not 0 < step <= 1e6:
                self.err(node.loc("step"), f"master.step = {step} must be positive and at most 1e6 (seconds)")
                ok = False
            else:
                step_ns = round(step * 1e9)
                if step_ns < 1 or abs(step_ns - step * 1e9) > 1e-6 * max(1.0, step * 1e9):
                    self.err(node.loc("step"), f"master.step = {step} s is not a whole number of nanoseconds")
                    ok = False
        else:
            ok = False
        engine = node.get("engine", "auto")
        if engine == "python":
            self.err(node.loc("engine"), PYTHON_GONE)
            ok = False
        elif engine not in engine_names():
            self.err(node.loc("engine"), f"master.engine = {engine!r}{suggest(str(engine), ENGINES)}; "
                                         f"expected one of {', '.join(ENGINES)}")
            ok = False
        inputs = node.get("inputs", "hold")
        if inputs not in INPUT_MODES:
            self.err(node.loc("inputs"), f"master.inputs = {inputs!r}{suggest(str(inputs), INPUT_MODES)}; expected "
                                         f"hold (zero-order hold) or linear (inputs interpolated or extrapolated "
                                         f"over the step)")
            ok = False
        record = node.get("record", "grid")
        if record not in RECORD_MODES:
            self.err(node.loc("record"), f"master.record = {record!r}{suggest(str(record), RECORD_MODES)}; expected "
                                         f"grid (a row at every output point) or steps (a row at every step a "
                                         f"variable-step algorithm accepted)")
            ok = False
        order = node.get("order")
        if order is not None:
            if not isinstance(order, list) or not all(isinstance(x, str) for x in order):
                self.err(node.loc("order"), "master.order must be a list of component names")
                ok = False
            else:
                for x in order:
                    if x not in comps:
                        self.err(node.loc("order"), f"master.order names unknown component {x!r}{suggest(x, comps)}")
                        ok = False
                dup = sorted({x for x in order if order.count(x) > 1})
                missing = [c for c in comps if c not in order]
                if dup:
                    self.err(node.loc("order"), f"master.order lists {', '.join(dup)} more than once")
                    ok = False
                if missing and ok:
                    self.err(node.loc("order"), f"master.order must list every component; missing: {', '.join(missing)}")
                    ok = False
        record_every = 1
        if "output_interval" in node and step_ns:
            oi = self.number(node, "output_interval", "master.output_interval")
            if oi is not None:
                k = round(oi * 1e9 / step_ns) if 0 < oi <= 1e9 else 0
                if oi <= 0 or k < 1 or abs(k * step_ns - oi * 1e9) > 1e-6 * oi * 1e9:
                    self.err(node.loc("output_interval"), f"master.output_interval = {oi} s must be a positive "
                                                          f"whole multiple of master.step = {step} s")
                    ok = False
                else:
                    record_every = k
        if step_ns and not self.rates(comps, step_ns, alg):
            ok = False
        if step_ns:
            for comp in comps.values():
                ts, sub = comp.description.sample_period, step / comp.rate
                if ts:
                    n = round(sub / ts)
                    if n < 1 or abs(n * ts - sub) > 1e-9 * max(ts, sub):
                        good = ts * max(1, n) * comp.rate
                        at = f" / rate {comp.rate}" if comp.rate > 1 else ""
                        self.err(node.loc("step"), f"master.step{at} = {sub} s is not a whole multiple of the sample "
                                                   f"period {ts} s of {comp.name} ({comp.label}); a sampled block "
                                                   f"advances whole samples: use e.g. step: {good:g}")
                        ok = False
        realtime = self.realtime(node)
        options = self._algorithm_options(node, alg) if isinstance(alg, str) and alg in ALGORITHMS else {}
        if options is None:
            ok = False
        if not ok or step_ns is None or realtime is False:
            return None
        estimate = node.get("estimate", True)
        if not isinstance(estimate, bool):
            self.err(node.loc("estimate"), f"master.estimate = {estimate!r}; expected true (default: the run estimates "
                                           f"its own error from a companion run) or false (no estimate, half the work)")
            return None
        if not estimate and tolerance_given and not auto:
            self.err(node.loc("estimate"), "master.estimate: false leaves master.tolerance nothing to check a run "
                                           "against; drop one of them")
            return None
        return MasterSettings(alg, step_ns / 1e9, step_ns, list(order) if order else None, engine, record_every,
                              inputs, realtime, options, tolerance, auto, "inputs" in node, estimate, tolerance_given,
                              record)

    def tolerance(self, node: YMap, auto: bool) -> float | None | bool:
        """``master.tolerance``: the worst error of a recorded signal relative to its range that a
        run may have (a number in (0, 0.5)), :data:`DEFAULT_TOLERANCE` when not given, whether the
        scene names its algorithm or not: a run whose estimate is over 10x it is "inaccurate".
        ``none`` (or null): the scene wants no verdict (None; only with a named algorithm, the
        choice needs a tolerance).  False when invalid (reported)."""
        if "tolerance" not in node:
            return DEFAULT_TOLERANCE
        tol = node["tolerance"]
        if tol is None or (isinstance(tol, str) and tol.strip().lower() == "none"):
            if auto:
                self.err(node.loc("tolerance"), "master.tolerance: none (no verdict) needs master.algorithm: the "
                                                "master chooses its algorithm to meet a tolerance")
                return False
            return None
        if not _is_number(tol) or not 0 < tol < 0.5:
            self.err(node.loc("tolerance"), f"master.tolerance = {tol!r}; expected a number in (0, 0.5): the worst "
                                            f"error of a recorded signal relative to its range, e.g. 1e-3 (or none: "
                                            f"no verdict on the run)")
            return False
        return float(tol)

    def rates(self, comps: dict[str, Component], step_ns: int, alg: object) -> bool:
        """``components.X.rate`` (doSteps per macro step, :mod:`cosim.master.multirate`): a whole
        number >= 1 dividing ``master.step`` into whole nanoseconds, for an algorithm that steps
        slaves at several rates.  Sets each component's ``rate``; False when one is wrong (reported)."""

        node, good = self.tree.get("components"), True
        for name, comp in comps.items():
            spec = node.get(name) if isinstance(node, YMap) else None
            if not isinstance(spec, YMap) or "rate" not in spec:
                continue
            problem = rate_problem(spec["rate"], step_ns)
            if problem:
                self.err(spec.loc("rate"), f"component {name!r}: {problem}")
                good = False
                continue
            comp.rate = int(spec["rate"])
            cls = ALGORITHMS.get(alg) if isinstance(alg, str) else None
            if comp.rate > 1 and cls is not None and not getattr(cls, "multirate", False):
                multi = sorted(n for n, c in ALGORITHMS.items() if getattr(c, "multirate", False))
                self.err(spec.loc("rate"), f"component {name!r}: rate = {comp.rate}, but master algorithm {alg} "
                                           f"steps every slave once per step; multirate needs {' or '.join(multi)}")
                good = False
        return good

    def realtime(self, node: YMap):
        """``master.realtime``: true/false or {max_misses: N, spin: S, priority: P}; the settings,
        None (not paced) or False (invalid, reported)."""

        rt = node.get("realtime", False)
        if rt is False or rt is None:
            return None
        if rt is True:
            return RealtimeSettings()
        if not isinstance(rt, Mapping):
            self.err(node.loc("realtime"), f"master.realtime = {rt!r}; expected true, false or "
                                           f"{{max_misses: N, spin: seconds, priority: P}}")
            return False
        bad = [k for k in rt if k not in ("max_misses", "spin", "priority")]
        mm, spin, prio = rt.get("max_misses", 50), rt.get("spin", 300e-6), rt.get("priority", 0)
        whole = [isinstance(v, int) and not isinstance(v, bool) for v in (mm, prio)]
        if bad or not all(whole) or mm < 1 or not 0 <= prio <= 99 or not _is_number(spin) or not 0 <= spin < 0.1:
            self.err(node.loc("realtime"), f"master.realtime = {dict(rt)!r}; expected max_misses: a whole number "
                                           f">= 1, spin: seconds in [0, 0.1), priority: 0 (normal) .. 99 (SCHED_FIFO)")
            return False
        return RealtimeSettings(int(mm), float(spin), int(prio))

    def _algorithm_options(self, node: YMap, alg: str) -> dict[str, float] | None:
        """``master.options`` checked against the options the algorithm declares (None on error)."""
        declared = getattr(ALGORITHMS[alg], "options", ())
        given = node.get("options", YMap())
        if not isinstance(given, YMap):
            self.err(node.loc("options"), f"master.options must be a mapping of option -> value, got {given!r}")
            return None
        if given and not declared:
            self.err(node.loc("options"), f"master algorithm {alg} has no options")
            return None

        try:
            return option_values(dict(given), declared)
        except ValueError as exc:
            bad = next((k for k in given if str(k) in str(exc)), None)
            self.err(given.loc(bad) if bad is not None else node.loc("options"), f"master.options: {exc}")
            return None

    def fmu_default(self, comps: dict[str, Component], key: str, what: str) -> float | None:
        """The FMUs' DefaultExperiment value ``key`` (start, stop, step) when they agree; an error
        naming them when they differ; None when none gives one."""
        given = {c.name: c.description.default_experiment[key] for c in comps.values()
                 if key in c.description.default_experiment}
        if len(set(given.values())) > 1:
            text = ", ".join(f"{n}: {v:g} s" for n, v in given.items())
            self.err(self.tree.where, f"the FMUs' default experiments disagree on the {what} ({text}); set {what} "
                                      f"in the scene")
            return None
        return next(iter(given.values()), None)

    def times(self, master: MasterSettings | None, comps: dict[str, Component]
              ) -> tuple[float | None, int | None, float, int]:
        """(stop_time, n_steps, start_time, start_ns): the scene's values, else the FMUs' default
        experiment; the run goes from start_time to stop_time in whole steps."""
        start, start_ns = 0.0, 0
        if "start_time" in self.tree:
            start = self.number(self.tree, "start_time", "start_time")
        else:
            start = self.fmu_default(comps, "start", "start_time") or 0.0
        if start is not None and not abs(start) < 1e12:
            self.err(self.tree.loc("start_time"), f"start_time = {start} must be a finite number of seconds below 1e12")
            start = None
        if start is not None:
            start_ns = round(start * 1e9)
            if abs(start_ns - start * 1e9) > 1e-6 * max(1.0, abs(start) * 1e9):
                self.err(self.tree.loc("start_time"), f"start_time = {start} s is not a whole number of nanoseconds")
                start = None
        if start is None:
            return None, None, 0.0, 0
        if "stop_time" in self.tree:
            stop = self.number(self.tree, "stop_time", "stop_time")
        else:
            stop = self.fmu_default(comps, "stop", "stop_time")
            if stop is None and not any(p.severity == "error" and "stop_time" in p.message for p in self.problems):
                self.err(self.tree.where, "stop_time is missing; expected a number in seconds (no FMU of the scene "
                                          "gives one in its default experiment)")
        if stop is None:
            return None, None, start, start_ns
        if not stop < 1e12:
            self.err(self.tree.loc("stop_time"), f"stop_time = {stop} must be a finite number of seconds below 1e12")
            return None, None, start, start_ns
        if stop <= start:
            self.err(self.tree.loc("stop_time"), f"stop_time = {stop} must be positive (seconds from the start)"
                     if start == 0 else f"stop_time = {stop} must be after the start time {start} s")
            return None, None, start, start_ns
        if master is None:
            return stop, None, start, start_ns
        span = stop * 1e9 - start_ns
        n = round(span / master.step_ns)
        if abs(n * master.step_ns - span) > 1e-6 * span:
            lo, hi = math.floor(span / master.step_ns), math.ceil(span / master.step_ns)
            self.err(self.tree.loc("stop_time"), f"stop_time = {stop} s is not a whole number of steps of "
                                                 f"{master.step} s{f' from the start {start:g} s' if start else ''}; use "
                                                 f"{start + lo * master.step:g} or {start + hi * master.step:g}")
            return None, None, start, start_ns
        return stop, n, start, start_ns

    def outputs(self, comps: dict[str, Component]) -> list[str]:
        node = self.tree.get("outputs")
        signals = [f"{c.name}.{v}" for c in comps.values() for v in c.description.of("output", "input")
                   if c.description.variables[v].type in TYPES]
        if node is None:
            return [f"{c.name}.{v}" for c in comps.values() for v in c.description.of("output")
                    if c.description.variables[v].type in TYPES]
        if isinstance(node, str):
            node = [node]
        if not isinstance(node, list):
            self.err(self.tree.loc("outputs"), "outputs must be a list of 'component.variable' patterns")
            return []
        every = {f"{c.name}.{v}": var for c in comps.values() for v, var in c.description.variables.items()
                 if var.type in TYPES and var.causality != "independent"}
        out: list[str] = []
        for i, pat in enumerate(node):
            where = node.loc(i) if isinstance(node, YList) else self.tree.loc("outputs")
            if not isinstance(pat, str):
                self.err(where, f"output pattern {pat!r} must be a string 'component.variable'")
                continue
            if pat in every:
                hits = [pat]
            else:
                rx = _output_pattern(pat)
                hits = [s for s in signals if rx.match(s)] + _inner(comps, pat)
            if not hits:
                self.err(where, f"output pattern {pat!r} matches no input or output{suggest(pat, signals)}")
            out.extend(h for h in hits if h not in out)
        return out
