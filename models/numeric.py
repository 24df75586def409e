"""Evaluate a CasADi SX function over numpy arrays of any shape, one numpy call per operation.

CasADi's own numeric evaluation runs its virtual machine once per point (about 0.7 µs per call
for even a tiny function); a 640 000-point map then costs seconds.  Replaying the function's
instruction list with numpy ufuncs instead costs one vectorised numpy call per instruction, so
the same expression serves both the symbolic models and the dense numpy maps.

The instruction list is plain data (:meth:`NumpyFunction.to_data`): a replay rebuilt from it
(:meth:`NumpyFunction.from_data`) needs numpy only, not CasADi.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

#: Operations by their CasADi name (``casadi.OP_*``), so that a stored program needs no CasADi.
_UNARY: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "OP_NEG": np.negative, "OP_EXP": np.exp, "OP_LOG": np.log, "OP_SQRT": np.sqrt,
    "OP_SQ": np.square, "OP_TWICE": lambda a: 2.0 * a, "OP_SIN": np.sin, "OP_COS": np.cos,
    "OP_TAN": np.tan, "OP_ASIN": np.arcsin, "OP_ACOS": np.arccos, "OP_ATAN": np.arctan,
    "OP_FABS": np.abs, "OP_SIGN": np.sign, "OP_INV": np.reciprocal, "OP_FLOOR": np.floor,
    "OP_CEIL": np.ceil, "OP_SINH": np.sinh, "OP_COSH": np.cosh, "OP_TANH": np.tanh,
    "OP_NOT": np.logical_not, "OP_ASSIGN": lambda a: a,
}
_BINARY: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "OP_ADD": np.add, "OP_SUB": np.subtract, "OP_MUL": np.multiply, "OP_DIV": np.divide,
    "OP_POW": np.power, "OP_CONSTPOW": np.power, "OP_ATAN2": np.arctan2, "OP_FMIN": np.minimum,
    "OP_FMAX": np.maximum, "OP_LT": np.less, "OP_LE": np.less_equal, "OP_EQ": np.equal,
    "OP_NE": np.not_equal, "OP_AND": np.logical_and, "OP_OR": np.logical_or,
    "OP_FMOD": np.fmod, "OP_HYPOT": np.hypot,
    "OP_IF_ELSE_ZERO": lambda c, a: np.where(c != 0, a, 0.0),
}
_INPUT, _OUTPUT, _CONST, _BIN, _UN = range(5)
_KIND = {"OP_INPUT": _INPUT, "OP_OUTPUT": _OUTPUT, "OP_CONST": _CONST}


def _op_names() -> dict[int, str]:
    """CasADi operation code -> name, for the operations this module can replay."""
    import casadi as ca

    return {getattr(ca, n): n for n in (*_UNARY, *_BINARY, *_KIND)}


_BLOCK_ELEMENTS = 32768


def _slice_rows(r: np.ndarray, ndim: int, sl: slice) -> np.ndarray:
    """Slice the first grid axis of ``r`` (broadcast to ``ndim`` trailing axes) when it is not 1."""
    if r.ndim < ndim or r.shape[r.ndim - ndim] == 1:
        return r
    return r[(slice(None),) * (r.ndim - ndim) + (sl,)]


class NumpyFunction:
    """A CasADi SX function replayed with numpy over broadcastable arrays.

    Call with one argument per function input: either an array whose *leading* axis holds the
    input's nonzeros (column-major), or a sequence with one array per nonzero.  Trailing shapes
    broadcast, so a constant entry (a scalar, or a grid axis of shape (1, n)) is computed on once,
    not per grid point.  Outputs come back as arrays of shape ``(nnz_out, *broadcast_shape)``.
    """

    def __init__(self, f):
        if not f.is_a("SXFunction"):
            f = f.expand()
        self.f = f
        names = _op_names()
        program = []
        for k in range(f.n_instructions()):
            op = f.instruction_id(k)
            if op not in names:
                raise ValueError(f"{f.name()}: CasADi operation code {op} has no numpy equivalent")
            const = f.instruction_constant(k) if names[op] == "OP_CONST" else None
            program.append((names[op], tuple(f.instruction_input(k)), tuple(f.instruction_output(k)), const))
        self._setup({"name": f.name(), "inputs": [f.name_in(i) for i in range(f.n_in())],
                     "nnz_in": [f.nnz_in(i) for i in range(f.n_in())],
                     "nnz_out": [f.nnz_out(i) for i in range(f.n_out())], "work": f.sz_w(), "program": program})

    def _setup(self, data: dict) -> None:
        self.name = data["name"]
        self._data = data
        self._inputs, self._nnz_in, self._nnz_out = data["inputs"], data["nnz_in"], data["nnz_out"]
        self._work = data["work"]
        run = []
        for op, ins, outs, const in data["program"]:
            kind = _KIND.get(op, _BIN if op in _BINARY else _UN if op in _UNARY else None)
            if kind is None:
                raise ValueError(f"{self.name}: operation {op} has no numpy equivalent")
            fn = _BINARY.get(op) or _UNARY.get(op)
            run.append((kind, fn, tuple(ins), tuple(outs), const))
        self._program = run

    def to_data(self) -> dict:
        """The replay as plain data (JSON-ready): name, input names and sizes, output sizes, work
        size and the instruction list with operations named as in CasADi (``OP_ADD``...)."""
        d = self._data
        return {**d, "program": [[op, list(ins), list(outs), const] for op, ins, outs, const in d["program"]]}

    @classmethod
    def from_data(cls, data: dict) -> "NumpyFunction":
        """The replay stored by :meth:`to_data` (needs numpy only)."""
        self = cls.__new__(cls)
        self.f = None
        self._setup(data)
        return self

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        if len(args) != len(self._inputs):
            raise TypeError(f"{self.name}: expected {len(self._inputs)} inputs, got {len(args)}")
        arrays = [self._rows(i, a) for i, a in enumerate(args)]
        shape = np.broadcast_shapes(*(r.shape for rows in arrays for r in rows))
        outs = [np.zeros((n,) + shape) for n in self._nnz_out]
        w: list = [None] * self._work
        # Work in blocks along the first grid axis that fit in cache: ~9x faster on large grids.
        n_rows = shape[0] if shape else 1
        per_row = max(1, int(np.prod(shape[1:]))) if shape else 1
        block = max(1, _BLOCK_ELEMENTS // per_row)
        with np.errstate(all="ignore"):
            if not shape or n_rows <= block:
                self._run(arrays, outs, w)
            else:
                for k in range(0, n_rows, block):
                    sl = slice(k, min(k + block, n_rows))
                    part = [[_slice_rows(r, len(shape), sl) for r in rows] for rows in arrays]
                    self._run(part, [o[:, sl] for o in outs], w)
        return outs

    def _rows(self, i: int, a) -> list[np.ndarray]:
        n = self._nnz_in[i]
        rows = [np.asarray(r, dtype=float) for r in a] if isinstance(a, (list, tuple)) else list(np.asarray(a, float))
        if len(rows) != n:
            raise ValueError(f"{self.name}: input {self._inputs[i]!r} needs {n} rows, got {len(rows)}")
        return rows

    def _run(self, arrays, outs, w) -> None:
        for kind, fn, ins, outs_idx, const in self._program:
            if kind == _BIN:
                w[outs_idx[0]] = fn(w[ins[0]], w[ins[1]])
            elif kind == _UN:
                w[outs_idx[0]] = fn(w[ins[0]])
            elif kind == _INPUT:
                w[outs_idx[0]] = arrays[ins[0]][ins[1]]
            elif kind == _OUTPUT:
                outs[outs_idx[0]][outs_idx[1]] = w[ins[0]]
            else:
                w[outs_idx[0]] = const


def vectorize(f) -> NumpyFunction:
    """Numpy replay of ``f`` (expanded to SX first if it is an MX function)."""
    return NumpyFunction(f)


def stack(rows: Sequence[np.ndarray]) -> np.ndarray:
    """Stack equally shaped arrays along a new leading axis (convenience for inputs)."""
    return np.stack([np.asarray(r, dtype=float) for r in rows])
