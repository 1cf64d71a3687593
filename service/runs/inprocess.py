"""Running a job's tiles in this process, on threads: what ``maxfs run`` does with the
embedded default when the stack fits in memory.

The exact kernel releases the GIL, so threads use every core without starting a
cluster or warming worker processes, and the images need not go through Zarr before
the first tile: they stay in memory, and the store records only their digests (the
input identity); a resumed run reads the folder again. Every tile goes through
:func:`worker.task.compute_tile`, the function the Dask tasks run, so results are
bit-identical to the distributed path. Tiles start in order of their masked-pixel
count, largest first, so the object's few heavy tiles do not finish last.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path

from numpy.typing import NDArray

from maxfs.service.runs.progress import ProgressFn, RunCounter, count_finished, resolve_eps
from maxfs.storage.layout import JobStore
from maxfs.storage.records import JobRecord, JobState, load_record, save_record
from maxfs.storage.tiles import Tile
from maxfs.worker.task import TileOutcome, TileStatus, compute_tile, estimate_eps_of


def run_in_process(
    job_dir: Path,
    *,
    threads: int,
    images: NDArray | None = None,
    on_progress: ProgressFn | None = None,
    progress_interval: float = 1.0,
    timings: Callable[[str, float], None] | None = None,
) -> JobRecord:
    """Run (or resume) every unfinished tile of the job at ``job_dir`` on ``threads`` threads.

    ``images``: the whole stack ``(k, H, W[, C])`` in memory, read instead of the store
    (which then holds only the images' digests). Ends ``done`` or ``failed`` (with a reason) like
    :func:`service.runs.orchestrator.run_job`; a KeyboardInterrupt leaves the job resumable.
    """
    job_dir = Path(job_dir)
    store = JobStore.open(job_dir)
    rec = load_record(job_dir)
    report = on_progress or (lambda r: None)
    note = timings or (lambda name, s: None)

    def save() -> None:
        save_record(job_dir, rec)
        report(rec)

    def read(t: Tile) -> NDArray:
        return images[:, t.y0 : t.y1, t.x0 : t.x1]

    reader = None if images is None else read
    store.clear_cancel()
    rec.state, rec.error, rec.finished_at = JobState.QUEUED, None, None
    save()
    try:
        params = store.params
        if params.eps is None:
            t0 = time.perf_counter()
            params = resolve_eps(store, estimate_eps_of(store, reader))
            note("eps estimate", time.perf_counter() - t0)
        rec.eps = params.eps
        count_finished(rec, store)
        rec.state, rec.started_at, rec.pixel_rate = JobState.RUNNING, time.time(), None
        save()
        done = store.done_grid().ravel()
        todo = store.by_masked_pixels(t for t in store.tiles() if not done[t.index])
        digest, counter, last = params.digest(), RunCounter(rec), 0.0
        t0 = time.perf_counter()
        pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="maxfs-tile")
        futures = {pool.submit(compute_tile, store, t.index, digest, reader): t for t in todo}
        try:
            while futures:
                finished, _ = wait(futures, return_when=FIRST_COMPLETED)
                for fut in finished:
                    t = futures.pop(fut)
                    try:
                        out: TileOutcome = fut.result()
                    except Exception as e:
                        raise RuntimeError(f"tile {t.index} failed: {type(e).__name__}: {e}") from e
                    if out.status is TileStatus.DONE:
                        counter.add(out)
                if time.monotonic() - last >= progress_interval:
                    save()
                    last = time.monotonic()
        finally:
            # on an error or Ctrl-C, queued tiles never start and nothing waits for running
            # ones: a tile counts only once its done marker is written, so none is lost
            pool.shutdown(wait=not futures, cancel_futures=True)
        note("tiles", time.perf_counter() - t0)
        count_finished(rec, store)
        rec.state, rec.finished_at = JobState.DONE, time.time()
        save()
        return rec
    except KeyboardInterrupt:
        save()  # still active: the same command resumes from the finished tiles
        raise
    except Exception as e:
        rec.state, rec.error, rec.finished_at = JobState.FAILED, str(e), time.time()
        save()
        return rec
