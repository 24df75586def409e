"""The FMI 2.0 and 3.0 C functions the master calls, declared once.

Each entry of :data:`FUNCTIONS` is one C prototype (the return type and the parameters with the C
types the standard's headers resolve to on our platforms: ``fmi2Component`` and ``fmi3Instance``
are ``void *``, value references ``uint32_t``, ``fmi2Boolean`` is ``int``, ``fmi3Boolean``
``bool``, an enumeration parameter ``unsigned int``: GCC's type of an enum without negative
values; the status returned is read as ``int``).  From it come both views the project needs:

* :func:`c_typedef` / :func:`c_typedefs`: a C function-pointer typedef ``<name>_t`` for the
  compiled master loops, which receive the FMU's entry points as addresses;
* :func:`prototype`: the ``ctypes.CFUNCTYPE`` the Python slaves call through (``raw=True``: every
  pointer parameter as ``c_void_p``, for buffers passed by address).

The FMUs we build and the hardware FMU implement these functions against the standard's own
headers (``fmi2Functions.h``/``fmi3Functions.h``, shipped with FMPy); this table is only the
callers' side, checked against those headers by ``tests/test_native.py``.
"""
from __future__ import annotations

import ctypes
from functools import lru_cache

#: C type (as written in :data:`FUNCTIONS`) -> ctypes type; a pointer type not listed maps to
#: ``POINTER`` of its pointee.
_SCALARS = {"int": ctypes.c_int, "unsigned int": ctypes.c_uint, "int32_t": ctypes.c_int32, "uint32_t": ctypes.c_uint32,
            "size_t": ctypes.c_size_t,
            "double": ctypes.c_double, "float": ctypes.c_float, "bool": ctypes.c_bool, "void *": ctypes.c_void_p,
            "int8_t": ctypes.c_int8, "uint8_t": ctypes.c_uint8, "int16_t": ctypes.c_int16,
            "uint16_t": ctypes.c_uint16, "int64_t": ctypes.c_int64, "uint64_t": ctypes.c_uint64}

Param = tuple[str, str]  # (C type, name)

_VR = "const uint32_t *"

#: FMI 3.0 numeric types: the name in the function (fmi3GetFloat64...) -> C type.
FMI3_NUMERIC = {"Float32": "float", "Float64": "double", "Int8": "int8_t", "UInt8": "uint8_t", "Int16": "int16_t",
                "UInt16": "uint16_t", "Int32": "int32_t", "UInt32": "uint32_t", "Int64": "int64_t",
                "UInt64": "uint64_t", "Boolean": "bool"}
#: FMI 2.0 numeric types -> C type (fmi2Real, fmi2Integer, fmi2Boolean).
FMI2_NUMERIC = {"Real": "double", "Integer": "int", "Boolean": "int"}


def _fmi2_io(t: str, c: str) -> dict[str, tuple[str, list[Param]]]:
    return {f"fmi2Get{t}": ("int", [("void *", "c"), (_VR, "vr"), ("size_t", "nvr"), (f"{c} *", "value")]),
            f"fmi2Set{t}": ("int", [("void *", "c"), (_VR, "vr"), ("size_t", "nvr"), (f"const {c} *", "value")])}


def _fmi3_io(t: str, c: str) -> dict[str, tuple[str, list[Param]]]:
    return {f"fmi3Get{t}": ("int", [("void *", "instance"), (_VR, "valueReferences"),
                                     ("size_t", "nValueReferences"), (f"{c} *", "values"), ("size_t", "nValues")]),
            f"fmi3Set{t}": ("int", [("void *", "instance"), (_VR, "valueReferences"),
                                     ("size_t", "nValueReferences"), (f"const {c} *", "values"),
                                     ("size_t", "nValues")])}


#: name -> (return type, parameters): the prototypes of the standard (fmi2Functions.h, fmi3Functions.h).
FUNCTIONS: dict[str, tuple[str, list[Param]]] = {
    "fmi2DoStep": ("int", [("void *", "c"), ("double", "currentCommunicationPoint"),
                           ("double", "communicationStepSize"),
                           ("int", "noSetFMUStatePriorToCurrentCommunicationPoint")]),
    **{k: v for t, c in FMI2_NUMERIC.items() for k, v in _fmi2_io(t, c).items()},
    "fmi2SetRealInputDerivatives": ("int", [("void *", "c"), (_VR, "vr"), ("size_t", "nvr"),
                                            ("const int *", "order"), ("const double *", "value")]),
    "fmi2GetFMUstate": ("int", [("void *", "c"), ("void **", "FMUstate")]),
    "fmi2SetFMUstate": ("int", [("void *", "c"), ("void *", "FMUstate")]),
    "fmi2FreeFMUstate": ("int", [("void *", "c"), ("void **", "FMUstate")]),
    "fmi2GetBooleanStatus": ("int", [("void *", "c"), ("unsigned int", "s"), ("int *", "value")]),
    "fmi2GetDirectionalDerivative": ("int", [("void *", "c"), (_VR, "vUnknown_ref"), ("size_t", "nUnknown"),
                                             (_VR, "vKnown_ref"), ("size_t", "nKnown"), ("const double *", "dvKnown"),
                                             ("double *", "dvUnknown")]),
    "fmi3DoStep": ("int", [("void *", "instance"), ("double", "currentCommunicationPoint"),
                           ("double", "communicationStepSize"),
                           ("bool", "noSetFMUStatePriorToCurrentCommunicationPoint"),
                           ("bool *", "eventHandlingNeeded"), ("bool *", "terminateSimulation"),
                           ("bool *", "earlyReturn"), ("double *", "lastSuccessfulTime")]),
    **{k: v for t, c in FMI3_NUMERIC.items() for k, v in _fmi3_io(t, c).items()},
    "fmi3GetFMUState": ("int", [("void *", "instance"), ("void **", "FMUState")]),
    "fmi3SetFMUState": ("int", [("void *", "instance"), ("void *", "FMUState")]),
    "fmi3FreeFMUState": ("int", [("void *", "instance"), ("void **", "FMUState")]),
    "fmi3GetDirectionalDerivative": ("int", [("void *", "instance"), (_VR, "unknowns"), ("size_t", "nUnknowns"),
                                             (_VR, "knowns"), ("size_t", "nKnowns"), ("const double *", "seed"),
                                             ("size_t", "nSeed"), ("double *", "sensitivity"),
                                             ("size_t", "nSensitivity")]),
}


def c_typedef(name: str) -> str:
    """``typedef int (*<name>_t)(void *c, double ...);`` for FMI function ``name``."""
    ret, params = FUNCTIONS[name]
    args = ", ".join(f"{t}{'' if t.endswith('*') else ' '}{p}" for t, p in params)
    return f"typedef {ret} (*{name}_t)({args});"


def c_typedefs(names=None) -> str:
    """The typedefs of ``names`` (default: every function), one a line."""
    return "\n".join(c_typedef(n) for n in (names or FUNCTIONS)) + "\n"


def _ctype(c: str, raw: bool):
    c = c.removeprefix("const ").strip()
    if c in _SCALARS:
        return _SCALARS[c]
    if raw:
        return ctypes.c_void_p
    base = c[:-1].strip()
    return ctypes.POINTER(_ctype(base, raw) if base != "void" else ctypes.c_void_p)


@lru_cache(maxsize=None)
def prototype(name: str, raw: bool = False):
    """The ``ctypes.CFUNCTYPE`` of FMI function ``name`` (``raw``: pointers as ``c_void_p``)."""
    ret, params = FUNCTIONS[name]
    return ctypes.CFUNCTYPE(_ctype(ret, raw), *(_ctype(t, raw) for t, _ in params))


__all__ = ["FMI2_NUMERIC", "FMI3_NUMERIC", "FUNCTIONS", "c_typedef", "c_typedefs", "prototype"]
