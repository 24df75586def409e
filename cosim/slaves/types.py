"""FMI variable types as the master sees them: storage, the FMI accessors, and the conversions a
scene may ask for explicitly (``a.y -> b.u as Float64``).

Canonical type names: ``Real`` is FMI 2.0 Real and FMI 3.0 Float64 (the fast path's type);
``Integer`` is FMI 2.0 Integer and FMI 3.0 Int32; the others are the FMI 3.0 names (``Float32``,
``Int8`` ... ``UInt64``, ``Boolean``, ``String``, ``Binary``, ``Enumeration``).  Two variables
connect without conversion when their canonical types (and array sizes) are equal.

Conversions (only with ``as TYPE`` on the connection, TYPE = the destination's type):

- any integer type, Boolean (0/1) or Enumeration -> Float64/Float32: the nearest float (exact up
  to 2**53 for Float64, 2**24 for Float32);
- Float32 -> Float64 exact, Float64 -> Float32 rounded to the nearest Float32;
- an integer type, Boolean or Enumeration (an Int64 value) -> an integer type whose range holds
  every value of the source;
- nothing else: a float does not become an integer without a rounding rule, a narrower integer
  could overflow, String and Binary connect only to their own type.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FmiType:
    """One canonical type: numpy storage (``object`` for String/Binary), the fmpy accessor suffix in
    FMI 2.0 (None: no such type there) and FMI 3.0, and the integer range (None for non-integers)."""

    name: str
    dtype: type
    fmi2: str | None
    fmi3: str
    lo: int | None = None
    hi: int | None = None

    @property
    def numeric(self) -> bool:
        return self.dtype is not object

    @property
    def floating(self) -> bool:
        return self.name in ("Real", "Float32")

    @property
    def integral(self) -> bool:
        return self.lo is not None


def _int(name: str, bits: int, signed: bool, fmi2: str | None = None) -> FmiType:
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    return FmiType(name, getattr(np, name.lower().replace("integer", "int32")), fmi2, name, lo, hi)


TYPES: dict[str, FmiType] = {t.name: t for t in [
    FmiType("Real", np.float64, "Real", "Float64"),
    FmiType("Float32", np.float32, None, "Float32"),
    _int("Int8", 8, True), _int("UInt8", 8, False), _int("Int16", 16, True), _int("UInt16", 16, False),
    FmiType("Integer", np.int32, "Integer", "Int32", -(1 << 31), (1 << 31) - 1),
    _int("UInt32", 32, False), _int("Int64", 64, True), _int("UInt64", 64, False),
    FmiType("Boolean", np.bool_, "Boolean", "Boolean", 0, 1),
    FmiType("String", object, "String", "String"),
    FmiType("Binary", object, None, "Binary"),
    FmiType("Enumeration", np.int64, "Integer", "Int64", -(1 << 63), (1 << 63) - 1),
]}

#: modelDescription type name -> canonical name
ALIASES = {"Real": "Real", "Float64": "Real", "Integer": "Integer", "Int32": "Integer",
           **{n: n for n in TYPES if n not in ("Real", "Integer")}}


def canonical(fmi_type: str) -> str:
    """The canonical name of a modelDescription type (``Float64`` -> ``Real``); unknown types
    (e.g. Clock) are returned unchanged."""
    return ALIASES.get(fmi_type, fmi_type)


def display(type_name: str, fmi_version: str | None = None) -> str:
    """The name a user reads in the FMU's own version: Real/Float64, Integer/Int32."""
    three = str(fmi_version or "").startswith("3")
    if type_name == "Real":
        return "Float64" if three else "Real"
    if type_name == "Integer":
        return "Int32" if three else "Integer"
    return type_name


def conversion(src: str, dst: str) -> str | None:
    """None when ``src`` values may be converted to ``dst`` with ``as``; else why not."""
    if src == dst:
        return None
    a, b = TYPES.get(src), TYPES.get(dst)
    if a is None or b is None:
        return f"{src if a is None else dst} variables cannot be connected"
    if not a.numeric or not b.numeric:
        return "String and Binary connect only to their own type"
    if b.name == "Enumeration":
        return "an Enumeration takes only values of its own items; connect an Enumeration to it"
    if b.floating:
        return None
    if a.floating:
        return "a float does not become an integer without a rounding rule; round it in the source model"
    if b.name == "Boolean":
        return "an integer does not become a Boolean without a rule; compare it in the source model"
    if a.lo < b.lo or a.hi > b.hi:
        return f"{b.name} cannot hold every {a.name} value ({a.lo} .. {a.hi})"
    return None


def parse_start(value, ftype: FmiType, size: int, what: str, label: str | None = None) -> np.ndarray | list:
    """A start value from YAML or a modelDescription (number, bool, text, list, or a blank-separated
    string for an array) as ``size`` values of ``ftype`` (called ``label`` in messages); raises
    ValueError saying what is expected."""
    label = label or ftype.name
    items = value if isinstance(value, (list, tuple)) else (
        value.split() if isinstance(value, str) and size > 1 and ftype.numeric else [value])
    if len(items) != size:
        raise ValueError(f"{what} needs {size} value{'s' if size != 1 else ''}, got {len(items)}")
    if ftype.name == "String":
        if not all(isinstance(x, str) for x in items):
            raise ValueError(f"{what} must be text (a String), got {value!r}")
        return list(items)
    if ftype.name == "Binary":
        out = []
        for x in items:
            try:
                out.append(bytes.fromhex(x) if isinstance(x, str) else bytes(x))
            except (ValueError, TypeError):
                raise ValueError(f"{what} must be hexadecimal bytes (a Binary, e.g. '666f6f'), got {x!r}") from None
        return out
    if ftype.name == "Boolean":
        vals = []
        for x in items:
            if isinstance(x, str) and x.lower() in ("true", "false"):
                x = x.lower() == "true"
            if not isinstance(x, (bool, np.bool_)) and x not in (0, 1):
                raise ValueError(f"{what} must be true or false (a Boolean), got {x!r}")
            vals.append(bool(x))
        return np.array(vals, dtype=np.bool_)
    vals = []
    for x in items:
        if isinstance(x, str):
            try:
                x = int(x) if ftype.integral else float(x)
            except ValueError:
                raise ValueError(f"{what} must be a number ({label}), got {x!r}") from None
        if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
            raise ValueError(f"{what} must be a number ({label}), got {x!r}")
        if ftype.integral:
            if isinstance(x, (float, np.floating)) and not float(x).is_integer():
                raise ValueError(f"{what} must be a whole number ({label}), got {x!r}")
            x = int(x)
            if not ftype.lo <= x <= ftype.hi:
                raise ValueError(f"{what} = {x} is outside the range of {label} ({ftype.lo} .. {ftype.hi})")
        elif not np.isfinite(float(x)):
            raise ValueError(f"{what} must be a finite number, got {x!r}")
        vals.append(x)
    return np.array(vals, dtype=ftype.dtype)
