"""Master algorithms: fixed-step Jacobi and Gauss-Seidel behind one base class and a registry.

Structure (after libcosim and scipy.integrate): a :class:`CoupledSystem` lays the slaves'
connected and recorded variables out in one float64 vector and precomputes every value
reference and index; an :class:`Algorithm` owns the public :meth:`Algorithm.step` and its
status, subclasses implement only :meth:`Algorithm._step_impl`; algorithms are found by name in
:data:`ALGORITHMS`; :func:`simulate` is the ~15-line run loop (algorithm, then observers).
Recording is the observers' business (:mod:`cosim.trace`), never the algorithm's.

Time is counted in whole steps of an integer number of nanoseconds: ``t_k = k * step_ns / 1e9``
exactly (no accumulated drift).  Communication step ``h = step_ns / 1e9``.

Conventions at communication point ``t_k`` (with ``inputs="hold"``, the default, inputs are held
constant over a step):

Jacobi
    1. every connected input takes the value its source output had when last read, i.e. the
       output at ``t_k`` read after the *previous* exchange;  2. every slave steps ``t_k -> t_k+1``;
    3. every slave's outputs are read.  So a slave's input over ``[t_k, t_k+1]`` is its source's
    output at ``t_k`` -- and for an output with direct feedthrough, that output was evaluated at
    ``t_k`` with its own inputs from ``t_k-1``: each feedthrough hop adds one step of delay
    (the "one-step delay" convention).
Gauss-Seidel
    slaves step one after another in a fixed order; each takes its inputs just before its own
    step, so an input whose source has already stepped sees the source's output at ``t_k+1``,
    the others see it at ``t_k``.  The default order is a topological order of the slave graph
    after cutting the fewest connections that close cycles (an exact search for cycles of up to
    seven slaves, a greedy one beyond); ``master.order`` in a scene overrides it.
Linear inputs (``inputs="linear"``)
    a slave that can follow input slopes (FMI 2.0 ``canInterpolateInputs``) also gets, per
    input, a slope for the coming step: an input whose source has already stepped (Gauss-Seidel)
    is *interpolated*, set to the source's value at ``t_k`` with slope ``(y_k+1 - y_k) / h``; the
    others are *extrapolated*, set to ``y_k`` with slope ``(y_k - y_k-1) / h`` (zero in the first
    step).  Holding makes the coupling first order in ``h``; this makes it second order.  Slaves
    that cannot interpolate keep holding.
Initialisation
    in initialisation mode every slave's outputs are read, then feedthrough outputs are
    propagated in a topological order of the port graph (output -> input connections plus
    input -> output feedthrough inside slaves), so the values at ``t_0`` are consistent.  A
    cycle in that graph is an algebraic loop and is refused (:func:`find_algebraic_loop`).

Failure: a Discard, Error or Fatal status from any call stops the run (a fixed-step master
cannot retry); the status and the slave's last log message become the run's reason.
Stop requests (FMI 3.0 ``terminateSimulation``, FMI 2.0 Discard with ``fmi2Terminated``): the
other slaves complete the step from ``t_k``, the outputs are read, the point ``t_k+1`` is recorded
(on the output grid or not) and the run ends with status "stopped", reason "stopped by C at t".

Types: the value vector carries scalar Float64 variables; other FMI types and arrays go through
:class:`cosim.typedio.TypedPorts` inside each slave's push/pull (same conventions, Python loop).
"""
from __future__ import annotations

import difflib
import itertools
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import ClassVar

import numpy as np

from .errors import UserError
from .fmitypes import TYPES
from .slaves import FAILING, Slave, Status
from .typedio import TypedPorts, element_names, is_fast
from .typedio import variable as typed_variable

_ns = time.perf_counter_ns


# --- graphs -----------------------------------------------------------------------------------
def find_algebraic_loop(edges: Iterable[tuple[object, object]]) -> list | None:
    """A directed cycle in the graph ``edges`` (as a node list, first node repeated at the end),
    or None.  Used on the port graph: output -> input connections and input -> output
    feedthrough inside a slave; a cycle there is an algebraic loop."""
    succ: dict[object, list] = {}
    for a, b in edges:
        succ.setdefault(a, []).append(b)
        succ.setdefault(b, [])
    colour = {n: 0 for n in succ}  # 0 new, 1 on the stack, 2 done
    parent: dict[object, object] = {}
    for root in succ:
        if colour[root]:
            continue
        stack = [(root, iter(succ[root]))]
        colour[root] = 1
        while stack:
            node, it = stack[-1]
            for nxt in it:
                if colour[nxt] == 0:
                    colour[nxt], parent[nxt] = 1, node
                    stack.append((nxt, iter(succ[nxt])))
                    break
                if colour[nxt] == 1:  # back edge: the cycle is nxt -> ... -> node -> nxt
                    cyc = [node]
                    while cyc[-1] != nxt:
                        cyc.append(parent[cyc[-1]])
                    cyc.reverse()
                    return cyc + [nxt]
            else:
                colour[node] = 2
                stack.pop()
    return None


def topological_order(nodes: Sequence, edges: Iterable[tuple[object, object]]) -> list:
    """Kahn's order, ties broken by the order of ``nodes``; raises ValueError on a cycle."""
    rank = {n: i for i, n in enumerate(nodes)}
    indeg = {n: 0 for n in nodes}
    succ: dict[object, list] = {n: [] for n in nodes}
    for a, b in set(edges):
        succ[a].append(b)
        indeg[b] += 1
    ready = sorted((n for n in nodes if indeg[n] == 0), key=rank.__getitem__)
    out = []
    while ready:
        n = ready.pop(0)
        out.append(n)
        for m in succ[n]:
            indeg[m] -= 1
            if indeg[m] == 0:
                ready.append(m)
                ready.sort(key=rank.__getitem__)
    if len(out) != len(nodes):
        raise ValueError("the graph has a cycle")
    return out


def _sccs(n: int, succ: list[set[int]]) -> list[list[int]]:
    """Tarjan's strongly connected components, in reverse topological order."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v: int) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(succ[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            out.append(sorted(comp))

    for v in range(n):
        if v not in index:
            visit(v)
    return out


def gauss_seidel_order(n: int, edges: Iterable[tuple[int, int]]) -> list[int]:
    """Stepping order of ``n`` slaves for Gauss-Seidel: sources before the slaves they feed.

    ``edges`` are (source slave, destination slave) pairs.  Strongly connected groups are
    ordered topologically; inside a group the order cuts the fewest edges (edges that go
    backwards, whose destination sees the source's output from the previous point) -- found by
    exhaustive search up to seven slaves, greedily (by out-degree minus in-degree) beyond;
    ties go to the declaration order."""
    return list(_gauss_seidel_order(n, frozenset((a, b) for a, b in edges if a != b)))


@lru_cache(maxsize=128)
def _gauss_seidel_order(n: int, e: frozenset[tuple[int, int]]) -> tuple[int, ...]:
    """:func:`gauss_seidel_order`, cached: the exhaustive search costs ~0.2 s for eight slaves,
    and a batch asks it again for every run of the same scene."""
    succ = [set() for _ in range(n)]
    for a, b in e:
        succ[a].add(b)
    comps = _sccs(n, succ)[::-1]  # topological order of the condensation
    comp_of = {v: ci for ci, c in enumerate(comps) for v in c}
    cedges = {(comp_of[a], comp_of[b]) for a, b in e if comp_of[a] != comp_of[b]}
    corder = topological_order(list(range(len(comps))), cedges)
    order: list[int] = []
    for ci in corder:
        comp = comps[ci]
        inner = [(a, b) for a, b in e if a in comp and b in comp]
        if len(comp) <= 7:
            best = min(itertools.permutations(comp),
                       key=lambda p: (sum(p.index(a) > p.index(b) for a, b in inner), p))
            order.extend(best)
        else:
            rest, seq = set(comp), []
            while rest:
                v = max(sorted(rest), key=lambda x: sum((x, y) in e for y in rest) - sum((y, x) in e for y in rest))
                seq.append(v)
                rest.discard(v)
            order.extend(seq)
    return tuple(order)


# --- the coupled system -----------------------------------------------------------------------
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

    def init_sequence(self) -> list[int]:
        """Slaves to update (push inputs, pull outputs), in order, so that every feedthrough
        output at ``t_0`` sees inputs that are already consistent."""
        edges = self.port_edges()
        nodes = list(dict.fromkeys([a for a, _ in edges] + [b for _, b in edges]))
        try:
            order = topological_order(nodes, edges)
        except ValueError:
            loop = find_algebraic_loop(edges)
            text = " -> ".join(f"{self.slaves[i].name}.{v}" for i, v in loop)
            raise UserError(f"algebraic loop: {text}") from None
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


# --- algorithms -------------------------------------------------------------------------------
def _gatherer(system: CoupledSystem, i: int) -> Callable[[], None]:
    """A function copying slave i's connected inputs from their sources into its input buffer
    (plain memoryview copies: a numpy call costs about a microsecond, more than a few items)."""
    src = [int(x) for x in system.in_src[i]]
    if not src:
        return lambda: None
    if system.in_affine[i] is not None:
        return lambda: system.gather(i)
    if len(src) > 8:
        v, idx, buf = system.v, system.in_src[i], system.in_buf[i]
        return lambda: np.take(v, idx, out=buf)
    mv, mb = memoryview(system.v), memoryview(system.in_buf[i])
    pairs = list(enumerate(src))
    if len(src) == 1:
        s0 = src[0]

        def one() -> None:
            mb[0] = mv[s0]
        return one

    def copy() -> None:
        for j, s in pairs:
            mb[j] = mv[s]
    return copy


class Algorithm(ABC):
    """Base class of master algorithms.  The public :meth:`step` advances one macro step and
    keeps :attr:`status` (``"running"``, ``"failed"``, ``"stopped"``); a subclass implements
    :meth:`_step_impl` and may name a compiled variant (:attr:`native_code`, see
    :mod:`cosim.fastloop`).  Numerical failure comes back as a status and :attr:`message`, never
    as an exception; bad arguments raise at once."""

    name: ClassVar[str]
    #: algorithm code of the compiled loop implementing the same steps, or None
    native_code: ClassVar[int | None] = None
    #: slaves step one after another in :attr:`order` (later ones see earlier ones' new outputs)
    sequential: ClassVar[bool] = False

    def __init__(self, system: CoupledSystem, step_ns: int, *, order: Sequence[int] | None = None,
                 timing: bool = True, inputs: str = "hold", start_ns: int = 0):
        if not (isinstance(step_ns, (int, np.integer)) and step_ns > 0):
            raise UserError(f"the communication step must be a positive whole number of nanoseconds, got {step_ns!r}")
        self.system = system
        self.step_ns = int(step_ns)
        self.h = self.step_ns / 1e9
        self.start_ns = int(start_ns)  # the start time [ns]; the compiled loop runs only from 0
        self.text_events: list[tuple[float, str, str]] = []  # (t, column, value) of recorded String/Binary
        self.k = 0
        self.status = "running"
        self.message = ""
        self.failed_slave: int | None = None
        n = len(system.slaves)
        self.order = list(order) if order is not None else gauss_seidel_order(n, system.slave_edges())
        if sorted(self.order) != list(range(n)):
            raise UserError(f"master order must list every slave once, got {self.order}")
        self.calls = [0] * n  # doStep calls per slave
        self.slave_ns = [0] * n  # wall time [ns] inside each slave's calls
        self.master_ns = 0  # the master's own time [ns] in the stepping loop
        self.timing = timing
        s = system.slaves
        self._push = [x.push for x in s]
        self._pull = [x.pull for x in s]
        self._do = [x.do_step for x in s]
        self._gather = [_gatherer(system, i) for i in range(n)]
        self._setup_inputs(inputs)

    def _setup_inputs(self, inputs: str) -> None:
        """Per slave: whether it gets input slopes (:attr:`interpolating`), the slope buffer, the
        inputs' previous source values (:attr:`hist`, from ``system.v`` at the current point) and
        which inputs are interpolated rather than extrapolated (:attr:`fresh`)."""
        if inputs not in ("hold", "linear"):
            raise UserError(f"inputs must be 'hold' or 'linear', got {inputs!r}")
        sysm, n = self.system, len(self.system.slaves)
        self.inputs = inputs
        self.slopes = [np.zeros(len(b)) for b in sysm.in_buf]
        self.hist = [sysm.source_values(i) for i in range(len(sysm.in_src))]
        self.fresh = [np.zeros(len(b), dtype=bool) for b in sysm.in_buf]
        self.interpolating = [False] * n
        if inputs == "hold":
            return
        pos = {s: k for k, s in enumerate(self.order)}
        for i, slave in enumerate(sysm.slaves):
            if not slave.bind_slopes(self.slopes[i]):
                continue
            self.interpolating[i] = True
            if self.sequential:
                self.fresh[i][:] = [pos[ln.src] < pos[i] for ln in sysm.links if ln.dst == i]
            self._push[i] = self._linear_push(i)

    def _linear_push(self, i: int) -> Callable[[], int]:
        """Slave i's push with slopes (after its gather; see the module docstring)."""
        buf, hist, slope, fresh = self.system.in_buf[i], self.hist[i], self.slopes[i], self.fresh[i]
        tmp, inv_h = np.empty_like(buf), 1.0 / self.h
        slave = self.system.slaves[i]
        push, push_slopes = slave.push, slave.push_slopes

        def push_linear() -> int:
            np.subtract(buf, hist, out=slope)
            np.multiply(slope, inv_h, out=slope)
            np.copyto(tmp, buf)
            np.copyto(buf, hist, where=fresh)
            np.copyto(hist, tmp)
            st = push()
            return st if st in FAILING else push_slopes()
        return push_linear

    @property
    def t(self) -> float:
        """Current communication point [s] (``(start_ns + k * step_ns) / 1e9``)."""
        return self.time_at(self.k)

    def time_at(self, k: int) -> float:
        """Communication point ``k`` [s]."""
        return (self.start_ns + k * self.step_ns) / 1e9

    def step(self) -> bool:
        """One macro step ``t_k -> t_k+1``; False (with :attr:`status`, :attr:`message`) when the
        run ends: a failure, or a stop request (then the step is completed first, see
        :meth:`complete_after_stop`)."""
        if self.status != "running":
            raise RuntimeError(f"{self.name}: cannot step a run that is {self.status}")
        t = self.time_at(self.k)
        bad = self._step_impl(t, self.h)
        if bad is None:
            self.k += 1
            return True
        if self.stop_requested(*bad):
            self.complete_after_stop(bad[0], t)
            return False
        self._fail(bad[0], bad[1], t)
        return False

    def stop_requested(self, i: int, status: int) -> bool:
        """Is ``status`` from slave ``i`` a request to end the simulation (FMI 3.0
        terminateSimulation, FMI 2.0 Discard with fmi2Terminated)?"""
        return status == Status.STOP_REQUESTED or (
            status == Status.DISCARD and self.system.slaves[i].asked_to_stop())

    def complete_after_stop(self, i: int, t: float) -> None:
        """Slave ``i`` asked to stop in the step from ``t``: the other slaves complete that step
        (so every output belongs to ``t_k+1``), then the run ends as ``stopped`` at ``t_k+1``, a point
        the run loop records."""
        bad = self._finish_step(i, t, self.h)
        if bad is not None and not self.stop_requested(*bad):
            self._fail(bad[0], bad[1], t)
            return
        self.k += 1
        sl = self.system.slaves[i]
        detail = sl.stop_detail() if hasattr(sl, "stop_detail") else ""
        self.status, self.failed_slave = "stopped", i
        self.message = (f"stopped by {sl.name} at t = {self.t:.9g} s: it asked to terminate the simulation in the "
                        f"step from t = {t:.9g} s" + (f" ({detail})" if detail else "")
                        + (f"; its last message: {sl.last_message}" if sl.last_message else ""))

    def _finish_step(self, i: int, t: float, h: float) -> tuple[int, int] | None:
        """Complete the step from ``t`` after slave ``i`` stepped and asked to stop; returns
        ``(slave, status)`` of a failing call, or None."""
        raise NotImplementedError(f"{self.name} cannot complete a step after a stop request")

    @abstractmethod
    def _step_impl(self, t: float, h: float) -> tuple[int, int] | None:
        """Advance every slave from ``t`` by ``h``; return ``(slave index, status)`` of the first
        failing call, or None."""

    def _fail(self, i: int, status: int, t: float) -> None:
        sl = self.system.slaves[i]
        self.failed_slave = i
        if status == Status.STOP_REQUESTED:
            self.status = "stopped"
            self.message = f"{sl.name} asked to terminate the simulation at t = {t:.9g} s (step {self.k})"
        else:
            self.status = "failed"
            name = Status(status).name if status in Status._value2member_map_ else str(status)
            self.message = (f"{sl.name} returned {name} in the step from t = {t:.9g} s (step {self.k})"
                            + (f": {sl.last_message}" if sl.last_message else ""))

    # helpers for subclasses: one slave's part of a step, timed ----------------------------------------
    def _io(self, i: int, fn: Callable[[], int]) -> int:
        t0 = _ns()
        st = fn()
        self.slave_ns[i] += _ns() - t0
        return st

    def _advance(self, i: int, t: float, h: float) -> int:
        t0 = _ns()
        st = self._do[i](t, h)
        self.slave_ns[i] += _ns() - t0
        self.calls[i] += 1
        return st


ALGORITHMS: dict[str, type[Algorithm]] = {}


def register(cls: type[Algorithm]) -> type[Algorithm]:
    """Class decorator: make an algorithm available by its ``name``."""
    ALGORITHMS[cls.name] = cls
    return cls


def algorithm(name: str) -> type[Algorithm]:
    """The algorithm class called ``name``; :class:`UserError` with the closest names otherwise."""
    try:
        return ALGORITHMS[name]
    except KeyError:
        close = difflib.get_close_matches(str(name), ALGORITHMS, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise UserError(f"unknown master algorithm {name!r}{hint} (known: {', '.join(sorted(ALGORITHMS))})") from None


@register
class Jacobi(Algorithm):
    """All slaves take inputs from outputs read at ``t_k``, then all step in parallel (in
    principle), then all outputs are read (see the module docstring for the delay convention)."""

    name = "jacobi"
    native_code = 0

    def _step_impl(self, t, h):
        gather, push, do, pull, acc, calls = (self._gather, self._push, self._do, self._pull, self.slave_ns,
                                               self.calls)
        n = len(do)
        tp = _ns()
        for i in range(n):
            gather[i]()
            st = push[i]()
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING:
                return i, st
        for i in range(n):
            st = do[i](t, h)
            calls[i] += 1
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING or st == Status.STOP_REQUESTED:
                return i, st
        for i in range(n):
            st = pull[i]()
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING:
                return i, st
        return None

    def _finish_step(self, i, t, h):
        for j in range(i + 1, len(self._do)):
            st = self._advance(j, t, h)
            if st in FAILING:
                return j, st
        for j in range(len(self._pull)):
            st = self._io(j, self._pull[j])
            if st in FAILING:
                return j, st
        return None


@register
class GaussSeidel(Algorithm):
    """Slaves step one after another in :attr:`order`; each reads the freshest outputs."""

    name = "gauss_seidel"
    native_code = 1
    sequential = True

    def _step_impl(self, t, h):
        gather, push, do, pull, acc, calls = (self._gather, self._push, self._do, self._pull, self.slave_ns,
                                               self.calls)
        tp = _ns()
        for i in self.order:
            gather[i]()
            st = push[i]()
            if st not in FAILING:
                st = do[i](t, h)
                calls[i] += 1
                if st not in FAILING and st != Status.STOP_REQUESTED:
                    st = pull[i]()
            tn = _ns()
            acc[i] += tn - tp
            tp = tn
            if st in FAILING or st == Status.STOP_REQUESTED:
                return i, st
        return None

    def _finish_step(self, i, t, h):
        st = self._io(i, self._pull[i])
        if st in FAILING:
            return i, st
        for j in self.order[self.order.index(i) + 1:]:
            self._gather[j]()
            st = self._io(j, self._push[j])
            if st not in FAILING:
                st = self._advance(j, t, h)
                if st not in FAILING:
                    st = self._io(j, self._pull[j])
            if st in FAILING:
                return j, st
        return None


# --- engines: who runs the steps ----------------------------------------------------------------
class _Compiled:
    """Runs an algorithm's steps in the compiled loop (:mod:`cosim.fastloop`)."""

    def __init__(self, alg: Algorithm):
        import ctypes

        from . import fastloop

        self.lib = fastloop.library()
        sysm = alg.system
        n = len(sysm.slaves)
        self.arr = (fastloop.CSlave * n)()
        self.keep = []
        for i, s in enumerate(sysm.slaves):
            ne = s.native()
            if ne is None:
                raise UserError(f"{s.name} has no C entry points; use master.engine: python")
            c = self.arr[i]
            c.fmi3, c.n_in, c.n_out = int(ne.fmi3), len(sysm.in_vrs[i]), len(sysm.out_vrs[i])
            if alg.interpolating[i]:
                orders, fresh = np.ones(c.n_in, dtype=np.int32), alg.fresh[i].astype(np.int8)
                self.keep += [orders, fresh]
                c.interp, c.set_der = 1, ne.set_input_derivatives
                c.orders, c.fresh = orders.ctypes.data, fresh.ctypes.data
                c.hist, c.slope = alg.hist[i].ctypes.data, alg.slopes[i].ctypes.data
            c.in_off, c.out_off = sysm.in_off[i], sysm.out_off[i]
            c.inst, c.do_step, c.get, c.set = ne.instance, ne.do_step, ne.get_real, ne.set_real
            for arr in (sysm.in_vrs[i], sysm.in_src[i], sysm.out_vrs[i]):
                self.keep.append(arr)
            c.in_vr = sysm.in_vrs[i].ctypes.data if c.n_in else None
            c.in_src = sysm.in_src[i].ctypes.data if c.n_in else None
            c.out_vr = sysm.out_vrs[i].ctypes.data if c.n_out else None
        self.order = np.array(alg.order, dtype=np.int32)
        self.rec_idx = sysm.record_idx
        self.alg = alg
        self.c = ctypes
        self.n_rows = ctypes.c_int64()
        self.fail_slave = ctypes.c_int32()
        self.fail_status = ctypes.c_int32()
        self.master_ns = ctypes.c_int64()
        #: wall time after which one call returns early [ns]: signals are handled between calls
        self.budget_ns = fastloop.CALL_BUDGET_NS

    def run(self, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
        alg, sysm = self.alg, self.alg.system
        self.master_ns.value = 0
        done = self.lib.rpr_run(self.arr, len(self.arr), self.order.ctypes.data, alg.native_code,
                                sysm.v.ctypes.data, alg.k, nsteps, alg.step_ns, int(alg.timing),
                                self.rec_idx.ctypes.data if self.rec_idx.size else None, len(self.rec_idx),
                                rec_every, rec.ctypes.data, self.c.byref(self.n_rows),
                                self.c.byref(self.fail_slave), self.c.byref(self.fail_status),
                                self.c.byref(self.master_ns), self.budget_ns)
        for i, c in enumerate(self.arr):
            alg.calls[i], alg.slave_ns[i] = c.calls, c.ns
        alg.master_ns += self.master_ns.value
        alg.k += int(done)
        t_fail = alg.t
        rows = int(self.n_rows.value)
        i, st = self.fail_slave.value, self.fail_status.value
        if i >= 0 and alg.stop_requested(i, st):
            alg.complete_after_stop(i, t_fail)
            if alg.status == "stopped":  # the last point, on the output grid or not
                rec[rows, 0] = alg.t
                np.take(sysm.v, sysm.record_idx, out=rec[rows, 1:])
                rows += 1
        elif i >= 0:
            alg._fail(i, st, t_fail)
        return rows


def _python_run(alg: Algorithm, nsteps: int, rec_every: int, rec: np.ndarray) -> int:
    v, idx = alg.system.v, alg.system.record_idx
    rows, typed = 0, alg.system.typed
    for _ in range(nsteps):
        ok = alg.step()
        if (ok and alg.k % rec_every == 0) or alg.status == "stopped":
            rec[rows, 0] = alg.t
            np.take(v, idx, out=rec[rows, 1:])
            rows += 1
            if typed.texts:
                alg.text_events += [(alg.t, c, x) for c, x in typed.text_changes()]
        if not ok:
            break
    return rows


# --- the run loop -----------------------------------------------------------------------------
@dataclass
class RunStats:
    """Statistics of one run: per-slave doStep calls and wall time [s] (inside its FMI calls),
    the master's own time [s] (everything else in the stepping loop), totals."""

    algorithm: str
    engine: str
    step: float
    steps_planned: int
    steps_done: int = 0
    status: str = "running"
    reason: str = ""
    init_s: float = 0.0
    wall_s: float = 0.0
    master_s: float = 0.0
    slaves: dict[str, dict[str, float]] = field(default_factory=dict)
    guards: dict = field(default_factory=dict)
    realtime: dict | None = None  # lateness statistics of a paced run (cosim.realtime)

    @property
    def simulated_s(self) -> float:
        return self.steps_done * self.step

    @property
    def real_time_factor(self) -> float:
        """Simulated time over wall time of the stepping loop (> 1: faster than real time)."""
        return self.simulated_s / self.wall_s if self.wall_s > 0 else float("inf")

    def as_dict(self) -> dict:
        return {"algorithm": self.algorithm, "engine": self.engine, "step": self.step,
                "steps_planned": self.steps_planned, "steps_done": self.steps_done, "status": self.status,
                "reason": self.reason, "init_s": self.init_s, "wall_s": self.wall_s, "master_s": self.master_s,
                "simulated_s": self.simulated_s, "real_time_factor": self.real_time_factor, "slaves": self.slaves,
                **({"guards": self.guards} if self.guards else {}),
                **({"realtime": self.realtime} if self.realtime is not None else {})}


def interruption_reason(exc: KeyboardInterrupt, t: float | None) -> str:
    """The reason of a run ended by Ctrl-C or a signal (``exc`` names the signal, see
    :mod:`cosim.interrupts`), at simulated time ``t`` when known."""
    return f"interrupted by {str(exc) or 'the user (KeyboardInterrupt)'}" + (f" at t = {t:.9g} s" if t is not None else "")


def slave_table(system: CoupledSystem, calls: Sequence[int], slave_ns: Sequence[int]) -> dict[str, dict[str, float]]:
    """Per-slave run statistics: doStep calls and wall time [s] inside the slave's calls."""
    return {s.name: {"do_step_calls": int(calls[i]), "wall_s": slave_ns[i] / 1e9} for i, s in enumerate(system.slaves)}


def initialize(system: CoupledSystem, start_values: Sequence[dict[str, float]], *, start_time: float = 0.0,
               stop_time: float, tolerances: Sequence[float | None] | None = None) -> None:
    """Instantiate, set start values, run the initial exchange (feedthrough order) and leave
    initialisation mode; afterwards ``system.v`` holds every bound variable at ``t_0``."""
    seq = system.init_sequence()
    for s, start in zip(system.slaves, start_values):
        s.instantiate()
        s.set_start(start)
    system.bind()
    for i, s in enumerate(system.slaves):
        tol = tolerances[i] if tolerances else None
        if tol is None:
            s.enter_initialization(start_time, stop_time)
        else:
            s.enter_initialization(start_time, stop_time, tol)
    for i, s in enumerate(system.slaves):
        _check(s, s.pull(), "reading outputs in initialisation mode")
    for i in seq:
        system.gather(i)
        _check(system.slaves[i], system.slaves[i].push(), "setting inputs in initialisation mode")
        _check(system.slaves[i], system.slaves[i].pull(), "reading outputs in initialisation mode")
    for i, s in enumerate(system.slaves):
        system.gather(i)
        _check(s, s.push(), "setting inputs in initialisation mode")
        s.exit_initialization()
    for s in system.slaves:
        _check(s, s.pull(), "reading outputs at the start time")


def _check(slave: Slave, status: int, what: str) -> None:
    if status in FAILING:
        raise UserError(f"{slave.name}: {what} returned {Status(status).name}"
                        + (f": {slave.last_message}" if slave.last_message else ""))


def choose_engine(system: CoupledSystem, alg_cls: type[Algorithm], engine: str, start_ns: int = 0) -> str:
    """``"compiled"`` or ``"python"`` for ``engine`` in auto | compiled | python."""
    if engine not in ("auto", "compiled", "python"):
        raise UserError(f"master.engine must be auto, compiled or python, got {engine!r}")
    if engine == "python":
        return "python"
    native = alg_cls.native_code is not None and all(s.native() is not None for s in system.slaves)
    if engine == "compiled" and system.transformed:
        raise UserError("master.engine: compiled copies connections as they are; connections with a linear "
                        "transformation (factor, offset) run in the Python loop: use master.engine: python or auto")
    if engine == "compiled" and system.typed.active:
        raise UserError("master.engine: compiled carries scalar Float64 variables only; this scene connects or "
                        "records other types or arrays: use engine auto or python")
    if engine == "compiled" and start_ns:
        raise UserError("master.engine: compiled runs from start_time 0; use engine auto or python")
    native = native and not system.typed.active and not start_ns and not system.transformed
    if engine == "compiled":
        if not native:
            raise UserError(f"master.engine: compiled needs FMU slaves and an algorithm with a compiled loop "
                            f"({alg_cls.name} / {', '.join(s.name for s in system.slaves if s.native() is None) or 'all FMUs'})")
        return "compiled"
    from . import fastloop

    return "compiled" if native and fastloop.available() else "python"


def _guarded(guard, alg: Algorithm, rows: np.ndarray, step_ns: int) -> np.ndarray:
    """``rows`` up to the first one ``guard`` trips on (all when it does not trip); a trip ends
    the run with the guard's status and reason at that row's time."""
    if guard is None or guard.tripped:
        return rows
    keep = guard.check(rows)
    if keep is None:
        return rows
    later = f" (afterwards: {alg.message})" if alg.status != "running" and alg.message else ""
    alg.status, alg.message = guard.status, guard.reason + later
    alg.k = round((rows[keep - 1, 0] * 1e9 - alg.start_ns) / step_ns)
    return rows[:keep]


def simulate(system: CoupledSystem, algorithm_name: str, *, step_ns: int, n_steps: int, record_every: int = 1,
             observers: Sequence = (), start_values: Sequence[dict[str, float]] | None = None,
             engine: str = "auto", order: Sequence[int] | None = None, timing: bool = True,
             progress: Callable[[int, int], None] | None = None, meta: dict | None = None,
             inputs: str = "hold", start_ns: int = 0, tolerances: Sequence[float | None] | None = None,
             realtime=None, options: dict | None = None, guard=None) -> RunStats:
    """Initialise ``system`` and run ``n_steps`` macro steps of ``step_ns`` nanoseconds, inputs
    held or linear over each step (``inputs``, see the module docstring).

    Observers receive ``start(columns, meta)``, ``record(rows)`` (rows of time and the recorded
    values, at ``t_0`` and every ``record_every`` steps) and ``finish(status, reason, stats)``,
    also when the run fails or is interrupted (then the exception propagates after ``finish``).
    ``realtime`` (a :class:`cosim.realtime.RealtimeSettings`) paces every step on the wall clock.

    ``guard`` (:class:`cosim.guards.Guard`) sees every row first, with the system's watched
    variables after the recorded ones; when it trips, the rows after the offending one are
    dropped and the run ends with the guard's status and reason.
    """
    cls = algorithm(algorithm_name)
    if getattr(cls, "needs_rollback", False):
        fixed = [s.name for s in system.slaves if not s.can_rollback]
        if fixed:
            raise UserError(f"master algorithm {cls.name} needs rollback (get/set state) but {', '.join(fixed)} "
                            f"cannot roll back (canGetAndSetFMUstate=false, e.g. hardware); use a fixed-step "
                            f"algorithm such as gauss_seidel or jacobi")
    if getattr(cls, "variable_step", False):
        from .adaptive import simulate_variable

        return simulate_variable(system, cls, step_ns=step_ns, n_steps=n_steps, observers=observers,
                                 start_values=start_values, order=order, progress=progress, meta=meta,
                                 options=options, start_ns=start_ns, tolerances=tolerances, engine=engine)
    if record_every < 1:
        raise UserError(f"record_every must be >= 1, got {record_every}")
    stats = RunStats(cls.name, "", step_ns / 1e9, n_steps)
    columns = ["time"] + system.record_names
    status, reason = "failed", ""
    for obs in observers:
        obs.start(columns, dict(meta or {}, algorithm=cls.name, step=step_ns / 1e9))
    alg, t_loop, pacer = None, None, None
    try:
        t0 = time.perf_counter()
        initialize(system, start_values or [{} for _ in system.slaves], start_time=start_ns / 1e9,
                   stop_time=(start_ns + n_steps * step_ns) / 1e9, tolerances=tolerances)
        alg = cls(system, step_ns, order=order, timing=timing, inputs=inputs, start_ns=start_ns)
        stats.engine = choose_engine(system, cls, engine, start_ns)
        runner = _Compiled(alg).run if stats.engine == "compiled" else (lambda n, e, r: _python_run(alg, n, e, r))
        stats.init_s = time.perf_counter() - t0
        row0 = np.concatenate([[alg.t], system.v[system.record_idx]])[None, :]
        row0 = _guarded(guard, alg, row0, step_ns)
        for obs in observers:
            obs.record(row0[:, :len(columns)])
        for c, x in system.typed.text_changes() if system.typed.texts else ():
            for obs in observers:
                if hasattr(obs, "record_text"):
                    obs.record_text(alg.t, c, x)
        chunk, t_loop, stepping = min(64, n_steps) or 1, time.perf_counter(), 0.0
        if realtime is not None:
            from .realtime import Pacer

            pacer, chunk = Pacer(step_ns, n_steps, realtime), 1
        width = 1 + len(system.record_idx)
        rec = np.empty((max(1, chunk // record_every + 1), width))
        while alg.k < n_steps and alg.status == "running":
            if pacer is not None and not pacer.wait(alg.k):
                alg.status, alg.message = "failed", pacer.reason
                break
            n = min(chunk, n_steps - alg.k)
            if rec.shape[0] < n // record_every + 1:
                rec = np.empty((n // record_every + 1, width))
            tc = time.perf_counter()
            rows = runner(n, record_every, rec)
            dt = time.perf_counter() - tc
            stepping += dt
            block = _guarded(guard, alg, rec[:rows], step_ns)
            if len(block) < rows:  # a guard cut the block: no text after its last row
                alg.text_events[:] = [ev for ev in alg.text_events if ev[0] <= block[-1, 0]]
            for obs in observers:
                obs.record(block[:, :len(columns)])
                for ev in alg.text_events if hasattr(obs, "record_text") else ():
                    obs.record_text(*ev)
            alg.text_events.clear()
            if progress:
                progress(alg.k, n_steps)
            if dt < 0.05 and chunk < 1 << 20 and pacer is None:  # aim at ~0.1 s per chunk: responsive to Ctrl-C
                chunk *= 2
        stats.wall_s = time.perf_counter() - t_loop
        if stats.engine == "python":  # the compiled loop measures its own share itself
            alg.master_ns = max(0, int(stepping * 1e9) - sum(alg.slave_ns))
        status, reason = ("ok", "") if alg.status == "running" else (alg.status, alg.message)
    except KeyboardInterrupt as exc:
        status, reason = "interrupted", interruption_reason(exc, alg.t if alg else None)
        raise
    except BaseException as exc:
        status, reason = "failed", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        stats.status, stats.reason = status, reason
        if guard is not None:
            stats.guards = guard.summary()
        if alg is not None:
            stats.steps_done = alg.k
            stats.master_s = alg.master_ns / 1e9
            stats.slaves = slave_table(system, alg.calls, alg.slave_ns)
        if stats.wall_s == 0.0 and t_loop is not None:
            stats.wall_s = time.perf_counter() - t_loop
        if pacer is not None:
            stats.realtime = pacer.finish()
        for obs in observers:
            obs.finish(status, reason, stats.as_dict())
        for s in system.slaves:
            s.terminate()
            s.free()
    return stats


from . import adaptive as _adaptive  # noqa: E402,F401  (registers the variable-step algorithm "adaptive")
