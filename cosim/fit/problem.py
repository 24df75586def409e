"""The least-squares problem of a fit: the scene's monolithic CasADi model
(:func:`cosim.run.reference.composite`, with the fitted parameters as symbols and each replayed
column as an input) integrated on the data's instants, and its outputs against the data.

Integration: classic Runge-Kutta of order 4 over each interval between two data instants, in
``substeps`` equal substeps (chosen from the model's fastest eigenvalue at the start so that
``h |lambda| <= 0.5``, unless given), a replayed column held or interpolated linearly over the
interval as its component says.  The whole trajectory is one CasADi expression of the parameters
(``mapaccum`` of the step), so its Jacobian is exact (algorithmic differentiation through the
integrator), not a finite difference.

Outputs at an instant are evaluated under the inputs of the interval that ends there (a held
column's previous sample), as a co-simulation records them: after the step, before the inputs
change.

Residual: per recorded signal, (model - data) / the data's range over the fitted span, so every
signal weighs alike whatever its unit.
"""
from __future__ import annotations

import fnmatch
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from models.block import Block, Param, Var

from ..errors import UserError
from ..master.estimate import FLAT
from ..run.reference import composite
from ..scenario import Scene
from ..scenario.replay import Recording, read_recording
from ..scenario.units import units_of
from fmus.index import real_block
from ..scenario.problems import suggest

#: Largest ``h |lambda|`` of an RK4 substep (well inside its stability interval of 2.78).
STIFF_LIMIT = 0.5
MAX_SUBSTEPS = 200


@dataclass(frozen=True)
class Unknown:
    """A fitted parameter: ``component.name``, its start value, catalog bounds and unit."""

    component: str
    name: str
    start: float
    lower: float
    upper: float
    unit: str

    @property
    def path(self) -> str:
        return f"{self.component}.{self.name}"


@dataclass
class Problem:
    """What :func:`cosim.fit.solve.solve` minimises (module docstring)."""

    scene: Scene
    data_path: Path
    unknowns: list[Unknown]
    signals: list[str]
    units: list[str]
    time: np.ndarray  # the data's instants inside the scene's span [s]
    data: np.ndarray  # (len(time), len(signals))
    scale: np.ndarray  # each signal's range
    simulate: ca.Function  # theta -> outputs (len(time), len(signals))
    jacobian: ca.Function  # theta -> d vec(outputs) / d theta (column-major vec)
    substeps: int

    @property
    def start(self) -> np.ndarray:
        return np.array([u.start for u in self.unknowns])

    def outputs(self, theta: np.ndarray) -> np.ndarray:
        return np.array(self.simulate(theta))

    def residual(self, theta: np.ndarray) -> np.ndarray:
        """Weighted residuals, signal by signal (column-major: all instants of the first signal first)."""
        return ((self.outputs(theta) - self.data) / self.scale).ravel(order="F")

    def residual_jacobian(self, theta: np.ndarray) -> np.ndarray:
        jac = np.array(self.jacobian(theta))
        return jac / np.repeat(self.scale, len(self.time))[:, None]


def _glob(pattern: str) -> str:
    """``fnmatch`` pattern where '[' is literal (``leg[1].R``) and ``*``, ``?`` are wildcards."""
    return pattern.replace("[", "[[]")


def unknowns(scene: Scene, patterns: Sequence[str]) -> list[Unknown]:
    """The parameters named by ``patterns`` (``component.parameter``, globs allowed in both parts:
    ``motor*.R``, ``rig.leg[*].raw_zero``), in scene order; a pattern that matches nothing is a
    :class:`UserError` naming it."""

    found: dict[tuple[str, str], Unknown] = {}
    every: list[str] = []
    for pat in patterns:
        pat = pat.strip()
        comp_pat, dot, par_pat = pat.partition(".")
        if not dot or not comp_pat or not par_pat:
            raise UserError(f"--params: {pat!r} must read COMPONENT.PARAMETER (globs allowed, e.g. motor*.R)")
        hits = 0
        for cname, c in scene.components.items():
            if c.kind != "model" or not fnmatch.fnmatchcase(cname, _glob(comp_pat)):
                continue
            block = real_block(c.block)
            for p in block.params:
                every.append(f"{cname}.{p.name}")
                if fnmatch.fnmatchcase(p.name, _glob(par_pat)):
                    hits += 1
                    value = float(c.params.get(p.name, p.default))
                    found.setdefault((cname, p.name), Unknown(cname, p.name, value, p.lower, p.upper, p.unit))
        if not hits:

            comps = [n for n, c in scene.components.items() if c.kind == "model"]
            hint = suggest(pat, sorted(set(every))) if every else ""
            raise UserError(f"--params: {pat!r} matches no parameter of scene {scene.name}{hint} "
                            f"(components with equations: {', '.join(comps)})")
    return list(found.values())


def _source(rec: Recording, columns: list[str]) -> tuple[Block, ca.SX]:
    """A replay's columns as a block whose outputs are its parameters (fed by the caller)."""
    sym = ca.SX.sym("replay", len(columns))
    blk = Block.build("replay", description=f"columns of {rec.path.name}",
                      params=[Param(f"value of {c}", 0.0, rec.units.get(c, "")) for c in columns], inputs=[],
                      outputs=[Var(c, rec.units.get(c, "")) for c in columns], states=[], p=sym, u=ca.SX(0, 1),
                      x=ca.SX(0, 1), ode=ca.SX(0, 1), out=sym, start=ca.SX(0, 1), integrator="none")
    return blk, sym


def _sample(rec: Recording, column: str, t: np.ndarray) -> np.ndarray:
    """A replayed column at the instants ``t`` as its FMU gives it (hold or linear)."""
    y = rec.column(column)
    if rec.interpolation == "linear":
        return np.interp(t, rec.time, y)
    k = np.clip(np.searchsorted(rec.time, t + 1e-9, side="right") - 1, 0, len(y) - 1)
    return y[k]


def _data(scene: Scene, path: Path, signals: Sequence[str] | None) -> tuple[Recording, list[str], np.ndarray]:
    """The data file, the signals fitted (``signals`` or every scene output the data has) and the
    rows inside the scene's span."""
    rec = read_recording(path)
    where = path.name
    if signals:
        missing = [s for s in signals if s not in rec.names]
        if missing:

            raise UserError(f"{where}: no column {missing[0]!r}{suggest(missing[0], rec.names)} "
                            f"(columns: {', '.join(rec.names[:8])}{', ...' if len(rec.names) > 8 else ''})")
        unknown = [s for s in signals if s not in scene.outputs and not _is_signal(scene, s)]
        if unknown:
            raise UserError(f"--signals: {unknown[0]!r} is not a variable of scene {scene.name}")
        chosen = list(signals)
    else:
        chosen = [o for o in scene.outputs if o in rec.names and o.split(".", 1)[0] in scene.components
                  and getattr(scene.components[o.split(".", 1)[0]], "replay", None) is None]
        if not chosen:
            raise UserError(f"{where}: none of the scene's recorded outputs ({', '.join(scene.outputs[:5])}"
                            f"{', ...' if len(scene.outputs) > 5 else ''}) is a column of the data "
                            f"({', '.join(rec.names[:5])}{', ...' if len(rec.names) > 5 else ''})")
    t0, t1 = scene.start_time, scene.stop_time
    if rec.time[0] > t0 + 1e-9 or rec.time[-1] < t1 - 1e-9:
        raise UserError(f"{where}: the data covers {rec.time[0]:g}..{rec.time[-1]:g} s, shorter than the scene's "
                        f"{t0:g}..{t1:g} s")
    units = units_of(scene)
    for s in chosen:
        have, want = rec.units.get(s, ""), units.get(s, "")
        if have and want and have != want:
            raise UserError(f"{where}: column {s!r} is in {have}, the scene's {s} in {want}")
    return rec, chosen, (rec.time >= t0 - 1e-9) & (rec.time <= t1 + 1e-9)


def _is_signal(scene: Scene, name: str) -> bool:
    comp, _, var = name.partition(".")
    c = scene.components.get(comp)
    return c is not None and var in c.description.variables


def _substeps(f: ca.Function, x0: np.ndarray, u0: np.ndarray, theta: np.ndarray, h: float) -> int:
    """Substeps per interval so that ``h / n * |lambda_max| <= STIFF_LIMIT`` at the start."""
    if not len(x0):
        return 1
    args = f.mx_in()
    jac = np.array(ca.Function("jx", args, [ca.jacobian(f(*args), args[0])])(x0, u0, theta))
    rho = float(np.max(np.abs(np.linalg.eigvals(jac)))) if jac.size else 0.0
    return int(min(MAX_SUBSTEPS, max(1, math.ceil(h * rho / STIFF_LIMIT))))


def build(scene: Scene, data_path: Path | str, patterns: Sequence[str], *, signals: Sequence[str] | None = None,
          substeps: int | None = None) -> Problem:
    """The fit of ``patterns`` (parameters) of ``scene`` to the file ``data_path`` (module docstring)."""
    data_path = Path(data_path)
    if not data_path.is_file():
        raise UserError(f"{data_path}: no such data file")
    unk = unknowns(scene, patterns)
    rec, chosen, rows = _data(scene, data_path, signals)
    time = rec.time[rows]
    if len(time) < 2:
        raise UserError(f"{data_path.name}: fewer than two instants inside the scene's span")
    data = np.column_stack([rec.column(s)[rows] for s in chosen])
    span = data.max(axis=0) - data.min(axis=0)
    scale = np.maximum(np.where(span > 0, span, np.abs(data).max(axis=0)), FLAT)

    theta = ca.SX.sym("theta", len(unk))
    symbols = {(u.component, u.name): theta[i] for i, u in enumerate(unk)}
    sources, feeds = {}, []  # feeds: (component, column) in the order of the input vector
    for cname, c in scene.components.items():
        rep = getattr(c, "replay", None)
        if rep is None:
            continue
        cols = sorted({cn.src_var for cn in scene.connections if cn.src == cname})
        sources[cname] = _source(rep, cols)
        feeds += [(cname, col) for col in cols]
    evented = [n for n, c in scene.components.items() if getattr(c.block, "has_events", False)]
    if evented:
        raise UserError(f"scene {scene.name}: {', '.join(evented)} has events (modes, located crossings); the fit "
                        f"integrates continuous models only (the rig's 'motor' fidelity is one)")
    comp = composite(scene, symbols=symbols, sources=sources)
    if comp.z.numel():
        raise UserError(f"scene {scene.name}: an algebraic loop ({', '.join(f'{b}.{i}' for b, i in comp.cuts)}); "
                        f"the fit integrates explicit ODEs only")
    u = ca.vertcat(*[sym for _, sym in sources.values()]) if sources else ca.SX(0, 1)  # feeds' order
    f = ca.Function("f", [comp.x, u, theta], [comp.ode])
    names = [tuple(s.split(".", 1)) for s in chosen]
    out = ca.Function("y", [comp.x, u, theta], [ca.vertcat(*[comp.signals[n] for n in names])])
    x0 = ca.Function("x0", [theta], [ca.SX(comp.x0) if isinstance(comp.x0, ca.SX) else ca.DM(comp.x0)])

    linear = [scene.components[c].replay.interpolation == "linear" for c, _ in feeds]
    U = np.column_stack([_sample(scene.components[c].replay, col, time) for c, col in feeds]) if feeds else \
        np.zeros((len(time), 0))
    h = np.diff(time)
    n = substeps or _substeps(f, np.array(x0(ca.DM(np.array([v.start for v in unk]))).full()).ravel(),
                              U[0], np.array([v.start for v in unk]), float(h.max()))
    step = _rk4_step(f, comp.x.numel(), u.numel(), len(unk), n, np.array(linear, dtype=bool))
    traj = step.mapaccum("traj", len(h))
    th = ca.MX.sym("theta", len(unk))
    xs0 = x0(th)
    X = traj(xs0, U[:-1].T, U[1:].T, ca.repmat(th, 1, len(h)), h.reshape(1, -1))
    Xall = ca.horzcat(xs0, X)
    left = U.copy()  # at an instant, a held column's value over the interval that ends there
    left[1:, ~np.array(linear, dtype=bool)] = U[:-1, ~np.array(linear, dtype=bool)]
    Y = out.map(len(time))(Xall, left.T, ca.repmat(th, 1, len(time)))  # (signals, instants)
    Yt = Y.T
    simulate = ca.Function("simulate", [th], [Yt])
    jac = ca.Function("jacobian", [th], [ca.jacobian(ca.vec(Yt), th)])
    return Problem(scene, data_path, unk, chosen, [units_of(scene).get(s, "") for s in chosen], time, data, scale,
                   simulate, jac, n)


def _rk4_step(f: ca.Function, nx: int, nu: int, np_: int, n: int, linear: np.ndarray) -> ca.Function:
    """``(x, u_start, u_end, theta, h) -> x`` after ``n`` RK4 substeps over ``h``, each input held
    at ``u_start`` or interpolated to ``u_end`` (``linear``)."""
    x, ua, ub = ca.SX.sym("x", nx), ca.SX.sym("ua", nu), ca.SX.sym("ub", nu)
    th, h = ca.SX.sym("theta", np_), ca.SX.sym("h")
    lin = ca.DM(linear.astype(float)) if nu else ca.DM(0, 1)

    def u_at(frac):
        return ua + lin * (ub - ua) * frac if nu else ua

    dt, xk = h / n, x
    for k in range(n):
        a = k / n
        k1 = f(xk, u_at(a), th)
        k2 = f(xk + dt / 2 * k1, u_at(a + 0.5 / n), th)
        k3 = f(xk + dt / 2 * k2, u_at(a + 0.5 / n), th)
        k4 = f(xk + dt * k3, u_at(a + 1.0 / n), th)
        xk = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("step", [x, ua, ub, th, h], [xk])


__all__ = ["Problem", "Unknown", "build", "unknowns"]
