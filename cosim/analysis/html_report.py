"""Interactive reports: one HTML file per run, batch or study, opening offline.

Plotly draws every chart; its library (``plotly-<version>.min.js``, 4.8 MB, from the plotly
package) is written once beside the reports of a directory and loaded from there, so a report
needs no network and no server: copy it with that file beside it.  Inlined in every page it made
pid_step's report 13 MB.

A run's signals are kept once in the page, at full resolution, as base64 typed arrays (the time
in float64; each column in float32 as its offset from its mid-range, so its precision is its
range / 1.7e7; the error against the reference computed in float64 and kept in float32); the
browser draws each line min/max-decimated to the pixels of the visible span (every extreme kept)
and again on each zoom, so zooming in shows every recorded row (pid_step: 1.3 MB instead of 13).

- :func:`run_report`: the recorded signals on linked, zoomable time axes (one panel per group of
  like signals, :func:`cosim.analysis.charts.run_panels`, each y axis in its unit, setpoints
  dashed in the colour of the signal they command), the monolithic reference overlaid with the
  error in a second column when given, the manipulator's animation (Plotly frames, a slider and
  a play button) beside the plots, and the run's status, reason and statistics.
- :func:`batch_report`: the results table (click a header to sort), a heat map or a line chart
  of each metric over the axes, and the traces of the run a point belongs to, shown below on
  click (the traces are embedded, decimated to at most ``max_points``), with a link to that
  run's own report where one was written.
- :func:`study_report`: the work-precision chart (worst error against wall time, a line per
  algorithm variant) of a ``study precision`` table, or the stability map of a
  ``study stability`` table (one panel per variant, hover: step, value, outcome, reason).

Written with pure functions of the data (a trace, a table's rows); the verbs pass them in.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..trace.traces import Trace, read_trace
from .charts import run_panels
from .safe_html import href, label, script_json, text
from ..errors import UserError
from ..outputs import write_text
from .animate import joints, pose_component
from models.geometry import preset

#: Colours of the lines of one panel (Plotly's default cycle).
COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
           "#bcbd22", "#17becf")

_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<script src="{plotly_file}" charset="utf-8"></script>
<style>
body {{ font-family: system-ui, sans-serif; margin: 1.2em; color: #222; }}
h1 {{ font-size: 1.4em; }} h2 {{ font-size: 1.1em; margin-top: 1.4em; }}
.status-ok {{ color: #1a7f37; font-weight: bold; }} .status-bad {{ color: #b42318; font-weight: bold; }}
.row {{ display: grid; grid-template-columns: minmax(0, 3fr) minmax(320px, 1fr); gap: 1em; align-items: start; }}
.plots, .side {{ min-width: 0; overflow: hidden; }} .side {{ position: sticky; top: 0; }}
@media (max-width: 900px) {{ .row {{ grid-template-columns: minmax(0, 1fr); }} .side {{ position: static; }} }}
table {{ border-collapse: collapse; font-size: 0.85em; }}
th, td {{ border: 1px solid #ccc; padding: 2px 6px; text-align: right; }}
th {{ background: #f3f3f3; cursor: pointer; }} td.text {{ text-align: left; }}
.note {{ color: #555; font-size: 0.85em; }}
</style></head><body>
<h1>{title}</h1>
{body}
<p class="note">rpr-cosim report, written {written}. Plotly {plotly_version}, from {plotly_file} beside this file: it opens offline.</p>
</body></html>
"""


def _status_html(status: str, reason: str) -> str:
    cls = "status-ok" if status == "ok" else "status-bad"
    return (f'<p>status: <span class="{cls}" id="run-status">{text(status or "unknown")}</span>'
            + (f" &mdash; {text(reason)}" if reason else "") + "</p>")


def _figure_html(fig, div_id: str, first: bool) -> str:
    import plotly.io as pio

    return pio.to_html(fig, include_plotlyjs=False, full_html=False, div_id=div_id,
                       config={"displaylogo": False, "responsive": True})


def _page(path: Path, title: str, body: str, library_dir: Path | None = None) -> Path:
    import time

    import plotly

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    import os

    library = Path(library_dir or path.parent) / f"plotly-{plotly.__version__}.min.js"
    page = _PAGE.format(title=text(title), body=body, written=time.strftime("%Y-%m-%d %H:%M:%S %Z"),
                        plotly_version=plotly.__version__,
                        plotly_file=text(href(os.path.relpath(library, path.parent))))

    try:  # a new temporary file renamed into place: whole or nothing, never through a planted link
        library.parent.mkdir(parents=True, exist_ok=True)  # a batch's library folder may not exist yet
        _library(library)
        write_text(path, page)
    except OSError as exc:
        raise UserError(f"cannot write the report {path} ({exc.strerror or exc})") from None
    return path


def _library(path: Path) -> None:
    """Plotly's JavaScript at ``path``, written once (kept when it is already there, whole)."""
    from plotly.offline import get_plotlyjs


    js = get_plotlyjs()
    if path.is_file() and not path.is_symlink() and path.stat().st_size == len(js.encode()):
        return
    write_text(path, js)


def decimate(n: int, max_points: int) -> np.ndarray:
    """Indices of at most ``max_points`` rows out of ``n``, evenly spread, first and last kept."""
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).round().astype(int))


def _unit(name: str, units: Mapping[str, str]) -> str:
    u = units.get(name, "")
    return f" [{u}]" if u else ""


# --- a run --------------------------------------------------------------------------------------
def signals_figure(trace: Trace, *, units: Mapping[str, str] | None = None,
                   pairs: Mapping[str, str] | None = None, reference: Trace | None = None, max_points: int = 20000):
    """The run's signals, one panel per :func:`run_panels` group, on one shared (linked) time
    axis; with ``reference`` its trace dotted over each signal and the difference (run minus
    reference, the reference interpolated to the run's instants) in a second column."""
    from plotly.subplots import make_subplots
    import plotly.graph_objects as go

    units = dict(units or trace.meta.get("units") or {})
    panels = run_panels(trace.names, units, pairs)
    ref = reference if reference is not None and len(reference.data) else None
    ncol = 2 if ref is not None else 1
    titles = []
    for p in panels:
        titles.append(p.title)
        if ncol == 2:
            titles.append(f"{p.title}: error against the reference")
    fig = make_subplots(rows=len(panels), cols=ncol, shared_xaxes="all", vertical_spacing=min(0.06, 0.3 / len(panels)),
                        horizontal_spacing=0.08, subplot_titles=titles)
    idx = decimate(len(trace.time), max_points)
    t = trace.time[idx]
    for row, panel in enumerate(panels, 1):
        colour: dict[str, str] = {}
        for i, (name, dashed) in enumerate(panel.lines):
            c = colour.get((pairs or {}).get(name, ""), COLOURS[i % len(COLOURS)]) if dashed else COLOURS[i % len(COLOURS)]
            colour[name] = c
            label = f"{name} (setpoint)" if dashed else name
            fig.add_trace(go.Scattergl(x=t, y=trace[name][idx], name=label + _unit(name, units), mode="lines",
                                       line={"color": c, "width": 1.3, "dash": "dash" if dashed else "solid"},
                                       legendgroup=name, meta={"col": name, "kind": "run"}, hovertemplate=f"{name}<br>t = %{{x:.6g}} s<br>%{{y:.6g}}"
                                       f"{_unit(name, units)}<extra></extra>"),
                          row=row, col=1)
            if ref is not None and not dashed and name in ref.columns:
                r = np.interp(trace.time, ref.time, ref[name])
                fig.add_trace(go.Scattergl(x=ref.time[decimate(len(ref.time), max_points)],
                                           y=ref[name][decimate(len(ref.time), max_points)],
                                           name=f"{name} (reference)", mode="lines", legendgroup=name,
                                           meta={"col": name, "kind": "ref"},
                                           line={"color": c, "width": 1, "dash": "dot"}), row=row, col=1)
                fig.add_trace(go.Scattergl(x=t, y=(trace[name] - r)[idx], name=f"{name} - reference",
                                           mode="lines", legendgroup=name, showlegend=False,
                                           meta={"col": name, "kind": "err"},
                                           line={"color": c, "width": 1}), row=row, col=2)
        fig.update_yaxes(title_text=panel.ylabel, title_font={"size": 10}, row=row, col=1)
        if ncol == 2:
            fig.update_yaxes(title_text=f"error{_unit(panel.lines[0][0], units)}", title_font={"size": 10},
                             row=row, col=2)
    fig.update_xaxes(title_text="time [s]", row=len(panels))
    fig.update_layout(height=max(360, 230 * len(panels)), margin={"l": 60, "r": 20, "t": 40, "b": 40},
                      legend={"font": {"size": 9}}, hovermode="closest", template="plotly_white")
    return fig


def animation_figure(trace: Trace, manipulator=None, component: str | None = None, max_frames: int = 120):
    """The platform and legs over the run as Plotly frames (play button and time slider); legs
    outside their stroke are red (see :mod:`cosim.analysis.animate`)."""
    import plotly.graph_objects as go


    comp = component or pose_component(trace)
    m = manipulator or preset("cross_leg")
    t = trace.time
    idx = np.unique(np.searchsorted(t, np.linspace(t[0], t[-1], max(2, min(max_frames, len(t))))).clip(0, len(t) - 1))
    q = np.vstack([trace[f"{comp}.platform.{k}"][idx] for k in ("x", "y", "phi")])
    A, B, L = joints(m, q)
    pts = np.vstack([A, B.reshape(-1, 2)])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.08 * float(np.max(hi - lo))

    def state(k: int) -> list:
        legs = [go.Scatter(x=[A[i, 0], B[k, i, 0]], y=[A[i, 1], B[k, i, 1]], mode="lines",
                           line={"width": 5, "color": "#2ca02c" if m.Lmin <= L[k, i] <= m.Lmax else "#d62728"},
                           name=f"leg {i + 1}: {L[k, i]:.4f} m", hoverinfo="name") for i in range(3)]
        plat = go.Scatter(x=[*B[k, :, 0], B[k, 0, 0]], y=[*B[k, :, 1], B[k, 0, 1]], fill="toself", mode="lines",
                          line={"color": "black"}, fillcolor="rgba(255,127,14,0.6)", name="platform",
                          hovertext=f"x = {q[0, k]:.4f} m, y = {q[1, k]:.4f} m, phi = {q[2, k]:+.4f} rad",
                          hoverinfo="text")
        path = go.Scatter(x=q[0, :k + 1], y=q[1, :k + 1], mode="lines", line={"color": "#1f77b4", "width": 1},
                          name="centre path", hoverinfo="skip")
        return [*legs, plat, path]

    base = go.Scatter(x=[*A[:, 0], A[0, 0]], y=[*A[:, 1], A[0, 1]], mode="markers+lines+text",
                      text=["A1", "A2", "A3", ""], textposition="top right", marker={"symbol": "square", "size": 9,
                                                                                   "color": "black"},
                      line={"dash": "dot", "color": "#999"}, name="fixed joints", hoverinfo="skip",
                      cliponaxis=False)  # a joint's label at the range's edge is drawn whole, in the margin
    frames = [go.Frame(data=state(k), name=f"{t[i]:.4g}", traces=[1, 2, 3, 4, 5]) for k, i in enumerate(idx)]
    fig = go.Figure(data=[base, *state(0)], frames=frames)
    steps = [{"args": [[f.name], {"frame": {"duration": 0, "redraw": False}, "mode": "immediate"}],
              "label": f.name, "method": "animate"} for f in frames]
    fig.update_layout(
        # the title just above the plot area, below the toolbar (the top 30 px of the 70 px margin)
        title={"text": f"{comp}: platform and legs", "font": {"size": 13}, "x": 0.01, "xanchor": "left",
               "yref": "paper", "y": 1.0, "yanchor": "bottom", "pad": {"b": 8}}, template="plotly_white",
        xaxis={"range": [lo[0] - pad, hi[0] + pad], "title": "x [m]"},
        yaxis={"range": [lo[1] - pad, hi[1] + pad], "title": "y [m]", "scaleanchor": "x", "scaleratio": 1},
        height=540, showlegend=False, margin={"l": 50, "r": 30, "t": 70, "b": 40},
        updatemenus=[{"type": "buttons", "x": 0, "y": -0.12, "xanchor": "left", "buttons": [
            {"label": "play", "method": "animate",
             "args": [None, {"frame": {"duration": 60, "redraw": False}, "fromcurrent": True}]},
            {"label": "pause", "method": "animate",
             "args": [[None], {"frame": {"duration": 0, "redraw": False}, "mode": "immediate"}]}]}],
        sliders=[{"steps": steps, "x": 0.25, "len": 0.75, "y": -0.05, "currentvalue": {"prefix": "t = ", "suffix": " s"}}])
    return fig


#: The statistics a run report shows: key -> (label, unit); the glossary of docs/reference/results.md
#: explains each.
STAT_LABELS = {
    "algorithm": ("master algorithm", ""), "engine": ("stepping loop", ""), "step": ("communication step", "s"),
    "steps_done": ("steps taken", ""), "steps_planned": ("steps planned", ""),
    "simulated_s": ("simulated time", "s"), "wall_s": ("wall time of the stepping", "s"),
    "real_time_factor": ("real-time factor (simulated / wall time)", ""), "init_s": ("initialisation time", "s"),
    "master_s": ("master's own time (exchange, extrapolation)", "s"), "accepted_steps": ("accepted steps", ""),
    "rejected_steps": ("rejected steps", ""), "rollbacks": ("rollbacks", ""),
    "smallest_step": ("smallest step", "s"), "largest_step": ("largest step", "s"),
}


def _estimate_html(stats: Mapping) -> str:
    """The run's own error estimate (:mod:`cosim.master.estimate`): the worst signal, then the
    five largest, each relative to the signal's range."""
    est = stats.get("estimate") if isinstance(stats.get("estimate"), dict) else {}
    if not est:
        return ""
    if not isinstance(est.get("worst"), (int, float)):
        return f"<h2>error estimate</h2><p>none: {text(est.get('method', ''))}</p>"
    errors = est.get("errors") if isinstance(est.get("errors"), dict) else {}
    errs = sorted(((n, e) for n, e in errors.items() if isinstance(e, (int, float))), key=lambda kv: -kv[1])[:5]
    rows = "".join(f"<tr><td class='text'>{text(n)}</td><td>{e:.3g}</td></tr>" for n, e in errs)
    at = f" at t = {est['at']:.6g} s" if isinstance(est.get("at"), (int, float)) else ""
    return (f"<h2>error estimate</h2><p>worst {est['worst']:.3g} of its range on "
            f"<b>{text(est.get('signal', ''))}</b>{at} ({text(est.get('method', ''))})</p>"
            f"<table><tr><th>signal</th><th>estimated error [of range]</th></tr>{rows}</table>")


def _setting(p: Mapping) -> str:
    """A pilot's setting (``step 0.001`` or ``rtol 1e-05, h_max 0.01``)."""
    return ", ".join(f"{k} {v:.3g}" for k, v in p.items()
                     if k not in ("estimate", "window_s") and isinstance(v, float))


def _choice_html(stats: Mapping) -> str:
    """What the master chose for the scene's tolerance (:mod:`cosim.run.choose`), with its pilots."""
    ch = stats.get("choice") if isinstance(stats.get("choice"), dict) else {}
    if not ch:
        return ""
    settings = ch.get("settings") if isinstance(ch.get("settings"), dict) else {}
    sets = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in settings.items())
    pilots = "".join(f"<tr><td class='text'>{text(_setting(p))}</td><td>{text(_fmt(p.get('window_s')))}</td>"
                     f"<td>{text(_fmt(p.get('estimate')))}</td></tr>"
                     for p in ch.get("pilots") or () if isinstance(p, dict))
    tol = ch.get("tolerance")
    out = (f"<h2>the master's choice</h2><p>{text(ch.get('algorithm', ''))} ({text(sets)}) for tolerance "
           f"{text(_fmt(tol))}: {text(ch.get('why', ''))}</p>")
    if pilots:
        out += (f"<table><tr><th>pilot setting</th><th>span [s]</th><th>estimated error [of range]</th></tr>"
                f"{pilots}</table>")
    return out


def _stats_table(stats: Mapping) -> str:
    rows = "".join(f"<tr><td class='text'>{name}</td><td>{text(_fmt(stats[k]))}"
                   f"{' ' + unit if unit and stats[k] is not None else ''}</td></tr>"
                   for k, (name, unit) in STAT_LABELS.items() if k in stats)
    slaves = stats.get("slaves") if isinstance(stats.get("slaves"), dict) else {}
    srows = "".join(f"<tr><td class='text'>{text(n)}</td><td>{text(_fmt(s.get('do_step_calls', '')))}</td>"
                    f"<td>{text(_fmt(_ms(s.get('wall_s'))))}</td></tr>"
                    for n, s in slaves.items() if isinstance(s, dict))
    out = (_estimate_html(stats) + _choice_html(stats)
           + f"<h2>statistics</h2><table id='stats'><tr><th>statistic</th><th>value</th></tr>{rows}</table>")
    if srows:
        out += (f"<h2>slaves</h2><table><tr><th>slave</th><th>doStep calls</th><th>time in doStep [ms]</th></tr>"
                f"{srows}</table>")
    guards = stats.get("guards") if isinstance(stats.get("guards"), dict) else {}
    warnings = guards.get("warnings") if isinstance(guards.get("warnings"), list) else []
    if warnings:
        out += "<h2>guard warnings</h2><ul>" + "".join(f"<li>{text(w)}</li>" for w in warnings) + "</ul>"
    return out


def _ms(seconds) -> float | str:
    """``seconds`` in milliseconds, or the text as it was when it is not a number."""
    try:
        return 1e3 * float(seconds)
    except (TypeError, ValueError):
        return "" if seconds is None else str(seconds)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return "" if v is None else str(v)


def run_report(trace: Trace, path: Path, *, title: str = "", units: Mapping[str, str] | None = None,
               pairs: Mapping[str, str] | None = None, reference: Trace | None = None, manipulator=None,
               max_points: int = 20000, library_dir: Path | None = None) -> Path:
    """Write the report of one run (module docstring) to ``path``; returns the path.  Plotly's
    library goes to ``library_dir`` (default beside the report: a batch's run reports share the
    batch's)."""

    if not len(trace.data):
        raise UserError(f"{path}: the run recorded no rows; nothing to report")
    title = title or f"run {trace.meta.get('scene', Path(path).stem)}"
    shown, ref = _labelled(trace), _labelled(reference)
    fig = signals_figure(shown, units=_labels(units), pairs=_labels(pairs), reference=ref, max_points=2)
    for tr in fig.data:  # drawn by the browser from the full-resolution data (module docstring)
        tr.x, tr.y = [], []
    figs = [_figure_html(fig, "signals", True) + _ZOOM_JS % script_json(full_resolution(shown, ref))]
    side = ""
    try:
        side = _figure_html(animation_figure(_labelled(trace), manipulator), "animation", False)
    except UserError as exc:  # no platform pose recorded
        side = f"<p class='note'>no animation: {text(exc)}</p>"
    ref_note = ""
    if reference is not None:
        ref_note = (f"<p>reference: {text(reference.meta.get('method', 'monolithic'))}, "
                    f"status {text(reference.status or 'unknown')}</p>")
    meta = trace.meta
    head = (f"<p>scene <b>{text(meta.get('scene', ''))}</b> "
            f"[{text(str(meta.get('scene_hash', ''))[:12])}]"
            + (f", started {text(meta['started'])}" if meta.get("started") else "")
            + (f", {text(meta['algorithm'])}" if meta.get("algorithm") else "") + "</p>"
            + _status_html(trace.status, trace.reason) + ref_note)
    body = (f"{head}<div class='row'><div class='plots'>{figs[0]}</div><div class='side'>{side}"
            f"{_stats_table(trace.stats)}</div></div>")
    return _page(path, title, body, library_dir)


def _b64(a: np.ndarray, dtype: str) -> str:
    import base64

    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _offsets(data: np.ndarray) -> tuple[list[float], list[str]]:
    """Columns of ``data`` as (mid-range, base64 float32 offsets from it): precision range / 1.7e7."""
    mids, cols = [], []
    for col in data.T:
        fin = col[np.isfinite(col)]
        mid = float(0.5 * (fin.min() + fin.max())) if len(fin) else 0.0
        mids.append(mid)
        cols.append(_b64(col - mid, "<f4"))
    return mids, cols


def full_resolution(trace: Trace, reference: Trace | None = None) -> dict:
    """Every row of ``trace`` (and of ``reference``, with the error against it at the trace's
    instants) as the compact base64 arrays the run report's page draws from (module docstring)."""
    mids, cols = _offsets(trace.data[:, 1:])
    out = {"t": _b64(trace.time, "<f8"), "names": trace.names, "mid": mids, "v": cols, "err": {}, "ref": None}
    if reference is not None and len(reference.data):
        common = [n for n in trace.names if n in reference.columns]
        err = np.column_stack([trace[n] - np.interp(trace.time, reference.time, reference[n]) for n in common]) \
            if common else np.zeros((len(trace.time), 0))
        out["err"] = {n: _b64(err[:, k], "<f4") for k, n in enumerate(common)}
        if np.array_equal(reference.time, trace.time):  # the reference is the run minus the error: kept once
            out["ref"] = "same"
        else:
            rmids, rcols = _offsets(reference.data[:, 1:])
            out["ref"] = {"t": _b64(reference.time, "<f8"), "names": reference.names, "mid": rmids, "v": rcols}
    return out


#: The run report's drawing: decode the arrays, then draw each line min/max-decimated to about
#: two points per pixel of the visible span, again on every zoom or pan (every row when zoomed in).
_ZOOM_JS = r"""<script>
window.addEventListener('load', function () {
  var D = %s, gd = document.getElementById('signals');
  function arr(s, T) { var b = atob(s), u = new Uint8Array(b.length);
    for (var i = 0; i < b.length; i++) u[i] = b.charCodeAt(i); return new T(u.buffer); }
  function cols(src) { var o = {}; src.names.forEach(function (n, k) {
    var v = arr(src.v[k], Float32Array), m = src.mid[k], y = new Float64Array(v.length);
    for (var i = 0; i < v.length; i++) y[i] = v[i] + m; o[n] = y; }); return o; }
  var t = arr(D.t, Float64Array), run = cols(D), err = {}, rt = null, ref = {};
  Object.keys(D.err).forEach(function (n) { var e = arr(D.err[n], Float32Array), y = new Float64Array(e.length);
    for (var i = 0; i < e.length; i++) y[i] = e[i]; err[n] = y; });
  if (D.ref === 'same') { rt = t; Object.keys(err).forEach(function (n) { var y = new Float64Array(t.length);
    for (var i = 0; i < t.length; i++) y[i] = run[n][i] - err[n][i]; ref[n] = y; }); }
  else if (D.ref) { rt = arr(D.ref.t, Float64Array); ref = cols(D.ref); }
  function series(meta) {
    if (meta.kind === 'ref') return [rt, ref[meta.col]];
    return [t, meta.kind === 'err' ? err[meta.col] : run[meta.col]];
  }
  function first(x, v) { var lo = 0, hi = x.length; while (lo < hi) { var m = (lo + hi) >> 1;
    if (x[m] < v) lo = m + 1; else hi = m; } return lo; }
  function view(x, y, a, b, buckets) {
    var j = first(x, b); while (j < x.length && x[j] <= b) j++;  // one row beyond the span each side
    var i0 = Math.max(0, first(x, a) - 1), i1 = Math.min(x.length, j + 1), n = i1 - i0;
    var xs = [], ys = [];
    if (n <= 2 * buckets) { for (var i = i0; i < i1; i++) { xs.push(x[i]); ys.push(y[i]); } return [xs, ys]; }
    for (var k = 0; k < buckets; k++) {
      var s = i0 + Math.floor(k * n / buckets), e = i0 + Math.floor((k + 1) * n / buckets), lo = s, hi = s;
      for (var j = s; j < e; j++) { if (y[j] < y[lo]) lo = j; if (y[j] > y[hi]) hi = j; }
      var p = Math.min(lo, hi), q = Math.max(lo, hi);
      xs.push(x[p]); ys.push(y[p]); if (q !== p) { xs.push(x[q]); ys.push(y[q]); }
    }
    return [xs, ys];
  }
  var busy = false;
  function draw(a, b) {
    var buckets = Math.max(200, Math.round(gd.clientWidth || 1000)), X = [], Y = [], idx = [];
    gd.data.forEach(function (tr, k) { var s = series(tr.meta || {}); if (!s[0] || !s[1]) return;
      var v = view(s[0], s[1], a, b, buckets); X.push(v[0]); Y.push(v[1]); idx.push(k); });
    busy = true; Plotly.restyle(gd, {x: X, y: Y}, idx); busy = false;
  }
  draw(-Infinity, Infinity);
  gd.on('plotly_relayout', function (ev) {
    if (busy) return;
    var key = Object.keys(ev).filter(function (k) { return /^xaxis\d*\.range\[0\]$/.test(k); })[0];
    if (key) { draw(ev[key], ev[key.replace('[0]', '[1]')]); return; }
    var r = Object.keys(ev).filter(function (k) { return /^xaxis\d*\.range$/.test(k); })[0];
    if (r) { draw(ev[r][0], ev[r][1]); return; }
    if (Object.keys(ev).some(function (k) { return /^xaxis\d*\.autorange$/.test(k); })) draw(-Infinity, Infinity);
  });
  gd.dataset.drawn = 'yes';
});
</script>"""


def _labels(mapping: Mapping | None) -> dict[str, str] | None:
    """``mapping``'s keys and values as Plotly labels (:func:`cosim.analysis.safe_html.label`)."""
    if not isinstance(mapping, Mapping):
        return None
    return {label(k): label(v) for k, v in mapping.items()}


def _labelled(trace: Trace | None) -> Trace | None:
    """``trace`` with its column names and units as Plotly labels: what the charts draw of it."""
    if trace is None:
        return None
    meta = dict(trace.meta, units=_labels(trace.meta.get("units")) or {})
    return Trace([label(c) for c in trace.columns], trace.data, meta, trace.status, trace.reason, trace.stats)


def run_report_from_files(trace_path: Path, path: Path | None = None, *, reference: Path | None = None,
                          units: Mapping[str, str] | None = None, pairs: Mapping[str, str] | None = None,
                          manipulator=None, library_dir: Path | None = None) -> Path:
    """:func:`run_report` of a trace file (any format; its ``<name>_reference`` beside it is
    overlaid when present), written to ``path`` (default ``<trace>.html``)."""
    trace_path = Path(trace_path)
    trace = read_trace(trace_path)
    if reference is None:
        for suffix in (".csv", ".parquet", ".npy"):
            cand = trace_path.with_name(f"{trace_path.stem}_reference{suffix}")
            if cand.is_file():
                reference = cand
                break
    ref = read_trace(reference) if reference is not None else None
    return run_report(trace, path or trace_path.with_suffix(".html"), units=units, pairs=pairs, reference=ref,
                      manipulator=manipulator, library_dir=library_dir)


# --- a batch ------------------------------------------------------------------------------------
_SORT_JS = """<script>
document.querySelectorAll('table.sortable th').forEach(function (th, col) {
  th.addEventListener('click', function () {
    var table = th.closest('table'), body = table.tBodies[0];
    var rows = Array.prototype.slice.call(body.rows);
    var dir = th.dataset.dir === 'asc' ? -1 : 1; th.dataset.dir = dir === 1 ? 'asc' : 'desc';
    rows.sort(function (a, b) {
      var x = a.cells[col].dataset.v, y = b.cells[col].dataset.v;
      var nx = parseFloat(x), ny = parseFloat(y);
      if (!isNaN(nx) && !isNaN(ny)) return dir * (nx - ny);
      if (!isNaN(nx)) return -1; if (!isNaN(ny)) return 1;
      return dir * String(x).localeCompare(String(y));
    });
    rows.forEach(function (r) { body.appendChild(r); });
  });
});
</script>"""

_CLICK_JS = """<script>
var RUNS = %s;
function showRun(id, scroll) {
  var run = RUNS[id]; if (!run) return;
  var data = run.signals.map(function (s) { return {x: run.t, y: s.y, name: s.name, mode: 'lines', type: 'scatter'}; });
  Plotly.react('run-traces', data, {title: {text: 'run ' + run.shown + ' (' + run.label + ')', font: {size: 13}},
    xaxis: {title: {text: 'time [s]'}}, height: 420, template: 'plotly_white', margin: {t: 40}});
  var link = document.getElementById('run-link');
  link.textContent = '';
  if (run.report) {
    var a = document.createElement('a'); a.setAttribute('href', run.report);
    a.textContent = 'open the report of run ' + run.id; link.appendChild(a);
  }
  if (scroll) document.getElementById('run-traces').scrollIntoView({behavior: 'smooth'});
}
document.querySelectorAll('.js-plotly-plot').forEach(function (div) {
  if (div.id === 'run-traces') return;
  div.on('plotly_click', function (ev) {
    var p = ev.points && ev.points[0]; if (p && p.customdata) showRun(Array.isArray(p.customdata) ? p.customdata[0] : p.customdata, true);
  });
});
document.querySelectorAll('tr[data-run]').forEach(function (tr) {
  tr.addEventListener('click', function () { showRun(tr.dataset.run, true); });
});
var first = Object.keys(RUNS)[0]; if (first) showRun(first);
</script>"""


def _cell(v) -> str:
    if isinstance(v, float):
        shown = "nan" if math.isnan(v) else f"{v:.6g}"
        return f"<td data-v='{v!r}'>{shown}</td>"
    if isinstance(v, int):
        return f"<td data-v='{v}'>{v}</td>"
    return f"<td class='text' data-v='{text(v)}'>{text(v)}</td>"


def results_table_html(rows: Sequence[Mapping], columns: Sequence[str]) -> str:
    """The rows as a table sorted by clicking a header; a row's click shows its run's traces."""
    head = "".join(f"<th>{text(c)}</th>" for c in columns)
    body = "".join(f"<tr data-run='{text(r.get('run_id', ''))}'>"
                   + "".join(_cell(r.get(c)) for c in columns) + "</tr>" for r in rows)
    return f"<table class='sortable' id='results'><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _number(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def metric_figures(rows: Sequence[Mapping], axes: Sequence[str], metrics: Sequence[str],
                   units: Mapping[str, str] | None = None) -> list:
    """For each metric: a heat map over the first two numeric axes (failed runs blank), a line
    per value of the second axis over one axis, or a histogram without axes; every point carries
    its run id (``customdata``) for the click.  ``units``: axis or metric -> unit, on the titles."""
    import plotly.graph_objects as go

    figs = []
    numeric = [a for a in axes if all(math.isfinite(_number(r.get(a))) for r in rows)]

    def titled(name: str) -> str:
        unit = (units or {}).get(name, "")
        return label(name) + (f" [{label(unit)}]" if unit else "")

    for metric in metrics:
        shown = titled(metric)
        if len(numeric) >= 2:
            xa, ya = numeric[0], numeric[1]
            xs, ys = sorted({_number(r[xa]) for r in rows}), sorted({_number(r[ya]) for r in rows})
            z = [[float("nan")] * len(xs) for _ in ys]
            ids = [[""] * len(xs) for _ in ys]
            for r in rows:
                i, j = ys.index(_number(r[ya])), xs.index(_number(r[xa]))
                if r.get("outcome") == "ok" and math.isfinite(_number(r.get(metric))):
                    z[i][j] = _number(r.get(metric))
                ids[i][j] = r["run_id"]
            fig = go.Figure(go.Heatmap(x=[f"{x:g}" for x in xs], y=[f"{y:g}" for y in ys], z=z, customdata=ids,
                                       colorbar={"title": {"text": shown, "side": "right"}},
                                       hovertemplate=f"{label(xa)} = %{{x}}<br>{label(ya)} = %{{y}}<br>{shown} = "
                                                     "%{z:.4g}<br>run %{customdata}<extra></extra>"))
            fig.update_layout(xaxis_title=titled(xa), yaxis_title=titled(ya))
        elif numeric:
            xa = numeric[0]
            ok = sorted((r for r in rows if r.get("outcome") == "ok"), key=lambda r: _number(r[xa]))
            fig = go.Figure(go.Scatter(x=[_number(r[xa]) for r in ok], y=[_number(r.get(metric)) for r in ok],
                                       customdata=[r["run_id"] for r in ok], mode="lines+markers",
                                       hovertemplate=f"{label(xa)} = %{{x:.4g}}<br>{shown} = %{{y:.4g}}<br>run "
                                                     "%{customdata}<extra></extra>"))
            fig.update_layout(xaxis_title=titled(xa), yaxis_title=shown)
        else:
            ok = [r for r in rows if r.get("outcome") == "ok"]
            fig = go.Figure(go.Scatter(x=list(range(len(ok))), y=[_number(r.get(metric)) for r in ok],
                                       customdata=[r["run_id"] for r in ok], mode="markers"))
            fig.update_layout(xaxis_title="run", yaxis_title=shown)
        fig.update_layout(title={"text": shown, "font": {"size": 13}}, height=420, template="plotly_white",
                          margin={"t": 40})
        figs.append(fig)
    return figs


def batch_report(path: Path, rows: Sequence[Mapping], columns: Sequence[str], axes: Sequence[str],
                 metrics: Sequence[str], traces: Mapping[str, Path], *, title: str = "",
                 signals: Sequence[str] = (), run_reports: Mapping[str, str] | None = None,
                 max_points: int = 800, max_runs: int = 400, units: Mapping[str, str] | None = None) -> Path:
    """Write a batch's report (module docstring) to ``path``: ``rows`` of its results table,
    ``traces`` run id -> trace file (read for the click view, ``signals`` of each, default the
    metrics' signals), ``run_reports`` run id -> link of that run's own report, ``units`` axis
    or metric -> unit."""
    import plotly.graph_objects as go

    shown = list(signals) or list(dict.fromkeys(m.split(":")[0] for m in metrics))
    runs = {}
    for r in list(rows)[:max_runs]:
        p = traces.get(r["run_id"])
        if p is None or not Path(p).is_file():
            continue
        tr = read_trace(p)
        if not len(tr.data):
            continue
        idx = decimate(len(tr.time), max_points)
        names = [s for s in shown if s in tr.columns] or tr.names[:6]
        link = (run_reports or {}).get(r["run_id"], "")
        runs[r["run_id"]] = {"t": tr.time[idx].tolist(), "id": str(r["run_id"]), "shown": label(r["run_id"]),
                             "label": label(", ".join(f"{a} = {_fmt(r.get(a))}" for a in axes)),
                             "signals": [{"name": label(n), "y": tr[n][idx].tolist()} for n in names],
                             "report": href(link) if link else ""}
    n_ok = sum(r.get("outcome") == "ok" for r in rows)
    parts = [f"<p>{len(rows)} runs, {n_ok} ok, {len(rows) - n_ok} not ok. Click a point of a chart or a row of "
             f"the table to see that run's traces below; click a header to sort.</p>"]
    first = True
    for k, fig in enumerate(metric_figures(rows, axes, metrics, units)):
        parts.append(_figure_html(fig, f"metric-{k}", first))
        first = False
    traces_fig = go.Figure()
    traces_fig.update_layout(height=420, template="plotly_white")
    parts.append("<h2>traces of the chosen run</h2><p id='run-link'></p>" + _figure_html(traces_fig, "run-traces", first))
    parts.append("<h2>results</h2>" + results_table_html(rows, columns))
    body = "".join(parts) + _SORT_JS + _CLICK_JS % script_json(runs)
    return _page(path, title or f"batch {Path(path).parent.name}", body)


# --- a study ------------------------------------------------------------------------------------
def _read_csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def precision_figure(rows: Sequence[Mapping[str, str]]):
    """Work-precision: worst error relative to range against wall time, log-log, one line per
    algorithm/inputs variant, hover with step or tolerance, doSteps and status."""
    import plotly.graph_objects as go

    fig = go.Figure()
    variants = list(dict.fromkeys((r["algorithm"], r["inputs"]) for r in rows))
    for k, (alg, inp) in enumerate(variants):
        # the rows measured over the whole run (an "inaccurate" one too: it is a point of the curve)
        vr = [r for r in rows if (r["algorithm"], r["inputs"]) == (alg, inp) and r["status"] in ("ok", "inaccurate")
              and _number(r["wall_s"]) > 0 and _number(r["worst_relative"]) > 0]
        vr.sort(key=lambda r: _number(r["wall_s"]))
        hover = [label(f"tol {r['tolerance']}" if r.get("tolerance") else f"step {r['step']} s")
                 + f"<br>doSteps {label(r['do_steps'])}<br>worst on {label(r['worst_signal'])}" for r in vr]
        name = label(f"{alg}/{inp}")
        fig.add_trace(go.Scatter(x=[_number(r["wall_s"]) for r in vr], y=[_number(r["worst_relative"]) for r in vr],
                                 name=name, mode="lines+markers", text=hover,
                                 marker={"color": COLOURS[k % len(COLOURS)]},
                                 hovertemplate=f"{name}<br>wall %{{x:.4g}} s<br>worst %{{y:.3e}}<br>%{{text}}"
                                               "<extra></extra>"))
    fig.update_xaxes(type="log", title_text="wall time of the stepping loop [s]")
    fig.update_yaxes(type="log", title_text="worst error relative to range")
    fig.update_layout(title={"text": "work-precision", "font": {"size": 13}}, height=560, template="plotly_white")
    return fig


def stability_figure(rows: Sequence[Mapping[str, str]], vary: str):
    """The stability map: per variant a panel over step x ``vary`` (log axes), each cell stable
    (green), unstable (red) or failed (grey), hover with the growth per step and the reason."""
    from plotly.subplots import make_subplots
    import plotly.graph_objects as go

    variants = list(dict.fromkeys((r["algorithm"], r["inputs"]) for r in rows))
    fig = make_subplots(rows=1, cols=len(variants), subplot_titles=[label(f"{a}/{i}") for a, i in variants],
                        shared_yaxes=True)
    code = {"stable": 0, "unstable": 1, "failed": 2}
    for k, v in enumerate(variants, 1):
        vr = [r for r in rows if (r["algorithm"], r["inputs"]) == v]
        steps, vals = sorted({_number(r["step"]) for r in vr}), sorted({_number(r[vary]) for r in vr})
        z = [[None] * len(steps) for _ in vals]
        hover = [[""] * len(steps) for _ in vals]
        for r in vr:
            i, j = vals.index(_number(r[vary])), steps.index(_number(r["step"]))
            z[i][j] = code.get(r["outcome"], 2)
            hover[i][j] = (f"{label(r['outcome'])}<br>growth/step {label(r['rho_measured'])}<br>analytic rho "
                           f"{label(r['rho_analytic'])}" + (f"<br>{label(r['reason'][:120])}" if r.get("reason") else ""))
        fig.add_trace(go.Heatmap(x=steps, y=vals, z=z, text=hover, zmin=0, zmax=2, showscale=False,
                                 colorscale=[[0, "#4caf50"], [0.5, "#e53935"], [1, "#9e9e9e"]],
                                 hovertemplate=f"step %{{x:.3g}} s<br>{label(vary)} = %{{y:.4g}}<br>%{{text}}<extra></extra>"),
                      row=1, col=k)
        fig.update_xaxes(type="log", title_text="step [s]", row=1, col=k)
    fig.update_yaxes(type="log", title_text=label(vary), row=1, col=1)
    fig.update_layout(title={"text": "stability map: green stable, red unstable, grey failed", "font": {"size": 13}},
                      height=520, template="plotly_white")
    return fig


def study_report(table: Path, path: Path | None = None) -> Path:
    """Write the report of a study table (``<scene>_precision.csv`` or ``<scene>_stability.csv``)
    to ``path`` (default beside it, ``.html``)."""

    table = Path(table)
    rows = _read_csv_rows(table)
    if not rows:
        raise UserError(f"{table}: an empty study table; nothing to report")
    cols = list(rows[0])
    if "worst_relative" in cols:
        fig, kind = precision_figure(rows), "precision"
    elif "rho_measured" in cols:
        fig, kind = stability_figure(rows, cols[3]), "stability"
    else:
        raise UserError(f"{table}: not a study table (expected the columns of study precision or study stability)")
    body = (_figure_html(fig, "study", True) + "<h2>table</h2>"
            + results_table_html([{c: _typed(v) for c, v in r.items()} for r in rows], cols) + _SORT_JS)
    return _page(path or table.with_suffix(".html"), f"study {kind}: {table.stem}", body)


def _typed(v: str):
    try:
        return float(v) if v not in ("",) else v
    except ValueError:
        return v


__all__ = ["animation_figure", "batch_report", "decimate", "metric_figures", "precision_figure",
           "results_table_html", "run_report", "run_report_from_files", "signals_figure", "stability_figure",
           "study_report"]
