"""Running a job's tiles in this process, on threads: what ``maxfs run`` does with the
embedded default when the stack fits in memory.

The exact kernel releases the GIL, so threads use every core without starting a
cluster or warming worker processes, and the images need not go through Zarr before
the first tile: they stay in memory (over the mask's box, :class:`storage.stack.HeldStack`),
and the store records only their digests (the input identity); a resumed run reads the
folder again. Every tile goes through
:func:`worker.task.compute_tile`, the function the Dask tasks run, and the run's states,
eps, counts and tile order are :class:`service.runs.lifecycle.JobRun`'s, as on Dask, so
results are bit-identical to the distributed path.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path

from numpy.typing import NDArray

from maxfs.service.runs.lifecycle import JobRun
from maxfs.service.runs.progress import ProgressFn
from maxfs.storage.errors import JobCancelledError
from maxfs.storage.records import JobRecord
from maxfs.storage.tiles import Tile
from maxfs.worker.task import compute_tile, estimate_eps_of


def run_in_process(
    job_dir: Path,
    *,
    threads: int,
    read_images: Callable[[Tile], NDArray] | None = None,
    on_progress: ProgressFn | None = None,
    progress_interval: float = 1.0,
    timings: Callable[[str, float], None] | None = None,
) -> JobRecord:
    """Run (or resume) every unfinished tile of the job at ``job_dir`` on ``threads`` threads.

    ``read_images``: a tile's images ``(k, h, w[, C])`` from memory (e.g.
    :meth:`storage.stack.HeldStack.tile`), read instead of the store (which then holds only
    the images' digests). Ends ``done``, ``failed`` (with a reason) or
    ``cancelled`` like :func:`service.runs.orchestrator.run_job`; a KeyboardInterrupt leaves the
    job resumable.
    """
    run = JobRun(job_dir, on_progress, progress_interval)
    note = timings or (lambda name, s: None)

    reader = read_images
    run.queue()
    try:
        if run.needs_eps:
            t0 = time.perf_counter()
            run.use_eps(estimate_eps_of(run.store, reader))
            note("eps estimate", time.perf_counter() - t0)
        todo = run.prepare()
        run.running()
        digest = run.store.params.digest()
        t0 = time.perf_counter()
        pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="maxfs-tile")
        futures = {pool.submit(compute_tile, run.store, t.index, digest, reader): t for t in todo}
        try:
            while futures:
                # wake at least every progress interval: a long tile reports how far it is
                finished, _ = wait(futures, timeout=progress_interval, return_when=FIRST_COMPLETED)
                for fut in finished:
                    t = futures.pop(fut)
                    try:
                        out = fut.result()
                    except Exception as e:
                        raise RuntimeError(f"tile {t.index} failed: {type(e).__name__}: {e}") from e
                    run.record(out)
                run.tick()
        finally:
            # on an error or Ctrl-C, queued tiles never start and nothing waits for running
            # ones: a tile counts only once its done marker is written, so none is lost
            pool.shutdown(wait=not futures, cancel_futures=True)
        note("tiles", time.perf_counter() - t0)
        run.check_complete()
        return run.done()
    except KeyboardInterrupt:
        run.save()  # still active: the same command resumes from the finished tiles
        raise
    except JobCancelledError:
        return run.cancelled()
    except Exception as e:
        return run.fail(e)
