"""Dask tasks: compute one tile of a job store, and estimate a job's eps.

Tasks are idempotent: a tile whose done marker matches the current parameters
is skipped, so a task that runs twice (a retry, a killed worker) costs nothing
and changes nothing. HiGHS objects are built inside the task (not picklable).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.errors import StoreError
from maxfs.storage.layout import GROUP_DIR, JobStore, job_folder
from maxfs.storage.options import Estimate
from maxfs.storage.tiles import Tile
from maxfs.worker import calibration
from maxfs.worker.cancel import TileCancelled, cancel_points
from maxfs.worker.problem import make_thresholds
from maxfs.worker.solve import eps_sample, estimate_job, solve_tile

#: Seconds between two progress notes of a running tile (its solved pixels so far).
PROGRESS_SECONDS = 1.0


class TileStatus(StrEnum):
    """How a tile task ended."""

    DONE = "done"  #: computed and written, done marker last
    SKIPPED = "skipped"  #: already done with these parameters
    CANCELLED = "cancelled"  #: the job was cancelled; nothing written
    OVERTIME = "overtime"  #: past the per-tile time limit; nothing written


@dataclass(frozen=True)
class TileOutcome:
    """What a tile task reports back to the orchestrator."""

    index: int
    status: TileStatus
    pixels: int = 0  # pixels in the tile
    active: int = 0  # pixels inside the mask
    solved: int = 0  # pixels that got a normal
    certified: int = 0  # active pixels whose optimum is proved
    nodes: int = 0


def run_tile(job_dir: str, tile_index: int, params_hash: str, time_limit: float | None = None) -> TileOutcome:
    """Compute tile ``tile_index`` of the job at ``job_dir``; write outputs, then the done marker."""
    store = open_store(job_dir)
    return compute_tile(store, tile_index, params_hash, time_limit=time_limit)


#: Job stores a worker process keeps open for its next tile tasks (:func:`open_store`), by folder.
STORES_KEPT = 4
_stores: dict[str, tuple[tuple, JobStore]] = {}
_stores_lock = threading.Lock()


def open_store(job_dir: str) -> JobStore:
    """``JobStore.open(job_dir)``, reused by the next tile tasks of the job in this process while
    its group's ``zarr.json`` is unchanged: same bytes (the spec and the parameters a store object
    keeps), same inode and times (a store removed and made again, whose writers' known folders
    are gone). Opening afresh, and the first reads of its arrays, cost a tile task about 30 ms.
    A store object is safe to share between threads (the in-process path does)."""
    meta = job_folder(Path(job_dir)) / GROUP_DIR / "zarr.json"
    try:
        st = os.stat(meta)
        key = (st.st_ino, st.st_mtime_ns, st.st_ctime_ns, st.st_size, meta.read_bytes())
    except OSError:
        return JobStore.open(Path(job_dir))  # with its own error for what is missing
    with _stores_lock:
        got = _stores.get(job_dir)
    if got is not None and got[0] == key:
        return got[1]
    store = JobStore.open(Path(job_dir))  # it may read a newer zarr.json: the next call reopens
    with _stores_lock:
        _stores.pop(job_dir, None)
        _stores[job_dir] = (key, store)
        while len(_stores) > STORES_KEPT:
            _stores.pop(next(iter(_stores)))
    return store


def compute_tile(
    store: JobStore,
    tile_index: int,
    params_hash: str,
    read_images: Callable[[Tile], NDArray] | None = None,
    *,
    time_limit: float | None = None,
) -> TileOutcome:
    """Compute one tile of ``store`` and write it: what every path runs (Dask task or in-process
    thread), so their results are bit-identical. ``read_images`` gives the tile's raw images
    ``(k, h, w[, C])`` from elsewhere (e.g. a stack held in memory); default: the store.

    The solve has cancel points (:mod:`worker.cancel`): within about a second of the job's
    cancel flag appearing the task stops, writes nothing and answers "cancelled", so its
    worker is free for other tiles. With ``time_limit`` (seconds), a tile still computing after
    that long stops the same way and answers "overtime" (the job then fails, naming the tile)."""
    params = store.params
    if not params.resolved or params.digest() != params_hash:
        raise StoreError(f"job parameters changed since tile {tile_index} was scheduled; restart the job")
    t = store.tiles()[tile_index]
    token = params.token()
    if store.tile_done(t):
        return TileOutcome(tile_index, TileStatus.SKIPPED)
    if store.cancel_requested:
        return TileOutcome(tile_index, TileStatus.CANCELLED)
    mask = store.read_tile_mask(t)
    if not mask.any():  # nothing of the object here: fill values, no image read, no solve
        store.write_empty_tile(t, token)
        store.log_run(tile_index, "done")
        return TileOutcome(tile_index, TileStatus.DONE, pixels=mask.size)
    raw = (read_images or store.read_tile_images)(t)
    spec = store.spec
    th = make_thresholds(
        spec.k,
        params.eps,
        shadow=params.shadow,
        saturation=params.saturation,
        box_factor=params.box_factor,
        **params.threshold_options(),
    )
    deadline = None if not time_limit else time.monotonic() + time_limit

    def stop_reason() -> str | None:
        if store.cancel_requested:
            return TileStatus.CANCELLED.value
        if deadline is not None and time.monotonic() > deadline:
            return TileStatus.OVERTIME.value
        return None

    try:
        active = int(mask.sum())

        def report(done: int, total: int) -> None:
            store.note_tile_progress(tile_index, active * done // total)

        with cancel_points(stop_reason, report=report, report_interval=PROGRESS_SECONDS):
            res = solve_tile(
                raw,
                spec.lights,
                store.observation_model,
                th,
                params.solver,
                mask,
                max_nodes=params.max_nodes,
                milp_time_limit=params.milp_time_limit,
            )
    except TileCancelled as e:
        store.clear_tile_progress(tile_index)
        store.log_run(tile_index, str(e))
        return TileOutcome(tile_index, TileStatus(str(e)), pixels=mask.size)
    solved = np.isfinite(res.normal[..., 0]) & mask
    stats = (int(mask.sum()), int(solved.sum()), int((res.optimal & solved).sum()))
    store.write_tile(t, res.outputs(), token, stats)
    store.clear_tile_progress(tile_index)
    store.log_run(tile_index, "done")
    return TileOutcome(
        tile_index,
        TileStatus.DONE,
        pixels=mask.size,
        active=stats[0],
        solved=stats[1],
        certified=stats[2],
        nodes=res.nodes,
    )


def estimate_store_eps(job_dir: str) -> Estimate:
    """eps and response "auto" as a Dask task (see :func:`estimate_eps_of`)."""
    return estimate_eps_of(JobStore.open(Path(job_dir), mode="r"))


def estimate_eps_of(store: JobStore, read_images: Callable[[Tile], NDArray] | None = None) -> Estimate:
    """Resolve eps and response "auto" (:func:`worker.solve.estimate_job`) from the same
    pixels on every path, whatever the tile size (``read_images`` as for
    :func:`compute_tile`, called with sample windows off the tile grid)."""
    spec, params = store.spec, store.params
    mask = store.read_mask()
    if read_images is None:  # the sample's windows read at once, each shard file opened once
        read_images = store.window_reader(t for t, _, _ in eps_sample((spec.height, spec.width), mask))
    return estimate_job(
        read_images,
        spec.lights,
        store.observation_model,
        mask,
        (spec.height, spec.width),
        eps=params.eps_request,
        response=params.response_request,
        drop_bright=params.drop_bright,
        model=params.model,
    )


def warm_up() -> bool:
    """Load the compiled solver kernels in this worker process (numba cache), so
    the first tile of the first job does not pay for it. Run on every worker.

    After an install (or a change to the kernel's source) this compiles them instead, about
    20 s on one core, and writes the cache every later process loads from (0.7 s)."""
    from maxfs.worker import synthetic
    from maxfs.worker.exact import exact_pixels

    L = synthetic.lights_uniform(4)
    I = np.array([[100.0, 90.0, 80.0, 0.0]])
    exact_pixels(I, I - 1.0, I + 1.0, I > 0, L, 10.0, 1000)
    return True


@dataclass(frozen=True)
class KernelLoad:
    """How :func:`load_kernels` went: its seconds, and whether numba compiled (a cache miss)."""

    seconds: float
    compiled: bool


def kernel_dispatchers(module: object | None = None) -> list:
    """The numba dispatchers (``@njit`` functions) of ``module`` (default: :mod:`worker.exact`)."""
    from numba.core.registry import CPUDispatcher

    if module is None:
        from maxfs.worker import exact as module
    return [f for f in vars(module).values() if isinstance(f, CPUDispatcher)]


def cache_misses(dispatchers: list) -> int:
    """Compiles so far of ``dispatchers`` in this process: numba counts a miss of its on-disk
    cache, per signature, right before it compiles one (``Dispatcher.stats.cache_misses``)."""
    return sum(sum(d.stats.cache_misses.values()) for d in dispatchers)


def load_kernels(
    on_compile: Callable[[], None] | None = None,
    *,
    dispatchers: list | None = None,
    load: Callable[[], object] | None = None,
    poll: float = 0.2,
) -> KernelLoad:
    """:func:`warm_up` (or ``load``) in this thread, before a run's first tile.

    Whether it compiles is read from numba's own cache statistics of ``dispatchers`` (default:
    :func:`kernel_dispatchers`), not from the time it takes: a cache load on a busy machine can
    be slow, a compile is a cache miss. ``on_compile`` is called once, from a watcher thread,
    as soon as the first miss shows (the first run after an install, about 20 s), so the user
    is told while it happens. Not on a thread beside the decoding or the eps estimate: on 2
    cores that cost more than it hid (the cache load holds the GIL for much of its 0.7 s)."""
    ds = kernel_dispatchers() if dispatchers is None else dispatchers
    before = cache_misses(ds)
    finished = threading.Event()

    def watch() -> None:
        while not finished.wait(poll):
            if cache_misses(ds) > before:
                on_compile()
                return

    watcher = threading.Thread(target=watch, daemon=True) if on_compile else None
    t0 = time.perf_counter()
    if watcher:
        watcher.start()
    try:
        (load or warm_up)()
    finally:
        finished.set()
    return KernelLoad(time.perf_counter() - t0, cache_misses(ds) > before)


def check_calibration(
    store: JobStore,
    read_images: Callable[[Tile], NDArray] | None = None,
    normal: NDArray | None = None,
    *,
    source: NDArray | None = None,
) -> list[calibration.Finding]:
    """Every calibration check (:mod:`worker.calibration`) on a finished job: the lights alone, the
    lights against the data on the fixed sample of the eps estimate (``read_images`` as for
    :func:`compute_tile`), the solved ``normal`` (read from the store when not given) and, without
    a mask, the share of background pixels (``normal`` and ``source``: the outputs, read from the
    store when not given)."""
    spec = store.spec
    obs = store.observation_model
    out = [calibration.lights_facing(spec.lights)]
    has_mask = store.mask_state() != "default"
    picks = eps_sample((spec.height, spec.width), store.read_mask() if has_mask else None)
    read = read_images or store.window_reader(t for t, _, _ in picks)
    if picks:
        raw = np.concatenate([read(t)[:, ys, xs] for t, ys, xs in picks], axis=1)
        grey, _, saturated = obs.prepare(raw)
        out += calibration.light_checks(grey, np.isfinite(grey) & ~saturated, spec.lights)
        if not has_mask:
            out.append(calibration.no_mask(grey.max(axis=1), _dark_level(grey, obs.step)))
    n = store.read_output("normal") if normal is None else normal
    src = store.read_output("source") if source is None else source
    out += [calibration.normals_facing(n, src), calibration.flip_integrability(n)]
    return out


def _dark_level(grey: NDArray, step: float | None) -> float:
    """What no lit surface stays under in every image: 2 % of the sample's 99th percentile, and
    at least two quantisation steps for integer input."""
    top = float(np.nanpercentile(grey, 99)) if grey.size else 0.0
    return max(calibration.DARK_SHARE * top, 2.0 * (step or 0.0))
