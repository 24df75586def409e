"""Graph analysis of a coupled system: algebraic loops, topological order and the default
Gauss-Seidel order (fewest connections cut to break cycles)."""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from functools import lru_cache

from .feedback_order import fewest_cut_order


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


def gauss_seidel_order(n: int, edges: Iterable[tuple[int, int]], first: Iterable[int] = ()) -> list[int]:
    """Stepping order of ``n`` slaves for Gauss-Seidel: sources before the slaves they feed.

    ``edges`` are (source slave, destination slave) pairs.  Strongly connected groups are
    ordered topologically; inside a group the order cuts the fewest edges (edges that go
    backwards, whose destination sees the source's output from the previous point) -- found by
    exhaustive search up to seven slaves, greedily (by out-degree minus in-degree) beyond;
    ties go to the declaration order, except that the slaves in ``first`` (event-reporting
    slaves: an early return then cuts the others' step, docs/explanation/events.md) come as early
    as the coupling allows: before any slave they do not depend on, and first among the orders of
    a group that cut the fewest edges."""
    e = frozenset((a, b) for a, b in edges if a != b)
    first = sorted(set(first))
    if not first:
        return list(_gauss_seidel_order(n, e))
    # relabel so that the slaves in ``first`` are the smallest (the tie-break prefers them), then back
    rank = first + [v for v in range(n) if v not in first]
    new = {v: i for i, v in enumerate(rank)}
    order = _gauss_seidel_order(n, frozenset((new[a], new[b]) for a, b in e), len(first))
    return [rank[v] for v in order]


@lru_cache(maxsize=128)
def _gauss_seidel_order(n: int, e: frozenset[tuple[int, int]], n_first: int = 0) -> tuple[int, ...]:
    """:func:`gauss_seidel_order`, cached: a batch asks it again for every run of the same scene
    (the fewest-cut order of a group of up to seven slaves, :func:`cosim.master.feedback_order.fewest_cut_order`,
    takes under a millisecond; the exhaustive search it replaces took ~0.04-0.2 s).  With
    ``n_first``, the groups holding a slave below ``n_first`` go first among those ready."""
    succ = [set() for _ in range(n)]
    for a, b in e:
        succ[a].add(b)
    comps = _sccs(n, succ)[::-1]  # topological order of the condensation
    comp_of = {v: ci for ci, c in enumerate(comps) for v in c}
    cedges = {(comp_of[a], comp_of[b]) for a, b in e if comp_of[a] != comp_of[b]}
    ranked = sorted(range(len(comps)), key=lambda ci: (min(comps[ci]) >= n_first, min(comps[ci]))) if n_first \
        else range(len(comps))
    corder = topological_order(list(ranked), cedges)
    order: list[int] = []
    for ci in corder:
        comp = comps[ci]
        inner = [(a, b) for a, b in e if a in comp and b in comp]
        if len(comp) <= 7:
            order.extend(fewest_cut_order(comp, inner))  # = the exhaustive search, by dynamic programming
        else:
            rest, seq = set(comp), []
            while rest:
                v = max(sorted(rest), key=lambda x: sum((x, y) in e for y in rest) - sum((y, x) in e for y in rest))
                seq.append(v)
                rest.discard(v)
            order.extend(seq)
    return tuple(order)
