"""The dynamic-programming Gauss-Seidel order equals the exhaustive search it replaces: the
lexicographically smallest permutation among those that cut the fewest edges."""
from __future__ import annotations

import itertools
import random

import pytest

from cosim.master.feedback_order import fewest_cut_order


def brute_force(group, edges):
    inner = [(a, b) for a, b in edges if a in group and b in group]
    return min(itertools.permutations(group), key=lambda p: (sum(p.index(a) > p.index(b) for a, b in inner), p))


@pytest.mark.parametrize("seed", range(40))
def test_same_order_as_the_exhaustive_search(seed):
    rng = random.Random(seed)
    n = rng.randint(1, 7)
    group = sorted(rng.sample(range(12), n))
    edges = {(a, b) for a in group for b in group if a != b and rng.random() < rng.choice([0.2, 0.4, 0.7])}
    edges |= {(rng.choice(group), 20)}  # an edge leaving the group is ignored
    assert fewest_cut_order(group, edges) == brute_force(group, edges)


def test_pid_step_loop():
    """pid_step's loop (setpoint 0 feeds the PIDs; PID i -> motor i -> mechanism 7 -> PID i, and
    the mechanism's flow back to each motor)."""
    group = list(range(1, 8))
    edges = {(1, 4), (2, 5), (3, 6), (4, 7), (5, 7), (6, 7), (7, 1), (7, 2), (7, 3), (7, 4), (7, 5), (7, 6)}
    assert fewest_cut_order(group, edges) == brute_force(group, edges)
