"""The job manager: creates job stores, takes uploads, runs and cancels jobs.

It owns the asynchronous Dask client (:mod:`service.runs.cluster`: an embedded
LocalCluster, SLURM worker jobs, or an external scheduler, from settings) and
one asyncio task per running job. On start it removes what a killed process left
half-made (a job folder without a record, staged uploads, temp files) and
resumes every job whose record says queued or running: a restarted server loses
no finished tile and finishes what was in flight. Every job belongs to a user;
other users get "no job" for it, as if it did not exist, unless they are admins.
Per-user and disk limits are checked before anything is stored (:mod:`service.http.quotas`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import tempfile
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import numpy as np
from distributed import Client
from numpy.typing import NDArray

from maxfs.service.http.guards import Decoder, DiskBudget, UploadSlots
from maxfs.service.http.index import JobIndex
from maxfs.service.http.quotas import JobLimits
from maxfs.service.runs.cluster import DaskCluster, start_cluster
from maxfs.service.runs.fairness import FairShare
from maxfs.service.runs.local import finish_beside_depth, load_depth_kernels
from maxfs.service.runs.orchestrator import run_job
from maxfs.service.runs.timings import Timings
from maxfs.service.settings import Settings
from maxfs.storage.errors import (
    ConflictError,
    InvalidInputError,
    NotFoundError,
    QuotaError,
    StoreError,
    is_disk_full,
)
from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.options import DepthMethod
from maxfs.storage.params import JobParams
from maxfs.storage.records import RECORD_NAME, TRANSITIONS, JobRecord, JobState, load_record, save_record
from maxfs.storage.tokens import User

log = logging.getLogger("maxfs.jobs")
#: Prefix of every temporary file a process writes in a job folder (removed on start).
TEMP_PREFIX = ".maxfs-"
#: Jobs whose store :meth:`JobManager._upload_store` keeps open for their uploads.
UPLOAD_STORES = 64
#: The longest a status request may wait for a job's record to change (``GET /jobs/{id}?wait=S``).
MAX_STATUS_WAIT = 30.0
#: Status requests one user may have waiting at once (``?wait=``); beyond, they answer at once: a
#: waiting request holds a connection that is never closed to make room (service.http.connections).
MAX_WAITS_PER_USER = 8


def owns(user: User, rec: JobRecord) -> bool:
    """Whether ``rec`` is ``user``'s job: the same name, and the same person (a name revoked
    and given a new token is someone else; see :mod:`storage.tokens`)."""
    return rec.owner == user.name and (not rec.owner_uid or not user.uid or rec.owner_uid == user.uid)


def _check_id(job_id: str) -> str:
    if not (len(job_id) == 32 and all(c in "0123456789abcdef" for c in job_id)):
        raise NotFoundError(f"no job {job_id!r}: job ids are 32 hexadecimal characters")
    return job_id


def _finish(job_dir: Path) -> list[str]:
    """Previews, depth and the calibration checks of a finished job, depth on a thread of its own
    beside the other two (:func:`service.runs.local.finish_beside_depth`): the job's workers are
    done, and this process alone would leave a core idle."""
    return finish_beside_depth(job_dir, Timings())


_warm_started = threading.Lock()


def _warm_finish(params: JobParams) -> None:
    """Load what a finished job's last step runs in this process (numba and the depth kernels these
    parameters ask for) on a thread of its own, once per process, when the first job that makes
    depth is made, while its images arrive: the first job after the server started otherwise paid
    it (~0.9 s here) between its last tile and done. Later jobs find it loaded; a failure is left to
    the finish step, which loads them again and reports it."""
    if params.depth_options()["depth"] == DepthMethod.NONE:
        return  # nothing to load for this job: a later one may take the load

    def load() -> None:
        # (not preload_numba_blas: it stands a module in for scipy.linalg for a moment, which
        # this process's other threads must not see)
        try:
            load_depth_kernels(params)
        except Exception:
            log.debug("warming the finish step failed", exc_info=True)

    if _warm_started.acquire(blocking=False):  # never released: once per process
        threading.Thread(target=load, name="maxfs-warm-finish", daemon=True).start()


class JobManager:
    """All jobs under ``settings.data_dir / 'jobs'``."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.root = Path(settings.data_dir).absolute() / "jobs"  # workers may run elsewhere
        self.client: Client | None = None
        #: where tiles run (service.runs.cluster): embedded, SLURM worker jobs or an external scheduler
        self.dask: DaskCluster | None = None
        self.runs: dict[str, asyncio.Task] = {}
        self.locks: dict[str, asyncio.Lock] = {}
        self.specs: dict[str, JobSpec] = {}
        self.writable: OrderedDict[str, JobStore] = OrderedDict()  # see _upload_store
        s = settings
        #: each user's jobs (service.http.index); every tile's priority (service.runs.fairness)
        self.index = JobIndex()
        self.fair = FairShare()
        self.disk = DiskBudget(self.root, s.min_free_bytes)
        self.uploads = UploadSlots(s.max_uploads_per_user)
        self.downloads = UploadSlots(s.max_downloads_per_user, "downloads", "MAXFS_MAX_DOWNLOADS_PER_USER")
        self.waits = UploadSlots(MAX_WAITS_PER_USER, "status requests waiting")  # (wait_change)
        self.decoder = Decoder(s.decode_slots)
        #: quota and disk checks (service.http.quotas)
        self.limits = JobLimits(s, self.index, self.disk, self._record_or_none)
        self.sweeper: asyncio.Task | None = None
        #: why a run ended, for jobs whose failure could not be written (a full disk): their
        #: records still say queued or running; :meth:`record` answers failed (and writes it
        #: once it can), so status tells the truth and a start resumes them
        self.unrecorded: dict[str, str] = {}
        #: per job, the event that status requests waiting for its next change wait on
        #: (:meth:`wait_change`); set and dropped by :meth:`changed`
        self.changes: dict[str, asyncio.Event] = {}
        self.loop: asyncio.AbstractEventLoop | None = None

    # -- life cycle ---------------------------------------------------------------------------
    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.root.mkdir(parents=True, exist_ok=True)
        self.clean_orphans()
        self.dask = await start_cluster(self.settings, log_dir=Path(self.settings.data_dir) / "slurm-logs")
        self.client = self.dask.client
        for job_dir in sorted(self.root.iterdir()):
            try:
                rec = load_record(job_dir)
            except StoreError:
                continue
            self.index.add(rec)
            if rec.state.active:
                self._launch(rec.id)
        if self.settings.retention_days > 0:
            self.sweeper = asyncio.create_task(self._sweep_forever(), name="maxfs-retention")

    def clean_orphans(self) -> list[Path]:
        """Remove what a killed process left half-made; return what was removed.

        A job folder without a record was cut short while being created (the
        record is written last) and never given to anyone; staged uploads and
        temp files belong to requests that can no longer finish.
        """
        removed: list[Path] = []
        for d in sorted(self.root.iterdir()):
            if d.is_dir() and not (d / RECORD_NAME).exists():
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
                continue
            for p in d.glob(TEMP_PREFIX + "*") if d.is_dir() else []:
                if p.is_file():
                    p.unlink(missing_ok=True)
                    removed.append(p)
        # results.zip of older versions went through the system's temp folder
        for p in Path(tempfile.gettempdir()).glob("maxfs-" + "[0-9a-f]" * 32 + "-*.zip"):
            p.unlink(missing_ok=True)
            removed.append(p)
        for p in removed:
            log.warning("removed orphan %s", p)
        return removed

    async def ensure_client(self) -> Client:
        """The Dask client, made anew if the scheduler was lost and the old one gave up."""
        assert self.dask is not None, "JobManager.start() was not awaited"
        self.client = await self.dask.reconnect()
        return self.client

    async def close(self) -> None:
        if self.sweeper is not None:
            self.sweeper.cancel()
            await asyncio.gather(self.sweeper, return_exceptions=True)
        runs = list(self.runs.values())
        for task in runs:
            task.cancel()
        await asyncio.gather(*runs, return_exceptions=True)
        if self.dask is not None:
            await self.dask.close()

    # -- jobs ---------------------------------------------------------------------------------
    def job_dir(self, job_id: str) -> Path:
        d = self.root / _check_id(job_id)
        if not d.is_dir():
            raise NotFoundError(f"no job {job_id}")
        return d

    def lock(self, job_id: str) -> asyncio.Lock:
        return self.locks.setdefault(job_id, asyncio.Lock())

    def access(self, job_id: str, user: User) -> JobRecord:
        """The record of a job ``user`` may see; someone else's job is "not found"."""
        rec = self.record(job_id)
        if not (user.admin or owns(user, rec)):
            raise NotFoundError(f"no job {job_id}")
        return rec

    def _record_or_none(self, job_id: str) -> JobRecord | None:
        try:
            return self.record(job_id)
        except (NotFoundError, StoreError):
            return None

    # -- waiting for a change (long polling: GET /jobs/{id}?wait=S) --------------------------------
    def changed(self, job_id: str) -> None:
        """The job's record changed (saved by its run, a start or a cancel): wake the status
        requests waiting for it. From any thread."""
        try:
            here = asyncio.get_running_loop()
        except RuntimeError:
            here = None
        if self.loop is not None and here is not self.loop:
            self.loop.call_soon_threadsafe(self._wake, job_id)
        else:
            self._wake(job_id)

    def _wake(self, job_id: str) -> None:
        ev = self.changes.pop(job_id, None)
        if ev is not None:
            ev.set()

    async def wait_change(self, job_id: str, user: User, timeout: float) -> None:
        """Wait at most ``timeout`` seconds for the next change of a queued or running job's
        record (return at once for a job in any other state: nothing changes it by itself).
        The event is taken before the record is read, so a change made meanwhile is not missed."""
        self.access(job_id, user)  # the id checked and the job the user's before anything is kept
        ev = self.changes.setdefault(job_id, asyncio.Event())
        if not self.record(job_id).state.active or self.waits.full(user.name):
            return
        with self.waits.take(user.name), contextlib.suppress(TimeoutError):
            async with asyncio.timeout(min(timeout, MAX_STATUS_WAIT)):
                await ev.wait()

    # -- limits (service.http.quotas), here so that callers need only the manager ------------------
    def open_jobs(self, user: User) -> int:
        """The user's unfinished jobs (reads only the records of those that may be)."""
        return self.limits.open_jobs(user)

    def check_disk(self, nbytes: int, what: str) -> None:
        """Refuse (507) what would eat into the disk reserve (see :class:`service.http.quotas.JobLimits`)."""
        self.limits.check_disk(nbytes, what)

    def create(
        self, spec: JobSpec, params: JobParams, user: User, label: str | None = None, name: str | None = None
    ) -> JobRecord:
        spec = spec.validate()
        self.limits.check_limits(spec, user)
        self.limits.check_tiles(spec, params)
        job_id = uuid.uuid4().hex
        d = self.root / job_id
        try:
            JobStore.create(d, spec, params)
            rec = JobRecord(id=job_id, owner=user.name, owner_uid=user.uid, label=label, name=name)
            save_record(d, rec)  # last: a folder without a record is an orphan
        except BaseException:
            shutil.rmtree(d, ignore_errors=True)
            raise
        self.index.add(rec)
        _warm_finish(params)
        return rec

    def record(self, job_id: str) -> JobRecord:
        rec = load_record(self.job_dir(job_id))
        reason = self.unrecorded.get(job_id)
        if reason is not None:
            if not rec.state.active or job_id in self.runs:
                self.unrecorded.pop(job_id, None)  # started again, or recorded since
            else:
                rec.state, rec.error = JobState.FAILED, reason
                rec.finished_at = rec.finished_at or time.time()
                try:
                    save_record(self.job_dir(job_id), rec)
                    self.unrecorded.pop(job_id, None)
                except OSError:
                    pass  # still no space: answered as failed all the same
        return rec

    def store(self, job_id: str, mode: str = "r") -> JobStore:
        return JobStore.open(self.job_dir(job_id), mode=mode)

    def _upload_store(self, job_id: str) -> JobStore:
        """The job's store opened for writing, kept while it takes uploads (an open reads a
        dozen metadata files, a sizeable share of a small image's upload); dropped when the
        job starts or goes, and beyond the :data:`UPLOAD_STORES` most recent jobs."""
        store = self.writable.pop(job_id, None) or self.store(job_id, "r+")
        self.writable[job_id] = store
        while len(self.writable) > UPLOAD_STORES:
            self.writable.popitem(last=False)
        return store

    def spec(self, job_id: str) -> JobSpec:
        """A job's input spec (it never changes, so it is read once)."""
        if job_id not in self.specs:
            self.specs[job_id] = self.store(job_id).spec
        return self.specs[job_id]

    def list_jobs(self, user: User, everyone: bool = True) -> list[JobRecord]:
        """Jobs ``user`` may see (an admin sees all when ``everyone``), oldest first; only
        those records are read (:class:`service.http.index.JobIndex`)."""
        ids = self.index.everyone() if user.admin and everyone else self.index.jobs_of(user.name)
        out = []
        for job_id in ids:
            rec = self._record_or_none(job_id)
            if rec is not None and ((user.admin and everyone) or owns(user, rec)):
                out.append(rec)
        return out

    async def _write_before_start(
        self,
        job_id: str,
        what: str,
        write: Callable[[JobStore], None],
        *,
        image: int | None,
        record: bool = True,
    ) -> JobRecord:
        """Run a store write while the job still takes uploads (under the job's lock, so a
        cancel or start waits for it and sees its result); an image marks it uploading and
        is recorded in the job record (status reads no store array), unless ``record`` is
        False (a batch of images records them together, :meth:`record_uploads`)."""
        event = "upload" if image is not None else "mask"
        async with self.lock(job_id):
            rec = self.record(job_id)
            if rec.state not in TRANSITIONS[event]:
                raise ConflictError(f"job {job_id} is {rec.state.value}; {what} only before start")
            await asyncio.to_thread(write, self._upload_store(job_id))
            if not record:
                return rec
            rec = self.record(job_id)  # nothing else changes it meanwhile (the lock); re-read anyway
            rec.state = rec.state.after(event)
            if image is not None:
                rec.uploaded_images = sorted({*rec.uploaded_images, image})
            save_record(self.job_dir(job_id), rec)
            return rec

    async def upload_image(
        self, job_id: str, index: int, write: Callable[[JobStore], None], record: bool = True
    ) -> JobRecord:
        """Store image ``index`` with ``write(store)`` (e.g. :meth:`JobStore.write_bands`); with
        ``record`` False the job record is left for :meth:`record_uploads`."""
        return await self._write_before_start(
            job_id, "images can be uploaded", write, image=index, record=record
        )

    async def record_uploads(self, job_id: str, images: list[int]) -> None:
        """Record images stored by :meth:`upload_image` with ``record=False`` in the job record, in
        one save (the job moves to uploading if it still takes uploads; a job cancelled or
        started meanwhile keeps its state, its stored images are recorded all the same)."""
        if not images:
            return
        async with self.lock(job_id):
            if not self.job_dir(job_id).exists():  # deleted meanwhile: nothing to record
                return
            rec = self.record(job_id)
            if rec.state.accepts_uploads:
                rec.state = rec.state.after("upload")
            rec.uploaded_images = sorted({*rec.uploaded_images, *images})
            save_record(self.job_dir(job_id), rec)

    async def upload_mask(self, job_id: str, mask: NDArray[np.bool_]) -> JobRecord:
        return await self._write_before_start(
            job_id, "the mask can be set", lambda store: store.write_mask(mask), image=None
        )

    async def start_job(self, job_id: str, user: User) -> JobRecord:
        """Start (or resume, after cancel or failure) a job whose images are all uploaded."""
        async with self.lock(job_id):
            rec = self.access(job_id, user)
            if job_id in self.runs:
                raise ConflictError(f"job {job_id} is already {rec.state.value}")
            if rec.state.active:  # the record says queued or running, but nothing runs it
                log.warning("job %s was %s with nothing running it; resuming it", job_id, rec.state.value)
                rec.state = rec.state.after("resume")
            elif rec.state not in TRANSITIONS["start"]:
                raise ConflictError(f"job {job_id} is already {rec.state.value}")
            self.writable.pop(job_id, None)
            store = self.store(job_id)

            def check_inputs() -> None:  # reads the store (the whole mask): in a thread
                missing = np.flatnonzero(~store.uploaded())
                if missing.size and rec.state is JobState.CANCELLED:
                    # a cancelled job takes no more uploads (a cancel is final for its inputs)
                    raise ConflictError(
                        f"job {job_id} was cancelled before all its images were uploaded ({missing.size} "
                        f"missing, first: {int(missing[0])}) and takes no more uploads; delete it "
                        f"(DELETE /jobs/{job_id}?purge=true, `maxfs delete {job_id}`) and submit again"
                    )
                if missing.size:
                    raise ConflictError(
                        f"job {job_id} is missing {missing.size} images (first: {int(missing[0])}); "
                        "upload them first"
                    )
                if store.mask_state() == "incomplete":
                    raise ConflictError(
                        f"job {job_id}: the mask upload was cut short (the server stopped while writing "
                        "it); upload the mask again"
                    )
                if not store.read_mask().any():
                    raise InvalidInputError(
                        f"job {job_id}: the mask selects no pixel; upload a mask with some"
                    )

            await asyncio.to_thread(check_inputs)
            if rec.state.final and self.open_jobs(User(rec.owner)) >= self.settings.max_open_jobs:
                raise QuotaError(
                    f"user {rec.owner!r} already has {self.settings.max_open_jobs} unfinished jobs; "
                    "wait for one to finish before resuming this one"
                )
            await self.ensure_client()
            if not rec.state.active:
                rec.state = rec.state.after("start")
            rec.error = None
            save_record(self.job_dir(job_id), rec)
            self.index.reopen(rec)
            self._launch(job_id)
            self.changed(job_id)
            return rec

    def _launch(self, job_id: str) -> None:
        assert self.client is not None, "JobManager.start() was not awaited"
        owner = self.index.owner.get(job_id, ("", ""))[0]

        async def go() -> None:
            try:
                await run_job(
                    self.client,
                    self.job_dir(job_id),
                    progress_interval=self.settings.progress_interval,
                    retries=self.settings.tile_retries,
                    fair=self.fair,
                    user=owner,
                    tile_time_limit=self.settings.tile_time_limit or None,
                    finish=_finish,  # previews and depth, as `maxfs run` makes them
                    on_progress=lambda rec: self.changed(job_id),  # wakes waiting status requests
                )
            except asyncio.CancelledError:
                raise
            except Exception as e:  # never leave a job "running" with nothing running it
                if is_disk_full(e):
                    log.error("job %s stopped: the disk is full (%s)", job_id, e)
                    self._fail(
                        job_id,
                        "the server's disk filled up while the job ran; its finished tiles are kept: "
                        "start it again once space is freed",
                    )
                else:
                    log.exception("job %s stopped by an internal error", job_id)
                    self._fail(job_id, f"internal error: {type(e).__name__}: {e}")
            finally:
                self.runs.pop(job_id, None)
                self.changed(job_id)

        task = asyncio.create_task(go(), name=f"maxfs-job-{job_id}")
        self.runs[job_id] = task
        # a task cancelled before it ever ran skips go()'s finally: forget it here too, or every
        # later start would find it and answer 409
        task.add_done_callback(lambda t: self.runs.pop(job_id, None) if self.runs.get(job_id) is t else None)

    def _fail(self, job_id: str, reason: str) -> None:  # the run task's last word: no lock needed
        try:
            rec = load_record(self.job_dir(job_id))
            if rec.state.active:
                rec.state, rec.error, rec.finished_at = JobState.FAILED, reason, time.time()
                save_record(self.job_dir(job_id), rec)
        except Exception as e:
            log.exception("cannot record the failure of job %s", job_id)
            self.unrecorded[job_id] = f"{reason} (not yet recorded: {type(e).__name__}: {e})"

    async def cancel(self, job_id: str, user: User) -> JobRecord:
        """Cancel a job: nothing more starts, and running tiles stop at their next cancel
        point (within about a second: :mod:`worker.cancel`), writing nothing.

        Under the job's lock: an upload in progress finishes first (and the job then takes
        no more), a start waits and then finds the job cancelled (and may resume it)."""
        async with self.lock(job_id):
            rec = self.access(job_id, user)
            if rec.state not in TRANSITIONS["cancel"]:
                raise ConflictError(f"job {job_id} is already {rec.state.value}")
            self.store(job_id, "r+").request_cancel()
            task = self.runs.get(job_id)
            if task is not None:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
                self.runs.pop(job_id, None)
            rec = self.record(job_id)
            if rec.state in TRANSITIONS["cancel"]:  # never started, or the run did not record it
                rec.state, rec.finished_at = rec.state.after("cancel"), time.time()
                save_record(self.job_dir(job_id), rec)
            elif rec.state is not JobState.CANCELLED:  # it finished (or failed) just before
                raise ConflictError(f"job {job_id} is already {rec.state.value}")
            self.changed(job_id)
            return rec

    async def delete(self, job_id: str, user: User) -> JobRecord:
        """Delete a job nothing runs for (created, uploading, done, failed, cancelled): its
        folder goes, its quota slot is free. A queued or running job must be cancelled first."""
        async with self.lock(job_id):
            rec = self.access(job_id, user)
            if rec.state not in TRANSITIONS["delete"] or job_id in self.runs:
                raise ConflictError(
                    f"job {job_id} is {rec.state.value}; cancel it first (DELETE without purge), "
                    "then delete it"
                )
            trash = self._unlink_job(job_id)
        await asyncio.to_thread(shutil.rmtree, trash, True)
        self.locks.pop(job_id, None)
        return rec

    def _unlink_job(self, job_id: str) -> Path:
        """Take a job out of the index and its folder out of ``jobs/`` (renamed, to be removed)."""
        trash = self.root / f"{TEMP_PREFIX}deleting-{job_id}"
        self.job_dir(job_id).rename(trash)  # tile tasks still finishing see their folder gone
        self.index.remove(job_id)
        self._wake(job_id)
        self.specs.pop(job_id, None)
        self.writable.pop(job_id, None)
        return trash

    async def sweep(self, now: float | None = None) -> list[str]:
        """Delete jobs past the retention period (``MAXFS_RETENTION_DAYS``): finished ones
        after their end, created or uploading ones after their last change."""
        days = self.settings.retention_days
        if days <= 0:
            return []
        cutoff = (now or time.time()) - days * 86400
        gone = []
        for job_id in self.index.everyone():
            rec = self._record_or_none(job_id)
            if rec is None or rec.state.active or job_id in self.runs:
                continue
            when = rec.finished_at if rec.state.final and rec.finished_at else rec.updated_at
            if when >= cutoff:
                continue
            async with self.lock(job_id):
                if job_id in self.runs or self._record_or_none(job_id) != rec:
                    continue  # changed meanwhile
                trash = self._unlink_job(job_id)
            await asyncio.to_thread(shutil.rmtree, trash, True)
            self.locks.pop(job_id, None)
            log.info("deleted job %s of %s: past the retention period (%g days)", job_id, rec.owner, days)
            gone.append(job_id)
        return gone

    async def _sweep_forever(self) -> None:
        period = min(3600.0, max(self.settings.retention_days * 86400 / 4, 0.5))
        while True:
            try:
                await self.sweep()
            except Exception:
                log.exception("retention sweep failed; trying again later")
            await asyncio.sleep(period)
