"""Real-time pacing of a run: communication point ``k`` starts at wall time ``t0 + k h`` on an
absolute monotonic schedule (no drift from sleeping late), so hardware in the loop sees the
scene's time as its own.

Before each step the run loop calls :meth:`Pacer.wait`: sleep until ``spin`` before the deadline
(``time.sleep`` wakes late by tens of microseconds to milliseconds under load), then spin on the
clock to the deadline.  Lateness (start of the step minus its deadline) is recorded per step;
p50, p99 and the maximum are in :meth:`Pacer.stats`.  Overrun policy: a step that starts more
than one step ``h`` late is a missed deadline; the schedule is kept (the loop catches up by
running late steps at once) and misses are counted; ``max_misses`` consecutive misses fail the
run with the reason.  A variable-step run (``ecco``) is paced the same way, each step's start at
its simulated time after the start (:meth:`Pacer.wait_ns`); ``h`` is then the scene's
``master.step``.

``priority`` > 0 runs the stepping thread under SCHED_FIFO at that priority for the run (Linux;
needs root or CAP_SYS_NICE; otherwise the run goes on at normal priority and the statistics say
why).  On a shared or loaded machine this is what keeps a 1 kHz loop on time.  Every other
thread of the process (the trace writer) is raised with it, and the interpreter's switch
interval drops to 100 us for the run: a thread at normal priority that held the GIL when the
machine's other processes preempted it kept the stepping thread waiting for milliseconds
(priority inversion through the GIL; measured as 1-7 ms stalls, several missed deadlines in 10 s
on a loaded machine).
"""
from __future__ import annotations

import gc
import os
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

_now = time.monotonic_ns


@dataclass
class RealtimeSettings:
    """``master.realtime`` of a scene: ``max_misses`` consecutive missed deadlines fail the run;
    ``spin`` [s] is how long before a deadline sleeping stops and spinning starts."""

    max_misses: int = 50
    spin: float = 300e-6
    priority: int = 0


def _other_threads() -> list[int]:
    """Thread ids of this process other than the calling thread's (Linux; else none)."""
    try:
        me = threading.get_native_id()
        return [int(t) for t in os.listdir("/proc/self/task") if int(t) != me]
    except OSError:
        return []


class Pacer:
    """Paces steps of ``step_ns`` nanoseconds (see the module docstring)."""

    def __init__(self, step_ns: int, n_steps: int, settings: RealtimeSettings | None = None):
        self.step_ns = int(step_ns)
        self.settings = settings or RealtimeSettings()
        self.spin_ns = int(self.settings.spin * 1e9)
        self.late = np.zeros(max(1, n_steps), dtype=np.int64)  # lateness per step [ns]
        self.n = 0
        self.missed = 0
        self.consecutive = 0
        self.worst_run = 0
        self.t0: int | None = None
        self.reason = ""
        self.priority_note = "not requested"
        self._old_policy = None
        # a full collection of a large heap stalls for 0.1-1 s: collect now, before the slaves
        # are initialised (a hardware slave's watchdog starts there) and the clock starts, and
        # keep what exists out of later collections (only the run's own young objects are
        # scanned while paced; :meth:`finish` undoes it)
        gc.collect()
        gc.freeze()
        self._frozen = True

    def _raise_priority(self) -> None:
        prio = self.settings.priority
        if prio <= 0:
            return
        try:
            old = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            self._old_policy, self.priority_note = old, f"SCHED_FIFO {prio}"
        except (AttributeError, OSError) as exc:
            self.priority_note = f"SCHED_FIFO {prio} refused ({getattr(exc, 'strerror', None) or exc}); normal priority"
            return
        self._others = {}
        for tid in _other_threads():
            try:
                was = (os.sched_getscheduler(tid), os.sched_getparam(tid))
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(prio))
                self._others[tid] = was
            except OSError:  # the thread ended meanwhile
                pass
        self._old_switch = sys.getswitchinterval()
        sys.setswitchinterval(1e-4)

    def finish(self) -> dict:
        """Restore the scheduling policy; the statistics (:meth:`stats`)."""
        if getattr(self, "_frozen", False):
            gc.unfreeze()
            self._frozen = False
        if self._old_policy is not None:
            for tid, (policy, param) in [(0, self._old_policy), *getattr(self, "_others", {}).items()]:
                try:
                    os.sched_setscheduler(tid, policy, param)
                except OSError:
                    pass
            self._old_policy, self._others = None, {}
            sys.setswitchinterval(self._old_switch)
        return self.stats()

    def wait(self, k: int) -> bool:
        """Wait for the deadline of step ``k``; False (with :attr:`reason`) when the overrun policy
        gives up."""
        return self.wait_ns(k * self.step_ns)

    def wait_ns(self, offset_ns: int) -> bool:
        """Wait for the deadline of the step starting ``offset_ns`` [ns] of simulated time after
        the start (a variable-step run's steps fall anywhere); False (with :attr:`reason`) when
        the overrun policy gives up."""
        now = _now()
        if self.t0 is None:
            self._raise_priority()
            now = _now()
            self.t0 = now
        deadline = self.t0 + offset_ns
        if now < deadline - self.spin_ns:
            time.sleep((deadline - self.spin_ns - now) / 1e9)
            now = _now()
        while now < deadline:
            now = _now()
        late = now - deadline
        if self.n == len(self.late):  # more steps than planned (a variable-step run): grow
            self.late = np.resize(self.late, 2 * len(self.late))
        self.late[self.n] = late
        self.n += 1
        if late > self.step_ns:
            self.missed += 1
            self.consecutive += 1
            self.worst_run = max(self.worst_run, self.consecutive)
            if self.consecutive >= self.settings.max_misses:
                self.reason = (f"real time lost: {self.consecutive} deadlines in a row missed by more than one step "
                               f"({self.step_ns / 1e6:g} ms) at step {self.n - 1} (t = {offset_ns / 1e9:.9g} s after "
                               f"the start), {late / 1e6:.1f} ms late")
                return False
        else:
            self.consecutive = 0
        return True

    def stats(self) -> dict:
        """Lateness p50/p99/max [s], missed deadlines, longest run of misses, paced steps."""
        lat = self.late[:min(self.n, len(self.late))] / 1e9
        pct = np.percentile(lat, [50, 99]) if lat.size else [0.0, 0.0]
        return {"paced_steps": self.n, "lateness_p50_s": float(pct[0]), "lateness_p99_s": float(pct[1]),
                "lateness_max_s": float(lat.max()) if lat.size else 0.0, "missed_deadlines": self.missed,
                "longest_miss_run": self.worst_run, "max_misses": self.settings.max_misses,
                "priority": self.priority_note}


#: Outputs a slave names ``<prefix>*`` are its own real-time figures (the rig's hardware FMU:
#: the board daemon's tick lateness and CPU per tick, :mod:`hardware.hil_fmu`); a paced run reports
#: their last values beside the master's own lateness.
OWN_FIGURES_PREFIX = "board_"


def slave_figures(system) -> dict[str, dict[str, float]]:
    """component -> {figure: last value} for every slave of ``system`` (a
    :class:`cosim.master.CoupledSystem`) with outputs named :data:`OWN_FIGURES_PREFIX` ``*``;
    a slave that cannot be read any more (failed, freed) is left out."""
    out: dict[str, dict[str, float]] = {}
    for slave in system.slaves:
        names = [n for n, v in slave.description.variables.items()
                 if n.startswith(OWN_FIGURES_PREFIX) and v.causality == "output" and v.type == "Real"]
        if not names:
            continue
        try:
            vals = slave.get_values("Real", [slave.vr(n) for n in names], len(names))
        except Exception:  # a slave after Error/Fatal or without an instance: nothing to report
            continue
        out[slave.name] = {n[len(OWN_FIGURES_PREFIX):]: float(v) for n, v in zip(names, vals)}
    return out
