"""SI units as dimensions: parsing Modelica/FMI unit strings (``"N.m/A"``, ``"kg.m2"``,
``"m/s2"``) into exponents of the seven base units, for the unit check of Modelica equations
(:mod:`models.modelica`).  Prefixes (``mm``, ``kN``, ``uA``) scale a unit without changing its
dimension; ``rad`` and ``sr`` are dimensionless.  An unknown symbol gives None (not checked)."""
from __future__ import annotations

import re
from fractions import Fraction

BASE = ("kg", "m", "s", "A", "K", "mol", "cd")
Dims = tuple[Fraction, ...]
ONE: Dims = tuple(Fraction(0) for _ in BASE)


def _d(**e: int) -> Dims:
    return tuple(Fraction(e.get(b, 0)) for b in BASE)


_SYMBOLS: dict[str, Dims] = {
    "1": ONE, "rad": ONE, "sr": ONE, "deg": ONE, "rev": ONE,
    "kg": _d(kg=1), "g": _d(kg=1), "m": _d(m=1), "s": _d(s=1), "A": _d(A=1), "K": _d(K=1), "mol": _d(mol=1),
    "cd": _d(cd=1), "min": _d(s=1), "h": _d(s=1), "Hz": _d(s=-1), "rpm": _d(s=-1),
    "N": _d(kg=1, m=1, s=-2), "J": _d(kg=1, m=2, s=-2), "W": _d(kg=1, m=2, s=-3), "Pa": _d(kg=1, m=-1, s=-2),
    "bar": _d(kg=1, m=-1, s=-2), "C": _d(A=1, s=1), "V": _d(kg=1, m=2, s=-3, A=-1),
    "Ohm": _d(kg=1, m=2, s=-3, A=-2), "S": _d(kg=-1, m=-2, s=3, A=2), "F": _d(kg=-1, m=-2, s=4, A=2),
    "H": _d(kg=1, m=2, s=-2, A=-2), "Wb": _d(kg=1, m=2, s=-2, A=-1), "T": _d(kg=1, s=-2, A=-1),
    "l": _d(m=3), "L": _d(m=3), "degC": _d(K=1),
}
_PREFIXES = ("da", "y", "z", "a", "f", "p", "n", "u", "m", "c", "d", "h", "k", "M", "G", "T", "P", "E", "Z", "Y")
_FACTOR = re.compile(r"^([A-Za-z]+)(-?\d+)?$")


def _symbol(sym: str) -> Dims | None:
    if sym in _SYMBOLS:
        return _SYMBOLS[sym]
    for p in _PREFIXES:
        if sym.startswith(p) and sym[len(p):] in _SYMBOLS and sym[len(p):] not in ("1", "kg"):
            return _SYMBOLS[sym[len(p):]]
    return None


def _product(text: str) -> Dims | None:
    total = ONE
    for factor in text.split("."):
        if factor in ("", "1"):
            continue
        m = _FACTOR.match(factor)
        dims = _symbol(m.group(1)) if m else None
        if dims is None:
            return None
        k = int(m.group(2) or 1)
        total = tuple(a + k * b for a, b in zip(total, dims))
    return total


def parse(unit: str | None) -> Dims | None:
    """The dimension of ``unit`` (None for no unit or a symbol not known here)."""
    if unit is None or not unit.strip():
        return None
    text = unit.strip().replace("(", "").replace(")", "")
    num, *dens = text.split("/")
    total = _product(num)
    for den in dens:
        d = _product(den)
        if total is None or d is None:
            return None
        total = tuple(a - b for a, b in zip(total, d))
    return total


def text(dims: Dims) -> str:
    """``kg.m2.s-2`` (``1`` when dimensionless)."""
    parts = []
    for b, e in zip(BASE, dims):
        if e:
            parts.append(b + ("" if e == 1 else str(e).replace("/", "|")))
    return ".".join(parts) or "1"


def times(a: Dims, b: Dims, k: Fraction | int = 1) -> Dims:
    """``a * b^k`` as dimensions."""
    return tuple(x + k * y for x, y in zip(a, b))


def power(a: Dims, k: Fraction) -> Dims:
    return tuple(x * k for x in a)
