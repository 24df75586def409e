"""The validated scene: :class:`Scene`, its components, connections and master settings."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..slaves.description import SlaveDescription
from .problems import Loc, Problem


#: Catalog blocks that stand for a system file's functions (:attr:`Component.memoryless`).
FUNCTION_BLOCKS = frozenset({"vector_sum"})


@dataclass
class Component:
    """A validated component: how to build it and what it looks like."""

    name: str
    kind: str  # "model" or "fmu"
    description: SlaveDescription
    model: str | None = None
    fidelity: str | None = None
    options: dict[str, Any] = field(default_factory=dict)
    params: dict[str, float] = field(default_factory=dict)  # set on the instance at start-up
    start: dict[str, float] = field(default_factory=dict)
    fmu: Path | None = None
    fmi: str = "2.0"
    block: Any = None  # the models.block.Block of a model component (or its fmus.index.IndexedBlock)
    where: Loc = ("", 0)
    recipe: Any = None  # fmus.index.Recipe of a component of the default catalog (its FMU's index key)
    rollback: bool = True  # false: stepped as a slave that cannot save/restore its state (``rollback: false``)
    rate: int = 1  # doSteps per macro step (cosim.master.multirate)
    origin: str | None = None  # a user's block: where it is defined (a 'blocks:' file, an entry point, a .mo file)
    depends: dict[str, str] = field(default_factory=dict)  # a user's Python block: files its module imported -> SHA-256
    guard: Any = None  # cosim.scenario.guard_settings.GuardNeeds: what the run-time guards need, as plain data
    replay: Any = None  # cosim.scenario.replay.Recording of a ``replay:`` component (an FMU with the table in it)

    @property
    def memoryless(self) -> bool:
        """A block that stands for a system file's function (``sum``: OSP's Sum and VectorSum),
        evaluated within Jacobi's exchange as libcosim evaluates its functions.  Every other block,
        stateless or not, is a slave like any FMU, with Jacobi's one-step delay (so a scene runs
        the same as its SSP export, whose FMUs carry no such mark)."""
        b = self.block
        return self.kind == "model" and b is not None and b.name in FUNCTION_BLOCKS and b.memoryless

    @property
    def label(self) -> str:
        return f"{self.model}/{self.fidelity}" if self.kind == "model" else (self.fmu.name if self.fmu else "?")

    def start_values(self) -> dict[str, float]:
        """Everything to set before initialisation: parameters, then start values."""
        return {**self.params, **self.start}


@dataclass(frozen=True)
class Connection:
    """A signal ``src.src_var -> dst.dst_var``; ``bond`` names the bond it comes from, if any."""

    src: str
    src_var: str
    dst: str
    dst_var: str
    bond: str | None = None
    where: Loc = ("", 0)
    as_type: str | None = None  # an explicit conversion to the destination's type
    factor: float = 1.0  # dst = factor * src + offset (a linear transformation, e.g. from an SSP)
    offset: float = 0.0

    def __str__(self) -> str:
        text = f"{self.src}.{self.src_var} -> {self.dst}.{self.dst_var}"
        if self.factor != 1.0:
            text += f" * {self.factor!r}"
        if self.offset != 0.0:
            text += f" {'-' if self.offset < 0 else '+'} {abs(self.offset)!r}"
        return text + (f" as {self.as_type}" if self.as_type else "")


@dataclass
class MasterSettings:
    algorithm: str
    step: float  # [s]
    step_ns: int
    order: list[str] | None
    engine: str
    record_every: int  # output interval in steps
    inputs: str = "hold"  # "hold" or "linear" (first-order hold, FMUs that can interpolate inputs)
    realtime: Any = None  # cosim.master.realtime.RealtimeSettings when the run is paced on the wall clock
    options: dict[str, float] = field(default_factory=dict)  # the algorithm's own options (its declaration)
    #: the accuracy asked for: worst error of a recorded signal relative to its range (default 1e-3;
    #: None: the scene wants no verdict, ``tolerance: none``)
    tolerance: float | None = None
    #: no algorithm named: the run chooses algorithm and settings from ``tolerance`` (cosim.run.choose)
    auto: bool = False
    inputs_given: bool = False  # master.inputs was set by the scene (the choice keeps it)
    #: the run's own error estimate (a companion run, cosim.master.estimate); off: none, and no verdict from it
    estimate: bool = True
    #: master.tolerance was written in the scene (not the default)
    tolerance_given: bool = False
    #: what the run records: "grid" (every output point, plus two rows per event) or "steps" (every
    #: accepted step of a variable-step algorithm)
    record: str = "grid"


@dataclass
class Scene:
    """A validated scene, ready to run (see :func:`load`)."""

    name: str
    path: Path | None
    description: str
    stop_time: float
    n_steps: int
    components: dict[str, Component]
    connections: list[Connection]
    bonds: list[tuple[str, str, str, str]]  # (comp, flange, comp, flange)
    master: MasterSettings
    outputs: list[str]
    data: dict  # the merged tree as plain data
    hash: str
    warnings: list[Problem] = field(default_factory=list)
    start_time: float = 0.0  # [s] the scene's start_time, else the FMUs' default experiment, else 0
    start_ns: int = 0
    guards: Any = None  # cosim.run.row_guards.GuardSettings (physical guards of a run)
    #: the overrides it was loaded with (``--set``, a batch axis, the Python API), as ``path=value``
    #: texts in the order applied (:func:`cosim.scenario.overrides.override_texts`); the sidecar's
    overrides: list[str] = field(default_factory=list)
