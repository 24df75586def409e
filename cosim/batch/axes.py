"""From a batch's axes to its runs: the product grid x zip x samples, in a fixed order.

Random samples are drawn from the batch's seed, the sample's number ``j`` and the axis's name
alone (``numpy.random.SeedSequence(seed, spawn_key=(j, key(axis)))``): sample ``j`` has the same
values whatever the number of workers, the number of samples or the other axes.
"""
from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from .spec import Axis, Batch


@dataclass(frozen=True)
class Point:
    """One run of a batch: its position ``index`` in the batch, the value of every axis by name,
    and the scene overrides (path -> value) that make its scene."""

    index: int
    values: dict[str, Any]
    overrides: dict[str, Any]


def draw(axis: Axis, seed: int, j: int) -> float:
    """Sample ``j`` of a random ``axis`` (see the module docstring)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(j, axis.key())))
    return axis.dist.sample(rng)


def samples(batch: Batch, j: int) -> dict[str, float]:
    """The random axes' values of sample ``j``."""
    return {ax.name: draw(ax, batch.seed, j) for ax in batch.random}


def _blocks(batch: Batch) -> Iterator[dict[str, Any]]:
    grid = [[(ax, v) for v in ax.values] for ax in batch.grid]
    n_zip = len(batch.zip[0].values) if batch.zip else 1
    n_rnd = batch.samples if batch.random else 1
    for combo in itertools.product(*grid):
        g = {ax.name: v for ax, v in combo}
        for i in range(n_zip):
            z = {ax.name: ax.values[i] for ax in batch.zip}
            for j in range(n_rnd):
                yield {**g, **z, **(samples(batch, j) if batch.random else {})}


def points(batch: Batch) -> Iterator[Point]:
    """Every run of ``batch`` in order (grid outermost, then zip, then samples), one at a time
    (planning memory does not grow with the number of runs); a batch listing its runs
    (:class:`cosim.batch.points.PointsBatch`) gives them as listed."""
    listed = getattr(batch, "points", None)
    if listed is not None:
        for i, (values, over) in enumerate(listed):
            yield Point(i, dict(values), {**batch.fixed, **over})
        return
    paths = {ax.name: ax.paths for ax in batch.axes}
    for i, values in enumerate(_blocks(batch)):
        over = dict(batch.fixed)
        for name, v in values.items():
            over.update({p: v for p in paths[name]})
        yield Point(i, values, over)


def count(batch: Batch) -> int:
    """The number of runs :func:`points` gives, without making them."""
    listed = getattr(batch, "points", None)
    return len(listed) if listed is not None else batch.n_runs


def expand(batch: Batch) -> list[Point]:
    """:func:`points` as a list."""
    return list(points(batch))


__all__ = ["Point", "count", "draw", "expand", "points", "samples"]
