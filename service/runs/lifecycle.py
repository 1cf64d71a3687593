"""One run of a job, whoever executes its tiles: the states, eps, counts, cancel and tile order.

Both executors, threads in this process (:mod:`service.runs.inprocess`) and Dask
(:mod:`service.runs.orchestrator`), drive a :class:`JobRun` through the same steps:

1. :meth:`JobRun.queue`: the cancel flag cleared, the job ``queued``;
2. :meth:`JobRun.use_eps` when eps is "auto" (:attr:`JobRun.needs_eps`), with the executor's estimate;
3. :meth:`JobRun.prepare` (store reads: counts and the unfinished tiles, largest masked-pixel count
   first, since work, not tile count, is what the workers share), then :meth:`JobRun.running`;
4. :meth:`JobRun.record` for every tile outcome (counts, overtime and cancel) and
   :meth:`JobRun.tick` for a throttled record save with the progress inside running tiles;
5. :meth:`JobRun.check_complete` and :meth:`JobRun.done`, or :meth:`JobRun.fail` /
   :meth:`JobRun.cancelled` with the reason.

Steps that read the store (3 and :meth:`check_complete`) do no record save, so an asynchronous
executor can run them in a thread and report from its event loop.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

from maxfs.service.runs.progress import ProgressFn, RunCounter, count_finished, resolve_eps
from maxfs.storage.errors import JobCancelledError
from maxfs.storage.layout import JobStore
from maxfs.storage.options import Estimate
from maxfs.storage.params import JobParams
from maxfs.storage.records import JobRecord, JobState, load_record, save_record
from maxfs.storage.tiles import Tile

if TYPE_CHECKING:  # worker.task imports the solver (numba): not for a finished job's re-run
    from maxfs.worker.task import TileOutcome


class JobRun:
    """The record and store of one job while a run of it goes on."""

    def __init__(self, job_dir: Path, on_progress: ProgressFn | None = None, interval: float = 1.0) -> None:
        self.job_dir = Path(job_dir)
        self.store = JobStore.open(self.job_dir)
        self.rec = load_record(self.job_dir)
        self.report = on_progress or (lambda r: None)
        self.interval = interval
        self.cancel_seen = False
        self.counter: RunCounter | None = None
        self._last_save = 0.0

    def save(self) -> None:
        save_record(self.job_dir, self.rec)
        self.report(self.rec)

    # -- the steps, in order ----------------------------------------------------------------------
    def queue(self) -> None:
        self.store.clear_cancel()
        self.store.clear_tile_progress()  # notes of an earlier, interrupted run
        self.rec.state, self.rec.error, self.rec.finished_at = JobState.QUEUED, None, None
        self.save()

    @property
    def needs_eps(self) -> bool:
        """Whether eps (and the response) are still "auto", or the raw step not yet measured (every
        new job): estimate them, then :meth:`use_eps`."""
        return not self.store.params.resolved

    def use_eps(self, estimate: float | Estimate) -> JobParams:
        """Record the estimate in the store's parameters (checked against the others)."""
        return resolve_eps(self.store, estimate)

    def prepare(self) -> list[Tile]:
        """The record's counts from the finished tiles, and the unfinished tiles, largest first
        (a tile without masked pixels is never one: :meth:`JobStore.done_grid`)."""
        params = self.store.params
        self.rec.eps = params.eps
        self.rec.raw_step = params.quantum
        count_finished(self.rec, self.store)
        done = self.store.done_grid().ravel()  # tiles without masked pixels count as done
        return self.store.by_masked_pixels(t for t in self.store.tiles() if not done[t.index])

    def running(self) -> None:
        self.rec.state, self.rec.started_at, self.rec.pixel_rate = JobState.RUNNING, time.time(), None
        self.counter = RunCounter(self.rec)
        self.save()

    def record(self, out: TileOutcome, time_limit: float | None = None) -> None:
        """One tile's outcome: counted when done; a tile stopped for overtime fails the run."""
        from maxfs.worker.task import TileStatus

        if out.status is TileStatus.OVERTIME:
            raise RuntimeError(
                f"tile {out.index} was stopped after {time_limit or 0:g} s (MAXFS_TILE_TIME_LIMIT); "
                "finished tiles are kept: use a smaller tile, or lower max_nodes or "
                "milp_time_limit, then start the job again"
            )
        if out.status is TileStatus.CANCELLED:
            self.cancel_seen = True
        elif out.status is TileStatus.DONE and self.counter is not None:
            self.counter.add(out)

    @property
    def due(self) -> bool:
        """Whether the last record save is older than the progress interval."""
        return time.monotonic() - self._last_save >= self.interval

    def tick(self, running: int | None = None) -> None:
        """Save the record if the last save is older than the progress interval, with the pixels
        solved so far in running tiles (``running``, or read from the store now)."""
        now = time.monotonic()
        if now - self._last_save >= self.interval:
            self.rec.pixels_running = self.store.running_pixels() if running is None else running
            self.save()
            self._last_save = now

    def check_complete(self) -> None:
        """After the last tile: cancelled, or every tile's done marker there (store reads)."""
        if self.cancel_seen or self.store.cancel_requested:
            raise JobCancelledError("cancelled by request")
        if not self.store.done_grid().all():
            raise RuntimeError(
                "some tiles finished without their done marker; start the job again to finish it"
            )
        count_finished(self.rec, self.store)

    # -- how it ends ------------------------------------------------------------------------------
    def done(self) -> JobRecord:
        self.store.clear_tile_progress()
        self.rec.pixels_running = 0
        self.rec.state, self.rec.finished_at = JobState.DONE, time.time()
        self.save()
        return self.rec

    def fail(self, error: BaseException | str) -> JobRecord:
        self.rec.state, self.rec.error, self.rec.finished_at = JobState.FAILED, str(error), time.time()
        self.save()
        return self.rec

    def cancelled(self) -> JobRecord:
        self.rec.state, self.rec.finished_at = JobState.CANCELLED, time.time()
        self.save()
        return self.rec
