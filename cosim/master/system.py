"""The coupled system: slaves, their connections (:class:`Link`) and the recorded variables laid out
in one float64 value vector with every value reference and index precomputed."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import UserError
from ..slaves.types import TYPES
from ..slaves.slave import Slave
from ..slaves.typedio import TypedPorts, element_names, is_fast
from ..slaves.typedio import variable as typed_variable
from .graph import find_algebraic_loop, topological_order


@dataclass(frozen=True)
class Link:
    """A signal connection between slaves by index: ``slaves[src].src_var -> slaves[dst].dst_var``,
    optionally through a linear transformation ``dst = factor * src + offset`` (SSP's
    LinearTransformation and unit conversions; the Python loop applies it in the gather)."""

    src: int
    src_var: str
    dst: int
    dst_var: str
    factor: float = 1.0
    offset: float = 0.0
    bond: str | None = None  # the power bond ``a.p <-> b.q`` this link is one half of, if any

    @property
    def transformed(self) -> bool:
        return self.factor != 1.0 or self.offset != 0.0


class CoupledSystem:
    """Slaves, their connections and the recorded variables, laid out for stepping.

    One float64 vector ``v`` holds, per slave, the variables it reads (connected outputs and
    recorded variables) and then, per slave, its connected inputs.  Value references and the
    gather indices are computed once here, so a step allocates nothing.
    """

    def __init__(self, slaves: Sequence[Slave], links: Sequence[Link], record: Sequence[tuple[int, str]] = (),
                 watch: Sequence[tuple[int, str]] = ()):
        """``record``: the traced variables; ``watch``: more scalar Float64 variables sampled with
        them at every recorded row but not traced (for guards: :attr:`watch_names`, after the
        recorded columns)."""
        self.slaves = list(slaves)
        self.links = list(links)
        n = len(self.slaves)
        names = [s.name for s in self.slaves]
        if len(set(names)) != n:
            raise UserError(f"slave names must be unique, got {names}")
        reads: list[list[str]] = [[] for _ in range(n)]
        ins: list[list[tuple[str, int, str]]] = [[] for _ in range(n)]
        seen_in: set[tuple[int, str]] = set()
        self.typed = TypedPorts(self.slaves)
        typed_in: list[Link] = []
        for ln in self.links:
            if (ln.dst, ln.dst_var) in seen_in:
                raise UserError(f"input {names[ln.dst]}.{ln.dst_var} is connected twice")
            seen_in.add((ln.dst, ln.dst_var))
            if not is_fast(self.slaves[ln.dst], ln.dst_var):
                if ln.transformed:
                    raise UserError(f"input {names[ln.dst]}.{ln.dst_var}: a linear transformation applies to "
                                    f"scalar Float64 (Real) signals only")
                typed_in.append(ln)  # a typed input: fed by the typed ports
                if is_fast(self.slaves[ln.src], ln.src_var) and ln.src_var not in reads[ln.src]:
                    reads[ln.src].append(ln.src_var)
                continue
            if is_fast(self.slaves[ln.src], ln.src_var) and ln.src_var not in reads[ln.src]:
                reads[ln.src].append(ln.src_var)
            ins[ln.dst].append((ln.dst_var, ln.src, ln.src_var))
        source = {(ln.dst, ln.dst_var): (ln.src, ln.src_var) for ln in self.links
                  if ln not in typed_in and not ln.transformed}  # a transformed input is read from its slave
        watch = [w for w in dict.fromkeys(watch) if w not in set(record) and is_fast(self.slaves[w[0]], w[1])]
        for i, var in list(record) + watch:
            if (i, var) in source or not is_fast(self.slaves[i], var):
                continue  # recorded as the value of its source output, or a typed variable
            if var not in reads[i]:
                reads[i].append(var)
        out_off, off = [], 0
        for r in reads:
            out_off.append(off)
            off += len(r)
        in_off = []
        for r in ins:
            in_off.append(off)
            off += len(r)
        self.index: dict[tuple[int, str], int] = {}
        for i, r in enumerate(reads):
            for j, var in enumerate(r):
                self.index[(i, var)] = out_off[i] + j
        # typed numbers that feed a Float64 input (a conversion) or are recorded: mirrored into v
        columns: list[tuple[str, int | None]] = []  # (column name, index in v; None for text)
        mirrored = [(ln.src, ln.src_var) for ln in self.links if ln not in typed_in
                    and not is_fast(self.slaves[ln.src], ln.src_var)]
        for i, var in record:
            if (i, var) not in source and not is_fast(self.slaves[i], var):
                mirrored.append((i, var))
        for i, var in dict.fromkeys(mirrored):
            desc = typed_variable(self.slaves[i], var)
            if not TYPES[desc.type].numeric:
                continue
            self.typed.mirror(i, var, off)
            for k, el in enumerate(element_names(var, desc.shape)):
                self.index[(i, el)] = off + k
            self.index[(i, var)] = off
            off += desc.size
        self.v = np.zeros(off)
        self.out_vrs = [np.array([s.vr(var) for var in r], dtype=np.uint32) for s, r in zip(self.slaves, reads)]
        self.in_vrs = [np.array([s.vr(var) for var, _, _ in r], dtype=np.uint32) for s, r in zip(self.slaves, ins)]
        self.in_src = [np.array([self.index[(si, sv)] for _, si, sv in r], dtype=np.int64) for r in ins]
        self.out_off, self.in_off = out_off, in_off
        self.reads, self.inputs = reads, [[var for var, _, _ in r] for r in ins]
        self.out_buf = [self.v[o:o + len(r)] for o, r in zip(out_off, reads)]
        self.in_buf = [self.v[o:o + len(r)] for o, r in zip(in_off, ins)]
        for ln in typed_in:
            if is_fast(self.slaves[ln.src], ln.src_var):
                k, v = self.index[(ln.src, ln.src_var)], self.v
                self.typed.add_input(ln.dst, ln.dst_var, lambda k=k, v=v: v[k:k + 1])
            else:
                self.typed.add_input(ln.dst, ln.dst_var, self.typed.source_of(ln.src, ln.src_var))
        for i, var in record:
            key = source.get((i, var), (i, var))
            desc = typed_variable(self.slaves[key[0]], key[1])
            if desc is not None and not TYPES[desc.type].numeric:
                self.typed.record_text(f"{names[i]}.{var}", *key)
                continue
            els = element_names(var, desc.shape) if desc is not None else [var]
            src_els = element_names(key[1], desc.shape) if desc is not None else [key[1]]
            columns += [(f"{names[i]}.{e}", self.index[(key[0], se)]) for e, se in zip(els, src_els)]
        watched = [(f"{names[i]}.{var}", self.index[source.get((i, var), (i, var))]) for i, var in watch]
        self.record_names = [c for c, _ in columns]
        self.watch_names = [c for c, _ in watched]
        self.record_idx = np.array([k for _, k in columns + watched], dtype=np.int64)  # watched ones last
        #: per slave, (factor, offset) arrays of its inputs when any of its links is transformed
        self.in_affine: list[tuple[np.ndarray, np.ndarray] | None] = [None] * n
        for i, r in enumerate(ins):
            lns = [next(ln for ln in self.links if ln.dst == i and ln.dst_var == var) for var, _, _ in r]
            if any(ln.transformed for ln in lns):
                self.in_affine[i] = (np.array([ln.factor for ln in lns]), np.array([ln.offset for ln in lns]))
        self.transformed = any(a is not None for a in self.in_affine)

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.slaves]

    def slave_edges(self) -> list[tuple[int, int]]:
        return [(ln.src, ln.dst) for ln in self.links]

    def port_edges(self) -> list[tuple[tuple[int, str], tuple[int, str]]]:
        """Edges of the port graph: connections, plus feedthrough inside each slave."""
        edges = [((ln.src, ln.src_var), (ln.dst, ln.dst_var)) for ln in self.links]
        for i, s in enumerate(self.slaves):
            for y in self.reads[i] + list(self.typed.reads[i]):
                for u in s.description.feedthrough.get(y, []):
                    edges.append(((i, u), (i, y)))
        return edges

    def init_sequence(self, allow_loops: bool = False) -> list[int]:
        """Slaves to update (push inputs, pull outputs), in order, so that every feedthrough
        output at ``t_0`` sees inputs that are already consistent.  An algebraic loop is refused
        unless ``allow_loops`` (the algorithm solves it itself: every slave once, in order)."""
        edges = self.port_edges()
        nodes = list(dict.fromkeys([a for a, _ in edges] + [b for _, b in edges]))
        try:
            order = topological_order(nodes, edges)
        except ValueError:
            if allow_loops:
                return list(range(len(self.slaves)))
            loop = find_algebraic_loop(edges)
            text = " -> ".join(f"{self.slaves[i].name}.{v}" for i, v in loop)
            raise UserError(f"algebraic loop: {text}; master.algorithm: iterative solves it within each step") from None
        seq: list[int] = []
        for i, var in order:
            fed = set(self.slaves[i].description.feedthrough.get(var, [])) & set(
                self.inputs[i] + [u for u, _ in self.typed.inputs[i]])
            if (var in self.reads[i] or var in self.typed.reads[i]) and fed and (not seq or seq[-1] != i):
                seq.append(i)
        return seq

    # lifecycle -----------------------------------------------------------------------------------
    def bind(self) -> None:
        for i, s in enumerate(self.slaves):
            s.bind(self.in_vrs[i], self.in_buf[i], self.out_vrs[i], self.out_buf[i])
        self.typed.wrap(self.v)

    def gather(self, i: int) -> None:
        np.take(self.v, self.in_src[i], out=self.in_buf[i])
        if self.in_affine[i] is not None:
            self.in_buf[i] *= self.in_affine[i][0]
            self.in_buf[i] += self.in_affine[i][1]

    def source_values(self, i: int) -> np.ndarray:
        """Slave i's inputs as its sources give them now (transformations applied), a new array."""
        vals = self.v[self.in_src[i]]
        if self.in_affine[i] is not None:
            vals = vals * self.in_affine[i][0] + self.in_affine[i][1]
        return vals
