"""Sums of signals: OSP's ``Sum`` and ``VectorSum`` functions (libcosim's ``vector_sum_function``)
as a block without state, so that a system file's functions run as components under every master
algorithm.

``inputs`` vectors of ``dimension`` elements each, summed element by element:
``out[j] = in[0][j] + in[1][j] + ... + in[inputs-1][j]`` (``j = 0 .. dimension-1``), every
input with the sign +, as libcosim sums (it has no signs, no gains: a ``LinearTransformation``
before an input scales it).  Names as libcosim's (0-based): with ``dimension`` 1 (a ``Sum``) the
inputs are ``in[0]``, ``in[1]``, ... and the output ``out``; with a larger ``dimension`` (a
``VectorSum``) ``in[i,j]`` and ``out[j]`` (libcosim's ``in[i][j]`` written as a structured FMI
name).  The signals carry whatever unit they have (unit
``"1"`` here: the block does not convert).

The block has no state and every output feeds through from its inputs: it is *memoryless*
(``Block.memoryless``), which the fixed-step masters use to evaluate it within the exchange, with
no delay of its own, as libcosim evaluates its functions (:mod:`cosim.master`).
"""
from __future__ import annotations

import casadi as ca

from ..block import Block, Var


def vector_sum(inputs: int = 2, dimension: int = 1) -> Block:
    """``inputs`` vectors of ``dimension`` elements summed element by element (module docstring)."""
    def name(base: str, i: int | None, j: int) -> str:
        idx = [k for k in (i,) if k is not None] + ([j] if dimension > 1 else [])
        return f"{base}[{','.join(map(str, idx))}]" if idx else base

    syms = [[ca.SX.sym(name("in", i, j)) for j in range(dimension)] for i in range(inputs)]
    ins = [Var(name("in", i, j), "1", f"input {i}" + (f", element {j}" if dimension > 1 else "") + " of the sum")
           for i in range(inputs) for j in range(dimension)]
    outs = [Var(name("out", None, j), "1", "the sum" + (f", element {j}" if dimension > 1 else "") + " of the inputs")
            for j in range(dimension)]
    total = [sum((syms[i][j] for i in range(1, inputs)), syms[0][j]) for j in range(dimension)]
    empty = ca.SX(0, 1)
    return Block.build(
        "vector_sum", description=f"sum of {inputs} input{'s' if inputs > 1 else ''}"
                                  + (f" of {dimension} elements" if dimension > 1 else ""),
        params=[], inputs=ins, outputs=outs, states=[], p=empty,
        u=ca.vertcat(*[s for row in syms for s in row]), x=empty, ode=empty, out=ca.vertcat(*total),
        start=empty, integrator="none", fidelity="vector")
