"""What a user sees of a batch: a progress line while it runs, the results table sorted by a
metric, the spread of each metric over Monte Carlo samples, charts, and every run compared with
one reference trace (``rpr-cosim compare OUT/ REF.csv``).

Charts (PNG in ``<out>/plots/``): ``lines`` (a metric against one axis, a line per value of a
second one), ``heatmap`` (a metric over two axes; a run that failed is a cross, one that did not
settle a grey cell marked inf), ``hist`` (a metric's distribution over the runs) and ``traces``
(one signal of chosen runs overlaid).  Without a ``report.plots`` list the batch gets the ones
that fit its axes.
"""
from __future__ import annotations

import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.tables import text_table
from ..errors import UserError
from .spec import Batch, PlotSpec, axis_units
from ..trace.traces import read_trace
from ..analysis.charts import save_figure
from .results import read_rows
from ..readers import read_json
from ..run.progress import bar


# --- progress ------------------------------------------------------------------------------------
class Progress:
    """The batch's progress bar (tqdm, :func:`cosim.run.progress.bar`): runs done of the total,
    with the running and failed runs beside it; redrawn in place on a terminal, whole lines
    without control characters in a pipe, a widget in a notebook."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self.running: set[str] = set()
        self.saw_start = False
        self.total = self.done = self.failed = self.ran = self.skipped = self.told = 0
        self.capacity = 1
        self.bar = None

    def begin(self, total: int, done: int, failed: int) -> None:
        self.total, self.done, self.failed, self.skipped = total, done, failed, done
        self._tell_skipped()

    def _tell_skipped(self) -> None:
        if self.skipped > self.told:
            self.stream.write(f"[batch] {self.skipped} of {self.total} runs already in the table\n")
            self.told = self.skipped

    def skipped_run(self, ok: bool, duplicate: bool = False) -> None:
        """A run found in the table (done already), or a point that duplicates another (not a run)."""
        if duplicate:
            self.total -= 1
            return
        self.done += 1
        self.skipped += 1
        self.failed += not ok

    def _bar(self):
        if self.bar is None:

            self.bar = bar(self.total, "[batch]", unit="run", stream=self.stream, initial=self.done)
        return self.bar

    def _postfix(self) -> None:
        left = self.total - self.done
        running = len(self.running) if self.saw_start else min(self.capacity, left)
        b = self._bar()
        b.set_postfix_str(f"{running} running, {self.failed} failed", refresh=False)
        b.update(self.done - b.n)

    def show(self) -> None:
        """Show the bar now (e.g. when the runs are handed out)."""
        self._tell_skipped()
        self._postfix()
        self._bar().refresh()

    def started(self, run_id: str) -> None:
        self.saw_start = True
        self.running.add(run_id)
        self._postfix()

    def finished(self, run_id: str, ok: bool, capacity: int = 1) -> None:
        self.running.discard(run_id)
        self.capacity = capacity
        self.done += 1
        self.ran += 1
        self.failed += not ok
        self._postfix()

    def line(self) -> str:
        """The bar's current text."""
        return str(self._bar())

    def end(self) -> None:
        self._tell_skipped()
        if self.done < self.total or self.bar is not None:
            self._postfix()
            self._bar().close()
        self.stream.flush()


# --- tables --------------------------------------------------------------------------------------
def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def sort_rows(rows: Sequence[dict], column: str | None, *, descending: bool = False) -> list[dict]:
    """Rows ok first, by ``column`` (non-numbers and nan last), failed ones after."""
    def key(r):
        v = _num(r.get(column)) if column else None
        bad = r.get("outcome") != "ok"
        missing = v is None or math.isnan(v)
        return (bad, missing, (-v if descending else v) if not missing else 0.0, r.get("index", 0))

    return sorted(rows, key=key)


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def format_results(rows: Sequence[dict], axes: Sequence[str], metrics: Sequence[str], sort: str | None, *,
                   most: int = 20, descending: bool = False) -> str:
    """The table, sorted by ``sort``, ``most`` rows at most (failed runs listed with reasons)."""
    ordered = sort_rows(rows, sort, descending=descending)
    shown_metrics = list(metrics)[:5]
    cols = ["run_id", *axes, "outcome", *shown_metrics, "wall_s"]
    head = {c: (c.split(":", 1)[1] if ":" in c and len(metrics) and len({m.split(":")[0] for m in metrics}) == 1
                else c) for c in cols}
    ok = [r for r in ordered if r.get("outcome") == "ok"][:most]
    cells = [[(_fmt(r.get(c))[:16] if c == "run_id" else _fmt(r.get(c))) for c in cols] for r in ok]
    lines = [text_table([head[c] for c in cols], cells, right=[True] * len(cols))]
    n_ok = sum(r.get("outcome") == "ok" for r in rows)
    if n_ok > most:
        lines.append(f"  ... {n_ok - most} more ok runs in the table")
    bad = [r for r in ordered if r.get("outcome") != "ok"]
    for r in bad[:10]:
        vals = ", ".join(f"{a}={_fmt(r.get(a))}" for a in axes)
        lines.append(f"  {r['outcome']}: {r['run_id']} ({vals}): {r.get('reason')}")
    if len(bad) > 10:
        lines.append(f"  ... {len(bad) - 10} more runs that did not end ok")
    if len(metrics) > len(shown_metrics):
        lines.append(f"  ({len(metrics) - len(shown_metrics)} more metric columns in the table)")
    return "\n".join(lines)


def spread(rows: Sequence[dict], metric: str) -> dict[str, float]:
    """Count, mean, std, min, 5 %, 50 %, 95 % and max of a metric over the ok runs (finite values)."""
    v = np.array([x for r in rows if r.get("outcome") == "ok" and (x := _num(r.get(metric))) is not None
                  and math.isfinite(x)])
    if not len(v):
        return {"n": 0}
    p5, p50, p95 = np.percentile(v, [5, 50, 95])
    return {"n": len(v), "mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "min": float(v.min()), "p5": float(p5), "p50": float(p50), "p95": float(p95), "max": float(v.max())}


def format_spread(rows: Sequence[dict], metrics: Sequence[str]) -> str:
    keys = ("n", "mean", "std", "min", "p5", "p50", "p95", "max")
    cells = []
    for m in metrics:
        s = spread(rows, m)
        cells.append([m] + [f"{s[k]:.4g}" if k in s else "" for k in keys])
    return text_table(["metric", *keys], cells)


# --- plots ---------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_")


def _axis_values(rows: Sequence[dict], axis: str) -> list:
    vals = []
    for r in rows:
        if r.get(axis) not in vals:
            vals.append(r.get(axis))
    numeric = all(_num(v) is not None for v in vals)
    return sorted(vals) if numeric else vals


#: Measures whose unit is their own, not the signal's (:mod:`cosim.batch.metrics`).
_MEASURE_UNITS = {"overshoot": "%", "settling_time": "s"}


def _labelled(name: str | None, units: dict[str, str] | None) -> str | None:
    """``name [unit]`` where ``units`` knows the unit, else ``name``."""
    unit = (units or {}).get(name or "", "")
    return f"{name} [{unit}]" if name and unit else name


def metric_units(out: Path, rows: Sequence[dict], columns: Sequence[str]) -> dict[str, str]:
    """Metric column (``signal:measure``) -> its unit: the measure's own (% for overshoot, s for
    settling time) or the signal's, as the first ok run's sidecar records it."""

    signal_units: dict[str, str] = {}
    for r in rows:
        p = run_trace_path(out, r["run_id"]) if r.get("outcome") == "ok" and r.get("run_id") else None
        if p is not None:
            signal_units = dict(read_trace(p).meta.get("units") or {})
            break
    found = {}
    for col in columns:
        signal, _, measure = col.rpartition(":")
        unit = _MEASURE_UNITS.get(measure) or signal_units.get(signal, "")
        if unit:
            found[col] = unit
    return found


def plot_lines(rows, metric: str, x: str, lines: str | None, others: Sequence[str], path: Path, *,
               scatter: bool = False, units: dict[str, str] | None = None) -> Path:
    """``metric`` against axis ``x``, one line per value of ``lines`` (and of the ``others``
    axes); points only (``scatter``) for a random axis; ``units``: axis or metric -> unit."""
    plt = _plt()
    ok = [r for r in rows if r.get("outcome") == "ok"]
    xs = _axis_values(ok, x)
    numeric = all(_num(v) is not None for v in xs)
    group_axes = [a for a in ([lines] if lines else []) + [a for a in others if a not in (x, lines)]]
    groups: dict[tuple, dict] = {}
    for r in ok:
        groups.setdefault(tuple(r.get(a) for a in group_axes), {})[r.get(x)] = _num(r.get(metric))
    fig, ax = plt.subplots(figsize=(7, 4.2), layout="constrained")
    for key in sorted(groups, key=lambda k: tuple(str(v) if _num(v) is None else v for v in k)):
        pts = groups[key]
        px = [v for v in xs if v in pts]
        label = ", ".join(f"{a}={_fmt(v)}" for a, v in zip(group_axes, key)) or None
        ax.plot([xs.index(v) for v in px] if not numeric else px, [pts[v] for v in px], "o" if scatter else "o-",
                ms=4, label=label)
    if not numeric:
        ax.set_xticks(range(len(xs)), [str(v) for v in xs])
    ax.set_xlabel(_labelled(x, units))
    ax.set_ylabel(_labelled(metric, units))
    ax.grid(alpha=0.3)
    if len(groups) > 1:
        ax.legend(fontsize=8, ncols=2 if len(groups) > 6 else 1)
    ax.set_title(f"{metric} against {x}", fontsize=10)
    return _save(fig, plt, path)


def plot_heatmap(rows, metric: str, x: str, y: str, path: Path, *, units: dict[str, str] | None = None) -> Path:
    """``metric`` over axes ``x`` (columns) and ``y`` (rows); the mean when other axes vary;
    ``units``: axis or metric -> unit."""
    plt = _plt()
    xs, ys = _axis_values(rows, x), _axis_values(rows, y)
    cells: dict[tuple, list] = {}
    failed: set[tuple] = set()
    for r in rows:
        k = (xs.index(r.get(x)), ys.index(r.get(y)))
        if r.get("outcome") != "ok":
            failed.add(k)
            continue
        v = _num(r.get(metric))
        if v is not None:
            cells.setdefault(k, []).append(v)
    grid = np.full((len(ys), len(xs)), np.nan)
    inf = np.zeros_like(grid, bool)
    for (i, j), vs in cells.items():
        m = float(np.mean(vs))
        grid[j, i] = m if math.isfinite(m) else np.nan
        inf[j, i] = math.isinf(m)
    fig, ax = plt.subplots(figsize=(1.0 * len(xs) + 2.5, 0.7 * len(ys) + 1.8), layout="constrained")
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.85")
    fin = grid[np.isfinite(grid)]
    lo, hi = (float(fin.min()), float(fin.max())) if len(fin) else (0.0, 1.0)
    if len(fin) > 4 and hi - lo > 3 * (np.percentile(fin, 90) - lo):  # an outlier would flatten the rest
        hi = float(np.percentile(fin, 90))
    im = ax.imshow(np.ma.masked_invalid(grid), origin="lower", aspect="auto", cmap=cmap, vmin=lo, vmax=hi)
    mid = (lo + hi) / 2
    for j in range(len(ys)):
        for i in range(len(xs)):
            text = "x" if (i, j) in failed else ("inf" if inf[j, i] else (f"{grid[j, i]:.3g}" if np.isfinite(grid[j, i]) else ""))
            ax.text(i, j, text, ha="center", va="center", fontsize=7,
                    color="white" if np.isfinite(grid[j, i]) and grid[j, i] < mid else "black")
    ax.set_xticks(range(len(xs)), [_fmt(v) for v in xs])
    ax.set_yticks(range(len(ys)), [_fmt(v) for v in ys])
    ax.set_xlabel(_labelled(x, units))
    ax.set_ylabel(_labelled(y, units))
    fig.colorbar(im, ax=ax, label=_labelled(metric, units), extend="max" if len(fin) and hi < fin.max() else "neither")
    ax.set_title(metric + (" (x: failed, inf: not settled)" if failed or inf.any() else ""), fontsize=9)
    return _save(fig, plt, path)


def plot_hist(rows, metric: str, path: Path, *, units: dict[str, str] | None = None) -> Path:
    """The distribution of ``metric`` over the ok runs, with its mean and 5-95 % range."""
    plt = _plt()
    s = spread(rows, metric)
    v = [x for r in rows if r.get("outcome") == "ok" and (x := _num(r.get(metric))) is not None and math.isfinite(x)]
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    ax.hist(v, bins=max(5, min(40, int(math.sqrt(len(v))) * 2)) if v else 5, color="C0", alpha=0.8)
    if s["n"]:
        for k, style in (("mean", "-"), ("p5", "--"), ("p95", "--")):
            ax.axvline(s[k], color="C3", ls=style, lw=1.2, label=f"{k} {s[k]:.3g}")
        ax.legend(fontsize=8)
        ax.set_title(f"{metric}: {s['n']} runs, mean {s['mean']:.3g}, std {s['std']:.3g}", fontsize=10)
    ax.set_xlabel(_labelled(metric, units))
    ax.set_ylabel("runs")
    ax.grid(alpha=0.3)
    return _save(fig, plt, path)


def run_dir(out: Path, run_id: str) -> Path:
    """``out/runs/<run_id>``, after checking that the run id read from the batch's table is a
    plain name that resolves inside ``out/runs`` (a table is data: ``../../victim`` or a link
    planted under a run's name is refused in one line, :class:`UserError`)."""
    rid = str(run_id)
    runs = Path(out) / "runs"
    if (not rid or rid in (".", "..") or rid.startswith(".") or any(c in rid for c in "/\\\0")
            or Path(rid).name != rid):
        raise UserError(f"{Path(out) / 'results.csv'}: run_id {rid[:80]!r} is not a run directory name "
                        f"(expected a plain name such as 3f2a9c0d1e4b5a6c)")
    d = runs / rid
    root = runs.resolve()
    if d.exists() and d.resolve().parent != root:
        raise UserError(f"{d}: the run's directory resolves to {d.resolve()}, outside {root}; refusing to read "
                        f"or write through it")
    return d


def run_trace_path(out: Path, run_id: str) -> Path | None:
    """The co-simulation trace of a run (not its reference), confined to ``out/runs``
    (:func:`run_dir`)."""
    d = run_dir(out, run_id)
    found = sorted(p for p in (*d.glob("*.csv"), *d.glob("*.parquet"), *d.glob("*.npy"))
                   if not p.stem.endswith("_reference") and not p.stem.endswith(".prev")) if d.is_dir() else []
    found = [p for p in found if not p.is_symlink() and p.resolve().parent == d.resolve()]
    return found[0] if found else None


#: At most this many runs' traces on one chart (its title says so beyond).
MAX_TRACES = 200


def plot_traces(out: Path, rows, signal: str, runs: Any, sort: str | None, axes: Sequence[str], path: Path) -> Path:
    """``signal`` of the chosen runs overlaid: ``runs`` is a count (first by ``sort``), 'all' or ids."""

    plt = _plt()
    ordered = [r for r in sort_rows(rows, sort) if r.get("outcome") == "ok"]
    if isinstance(runs, list):
        chosen = [r for r in rows if r["run_id"] in runs or r["run_id"][:len(min(runs, key=len))] in runs]
    else:
        chosen = ordered if runs == "all" else ordered[:int(runs)]
    fig, ax = plt.subplots(figsize=(8, 4.5), layout="constrained")
    units: set[str] = set()
    for r in chosen[:MAX_TRACES]:
        p = run_trace_path(out, r["run_id"])
        if p is None:
            continue
        tr = read_trace(p)
        if signal not in tr.columns:
            continue
        units.add((tr.meta.get("units") or {}).get(signal) or "1")
        label = ", ".join(f"{a}={_fmt(r.get(a))}" for a in axes) or r["run_id"]
        ax.plot(tr.time, tr[signal], lw=1, alpha=0.85 if len(chosen) <= 12 else 0.4, label=label)
    if 1 < len(chosen) <= 12:
        ax.legend(fontsize=7)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"{signal} [{', '.join(sorted(units)) or '1'}]")  # the unit the runs' sidecars give
    ax.grid(alpha=0.3)
    shown = f"{len(chosen)} runs" if len(chosen) <= MAX_TRACES else f"the first {MAX_TRACES} of {len(chosen)} runs"
    ax.set_title(f"{signal}: {shown}" + (f" (first by {sort})" if sort and runs != "all" and not isinstance(runs, list) else ""),
                 fontsize=10)
    return _save(fig, plt, path)


def _save(fig, plt, path: Path) -> Path:

    return save_figure(fig, path, dpi=90)


def default_plots(batch: Batch) -> list[PlotSpec]:
    """The charts a batch gets without ``report.plots``."""
    swept = [a.name for a in [*batch.grid, *batch.zip]]
    plots: list[PlotSpec] = []
    for m in batch.metric_columns[:4]:
        if len(swept) >= 2:
            plots.append(PlotSpec("heatmap", m, swept[0], swept[1]))
        if swept:
            plots.append(PlotSpec("lines", m, swept[0], swept[1] if len(swept) > 1 else None))
        if batch.random:
            plots.append(PlotSpec("hist", m))
    if batch.metrics:
        plots.append(PlotSpec("traces", signal=batch.metrics[0].signal, runs=8))
    return plots


def make_plots(batch: Batch, out: Path, rows: Sequence[dict], sort: str | None) -> list[Path]:
    """Write the batch's charts into ``out/plots``; returns their paths."""
    axes = [a.name for a in batch.axes]
    swept = [a.name for a in [*batch.grid, *batch.zip]]
    random = {a.name for a in batch.random}
    specs = batch.plots or default_plots(batch)
    units = {**axis_units(batch), **metric_units(out, rows, [p.metric for p in specs if p.metric])}
    made = []
    for p in specs:
        d = Path(out) / "plots"
        if p.kind == "lines":
            made.append(plot_lines(rows, p.metric, p.x, p.y, swept, d / f"lines_{_safe(p.metric)}_vs_{_safe(p.x)}.png",
                                   scatter=p.x in random, units=units))
        elif p.kind == "heatmap":
            made.append(plot_heatmap(rows, p.metric, p.x, p.y, d / f"heatmap_{_safe(p.metric)}.png", units=units))
        elif p.kind == "hist":
            made.append(plot_hist(rows, p.metric, d / f"hist_{_safe(p.metric)}.png", units=units))
        else:
            made.append(plot_traces(out, rows, p.signal, p.runs, sort, swept or axes, d / f"traces_{_safe(p.signal)}.png"))
    return made


# --- many against one ----------------------------------------------------------------------------
def compare_batch(out: Path, reference, patterns: Sequence[str] | None = None) -> tuple[list[str], list[tuple[dict, list]]]:
    """Every ok run of the batch in ``out`` against one ``reference`` trace: the axes and, per
    run, its row and its :class:`cosim.analysis.trace_diff.Difference` list."""

    from ..analysis.trace_diff import compare

    out = Path(out)
    _, rows = read_rows(out / "results.csv")
    meta = batch_meta(out)
    axes = meta["axes"]
    found = []
    for r in rows:
        if r.get("outcome") != "ok":
            continue
        p = run_trace_path(out, r["run_id"])
        if p is None:
            continue
        found.append((r, compare(read_trace(p), reference, patterns)))
    if not found:
        raise UserError(f"{out}: no finished run with a trace to compare")
    return axes, found


def batch_meta(out: Path) -> dict:
    """``batch.json`` of the batch in ``out``, bounded and typed (:mod:`cosim.readers`):
    ``{"batch": name, "axes": [axis names], "metrics": [metric columns], "axis_units": {axis
    name: unit}}`` (empty without one)."""

    path = Path(out) / "batch.json"
    data = read_json(path, "batch description") if path.exists() else {}
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a JSON object")
    names = {}
    for key, field_ in (("axes", "name"), ("metrics", "column")):
        items = data.get(key) or []
        if not isinstance(items, list) or not all(isinstance(i, dict) and isinstance(i.get(field_), str)
                                                  for i in items):
            raise UserError(f"{path}: '{key}' must be a list of objects with a string '{field_}'")
        names[key] = [i[field_] for i in items]
    units = {i["name"]: i["unit"] for i in data.get("axes") or [] if isinstance(i.get("unit"), str) and i["unit"]}
    return {"batch": str(data.get("batch", Path(out).name)), **names, "axis_units": units}


def format_batch_comparison(axes: Sequence[str], found: Sequence[tuple[dict, list]], *, most: int | None = None) -> str:
    """One line per run, worst relative error first (``most`` lines at most): its axes, worst
    variable and its error."""
    items = []
    for r, diffs in found:
        worst = max(diffs, key=lambda d: d.relative)
        items.append((worst.relative, r, worst))
    items.sort(key=lambda it: -it[0])
    items = items[:most] if most else items
    cells = [[r["run_id"], *[_fmt(r.get(a)) for a in axes], w.name, f"{w.max_abs:.3e}", f"{w.at:.4f}", f"{rel:.2e}"]
             for rel, r, w in items]
    return text_table(["run_id", *axes, "worst variable", "max |diff|", "at t [s]", "max/range"], cells,
                      right=[False, *[True] * len(axes), False, True, True, True])


__all__ = ["Progress", "compare_batch", "default_plots", "format_batch_comparison", "format_results",
           "format_spread", "make_plots", "sort_rows", "spread"]
