"""Running a job's tiles on a Dask cluster, with progress, cancel and resume.

One task per tile, with explicit keys that are never reused (a retry of the
whole job gets a new nonce, so no stale result is picked up), ``retries`` for
transient failures, and futures dropped as soon as their result is recorded.
All state lives in the job store and record: restart the process and call
:func:`run_job` again, and it continues from the finished tiles.
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from distributed import Client, as_completed
from distributed.comm.core import CommClosedError

from maxfs.service.runs.cluster import check_store_visible, result
from maxfs.service.runs.fairness import BATCH as FAIR_BATCH
from maxfs.service.runs.fairness import FairShare
from maxfs.service.runs.lifecycle import JobRun
from maxfs.service.runs.progress import ProgressFn
from maxfs.storage.errors import JobCancelledError
from maxfs.storage.records import JobRecord, JobState
from maxfs.worker.task import TileOutcome, estimate_store_eps, run_tile

log = logging.getLogger("maxfs.orchestrator")
#: Futures of a job waited on at once (all are submitted; see run_job).
WAIT_WINDOW = 128


async def run_job(
    client: Client,
    job_dir: Path,
    *,
    on_progress: ProgressFn | None = None,
    progress_interval: float = 1.0,
    retries: int = 2,
    fair: FairShare | None = None,
    user: str = "",
    tile_time_limit: float | None = None,
    finish: Callable[[Path], list[str] | None] | None = None,
) -> JobRecord:
    """Run (or resume) every unfinished tile of a job; return its final record.

    ``finish(job_dir)`` runs (in a thread) after the last tile and before the job is
    recorded done, so a client that sees ``done`` also sees previews and depth; what it
    returns is the record's ``calibration`` (the checks that found the inputs suspect). If
    it fails, the job is still done (the arrays stand) and the failure is logged.

    The job ends ``done``, ``failed`` (with a reason) or ``cancelled`` (a cancel
    flag was set in the store). If this coroutine itself is cancelled without a
    cancel flag (server shutdown), the record keeps its active state so the next
    start resumes it.
    """
    run = JobRun(job_dir, on_progress, progress_interval)
    rec, store = run.rec, run.store
    run.queue()
    log.info("job %s of %s queued: checking that a worker sees its store", rec.id, user or "-")
    futures: dict[str, object] = {}
    ticker: asyncio.Task | None = None
    held = 0  # ranks of this job's tiles in its user's backlog (service.runs.fairness), not yet released
    try:
        # a worker must see this very store (a shared filesystem) before any task reads it
        prep = fair.prep_priority(user) if fair is not None else 0
        await check_store_visible(client, run.job_dir, rec.id, priority=prep)
        if run.needs_eps:
            key = f"maxfs-eps-{rec.id}-{uuid.uuid4().hex[:8]}"
            try:
                eps = await result(
                    client.submit(
                        estimate_store_eps,
                        str(run.job_dir),
                        key=key,
                        pure=False,
                        retries=retries,
                        priority=prep,
                    )
                )
            except Exception as e:
                raise RuntimeError(f"estimating eps and the response failed: {type(e).__name__}: {e}") from e
            run.use_eps(eps)
        # many small reads (one per tile): in a thread, so the server keeps answering meanwhile
        todo = [t.index for t in await asyncio.to_thread(run.prepare)]
        run.running()
        log.info("job %s running: %d of %d tiles to do", rec.id, len(todo), rec.tiles_total)
        digest, nonce = store.params.digest(), uuid.uuid4().hex[:8]
        index_of: dict[str, int] = {}
        # in batches (one message each), yielding to the event loop between them; each batch's
        # priority is minus its last tile's rank in the user's backlog, so users share the workers
        for b in range(0, len(todo), FAIR_BATCH):
            batch = todo[b : b + FAIR_BATCH]
            keys = [f"maxfs-tile-{rec.id}-{i}-{nonce}" for i in batch]
            rank = fair.take(user, len(batch)) if fair is not None else 0
            held += len(batch)
            n = len(batch)
            futs = client.map(
                run_tile,
                [str(run.job_dir)] * n,
                batch,
                [digest] * n,
                [tile_time_limit] * n,
                key=keys,
                pure=False,
                retries=retries,
                priority=FairShare.batch_priority(rank, n),
            )
            for key, fut, i in zip(keys, futs, batch, strict=True):
                futures[key] = fut
                index_of[key] = i
            await asyncio.sleep(0)
        # wait on a window of futures at a time (in submission order, topped up as they finish):
        # as_completed on thousands at once runs thousands of callbacks in one loop turn
        ticker = asyncio.create_task(_tick(run, progress_interval))
        queue = list(futures.values())
        window = as_completed(queue[:WAIT_WINDOW])
        nxt = WAIT_WINDOW
        async for fut in window:
            if nxt < len(queue):
                window.add(queue[nxt])
                nxt += 1
            futures.pop(fut.key, None)
            try:
                out: TileOutcome = await result(fut)
            except Exception as e:  # a tile failed after its retries, or the cluster went away
                # a closed comm is the client's link to the scheduler (tile code never raises it);
                # the client's status may not say so yet
                lost = isinstance(e, CommClosedError) or "scheduler-connection-lost" in str(e)
                if lost or client.status != "running":
                    raise RuntimeError(
                        "lost the Dask scheduler while the job ran; finished tiles are kept: "
                        "start the job again once the scheduler is back"
                    ) from e
                raise RuntimeError(
                    f"tile {index_of.get(fut.key, '?')} failed: {type(e).__name__}: {e}"
                ) from e
            finally:
                fut.release()
                if fair is not None and held:
                    fair.release(user)
                    held -= 1
            run.record(out, tile_time_limit)
            # no store read in the event loop: the timer (_tick) refreshes the running tiles' progress
            run.tick(rec.pixels_running)
        ticker.cancel()
        await asyncio.to_thread(run.check_complete)
        if finish is not None:
            try:
                rec.calibration = list(await asyncio.to_thread(finish, run.job_dir) or ())
            except Exception:
                log.exception("job %s: previews or depth failed; the results stand", rec.id)
        run.done()
        log.info("job %s done", rec.id)
        return rec
    except JobCancelledError:
        await _drop(client, futures)
        run.cancelled()
        log.info("job %s cancelled", rec.id)
        return rec
    except asyncio.CancelledError:
        await _drop(client, futures)
        task = asyncio.current_task()
        if task is not None and not task.cancelling():
            # nobody stopped this run: a library raised CancelledError (e.g. a shared result fetch
            # cancelled by another waiter); ending quietly would leave the job active with nothing
            # running it
            run.fail("internal error: a Dask result fetch was cancelled; start the job again to resume it")
            log.error("job %s: %s", rec.id, rec.error)
            return rec
        if store.cancel_requested:
            rec.state, rec.finished_at = JobState.CANCELLED, time.time()
        run.save()  # without a cancel flag: shutdown; the active state makes the next start resume
        log.info("job %s: its run was stopped (%s)", rec.id, rec.state.value)
        raise
    except Exception as e:
        await _drop(client, futures)
        run.fail(e)
        log.warning("job %s failed: %s", rec.id, e)
        return rec
    finally:
        if ticker is not None:
            ticker.cancel()
        if fair is not None and held:
            fair.release(user, held)


async def _tick(run: JobRun, interval: float) -> None:
    """Save the record every ``interval`` while tiles run, with the progress inside running tiles
    (a job of a few long tiles would otherwise show nothing until one finishes)."""
    while True:
        await asyncio.sleep(interval)
        if not run.due:  # tiles ending keep the record fresh; read the notes only when they do not
            continue
        try:
            run.tick(await asyncio.to_thread(run.store.running_pixels))
        except Exception:  # progress is a courtesy: a failed save shows next time, or the run fails
            log.debug("job %s: progress save failed", run.rec.id, exc_info=True)


async def _drop(client: Client, futures: dict) -> None:
    if futures:
        try:
            await client.cancel(list(futures.values()))
        except Exception:  # the scheduler may be gone already; nothing to cancel then
            pass
        futures.clear()
