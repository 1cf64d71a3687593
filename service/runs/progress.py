"""A job record's progress counts, shared by the Dask and the in-process paths.

Kept apart from :mod:`service.runs.orchestrator` so that ``maxfs run`` solving in its own
process never imports ``distributed`` (about half a second).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from maxfs.storage.layout import JobStore
from maxfs.storage.options import Estimate, check_options
from maxfs.storage.params import JobParams
from maxfs.storage.records import JobRecord

if TYPE_CHECKING:  # worker.task imports the solver (numba): not for a finished job's re-run
    from maxfs.worker.task import TileOutcome

ProgressFn = Callable[[JobRecord], None]


class RunCounter:
    """Adds finished tiles to a record and keeps the pixel rate of this run."""

    def __init__(self, rec: JobRecord) -> None:
        self.rec, self.t0, self.pixels = rec, time.monotonic(), 0

    def add(self, out: TileOutcome) -> None:
        rec = self.rec
        rec.tiles_done += 1
        rec.pixels_done += out.active
        rec.solved_pixels += out.solved
        rec.certified_pixels += out.certified
        self.pixels += out.active
        rec.pixel_rate = self.pixels / max(time.monotonic() - self.t0, 1e-9)


def resolve_eps(store: JobStore, eps: float | Estimate) -> JobParams:
    """Record an estimated eps (and response: an :class:`~worker.noise.Estimate`) in the
    store's parameters, after checking it fits the others (e.g. a saturation given by hand)."""
    params = store.params
    # with the job's own model: its default shadow threshold is what creation checked against
    check_options(
        eps=getattr(eps, "eps", eps), shadow=params.shadow, saturation=params.saturation, model=params.model
    )
    params = params.with_eps(eps)
    store.set_params(params)
    return params


def count_finished(rec: JobRecord, store: JobStore) -> None:
    """Set the record's counts from what the store's finished tiles hold."""
    c = store.progress()
    rec.tiles_done, rec.tiles_total = c.tiles_done, c.tiles_total
    rec.pixels_done, rec.pixels_total = c.pixels_done, c.pixels_total
    rec.solved_pixels, rec.certified_pixels = c.solved, c.certified
