"""Batches: many runs of one scene (sweeps, Monte Carlo), on local worker processes or a Dask
cluster, resumable, with one results table.

A batch file names a base scene and the axes to vary over it (:mod:`cosim.batch.spec`); the axes
expand into runs (:mod:`cosim.batch.axes`), each a resolved scene whose hash is the run's id;
every run executes :func:`cosim.run.run` in its own directory ``<out>/runs/<run id>/`` on a
worker (:mod:`cosim.batch.worker`, :mod:`cosim.batch.executors`), which computes the metrics
(:mod:`cosim.batch.metrics`) and returns one row for ``<out>/results.csv``
(:mod:`cosim.batch.results`).  :mod:`cosim.batch.overview` prints and plots the table.
"""
from __future__ import annotations

from .points import PointsBatch, points_batch
from .runner import BatchOutcome, plan, run_batch
from .spec import Batch, BatchError, load_batch

__all__ = ["Batch", "BatchError", "BatchOutcome", "PointsBatch", "load_batch", "plan", "points_batch", "run_batch"]
