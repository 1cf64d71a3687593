"""Running a dataset folder on this machine: what ``maxfs run`` and ``maxfs demo`` do.

The output is a job store (see :mod:`storage.layout`); running again on the same
output resumes from its finished tiles. Parameters that differ from the stored
ones make every tile count as unfinished (their done markers no longer match).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from maxfs.service.results.previews import PNG_LEVEL, PREVIEW_INPUTS, PREVIEWS, render, with_legend
from maxfs.service.runs.progress import ProgressFn
from maxfs.service.runs.timings import Timings
from maxfs.service.settings import Settings, cluster_kind, cluster_settings, runs_in_process
from maxfs.storage.datasets import Dataset
from maxfs.storage.errors import ConflictError, InvalidInputError, MaxfsError, StoreError
from maxfs.storage.imageio import encode_png
from maxfs.storage.layout import GROUP_DIR, JobSpec, JobStore, array_digest, is_job_folder, lights_digest
from maxfs.storage.params import JobParams
from maxfs.storage.records import JobRecord, JobState, load_record, save_record
from maxfs.storage.stack import HeldStack, StackReader
from maxfs.storage.tiles import Tile

log = logging.getLogger("maxfs.local")

#: Said when numba misses its cache while loading the solver kernels: they are being compiled.
COMPILING = (
    "compiling the exact solver for this machine: once after an install, about 20 s "
    "(`maxfs warm` does it ahead of time)"
)


def ingest(
    ds: Dataset,
    out: Path,
    params: JobParams,
    *,
    overwrite: bool = False,
    copy_images: bool = True,
    threads: int = 2,
    stop: threading.Event | None = None,
    tile_auto: bool = False,
) -> tuple[JobStore, str]:
    """Create or reopen the output store for ``ds``; copy images not yet stored (into a
    new store only if ``copy_images``: :func:`run_folder` may keep them in memory and
    store only their digests instead), on ``threads`` threads (:func:`store_images`; ``stop``
    set: the images not yet begun are skipped).

    A store that already holds *other* inputs (images, mask, lights or intensities,
    compared by content digest) or parameters is refused unless ``overwrite``, which removes it
    and starts from scratch, or unless it holds no finished tile (a run that stopped before
    solving anything: it is replaced, with a note). Unchanged inputs are recognised from the
    files' fingerprint (paths, sizes, times) without decoding them again. ``tile_auto``: the user
    left the tile edge to "auto", so an existing store's own edge is accepted. Returns the store
    and a note for the user ("" when nothing notable happened).
    """
    out = Path(out)
    if ds.mask is not None and not ds.mask.any():  # before anything is written or replaced
        raise InvalidInputError(f"the mask of {ds.name} selects no pixel; nothing to solve")
    spec = JobSpec.of(ds)
    note = ""
    if out.exists() and not out.is_dir():
        raise ConflictError(f"{out} is a file; give a folder path for the results")
    if out.exists() and any(out.iterdir()):
        if not is_job_folder(out):
            raise ConflictError(
                f"{out} is not empty and holds no maxfs results; choose a new or empty output folder"
            )
        if overwrite:
            shutil.rmtree(out)
    store = None
    if (out / GROUP_DIR / "zarr.json").exists():
        store = JobStore.open(out)
        try:
            params = _resumable(store, ds, spec, out, params, copy_images, tile_auto)
        except ConflictError:
            if store.progress().tiles_done:
                raise
            # a run that stopped before its first tile (bad input, no eps, an interrupt): nothing
            # of it is worth keeping, and refusing would send the user to --overwrite for nothing
            store = None
            shutil.rmtree(out)
            note = f"replacing {out}: it held a run with other inputs or options and no finished tile"
        else:
            # counted as the progress line counts them: tiles that hold masked pixels
            c = store.progress()
            note = f"resuming {out}: {c.tiles_done} of {c.tiles_total} tiles already done"
            try:
                load_record(out)
            except StoreError:
                save_record(out, JobRecord(id=out.name))
    if store is None:
        store = JobStore.create(out, spec, params)
        save_record(out, JobRecord(id=out.name))
        if ds.mask is not None:
            store.write_mask(ds.mask)
        if copy_images:
            store_images(ds, store, range(ds.k), threads, stop)
    store.source_fingerprint = ds.fingerprint()
    if not store.read_mask().any():
        raise InvalidInputError(f"the mask of {ds.name} selects no pixel; nothing to solve")
    return store, note


def _resumable(
    store: JobStore,
    ds: Dataset,
    spec: JobSpec,
    out: Path,
    params: JobParams,
    copy_images: bool,
    tile_auto: bool,
) -> JobParams:
    """The parameters to resume ``store`` with; ConflictError if it holds other inputs or parameters."""
    _check_same_inputs(store, ds, spec, out, copy_images)
    old = store.params
    if tile_auto:
        # "auto" resumes on the grid the job began with: the rule may have changed since
        # (or the mask's balance differs), and finished tiles are kept only on that grid
        params = replace(params, tile=old.tile)
    comparable = old.unresolved() if not params.resolved else old
    if comparable != params:
        # never a quiet replacement: a sweep into one folder would keep only its last run
        raise ConflictError(
            f"{out} holds results made with other parameters ({param_changes(comparable, params)}); "
            "choose another output folder (-o) to keep both, or add --overwrite to replace them"
        )
    return params


def finished_before(store: JobStore) -> bool:
    """Whether the job was finished earlier with these inputs and parameters (every tile done and
    the previews made): ``maxfs run`` then has nothing to do."""
    return bool(store.done_grid().all()) and (store.path / "previews").is_dir()


def store_images(
    ds: Dataset, store: JobStore, indices: Iterable[int], threads: int, stop: threading.Event | None = None
) -> None:
    """Decode images ``indices`` of ``ds`` and store them (:meth:`JobStore.write_image`: whole
    shards, digests made as they are written) on ``threads`` threads: each image is read once and
    reaches the store once, and the decoders, zstd, the digests and file writes release the GIL, so
    the copy runs at about the rate of decoding. The first error is raised, and images not begun
    are skipped, as they are once ``stop`` is set."""

    def one(i: int) -> None:
        if stop is None or not stop.is_set():
            store.write_image(i, ds.read(i))

    pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="maxfs-store")
    try:
        for f in [pool.submit(one, i) for i in indices]:
            f.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def param_changes(old: JobParams, new: JobParams) -> str:
    """'eps 1.0 -> 2.0, tile 64 -> 32': the options that differ, as the user gives them."""
    a, b = old.to_json(), new.to_json()
    shown = {
        "eps_request": "eps",
        "response_request": "response",
        "eps": None,
        "response": None,
        "quantum": None,
    }
    return (
        ", ".join(
            f"{shown.get(k, k)} {a[k]} -> {b[k]}"
            for k in a
            if a[k] != b.get(k) and shown.get(k, k) is not None
        )
        or "eps or response"
    )


def _check_same_inputs(store: JobStore, ds: Dataset, spec: JobSpec, out: Path, copy_images: bool) -> None:
    """Refuse a store that holds other inputs than ``ds``; complete a cut-short ingest.

    Images already stored are compared by digest (decoding each file once, unless the
    files' fingerprint is unchanged); missing ones, and a mask cut short, are written.
    """

    def differ(what: str) -> ConflictError:
        return ConflictError(
            f"{out} holds results for other inputs ({what} differ from {ds.name}); run again with "
            "--overwrite to replace them, or choose another output folder"
        )

    s = store.spec
    if (s.k, s.height, s.width, s.channels, s.dtype) != (ds.k, ds.height, ds.width, ds.channels, ds.dtype):
        raise differ(f"{s.k} images of {s.height} x {s.width} {s.dtype}: the image count, size or type")
    if store.lights_digest != lights_digest(spec):
        raise differ("the light directions or intensities")
    stored = store.digests()  # k + 1 chunks each, like uploaded: read once, and only when needed
    known = store.known_images(stored)
    fp = ds.fingerprint()
    same_files = fp is not None and fp == store.source_fingerprint
    same_files = same_files and store.input_identity(stored) is not None
    uploaded = store.uploaded() if copy_images or not same_files else None
    if uploaded is not None and not (same_files and uploaded.all()):
        new: dict[int, bytes] = {}
        for i in range(ds.k):
            if same_files and uploaded[i]:
                continue
            img = ds.read(i)
            d = array_digest(img, s.digest)
            if known[i] and d != stored[i]:
                raise differ(f"the images ({ds.label(i)} first)")
            if copy_images and not uploaded[i]:
                store.write_image(i, img)
            elif not known[i]:
                new[i] = d
        store.record_digests(new)
    state = store.mask_state()
    if ds.mask is None:
        if state != "default":
            raise differ("the masks")
    elif state == "incomplete":
        store.write_mask(ds.mask)
    elif state == "default" or array_digest(np.ascontiguousarray(ds.mask, bool), s.digest) != stored[s.k]:
        raise differ("the masks")


async def _run(out: Path, settings: Settings, on_progress: ProgressFn | None) -> JobRecord:
    from maxfs.service.runs.cluster import open_cluster  # imports distributed: only for cluster runs
    from maxfs.service.runs.orchestrator import run_job

    # SLURM worker jobs write their logs beside the results (a shared filesystem either way)
    out = out.absolute()  # workers elsewhere have other working folders
    async with open_cluster(settings, log_dir=out / "slurm-logs") as dc:
        return await run_job(dc.client, out, on_progress=on_progress)


async def _ingest_and_run(
    ds: Dataset,
    out: Path,
    params: JobParams,
    settings: Settings,
    *,
    overwrite: bool,
    early: bool,
    on_note: Callable[[str], None] | None,
    on_progress: ProgressFn | None,
    tm: Timings,
    tile_auto: bool = False,
) -> tuple[JobStore, JobRecord | None]:
    """:func:`run_folder` on a Dask cluster. With ``early`` (a fresh output: the job cannot be
    finished already) the cluster starts while the images are decoded and stored, its workers
    loading the solver meanwhile; a done job's previews and depth are made while it stops.
    Returns the store and the record, or None for the record when the job was finished before."""
    if early and cluster_kind(settings) == "local":
        from maxfs.service.runs import forkserver

        forkserver.launch()  # unless `maxfs run` did: loads the solver for the workers meanwhile

    from maxfs.service.runs.cluster import DaskCluster, start_cluster  # imports distributed
    from maxfs.service.runs.orchestrator import run_job

    out = out.absolute()  # workers elsewhere have other working folders
    logs = out / "slurm-logs"  # SLURM worker jobs write their logs beside the results

    starting = asyncio.ensure_future(start_cluster(settings, log_dir=logs)) if early else None
    stop = threading.Event()
    dc: DaskCluster | None = None
    depth_pool = ThreadPoolExecutor(1, thread_name_prefix="maxfs-depth")  # one after the other
    sample = SampleWindows(ds)
    try:
        t0 = time.perf_counter()
        try:
            store, note = await asyncio.to_thread(
                ingest,
                sample.dataset,
                out,
                params,
                overwrite=overwrite,
                threads=settings.workers,
                stop=stop,
                tile_auto=tile_auto,
            )
        finally:
            stop.set()  # interrupted: the copy threads stop after the images they hold
            tm.add("open or create the store", time.perf_counter() - t0)
        if note and on_note:
            on_note(note)
        if finished_before(store):
            return store, None
        reader = sample.reader(store)
        if reader is not None and not store.params.resolved:
            # while the cluster starts, from the windows kept: no task reading them back from the store
            t0 = time.perf_counter()
            await asyncio.to_thread(_estimate_eps, store, reader)
            tm.add("eps estimate", time.perf_counter() - t0)
        # this process integrates depth once the tiles are done: its kernels load meanwhile, while
        # the cluster starts (this process waits for the workers' fork server then)
        depth_pool.submit(load_depth_kernels, store.params)
        t0 = time.perf_counter()
        dc = await (starting or start_cluster(settings, log_dir=logs))
        starting = None
        tm.add("cluster start (what reading left)", time.perf_counter() - t0)
        t0 = time.perf_counter()
        rec = await run_job(dc.client, out, on_progress=on_progress)
        tm.add("cluster run (tiles)", time.perf_counter() - t0)
        if rec.state is JobState.DONE:
            closing, dc = asyncio.ensure_future(dc.close()), None
            try:
                found = await asyncio.to_thread(finish_beside_depth, out, tm, reader, depth_pool)
            finally:
                await closing
            rec.calibration = [*(f"input folder: {n}" for n in ds.notes), *found]
            save_record(out, rec)
        return store, rec
    finally:
        if starting is not None:  # never cancelled half-way: a cluster half started leaves processes
            with contextlib.suppress(Exception):
                dc = await starting
        depth_pool.shutdown(wait=False)  # a kernel load still running ends by itself
        if dc is not None:
            t0 = time.perf_counter()
            await dc.close()
            tm.add("cluster stop", time.perf_counter() - t0)


def load_depth_kernels(params: JobParams) -> None:
    """Load the kernels of the depth step these parameters ask for (numba's cache; the first
    kernels loaded in a process also cost numba's own start), on a 16 x 16 sphere: what the
    Dask path's process would otherwise pay when it integrates the normals. A failure is left to
    the depth step itself."""
    from maxfs.service.results.research import camera_of
    from maxfs.storage.options import DepthMethod
    from maxfs.worker import depth_scenes
    from maxfs.worker.depth import integrate

    try:
        opts = params.depth_options()
        if opts["depth"] == DepthMethod.NONE:
            return
        scene = depth_scenes.sphere_ortho(16)
        integrate(
            scene.normal.astype(np.float32),
            scene.mask,
            method=opts["depth"],
            camera=camera_of(opts),
            distance=opts["distance"],
            k=opts["depth_k"],
            max_iterations=2,
        )
    except Exception:
        log.debug("loading the depth kernels failed; the depth step tries again", exc_info=True)


class SampleWindows:
    """The windows of the eps sample (:func:`worker.solve.eps_sample`, a function of the image size
    and mask alone) cut from every image of ``ds`` as :attr:`dataset` is read: the Dask path
    stores the images and keeps only these (a few thousand pixels per image), from which the eps
    estimate and the calibration checks read what they would read back from the store."""

    def __init__(self, ds: Dataset) -> None:
        from maxfs.worker.solve import eps_sample

        self._windows = [(t.y0, t.y1, t.x0, t.x1) for t, _, _ in eps_sample((ds.height, ds.width), ds.mask)]
        self._cuts: list[list[NDArray] | None] = [None] * ds.k
        self._source = ds
        self.dataset = replace(ds, _reader=self._read)

    def _read(self, i: int) -> NDArray:
        img = self._source.read(i)
        self._cuts[i] = [np.array(img[y0:y1, x0:x1]) for y0, y1, x0, x1 in self._windows]
        return img

    def reader(self, store: JobStore) -> Callable[[Tile], NDArray] | None:
        """What :meth:`JobStore.read_tile_images` gives for a window of the sample, from the windows
        kept (any other window from ``store``); None unless every image was read."""
        if any(c is None for c in self._cuts):
            return None
        stacks = {w: np.stack([c[j] for c in self._cuts]) for j, w in enumerate(self._windows)}

        def read(t: Tile) -> NDArray:
            got = stacks.get((t.y0, t.y1, t.x0, t.x1))
            return store.read_tile_images(t) if got is None else got.copy()

        return read


def _estimate_eps(store: JobStore, reader: Callable[[Tile], NDArray]) -> None:
    """eps (and response) "auto" resolved in this process, as the in-process path does. A failure
    leaves them unresolved: the run's estimate task then fails the job with the error, as ever."""
    from maxfs.service.runs.progress import resolve_eps
    from maxfs.worker.task import estimate_eps_of

    try:
        resolve_eps(store, estimate_eps_of(store, reader))
    except Exception:
        log.debug("eps estimate in this process failed; the cluster tries it", exc_info=True)


def run_store(
    out: Path,
    *,
    scheduler: str = "",
    workers: int = 2,
    cluster: str = "",
    on_progress: ProgressFn | None = None,
) -> JobRecord:
    """Run every unfinished tile of the store at ``out`` on a Dask cluster (the embedded
    one, SLURM worker jobs, or ``scheduler``); write previews and derived results when done,
    and the calibration checks' findings into the record."""
    rec = asyncio.run(_run(Path(out), cluster_settings(scheduler, workers, cluster), on_progress))
    if rec.state is JobState.DONE:
        rec.calibration = finish(Path(out))
        save_record(Path(out), rec)
    return rec


def finish(
    out: Path, timings: Timings | None = None, read_images: Callable[[Tile], NDArray] | None = None
) -> list[str]:
    """What a finished job gets besides its arrays: PNG previews, depth (see :mod:`service.results.research`),
    and the calibration checks (:func:`worker.task.check_calibration`; ``read_images`` as there).
    Returns what those checks found suspect, for the record's ``calibration``. The outputs are read
    once, for all three (a chunk per tile each)."""
    from maxfs.service.results.research import finish_results

    tm = timings or Timings()
    with tm.phase("previews"):
        store = JobStore.open(out, mode="r")
        arrays = preview_inputs(store)
        write_previews(store, arrays)
    with tm.phase("depth and derived results"):
        finish_results(out, normal=arrays["normal"])
    with tm.phase("calibration checks"):
        return calibration_messages(out, read_images, arrays)


def finish_beside_depth(
    out: Path,
    timings: Timings,
    read_images: Callable[[Tile], NDArray] | None = None,
    depth_pool: ThreadPoolExecutor | None = None,
) -> list[str]:
    """:func:`finish` with the depth step on a thread of its own (of ``depth_pool``, after what it
    runs already: :func:`load_depth_kernels`) beside the previews and the calibration checks: the
    Dask path, whose workers are done, where this process alone would leave a core idle. The
    depth step writes only its own array and ``previews/depth.png``; the outputs are read once,
    as there. Its timings row is what the previews and the checks left of it. Every step has
    ended when this returns or raises."""
    from maxfs.service.results.research import finish_results

    pool = depth_pool or ThreadPoolExecutor(1, thread_name_prefix="maxfs-depth")
    t0 = time.perf_counter()
    store = JobStore.open(out, mode="r")
    arrays = preview_inputs(store)
    depth = pool.submit(finish_results, out, normal=arrays["normal"].copy())
    try:
        write_previews(store, arrays)
        t1 = time.perf_counter()
        found = calibration_messages(out, read_images, arrays)
    finally:
        t2 = time.perf_counter()
        wait([depth])
    timings.add("previews", t1 - t0)
    timings.add("depth and derived results", time.perf_counter() - t2)
    timings.add("calibration checks", t2 - t1)
    depth.result()
    if depth_pool is None:
        pool.shutdown()
    return found


def calibration_messages(
    out: Path, read_images: Callable[[Tile], NDArray] | None = None, arrays: dict[str, NDArray] | None = None
) -> list[str]:
    """The messages of the calibration checks that tripped on the finished job at ``out``
    (``arrays``: its ``normal`` and ``source`` outputs, if the caller has read them)."""
    from maxfs.worker.task import check_calibration  # imports the solver module: only once a job is done

    got = arrays or {}
    try:
        found = check_calibration(
            JobStore.open(out, mode="r"), read_images, got.get("normal"), source=got.get("source")
        )
    except Exception as e:  # the results stand; a user must still hear that nothing was checked
        log.exception("calibration checks of %s failed", out)
        return [f"the calibration checks could not run ({type(e).__name__}: {e})"]
    return [f"{f.check}: {f.message}" for f in found if f.message]


class _LinalgAttributes:
    """An import hook, for one import: when ``scipy.linalg`` is imported for real after
    :func:`preload_numba_blas`, its ``cython_blas`` and ``cython_lapack`` attributes are set
    (the submodules are already in ``sys.modules``, so importing the package does not set them)."""

    def find_spec(self, name: str, path: object, target: object = None) -> object:
        import importlib.util
        import sys

        if name != "scipy.linalg":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def exec_module(module: object) -> None:
            run(module)
            for sub in ("cython_blas", "cython_lapack"):
                if f"scipy.linalg.{sub}" in sys.modules:
                    setattr(module, sub, sys.modules[f"scipy.linalg.{sub}"])

        spec.loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec


def preload_numba_blas() -> bool:
    """Import ``scipy.linalg.cython_blas`` and ``cython_lapack`` without the rest of
    ``scipy.linalg``, before numba needs them.

    numba's first compile or cache load imports ``scipy.linalg.cython_blas`` to see whether a
    BLAS is there (``numba.np.linalg.ensure_blas``); the import runs ``scipy.linalg``'s
    ``__init__`` too, 0.25-0.3 CPU s of Python (scipy's array-API layer, docstrings), in every
    run, l2 included (the depth step loads numba), for two extension modules that import
    nothing of it. Here the package is stood in for while they load; a real ``import
    scipy.linalg`` later still gets the whole package, with both attributes
    (:class:`_LinalgAttributes`). False (nothing done) if scipy.linalg is already imported or
    this scipy lays its modules out otherwise."""
    import importlib.util
    import sys
    import types

    if "scipy.linalg" in sys.modules or "scipy.linalg.cython_blas" in sys.modules:
        return False
    try:
        import scipy

        spec = importlib.util.find_spec("scipy.linalg")
        if spec is None or not spec.submodule_search_locations:
            return False
        stand_in = types.ModuleType("scipy.linalg")
        stand_in.__path__ = list(spec.submodule_search_locations)
        sys.modules["scipy.linalg"] = stand_in
        try:
            import scipy.linalg.cython_blas
            import scipy.linalg.cython_lapack
        finally:
            del sys.modules["scipy.linalg"]
            scipy.__dict__.pop("linalg", None)
    except Exception:  # anything unexpected: numba imports scipy.linalg itself, as before
        for sub in ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack"):
            sys.modules.pop(sub, None)
        return False
    sys.meta_path.insert(0, _LinalgAttributes())
    return True


#: Where ``run_folder(overwrite=True)`` keeps the results it replaces until the new run has
#: finished a tile: a hidden sibling of the output folder (the same filesystem: a rename).
ASIDE = ".{name}.maxfs-replaced"


def run_folder(
    ds: Dataset, out: Path, params: JobParams, *, overwrite: bool = False, **kw: Any
) -> tuple[JobStore, JobRecord]:
    """:func:`_run_folder`; with ``overwrite``, the results already in ``out`` are removed only
    once the new run has finished a tile. Until then they wait beside it (:data:`ASIDE`), and a
    run that ends before (bad input, no eps, an interrupt, an error) puts them back: a mistake in
    the new inputs never costs the old results. Returns what :func:`_run_folder` does."""
    out = Path(out)
    if not (overwrite and out.is_dir() and is_job_folder(out)):
        return _run_folder(ds, out, params, overwrite=overwrite, **kw)
    aside = out.parent / ASIDE.format(name=out.name)
    try:
        if aside.exists():  # left by a run killed before it settled: an older generation
            shutil.rmtree(aside)
        out.rename(aside)
    except OSError:  # e.g. a parent folder we may not write to: replace in place, as before
        return _run_folder(ds, out, params, overwrite=True, **kw)
    on_note = kw.get("on_note")
    try:
        return _run_folder(ds, out, params, overwrite=False, **kw)
    finally:
        if _progressed(out):
            shutil.rmtree(aside, ignore_errors=True)
        else:
            shutil.rmtree(out, ignore_errors=True)
            aside.rename(out)
            if on_note:
                on_note(f"kept the earlier results in {out}: the new run ended before finishing a tile")


def _progressed(out: Path) -> bool:
    """Whether ``out`` holds a job with at least one finished tile (with masked pixels)."""
    try:
        return is_job_folder(out) and JobStore.open(out, mode="r").progress().tiles_done > 0
    except (MaxfsError, OSError, ValueError):
        return False


def _run_folder(
    ds: Dataset,
    out: Path,
    params: JobParams,
    *,
    overwrite: bool = False,
    scheduler: str = "",
    workers: int = 2,
    cluster: str = "",
    in_process_bytes: int = 2 << 30,
    on_note: Callable[[str], None] | None = None,
    on_progress: ProgressFn | None = None,
    timings: Timings | None = None,
    prefetch: StackReader | None = None,
    tile_auto: bool = False,
) -> tuple[JobStore, JobRecord]:
    """``maxfs run``: ingest ``ds`` into ``out`` (or resume it) and solve every tile.

    On the ``local`` cluster (no ``scheduler``, ``cluster`` unset or "local") and a stack of at
    most ``in_process_bytes``, tiles run on ``workers`` threads in this process
    (:mod:`service.runs.inprocess`) with the images held in memory and only their digests stored;
    otherwise on a Dask cluster (:mod:`service.runs.cluster`): the embedded one, SLURM
    worker jobs, or ``scheduler``. A finished job is not run again: it costs a look at
    its done markers. Results are bit-identical either way. ``prefetch``: the stack, being
    decoded since the folder was opened (used in process, cancelled otherwise). ``tile_auto``:
    as for :func:`ingest`.
    """
    out = Path(out)
    tm = timings or Timings()
    # a refused store, an interrupt or a run that did not need them: the decoding threads stop too
    with prefetch or contextlib.nullcontext():
        settings = cluster_settings(scheduler, workers, cluster)
        in_process = runs_in_process(settings, ds.nbytes, in_process_bytes)
        if not in_process:
            fresh = overwrite or not out.exists() or (out.is_dir() and not any(out.iterdir()))
            store, got = asyncio.run(
                _ingest_and_run(
                    ds,
                    out,
                    params,
                    settings,
                    overwrite=overwrite,
                    early=fresh,
                    on_note=on_note,
                    on_progress=on_progress,
                    tm=tm,
                    tile_auto=tile_auto,
                )
            )
            return store, got if got is not None else load_record(out)
        with tm.phase("open or create the store"):
            store, note = ingest(ds, out, params, overwrite=overwrite, copy_images=False, tile_auto=tile_auto)
        if note and on_note:
            on_note(note)
        if finished_before(store):
            return store, load_record(out)
        with tm.phase("imports"):  # the solver (numba) only now: a finished job never loads it
            preload_numba_blas()
            from maxfs.service.runs.inprocess import run_in_process
            from maxfs.worker.task import load_kernels

        held = None
        if not store.uploaded().all():  # the stack stays in memory; only its digests are stored
            with tm.phase("read images"):
                held = read_stack(ds, store, workers, prefetch)
        if store.params.solver == "exact":
            with tm.phase("load the solver"):  # its own row: 0.7 s from the cache, or a compile
                try:
                    load_kernels(on_compile=(lambda: on_note(COMPILING)) if on_note else None)
                except Exception:  # the first tile raises it again, and the job fails with it
                    pass
        reader = None if held is None else held.tile
        rec = run_in_process(
            out, threads=workers, read_images=reader, on_progress=on_progress, timings=tm.add
        )
        if rec.state is JobState.DONE:
            rec.calibration = [*(f"input folder: {n}" for n in ds.notes), *finish(out, tm, reader)]
            save_record(out, rec)
        return store, rec


def read_stack(ds: Dataset, store: JobStore, threads: int, reader: StackReader | None = None) -> HeldStack:
    """The stack in memory over the mask's box (:class:`storage.stack.HeldStack`), decoded on
    ``threads`` threads (PNG/TIFF decoders release the GIL), or taken from ``reader`` (started
    earlier, :class:`storage.stack.StackReader`); each image's digest is recorded in the store
    where it is not yet known, in one write."""
    if reader is not None and reader.digest != store.spec.digest:
        reader.cancel()  # started before the store was open, with a new store's hash: not this one's
        reader = None
    held, digests = (reader or StackReader(ds, threads, store.spec.digest)).result()
    known = store.known_images()
    store.record_digests({i: d for i, d in enumerate(digests) if not known[i]})
    return held


def preview_inputs(store: JobStore) -> dict[str, NDArray]:
    """The outputs the previews are drawn from, by name (``normal`` and ``source`` among them)."""
    return {n: store.read_output(n) for n in store.output_names() if n in PREVIEW_INPUTS}


def write_previews(store: JobStore, arrays: dict[str, NDArray] | None = None) -> list[Path]:
    """PNG previews under ``previews/`` in the job directory (``arrays``: :func:`preview_inputs`,
    if the caller has read them)."""
    d = store.path / "previews"
    d.mkdir(exist_ok=True)
    arrays = preview_inputs(store) if arrays is None else arrays
    paths = []
    for name in PREVIEWS:
        p = d / f"{name}.png"
        p.write_bytes(
            encode_png(with_legend(name, render(name, arrays, store.spec.k), store.spec.k), PNG_LEVEL)
        )
        paths.append(p)
    return paths
