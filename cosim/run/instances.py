"""The FMU instances of one run, shared by its pilot runs (:mod:`cosim.run.choose`), its companion
runs (:mod:`cosim.run.companion`) and the run itself, one after the other: each component's FMU is
loaded and instantiated once, and every later run starts from an FMI reset (fmi2Reset /
fmi3Reset: every variable back to its default, then the start values set again), as a batch
worker does between runs (:mod:`cosim.batch.worker`), instead of loading the library again
(FMPy's loading, about 3 ms per instance, was most of what the pilots cost beyond stepping).

Only the project's own FMUs (catalog blocks, whose reset this project writes) are shared: an
external FMU (a scene's ``fmu:`` component) is loaded anew for each run as before, since a reset
that does not reset is not always caught by the behavioural check (:mod:`cosim.slaves.behaviour`;
libcosim's quarter-truck Wheel keeps its position through fmi2Reset).  A shared instance is
loaded anew after a run that did not end cleanly (a failed FMI call may leave it unusable) and
for an FMU whose reset is known not to reset (workaround ``no_reset``).  ``$RPR_COSIM_REUSE=0``
loads every instance anew for every run (for comparison: the runs are the same to the bit)."""
from __future__ import annotations

import os
from collections.abc import Callable, Sequence

from ..slaves.fmu_slave import FmuSlave
from ..slaves.slave import Slave

REUSE_ENV = "RPR_COSIM_REUSE"
#: Run statuses after which the instances are kept: the master ended the run, not an FMI call.
CLEAN = frozenset({"ok", "inaccurate", "unstable", "out_of_limits"})


def enabled() -> bool:
    """Whether a run's instances are shared by its runs (``$RPR_COSIM_REUSE`` is not 0)."""
    return os.environ.get(REUSE_ENV, "1").strip().lower() not in ("0", "no", "false", "off")


class Instances:
    """The slaves of a run's components (in scene order): ``main``, the run's own, handed out for
    each of its runs by :meth:`take` where ``shared`` (per component), fresh ones from
    ``fresh(i)`` elsewhere (and everywhere with reuse off); :meth:`ended` after each run with its
    status; :meth:`close` at the end frees what the caller did not ask to keep (each slave's
    ``reuse`` as it came)."""

    def __init__(self, main: Sequence[Slave], fresh: Callable[[int], Slave], shared: Sequence[bool],
                 reuse: bool | None = None) -> None:
        self.main, self.fresh = list(main), fresh
        on = enabled() if reuse is None else reuse
        self.shared = [bool(on and sh and isinstance(s, FmuSlave)) for s, sh in zip(self.main, shared)]
        self._kept = {i: s.reuse for i, s in enumerate(self.main) if self.shared[i]}
        for i in self._kept:
            self.main[i].reuse = True

    def take(self) -> list[Slave]:
        """The slaves for the next run (a shared instance still loaded is reset when the run
        instantiates it)."""
        return [s if sh else self.fresh(i) for i, (s, sh) in enumerate(zip(self.main, self.shared))]

    def ended(self, status: str) -> None:
        """After a run that ended ``status``: unless it ended cleanly, the shared instances are freed."""
        if status not in CLEAN:
            self._release(every=True)

    def close(self) -> None:
        """The last run is over: each shared slave's ``reuse`` back as it came, and an instance
        kept only for this run's runs freed."""
        for i, was in self._kept.items():
            self.main[i].reuse = was
        self._release(every=False)

    def _release(self, every: bool) -> None:
        for i in self._kept:
            s = self.main[i]
            if s.fmu is not None and (every or not s.reuse):
                s.release()
