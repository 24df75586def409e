"""The Gauss-Seidel order inside a strongly connected group of slaves: of all orders, the
lexicographically smallest among those that cut the fewest edges (an edge ``(a, b)`` is cut when
``a`` steps after ``b``, so ``b`` sees ``a``'s output of the previous communication point).

Found by dynamic programming over subsets, O(2^n n^2): the same order as the exhaustive search
over the n! permutations (the same minimum, the same tie-break), which tests/test_feedback_order.py
checks it against.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence


def fewest_cut_order(group: Sequence[int], edges: Iterable[tuple[int, int]]) -> tuple[int, ...]:
    """``min(permutations(group), key=lambda p: (cut edges of p, p))`` without enumerating them."""
    verts = sorted(group)
    n = len(verts)
    bit = {v: 1 << i for i, v in enumerate(verts)}
    # out_mask[i]: the destinations of vertex i's edges inside the group
    out_mask = [0] * n
    for a, b in edges:
        if a in bit and b in bit and a != b:
            out_mask[verts.index(a)] |= bit[b]
    full = (1 << n) - 1
    best = [0] * (1 << n)  # best[S]: fewest cuts ordering the vertices not in S after those in S
    for S in range(full - 1, -1, -1):
        best[S] = min(bin(out_mask[i] & S).count("1") + best[S | (1 << i)]
                      for i in range(n) if not S & (1 << i))
    order, S = [], 0
    while S != full:  # the smallest vertex that keeps the optimum, position by position
        for i in range(n):
            if not S & (1 << i) and bin(out_mask[i] & S).count("1") + best[S | (1 << i)] == best[S]:
                order.append(verts[i])
                S |= 1 << i
                break
    return tuple(order)
