"""The Python twins of the variable-step kernels (``rpr_adapt_run`` and ``rpr_ecco_run`` in
``cosim/master/adaptive_engine.c``), a test oracle: each class is the product's stepping (its
state, the event handling, the endings' wording: written once, in ``cosim/``) with the Python
steps the kernel's are compared with, bit for bit; :class:`Loop` runs them through the product's
one seam, the loop :class:`cosim.master.algorithms.adaptive.VariableStepper` takes (the interface
of :class:`cosim.master.adaptive_engine.CompiledAdaptive`), registered as the engine ``oracle``
(:mod:`oracles`)."""
from __future__ import annotations

import math
import time

import numpy as np

from cosim.master.algorithms import adaptive, ecco
from cosim.master.entries import AdaptiveEnd, EccoEnd
from cosim.slaves.slave import FAILING, Status


class AdaptiveSteps:
    """``AdaptiveStepper``'s accepted step in Python (``rpr_adapt_run``): the Gauss-Seidel attempt
    with its error estimate, rejections and rollbacks, the step-size controller (``propose()``),
    the landing on the output grid (``plan_ns()``), the cut at an event."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.landed = True  # the last accepted step ended on an output point (or the stop time)
        self.calls = [0] * len(self.system.slaves)
        self.slave_ns = [0] * len(self.system.slaves)

    def _attempt(self, h: float) -> tuple[float, int | None, int]:
        """One Gauss-Seidel step of ``h``; returns (scaled error, failing slave or None, status)."""
        sysm, opt = self.system, self.opt
        t = self.t
        err, weight = 0.0, h / opt["h_ref"] if "h_ref" in opt else 1.0  # (steppers without the weight: 1)
        guesses: list[tuple[int, np.ndarray, np.ndarray]] = []  # (slave, source indices, guessed values)
        for i in self.order:
            s = sysm.slaves[i]
            buf, src = sysm.in_buf[i], sysm.in_src[i]
            if len(src):
                now = sysm.v[src]
                fresh = self.fresh[i]
                if self.interp[i]:
                    slope = self.slopes[i]
                    # extrapolated: slope from the previous point; interpolated: towards the new value
                    with np.errstate(invalid="ignore", divide="ignore"):
                        ext = (self.cur_src[i] - self.prev_src[i]) / self.h_prev if self.h_prev > 0 else \
                            np.zeros_like(now)
                    slope[:] = np.where(fresh, (now - self.cur_src[i]) / h, ext)
                    buf[:] = np.where(fresh, self.cur_src[i], now)
                    guess = now + ext * h
                else:
                    buf[:] = now
                    guess = now.copy()
                aff = sysm.in_affine[i]
                if aff is not None:  # the connections' dst = factor * src + offset
                    buf *= aff[0]
                    buf += aff[1]
                    if self.interp[i]:
                        self.slopes[i] *= aff[0]
                if (~fresh).any():
                    guesses.append((i, src[~fresh], guess[~fresh]))
            t0 = time.perf_counter_ns()
            st = s.push()
            if st not in FAILING and self.interp[i] and len(src):
                st = s.push_slopes()
            if st not in FAILING:
                st = s.do_step(t, h)
                self.calls[i] += 1
                if st not in FAILING and st != Status.STOP_REQUESTED:
                    st = s.pull()
            self.slave_ns[i] += time.perf_counter_ns() - t0
            if st in FAILING or st == Status.STOP_REQUESTED:
                return math.inf, i, st
        for i, src, guess in guesses:
            actual = sysm.v[src]
            span = np.maximum(self.hi[src], actual) - np.minimum(self.lo[src], actual)
            tol = opt["atol"] + opt["rtol"] * span
            with np.errstate(invalid="ignore", divide="ignore"):
                e = np.abs(actual - guess) * weight / tol
            if e.size:
                m = float(np.max(e))
                err = max(err, m if math.isfinite(m) else math.inf)
        return err, None, Status.OK

    def _commit(self, h: float, h_ns: int) -> None:
        """Book an accepted step of ``h`` (``h_ns``): statistics, input history, ranges, time."""
        sysm = self.system
        self.stats.accepted += 1
        self.stats.h_min_taken = min(self.stats.h_min_taken, h)
        self.stats.h_max_taken = max(self.stats.h_max_taken, h)
        self.stats.steps.append(h)
        for i, src in enumerate(sysm.in_src):
            if len(src):
                self.prev_src[i][:] = self.cur_src[i]
                self.cur_src[i][:] = sysm.v[src]
        np.maximum(self.hi, sysm.v, out=self.hi)
        np.minimum(self.lo, sysm.v, out=self.lo)
        self.t_ns += h_ns
        self.h_prev = h
        self.landed = self._on_output(self.t_ns)
        if self.event_slaves:
            self._note_event()

    def step(self) -> bool:
        """Advance by one accepted step (retrying smaller after rejections); False when the run
        ends early (:attr:`status`, :attr:`message`)."""
        sysm, opt = self.system, self.opt
        v_saved = sysm.v.copy()
        for s in sysm.slaves:
            s.save_state()
        cut: int | None = None  # an event's time [ns] the step is retaken to
        while True:
            h_ns = self._plan_ns() if cut is None else cut - self.t_ns
            h = h_ns / 1e9
            err, bad, st = self._attempt(h)
            p = self.order_p_linear if any(self.interp) and self.h_prev > 0 else self.order_p_hold
            if bad is not None and st == Status.STOP_REQUESTED:
                self._end(AdaptiveEnd.STOP_REQUESTED, bad, st)
                return False
            if bad is None and self.event_slaves:
                early = self._early_return(h_ns)
                if early is not None:  # an event inside the step: it ends there for every slave (no rejection)
                    if early <= self.t_ns:
                        return self._no_progress(early)
                    cut = early
                    self.stats.event_cuts += 1
                    for s in sysm.slaves:
                        s.restore_state()
                    np.copyto(sysm.v, v_saved)
                    continue
            if bad is None and (err <= 1.0 or self.h_prev == 0):  # the first step has no estimate
                break
            cut = None  # retried smaller: the event, if still inside, is found again
            self.stats.rejected += 1
            if bad is not None:
                self.stats.discards += 1
            for s in sysm.slaves:
                s.restore_state()
            self.stats.rollbacks += 1
            np.copyto(sysm.v, v_saved)
            shrink = opt["fac_min"] if not math.isfinite(err) else max(opt["fac_min"], opt["safety"] * err ** (-1 / p))
            if h <= opt["h_min"] * (1 + 1e-12):
                self._end(AdaptiveEnd.STEP_FLOOR, -1 if bad is None else bad, st, err)
                return False
            self.h = max(opt["h_min"], h * min(shrink, 0.9))
        self._commit(h, h_ns)
        if cut is not None:  # a step cut short at an event says nothing new of the error: keep the proposal
            return True
        e = max(err, 1e-10)
        fac = opt["safety"] * e ** (-self.k_i / p) * self.err_prev ** (self.k_p / p)
        self.err_prev = e
        self._propose(h, h_ns, fac)
        return True

    # -- the output grid (docs/explanation/events.md, "Trace rows") ------------------------------------
    def _plan_ns(self) -> int:
        """The step [ns] from the current time for the controller's proposal :attr:`h`: the rest of
        the way to the next output point when the proposal reaches it, else that way split into the
        fewest equal steps no longer than the proposal (no sliver of a step before a point; whole
        nanoseconds, the last one landing).  Without a grid, the proposal clipped to the stop time."""
        want, left = round(self.h * 1e9), self.target_ns() - self.t_ns
        if want >= left:
            return max(1, left)
        if not self.grid_ns:
            return max(1, want)
        n = -(-left // max(1, want))
        return max(1, -(-left // n))

    # -- events: a step boundary (docs/explanation/events.md) -------------------------------------------
    def _early_return(self, h_ns: int) -> int | None:
        """The earliest time [ns] an event-mode slave returned early inside the step of ``h_ns``
        just taken, or None when every one reached its end."""
        t1 = self.t_ns + h_ns
        ends = [round(self.system.slaves[i].step_end()[0] * 1e9) for i in self.event_slaves]
        early = min(ends, default=t1)
        return early if early < t1 else None

    def _propose(self, h: float, h_ns: int, fac: float) -> None:
        """The next step after an accepted step ``h`` (``h_ns``): ``h`` times the controller's
        factor ``fac``, bounded by ``fac_min``/``fac_max`` and ``h_min``/``h_max``; a step cut
        short to land on the stop time does not shrink the proposal."""
        opt = self.opt
        fac = min(opt["fac_max"], max(opt["fac_min"], fac))
        if h_ns < round(self.h * 1e9):  # clipped to land on the stop time: keep the proposal
            fac = max(fac, 1.0)
        self.h = min(opt["h_max"], max(opt["h_min"], h * fac))



class AdaptiveStepper(AdaptiveSteps, adaptive.AdaptiveStepper):
    """``adaptive``'s Python steps."""


def bond_energy(h: float, y0: np.ndarray, y1: np.ndarray, u0: np.ndarray, u1: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Energy residual and energy carried [J] of bonds over a step of ``h`` [s]: ``y0``, ``y1``
    (rows: bonds, columns: sides a, b) the outputs at the step's start and end, ``u0``, ``u1`` the
    inputs each side saw there (see the module docstring)."""
    p0, p1 = y0 * u0, y1 * u1
    residual = 0.5 * h * ((p0[:, 0] - p0[:, 1]) + (p1[:, 0] - p1[:, 1]))
    carried = 0.5 * h * np.maximum(np.abs(p0[:, 0]) + np.abs(p1[:, 0]), np.abs(p0[:, 1]) + np.abs(p1[:, 1]))
    return residual, carried



class EccoStepper(AdaptiveSteps, ecco.EccoStepper):
    """``ecco``'s Python steps (``rpr_ecco_run``): never retried, the next step from the bonds'
    energy residual."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self._at_floor = 0  # steps in a row at h_min over tolerance
        self._ending: tuple[int, float, int] | None = None  # the run ends before the next step: (bond, eps, steps)

    def _seen_slopes(self) -> np.ndarray:
        """Slopes [unit/s] of the bonds' inputs over the step just taken (0 where held)."""
        return np.array([[self.slopes[s][k] if self.interp[s] else 0.0 for s, k in zip(b.side, b.slot)]
                         for b in self.bonds])

    def step(self) -> bool:
        """Advance by one step (never retried); False when the run ends early."""
        sysm, opt = self.system, self.opt
        if self._ending is not None:
            self._end(EccoEnd.FLOOR_PATIENCE, self._ending[0], 0, self._ending[1], self._ending[2])
            return False
        h_ns = self._plan_ns()
        y0 = sysm.v[self._out_idx]
        if self.event_slaves:  # (the run uses event mode only where every slave can roll back)
            v_saved = sysm.v.copy()
            for s in sysm.slaves:
                s.save_state()
        cut: int | None = None
        while True:
            h = h_ns / 1e9
            _, bad, st = self._attempt(h)
            if bad is not None:
                asked = st == Status.STOP_REQUESTED or (st == Status.DISCARD and sysm.slaves[bad].asked_to_stop())
                self._end(EccoEnd.STOP_REQUESTED if asked else EccoEnd.SLAVE_FAILED, bad, st)
                return False
            early = self._early_return(h_ns) if self.event_slaves else None
            if early is None:
                break
            if early <= self.t_ns:
                return self._no_progress(early)
            cut, h_ns = early, early - self.t_ns  # an event inside the step: retaken to end there
            self.stats.event_cuts += 1
            for s in sysm.slaves:
                s.restore_state()
            np.copyto(sysm.v, v_saved)
        u0 = sysm.v[self._in_idx]
        residual, carried = bond_energy(h, y0, sysm.v[self._out_idx], u0, u0 + self._seen_slopes() * h)
        scaled = np.abs(residual) / (opt["atol"] + opt["rtol"] * carried)
        if not np.all(np.isfinite(scaled)):
            self._end(EccoEnd.NOT_FINITE, int(np.argmin(np.isfinite(scaled))))
            return False
        for b, r, e, x in zip(self.bonds, residual, carried, scaled):
            self.stats.bonds[b.name].add(float(r), float(e), float(x))
        self._commit(h, h_ns)
        if cut is not None:  # a step cut short at an event: the controller keeps its proposal
            return True
        err = max(float(np.max(scaled)), 1e-10)
        self._at_floor = self._at_floor + 1 if err > 1.0 and h <= opt["h_min"] * (1 + 1e-12) else 0
        if self.patience and self._at_floor >= self.patience:  # this step is taken and recorded; the run ends before the next
            k = int(np.argmax(scaled))
            self._ending = (k, float(scaled[k]), self._at_floor)
        fac = (opt["safety"] / err) ** opt["k_i"] * (self.err_prev / err) ** opt["k_p"]
        self.err_prev = err
        self._propose(h, h_ns, fac)
        return True


#: the oracle class of each product stepping
ORACLES = {adaptive.AdaptiveStepper: AdaptiveStepper, ecco.EccoStepper: EccoStepper}


def oracle_stepping(kind: type) -> type:
    """The class whose Python steps run the stepping ``kind``."""
    return ORACLES[kind]


class Loop:
    """A stepping's Python steps behind the loop interface :class:`VariableStepper` takes:
    :meth:`run` takes accepted steps into rows; time, statistics and counters are the stepping's
    (the master's own time is not measured: ``master_ns`` None)."""

    master_ns = None

    def __init__(self, stepping: AdaptiveSteps):
        self.py = stepping

    @property
    def t_ns(self) -> int:
        return self.py.t_ns

    @property
    def stats(self):
        return self.py.stats

    @property
    def calls(self) -> list[int]:
        return self.py.calls

    @property
    def slave_ns(self) -> list[int]:
        return self.py.slave_ns

    def run(self, rec: np.ndarray) -> int:
        """Up to ``len(rec)`` accepted steps, until the stop time, an event or the end of the run; a
        row (time, the recorded values) at each that lands on an output point or ends at an event."""
        py, v, idx = self.py, self.py.system.v, self.py.system.record_idx
        rows = 0
        for _ in range(len(rec)):
            ok = py.step()
            event = py.pending_event is not None
            if ok and (py.landed or event):
                rec[rows, 0] = py.t
                np.take(v, idx, out=rec[rows, 1:])
                rows += 1
            if not ok or event or py.t_ns >= py.stop_ns or py.status != "running":
                break
        return rows

    def close(self) -> None:
        """Nothing to free."""
