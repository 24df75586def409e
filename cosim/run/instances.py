"""The FMU instances of one run, shared by its pilot runs (:mod:`cosim.run.choose`), its companion
runs (:mod:`cosim.run.companion`) and the run itself, one after the other: each component's FMU is
loaded and instantiated once, and every later run starts from an FMI reset (fmi2Reset /
fmi3Reset: every variable back to its default, then the start values set again), as a batch
worker does between runs (:mod:`cosim.batch.worker`), instead of loading the library again
(FMPy's loading, about 3 ms per instance, was most of what the pilots cost beyond stepping).

An instance is loaded anew after a run that did not end cleanly (a failed FMI call may leave
it unusable) and for an FMU whose reset is known not to reset (workaround ``no_reset`` of the
behavioural check, :mod:`cosim.slaves.behaviour`).  ``$RPR_COSIM_REUSE=0`` loads every
instance anew for every run (for comparison: the runs are the same to the bit)."""
from __future__ import annotations

import os
from collections.abc import Callable, Sequence

from ..slaves.fmu import FmuSlave
from ..slaves.slave import Slave

REUSE_ENV = "RPR_COSIM_REUSE"
#: Run statuses after which the instances are kept: the master ended the run, not an FMI call.
CLEAN = frozenset({"ok", "inaccurate", "unstable", "out_of_limits"})


def enabled() -> bool:
    """Whether a run's instances are shared by its runs (``$RPR_COSIM_REUSE`` is not 0)."""
    return os.environ.get(REUSE_ENV, "1").strip().lower() not in ("0", "no", "false", "off")


class Instances:
    """The slaves of a run's components (in scene order): ``main``, the run's own, handed out for
    each of its runs by :meth:`take` (with reuse off, fresh ones from ``fresh()`` instead);
    :meth:`ended` after each run with its status; :meth:`close` at the end frees what the caller
    did not ask to keep (each slave's ``reuse`` as it came)."""

    def __init__(self, main: Sequence[Slave], fresh: Callable[[], list[Slave]], reuse: bool | None = None) -> None:
        self.main, self.fresh = list(main), fresh
        self.reuse = enabled() if reuse is None else reuse
        self._kept = {id(s): s.reuse for s in self.main if isinstance(s, FmuSlave)}
        if self.reuse:
            for s in self.main:
                if isinstance(s, FmuSlave):
                    s.reuse = True

    def take(self) -> list[Slave]:
        """The slaves for the next run (an instance still loaded is reset when the run instantiates it)."""
        return self.main if self.reuse else self.fresh()

    def ended(self, status: str) -> None:
        """After a run that ended ``status``: unless it ended cleanly, its instances are freed."""
        if status not in CLEAN:
            self._release(every=True)

    def close(self) -> None:
        """The last run is over: each slave's ``reuse`` back as it came, and an instance kept only
        for this run's runs freed."""
        for s in self.main:
            if id(s) in self._kept:
                s.reuse = self._kept[id(s)]
        self._release(every=False)

    def _release(self, every: bool) -> None:
        for s in self.main:
            if isinstance(s, FmuSlave) and s.fmu is not None and (every or not s.reuse):
                s.release()
