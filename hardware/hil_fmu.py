"""The hardware FMU: hand-written C (``hardware/c/hil_fmu.c``, ``hmac_sha256.c``) with a
generated ``modelDescription.xml``, compiled and cached by :func:`fmus.build_from_sources`.

Interface (value references as in ``hil_fmu.c``):

- inputs ``leg[i].u`` [V];
- outputs ``leg[i].s`` (leg length) and ``leg[i].stroke`` [m], ``leg[i].raw`` [counts],
  ``sample_age`` [s] (ADC reading to arrival here), ``round_trip`` [s], ``fault`` (bits of
  :data:`hardware.protocol.FAULT_NAMES`), ``state`` (0 idle, 1 armed, 2 running, 3 fault), and
  the board's real-time figures of the session: ``board_tick_late`` (largest tick lateness
  since the last step), ``board_tick_p50``/``_p99``/``_max`` [s], ``board_cpu_per_tick`` [s],
  ``board_dropped``, ``board_throttled``;
- parameters ``address`` and ``key_file`` (strings), ``timeout`` [s], ``reset_fault`` (clears a
  latched fault when connecting) and the calibration ``leg[i].raw_zero``, ``leg[i].raw_full``,
  ``leg[i].stroke_full`` [m], ``leg[i].s_offset`` [m].

The string parameters' start values are compiled in (``address``, ``key_file`` arguments of
:func:`build_hil_fmu`), so a scene needs no string settings; any master can still set them.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable

from .convert import Calibration
from .protocol import c_header
from .virtual import RIG_CALIBRATION

C_DIR = Path(__file__).with_name("c")
IDENT = "rpr_hil_board"
C_SOURCES = ["hil_fmu.c", "hmac_sha256.c"]
HEADERS = ["hmac_sha256.h"]
_PLACEHOLDER = "{00000000-0000-0000-0000-000000000000}"
LEGS = (1, 2, 3)


def _real_vars(cal: Calibration, timeout: float) -> list[tuple]:
    """(name, causality, variability, unit, start, description) in value-reference order."""
    v = []
    v += [(f"leg[{i}].u", "input", "continuous", "V", 0.0, f"leg {i} voltage command") for i in LEGS]
    v += [(f"leg[{i}].s", "output", "continuous", "m", None, f"leg {i} length (calibrated)") for i in LEGS]
    v += [(f"leg[{i}].stroke", "output", "continuous", "m", None, f"leg {i} stroke (calibrated)") for i in LEGS]
    v += [(f"leg[{i}].raw", "output", "discrete", "", None, f"leg {i} raw ADC counts (0..4095)") for i in LEGS]
    v += [("sample_age", "output", "discrete", "s", None, "age of the ADC reading when it arrived here"),
          ("fault", "output", "discrete", "", None, "latched fault bits of the board (0: none)"),
          ("state", "output", "discrete", "", None, "board state: 0 idle, 1 armed, 2 running, 3 fault"),
          ("round_trip", "output", "discrete", "s", None, "command to sample round trip of the last step"),
          ("timeout", "parameter", "fixed", "s", timeout, "longest wait for the board's answer; then fmi2Error")]
    v += [(f"leg[{i}].raw_zero", "parameter", "fixed", "", cal.raw_zero, f"leg {i}: counts at zero stroke") for i in LEGS]
    v += [(f"leg[{i}].raw_full", "parameter", "fixed", "", cal.raw_full, f"leg {i}: counts at stroke_full") for i in LEGS]
    v += [(f"leg[{i}].stroke_full", "parameter", "fixed", "m", cal.stroke_full, f"leg {i}: calibrated stroke")
          for i in LEGS]
    v += [(f"leg[{i}].s_offset", "parameter", "fixed", "m", cal.s_offset, f"leg {i}: leg length at zero stroke")
          for i in LEGS]
    v += [("board_tick_late", "output", "discrete", "s", None, "board: largest tick lateness since the last step"),
          ("board_tick_p50", "output", "discrete", "s", None, "board: tick lateness p50 over the session"),
          ("board_tick_p99", "output", "discrete", "s", None, "board: tick lateness p99 over the session"),
          ("board_tick_max", "output", "discrete", "s", None, "board: largest tick lateness of the session"),
          ("board_cpu_per_tick", "output", "discrete", "s", None, "board: CPU time per tick (session mean)"),
          ("board_dropped", "output", "discrete", "", None, "board: datagrams dropped (bad, stale, throttled)"),
          ("board_throttled", "output", "discrete", "", None, "board: of those, beyond its authentication budget")]
    return v


def model_description(address: str, key_file: str, cal: Calibration, timeout: float) -> str:
    root = ET.Element("fmiModelDescription", {"fmiVersion": "2.0", "modelName": IDENT, "guid": _PLACEHOLDER,
                                              "description": "the 3-RPR rig through its BeagleBone I/O daemon "
                                                             "(hardware in the loop)",
                                              "generationTool": "rpr-cosim hardware.hil_fmu",
                                              "variableNamingConvention": "structured",
                                              "numberOfEventIndicators": "0"})
    cs = ET.SubElement(root, "CoSimulation", {
        "modelIdentifier": IDENT, "needsExecutionTool": "false", "canHandleVariableCommunicationStepSize": "true",
        "canInterpolateInputs": "false", "maxOutputDerivativeOrder": "0", "canRunAsynchronuously": "false",
        "canBeInstantiatedOnlyOncePerProcess": "false", "canNotUseMemoryManagementFunctions": "true",
        "canGetAndSetFMUstate": "false", "canSerializeFMUstate": "false", "providesDirectionalDerivative": "false"})
    files = ET.SubElement(cs, "SourceFiles")
    for s in C_SOURCES:
        ET.SubElement(files, "File", name=s)
    units = ET.SubElement(root, "UnitDefinitions")
    for name, exps in (("V", {"kg": "1", "m": "2", "s": "-3", "A": "-1"}), ("m", {"m": "1"}), ("s", {"s": "1"})):
        ET.SubElement(ET.SubElement(units, "Unit", name=name), "BaseUnit", exps)
    cats = ET.SubElement(root, "LogCategories")
    ET.SubElement(cats, "Category", name="logStatusError", description="board silent, faulted or misconfigured")
    ET.SubElement(cats, "Category", name="logCalls", description="sessions with the board")
    ET.SubElement(root, "DefaultExperiment", startTime="0.0", stopTime="1.0", stepSize="0.001")
    mv = ET.SubElement(root, "ModelVariables")
    outputs = []
    reals = _real_vars(cal, timeout)
    for vr, (name, caus, var, unit, start, text) in enumerate(reals):
        attrs = {"name": name, "valueReference": str(vr), "causality": caus, "variability": var, "description": text}
        if caus == "output":
            attrs["initial"] = "calculated"
            outputs.append(vr)
        typed = {"unit": unit} if unit else {}
        if start is not None:
            typed["start"] = repr(float(start))
        ET.SubElement(ET.SubElement(mv, "ScalarVariable", attrs), "Real", typed)
    n_real = len(reals)
    sv = ET.SubElement(mv, "ScalarVariable", {"name": "reset_fault", "valueReference": "0", "causality": "parameter",
                                              "variability": "fixed",
                                              "description": "clear a latched board fault when connecting"})
    ET.SubElement(sv, "Boolean", start="false")
    for vr, (name, start, text) in enumerate((("address", address, "board HOST:PORT (UDP)"),
                                              ("key_file", key_file, "shared key file (rpr-cosim board keygen)"))):
        sv = ET.SubElement(mv, "ScalarVariable", {"name": name, "valueReference": str(vr), "causality": "parameter",
                                                  "variability": "fixed", "description": text})
        ET.SubElement(sv, "String", start=start)
    ms = ET.SubElement(root, "ModelStructure")
    out_el = ET.SubElement(ms, "Outputs")
    for vr in outputs:
        ET.SubElement(out_el, "Unknown", index=str(vr + 1), dependencies="")
    init_el = ET.SubElement(ms, "InitialUnknowns")
    for vr in outputs:
        ET.SubElement(init_el, "Unknown", index=str(vr + 1), dependencies="")
    assert n_real == 36, "the value references must match hil_fmu.c"
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _c_string(text: str) -> str:
    if any(ord(c) < 32 or c in '"\\' for c in text):
        raise ValueError(f"{text!r}: quotes, backslashes and control characters are not allowed")
    return f'"{text}"'


def config_header(address: str, key_file: str, cal: Calibration, timeout: float) -> str:
    return "\n".join([
        "/* generated by hardware/hil_fmu.py: this build's start values */",
        f'#define HIL_GUID "{_PLACEHOLDER}"',
        f"#define HIL_ADDRESS {_c_string(address)}",
        f"#define HIL_KEY_FILE {_c_string(key_file)}",
        f"#define HIL_TIMEOUT {float(timeout)!r}",
        f"#define HIL_RAW_ZERO {float(cal.raw_zero)!r}",
        f"#define HIL_RAW_FULL {float(cal.raw_full)!r}",
        f"#define HIL_STROKE_FULL {float(cal.stroke_full)!r}",
        f"#define HIL_S_OFFSET {float(cal.s_offset)!r}", ""])


def build_hil_fmu(*, address: str = "127.0.0.1:5005", key_file: str | Path = "~/.config/rpr-cosim/board.key",
                  calibration: Calibration = RIG_CALIBRATION, timeout: float = 0.05, cache_dir: Path | None = None,
                  progress: Callable[[str], None] | None = None) -> Path:
    """The hardware FMU with these start values (built on a cache miss, about a second).  Scenes
    build it with the defaults and set ``address`` and ``key_file`` as start values; a leading
    ``~/`` of ``key_file`` is the user's home directory."""
    from fmus import build_from_sources
    from fmus.codegen import FMI_HEADER_DIR, FMI_HEADERS

    key_file = str(key_file)
    if not (0 < timeout < 10):
        raise ValueError(f"timeout = {timeout} s: expected 0 < timeout < 10")
    files = {n: (C_DIR / n).read_text() for n in C_SOURCES + HEADERS}
    files |= {n: (FMI_HEADER_DIR / n).read_text() for n in FMI_HEADERS["2.0"]}
    files["hil_config.h"] = config_header(address, key_file, calibration, timeout)
    files["board_protocol.h"] = c_header()
    xml = model_description(address, key_file, calibration, timeout)
    return build_from_sources(IDENT, files, list(C_SOURCES), xml, cache_dir=cache_dir, progress=progress,
                              record={"kind": "hardware", "integrator": "board", "states": 0, "address": address,
                                      "key_file": key_file},
                              label="hardware FMU")
