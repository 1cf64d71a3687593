"""The embedded cluster's fork server: the parent of its worker processes (see
:func:`service.runs.cluster.start_forkserver`). No Dask import here: ``maxfs run`` starts it
first thing on its Dask path, so that it loads the solver while this process imports Dask."""

from __future__ import annotations

import multiprocessing
import multiprocessing.forkserver

#: What the fork server imports before it forks the first worker (:mod:`worker.forkserver`).
PRELOAD = ["maxfs.worker.forkserver"]


def launch() -> None:
    """Start this process's fork server with :data:`PRELOAD`, unless it runs already. Returns at
    once: the fork server imports and loads in its own process, and the first worker forked
    waits for that."""
    multiprocessing.get_context("forkserver").set_forkserver_preload(PRELOAD)
    multiprocessing.forkserver.ensure_running()
