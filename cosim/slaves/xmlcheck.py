"""The modelDescription.xml of an external FMU checked like FMPy checks it, plus what the master
relies on: the root element, the FMI schema (FMPy's), unique variable names, unique value
references (across all variables in FMI 3.0; per type in FMI 2.0, where aliases are allowed except
for inputs), one type per FMI 2.0
ScalarVariable, and numbers where numbers belong (value references, start/min/max/nominal of
numeric variables, the DefaultExperiment's times).  Those are errors; what FMPy's validation
finds beyond them (e.g. an incomplete ModelStructure), which the standard only recommends or
which the master does not rely on, is a warning.

:func:`check_xml` returns ``[(severity, line, message)]``; each message names the element.
"""
from __future__ import annotations

import math
import zipfile
from pathlib import Path

REAL2 = ("Real",)
INT_TYPES = ("Integer", "Enumeration", "Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32", "Int64", "UInt64")
FLOAT_TYPES = ("Real", "Float32", "Float64")
TYPES2 = ("Real", "Integer", "Boolean", "String", "Enumeration")


def _float(text: str | None) -> bool:
    try:
        return math.isfinite(float(text)) or text.strip().lower() in ("inf", "-inf", "infinity", "-infinity")
    except (TypeError, ValueError):
        return False


def _int(text: str | None) -> bool:
    try:
        int(str(text).strip())
        return True
    except ValueError:
        return False


def _element(el) -> str:
    name = el.get("name")
    tag = el.tag.split("}")[-1] if isinstance(el.tag, str) else "?"
    return f"<{tag}{f' name={name!r}' if name is not None else ''}>"


def check_xml(path: Path) -> list[tuple[str, int, str]]:
    """Problems of the FMU ``path``'s modelDescription.xml (see the module docstring)."""
    from lxml import etree

    out: list[tuple[str, int, str]] = []
    try:
        with zipfile.ZipFile(path) as z:
            text = z.read("modelDescription.xml")
    except (zipfile.BadZipFile, KeyError, OSError) as exc:
        return [("error", 0, f"no readable modelDescription.xml ({exc})")]
    try:
        root = etree.fromstring(text)
    except etree.XMLSyntaxError as exc:
        return [("error", exc.lineno or 0, f"XML syntax: {exc.msg}")]
    if root.tag != "fmiModelDescription":
        return [("error", root.sourceline or 0, f"root element <{root.tag}>; an FMU's model description is "
                                                f"<fmiModelDescription>")]
    version = str(root.get("fmiVersion", ""))
    fmi3 = version.startswith("3")
    if not version.startswith(("2", "3")):
        return []  # an FMI 1.0 FMU: refused as such when it is described (cosim.slaves.description)
    de = root.find("DefaultExperiment")
    if de is not None:
        for attr in ("startTime", "stopTime", "tolerance", "stepSize"):
            if de.get(attr) is not None and not _float(de.get(attr)):
                out.append(("error", de.sourceline or 0, f"<DefaultExperiment>: {attr}={de.get(attr)!r} is not a number"))
    mv = root.find("ModelVariables")
    names: dict[str, int] = {}
    vrs: dict[tuple, tuple[str, int]] = {}
    for el in (mv if mv is not None else []):
        if not isinstance(el.tag, str):
            continue
        line = el.sourceline or 0
        name = el.get("name")
        if name is None:
            out.append(("error", line, f"{_element(el)}: no name"))
            continue
        if name in names:
            out.append(("error", line, f"{_element(el)}: the name {name!r} is used twice (also line {names[name]})"))
        names.setdefault(name, line)
        if fmi3:
            typ, holder = el.tag, el
        else:
            kinds = [c for c in el if isinstance(c.tag, str) and c.tag in TYPES2]
            if len(kinds) != 1:
                out.append(("error", line, f"{_element(el)}: {'no type element' if not kinds else 'several type elements'}"
                                           f" (one of {', '.join(TYPES2)} expected)"))
                continue
            typ, holder = kinds[0].tag, kinds[0]
        vr = el.get("valueReference")
        if not _int(vr) or int(vr) < 0:
            out.append(("error", line, f"{_element(el)}: valueReference={vr!r} is not a non-negative integer"))
        else:
            key = (int(vr),) if fmi3 else (typ, int(vr))
            caus = el.get("causality", "local")
            if key in vrs:
                other, oline, ocaus = vrs[key]
                # FMI 2.0 allows aliases (one value, several names), but not for an input: setting it would set another
                if fmi3 or "input" in (caus, ocaus):
                    out.append(("error", line, f"{_element(el)}: valueReference {vr} is also {other!r}'s (line {oline})"
                                               f"{'' if fmi3 else f' for type {typ}, and an input cannot be an alias'}"))
            vrs.setdefault(key, (name, line, caus))
        if typ in FLOAT_TYPES or typ in INT_TYPES:
            test = _float if typ in FLOAT_TYPES else _int
            for attr in ("start", "min", "max", "nominal"):
                raw = holder.get(attr)
                if raw is None or (attr == "nominal" and typ in INT_TYPES):
                    continue
                parts = raw.split() if fmi3 and attr == "start" else [raw]
                if not all(test(p) for p in parts):
                    out.append(("error", line, f"{_element(el)}: {attr}={raw!r} is not "
                                               f"{'a number' if typ in FLOAT_TYPES else 'an integer'}"))
    if any(s == "error" for s, _, _ in out):
        return out
    out += _fmpy_findings(path)
    return out


def _fmpy_findings(path: Path) -> list[tuple[str, int, str]]:
    """FMPy's validation: schema violations are errors, its other findings warnings."""
    import fmpy
    from fmpy.validation import validate_fmu

    try:
        fmpy.read_model_description(str(path), validate=True, validate_variable_names=False,
                                    validate_model_structure=False)
    except Exception as exc:  # fmpy raises ValidationError (with .problems) or bare Exceptions
        probs = getattr(exc, "problems", None) or [str(exc).splitlines()[0] if str(exc) else type(exc).__name__]
        return [("error", 0, f"FMI schema: {p}") for p in probs]
    try:
        found = validate_fmu(str(path))
    except Exception as exc:
        return [("warning", 0, f"FMPy's validation stopped: {exc}")]
    return [("warning", 0, f"FMPy: {p}") for p in found]
