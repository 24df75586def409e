"""The declarative parts of a block's interface: parameters, variables, flanges, ratings and the
block error, without CasADi (so that code which only describes a block, such as a run whose FMUs
are cached, never loads the symbolic layer).  :mod:`models.block` re-exports them.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal


class BlockError(ValueError):
    """A malformed block: the message names the block and the variable."""


def suggest(name: str, choices: Sequence[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest of ``choices`` (difflib), or ``""``."""
    close = difflib.get_close_matches(name, list(choices), n=1, cutoff=0.5)
    return f"; did you mean {close[0]!r}?" if close else ""


@dataclass(frozen=True)
class Param:
    """A real parameter: ``name``, SI ``unit``, ``default``, closed bounds, description.

    ``structural`` parameters change the equations: they are baked into the generated code, are
    part of the build-cache key and are exported as ``fixed`` (visible, not settable); the others
    are ``tunable``, settable after instantiation.
    """

    name: str
    default: float
    unit: str = ""
    lower: float = -math.inf
    upper: float = math.inf
    description: str = ""
    structural: bool = False


@dataclass(frozen=True)
class Var:
    """An input, output or state variable: structured ``name`` (e.g. ``leg[1].s``), unit, text.
    An output with ``local`` is an internal variable the block computes like an output but
    exports as an FMI local: recordable, not an interface to connect (a Modelica model's
    ``mass1.s``)."""

    name: str
    unit: str = ""
    description: str = ""
    local: bool = False


@dataclass(frozen=True)
class Flange:
    """A power port: ``effort`` and ``flow`` name variables of the block (force [N] and
    velocity [m/s], or torque and angular velocity).  ``causality`` says which of the pair the
    block computes: ``"flow_out"`` (effort in, flow out) or ``"effort_out"``.  ``why``: why the
    block cannot take the other causality, where it was derived (a Modelica flange whose other
    choice leaves an index problem); "" where it was not asked or can.  Not part of equality."""

    name: str
    effort: str
    flow: str
    causality: Literal["flow_out", "effort_out"] = "flow_out"
    why: str = field(default="", compare=False)


@dataclass(frozen=True)
class Rating:
    """Operating limits of one input or output of a block: its value must stay in
    ``[low, high]`` (the variable's SI unit).  ``kind`` says what leaving them means:
    ``"stroke"`` (an actuator beyond its end of travel) or ``"rated"`` (a component beyond its
    rated values); ``source`` cites where the numbers come from.  Metadata only: the equations do
    not use it; run-time guards (:mod:`cosim.guards`) do."""

    low: float
    high: float
    kind: Literal["stroke", "rated"] = "rated"
    source: str = ""
