"""SI units as dimensions: parsing Modelica/FMI unit strings (``"N.m/A"``, ``"kg.m2"``,
``"m/s2"``) into exponents of the seven base units, for the unit check of Modelica equations
(:mod:`models.modelica`) and of a scene's connections (Modelica's rule: connected variables have
compatible units).  Prefixes (``mm``, ``kN``, ``uA``) scale a unit without changing its
dimension (:func:`scaled` gives the scale too); ``rad`` and ``sr`` are dimensionless.  An unknown
symbol gives None (not checked).  :func:`compose` writes products and quotients of unit texts as
one text with at most one ``/`` (``N/(m/s)`` -> ``N.s/m``), the grammar FMI exporters read."""
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
#: Each symbol's factor to its SI unit (the others: 1).
_FACTORS = {"g": 1e-3, "deg": 3.141592653589793 / 180, "rev": 2 * 3.141592653589793, "min": 60.0, "h": 3600.0,
            "rpm": 2 * 3.141592653589793 / 60, "bar": 1e5, "l": 1e-3, "L": 1e-3}
_PREFIX_FACTORS = {"da": 1e1, "y": 1e-24, "z": 1e-21, "a": 1e-18, "f": 1e-15, "p": 1e-12, "n": 1e-9, "u": 1e-6,
                   "m": 1e-3, "c": 1e-2, "d": 1e-1, "h": 1e2, "k": 1e3, "M": 1e6, "G": 1e9, "T": 1e12, "P": 1e15,
                   "E": 1e18, "Z": 1e21, "Y": 1e24}
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


def _scaled_symbol(sym: str) -> tuple[float, Dims] | None:
    if sym in _SYMBOLS:
        return _FACTORS.get(sym, 1.0), _SYMBOLS[sym]
    for p in _PREFIXES:
        rest = sym[len(p):]
        if sym.startswith(p) and rest in _SYMBOLS and rest not in ("1", "kg"):
            return _PREFIX_FACTORS[p] * _FACTORS.get(rest, 1.0), _SYMBOLS[rest]
    return None


def _factors(text: str) -> list[tuple[str, int]] | None:
    """``"N.m2"`` -> [("N", 1), ("m", 2)] (None when a factor is not ``symbol[exponent]``)."""
    out = []
    for factor in text.replace("*", ".").split("."):
        if factor in ("", "1"):
            continue
        m = _FACTOR.match(factor)
        if not m:
            return None
        out.append((m.group(1), int(m.group(2) or 1)))
    return out


def symbols(unit: str) -> dict[str, int] | None:
    """The symbols of ``unit`` with their exponents (``"N/(m/s)"`` -> {N: 1, m: -1, s: 1}), the
    symbols kept as written (``mm`` stays ``mm``); None when it is not a product and quotients of
    ``symbol[exponent]`` factors.  ``a/b/c`` reads ``(a/b)/c``; parentheses group."""
    text = unit.strip()
    if not text:
        return {}
    out: dict[str, int] = {}
    depth, sign_stack, sign, token = 0, [1], 1, ""

    def flush(tok: str, k: int) -> bool:
        fs = _factors(tok)
        if fs is None:
            return False
        for sym, e in fs:
            out[sym] = out.get(sym, 0) + k * e
        return True

    for ch in text + "\0":
        if ch in "/()\0":
            if token and not flush(token, sign):
                return None
            token = ""
            if ch == "/":
                sign = -sign_stack[-1]
            elif ch == "(":
                sign_stack.append(sign)
                depth += 1
            elif ch == ")":
                if depth == 0:
                    return None
                depth -= 1
                sign = sign_stack.pop()
        else:
            token += ch
    if depth:
        return None
    return {k: v for k, v in out.items() if v}


def compose(*terms: tuple[str, int]) -> str:
    """The unit of the product of ``unit^k`` over ``terms`` as one text with at most one ``/``
    (``compose(("N", 1), ("m/s", -1))`` -> ``"N.s/m"``; ``"1"`` when nothing is left).  A unit
    that :func:`symbols` cannot read is kept whole, in parentheses."""
    total: dict[str, int] = {}
    raw: list[str] = []
    for unit, k in terms:
        syms = symbols(unit)
        if syms is None:
            raw.append(f"({unit})" if k == 1 else f"({unit}){k}")
            continue
        for sym, e in syms.items():
            total[sym] = total.get(sym, 0) + k * e
    def term(sym: str, e: int) -> str:
        return sym if e == 1 else f"{sym}{e}"
    num = [term(s, e) for s, e in total.items() if e > 0] + raw
    den = [term(s, -e) for s, e in total.items() if e < 0]
    text = ".".join(num) or "1"
    if den:
        text += "/" + (den[0] if len(den) == 1 else f"({'.'.join(den)})")
    return text


def scaled(unit: str | None) -> tuple[float, Dims] | None:
    """``unit`` as (factor to SI, dimension): ``"mm"`` -> (1e-3, m); None for no unit or a symbol
    not known here."""
    if unit is None or not unit.strip():
        return None
    syms = symbols(unit)
    if syms is None:
        return None
    factor, dims = 1.0, ONE
    for sym, e in syms.items():
        got = _scaled_symbol(sym)
        if got is None:
            return None
        factor *= got[0] ** e
        dims = times(dims, got[1], e)
    return factor, dims
