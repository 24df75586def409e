"""FMI names and units, without the symbolic machinery: the structured-name rule, the unit
grammar the exporter writes into ``UnitDefinitions``, and the check of a block's names and
units (so a scene check can refuse them without importing CasADi)."""
from __future__ import annotations

import math
import re
from typing import TYPE_CHECKING

from .errors import BuildError

if TYPE_CHECKING:
    from models.block import Block

_BASE = ("kg", "m", "s", "A", "K", "mol", "cd", "rad")


def _u(factor: float = 1.0, **exp: int) -> tuple[float, dict[str, int]]:
    return factor, exp


#: Unit symbols: factor to SI and base-unit exponents.
UNIT_SYMBOLS: dict[str, tuple[float, dict[str, int]]] = {
    "kg": _u(kg=1), "m": _u(m=1), "s": _u(s=1), "A": _u(A=1), "K": _u(K=1), "mol": _u(mol=1),
    "cd": _u(cd=1), "rad": _u(rad=1),
    "N": _u(kg=1, m=1, s=-2), "J": _u(kg=1, m=2, s=-2), "W": _u(kg=1, m=2, s=-3),
    "V": _u(kg=1, m=2, s=-3, A=-1), "Ohm": _u(kg=1, m=2, s=-3, A=-2), "H": _u(kg=1, m=2, s=-2, A=-2),
    "Wb": _u(kg=1, m=2, s=-2, A=-1), "C": _u(A=1, s=1), "Hz": _u(s=-1), "Pa": _u(kg=1, m=-1, s=-2),
    "g": _u(1e-3, kg=1), "mm": _u(1e-3, m=1), "cm": _u(1e-2, m=1), "km": _u(1e3, m=1),
    "ms": _u(1e-3, s=1), "min": _u(60.0, s=1), "mA": _u(1e-3, A=1), "mH": _u(1e-3, kg=1, m=2, s=-2, A=-2),
    "mV": _u(1e-3, kg=1, m=2, s=-3, A=-1), "deg": _u(math.pi / 180, rad=1),
    "rpm": _u(2 * math.pi / 60, rad=1, s=-1),
}
_FACTOR = re.compile(r"^([A-Za-z]+)(-?\d+)?$")
#: Structured FMI names without quoted identifiers: ``a.b[1].c``.
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\[\d+(,\d+)*\])?(\.[A-Za-z_][A-Za-z0-9_]*(\[\d+(,\d+)*\])?)*$")


def parse_unit(unit: str) -> tuple[float, dict[str, int]]:
    """``unit`` -> (factor to SI, base exponents).  Grammar: ``term ['/' term]``, a term being
    ``1`` or factors joined by ``.`` (or ``*``), each a symbol of :data:`UNIT_SYMBOLS` with an
    optional integer exponent (``m2``, ``s-1``); the denominator may be parenthesised."""
    text = unit.strip()
    if text.count("/") > 1:
        raise ValueError("more than one '/'")
    num, _, den = text.partition("/")
    den = den.strip()
    if den.startswith("(") and den.endswith(")"):
        den = den[1:-1]
    factor, exps = 1.0, {b: 0 for b in _BASE}
    for part, sign in ((num, 1), (den, -1)):
        part = part.strip()
        if part in ("", "1"):
            if sign == -1 and part == "" and "/" in text:
                raise ValueError("empty denominator")
            continue
        for tok in re.split(r"[.*]", part):
            m = _FACTOR.match(tok.strip())
            if not m or m.group(1) not in UNIT_SYMBOLS:
                raise ValueError(f"unknown unit symbol {tok!r}")
            f, e = UNIT_SYMBOLS[m.group(1)]
            k = int(m.group(2) or 1) * sign
            factor *= f ** k
            for b, v in e.items():
                exps[b] += v * k
    return factor, {b: v for b, v in exps.items() if v}


def check_names(block: Block) -> None:
    """Every variable name must be a legal structured FMI name, and ``time`` is reserved."""
    for kind, seq in (("parameter", block.params), ("input", block.inputs), ("output", block.outputs),
                      ("state", block.states), ("mode", block.modes)):
        for v in seq:
            if v.name == "time":
                raise BuildError(f"block {block.name}: {kind} 'time' clashes with the FMU's independent "
                                 f"variable; rename it")
            if not _NAME.match(v.name):
                raise BuildError(f"block {block.name}: {kind} name {v.name!r} is not a structured FMI name "
                                 f"(expected e.g. 'leg[1].s' or 'platform.x')")
    for kind, seq in (("parameter", block.params), ("input", block.inputs), ("output", block.outputs),
                      ("state", block.states), ("mode", block.modes)):
        for v in seq:
            if v.unit:
                try:
                    parse_unit(v.unit)
                except ValueError as exc:
                    raise BuildError(f"block {block.name}: {kind} {v.name!r} has unit {v.unit!r} that the "
                                     f"exporter cannot read ({exc}); write SI symbols joined by '.', with "
                                     f"integer exponents and one '/', e.g. 'N.m', 'kg.m2', 'm/s2'") from None
