"""Imported by the embedded cluster's fork server (:func:`service.runs.cluster.start_forkserver`):
the worker modules and the solver kernels loaded once, in the one process every worker process is
forked from, instead of in each worker after it starts."""

from __future__ import annotations

import contextlib

import distributed  # noqa: F401  # what a worker process runs

from maxfs.worker import task

with contextlib.suppress(Exception):  # a worker that lacks them loads them itself (task.warm_up)
    task.warm_up()
