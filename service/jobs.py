"""The job manager: creates job stores, takes uploads, runs and cancels jobs.

It owns the asynchronous Dask client (:mod:`service.cluster`: an embedded
LocalCluster, SLURM worker jobs, or an external scheduler, from settings) and
one asyncio task per running job. On start it removes what a killed process left
half-made (a job folder without a record, staged uploads, temp files) and
resumes every job whose record says queued or running: a restarted server loses
no finished tile and finishes what was in flight. Every job belongs to a user;
other users get "no job" for it, as if it did not exist, unless they are admins.
Per-user and disk limits are checked here, before anything is stored.
"""

from __future__ import annotations

import asyncio
import io
import logging
import shutil
import tempfile
import time
import uuid
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from distributed import Client
from numpy.typing import NDArray

from service.cluster import DaskCluster, start_cluster
from service.orchestrator import run_job
from service.settings import Settings
from storage.layout import JobSpec, JobStore
from storage.params import JobParams
from storage.records import RECORD_NAME, JobRecord, JobState, load_record, save_record
from storage.tokens import User
from worker.errors import (
    ConflictError,
    InsufficientStorageError,
    InvalidInputError,
    NotFoundError,
    PayloadTooLargeError,
    QuotaError,
    StoreError,
)

log = logging.getLogger("maxfs.jobs")
#: Prefix of every temporary file a process writes in a job folder (removed on start).
TEMP_PREFIX = ".maxfs-"


def _check_id(job_id: str) -> str:
    if not (len(job_id) == 32 and all(c in "0123456789abcdef" for c in job_id)):
        raise NotFoundError(f"no job {job_id!r}: job ids are 32 hexadecimal characters")
    return job_id


class JobManager:
    """All jobs under ``settings.data_dir / 'jobs'``."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.root = Path(settings.data_dir) / "jobs"
        self.client: Client | None = None
        #: where tiles run (service.cluster): embedded, SLURM worker jobs or an external scheduler
        self.dask: DaskCluster | None = None
        self.runs: dict[str, asyncio.Task] = {}
        self.locks: dict[str, asyncio.Lock] = {}
        self.specs: dict[str, JobSpec] = {}

    # -- life cycle ---------------------------------------------------------------------------
    async def start(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        self.clean_orphans()
        self.dask = await start_cluster(self.settings, log_dir=Path(self.settings.data_dir) / "slurm-logs")
        self.client = self.dask.client
        for job_dir in sorted(self.root.iterdir()):
            try:
                rec = load_record(job_dir)
            except StoreError:
                continue
            if rec.state.active:
                self._launch(rec.id)

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
        for p in removed:
            log.warning("removed orphan %s", p)
        return removed

    async def ensure_client(self) -> Client:
        """The Dask client, made anew if the scheduler was lost and the old one gave up."""
        assert self.dask is not None, "JobManager.start() was not awaited"
        self.client = await self.dask.reconnect()
        return self.client

    async def close(self) -> None:
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
        if rec.owner != user.name and not user.admin:
            raise NotFoundError(f"no job {job_id}")
        return rec

    def open_jobs(self, user: User) -> int:
        return sum(1 for r in self.list(user, everyone=False) if not r.state.final)

    def check_disk(self, nbytes: int, what: str) -> None:
        """Refuse (507) to store ``nbytes`` more if that would eat into the disk reserve."""
        free = shutil.disk_usage(self.root).free
        reserve = self.settings.min_free_bytes
        if free - nbytes < reserve:
            raise InsufficientStorageError(
                f"{what} needs up to {nbytes / 2**30:.2f} GiB but the server has "
                f"{max(free - reserve, 0) / 2**30:.2f} GiB free above its reserve; "
                "delete old jobs or ask the administrator for space"
            )

    def check_limits(self, spec: JobSpec, user: User) -> None:
        """Per-job and per-user limits, then disk space, before anything is stored."""
        s = self.settings
        if spec.k > s.max_k:
            raise PayloadTooLargeError(
                f"k={spec.k} images is more than this server allows per job ({s.max_k}, MAXFS_MAX_K); "
                "split the lights into several jobs"
            )
        if spec.pixels > s.max_pixels:
            raise PayloadTooLargeError(
                f"{spec.height} x {spec.width} = {spec.pixels} pixels is more than this server allows "
                f"({s.max_pixels}, MAXFS_MAX_PIXELS); crop or bin the images"
            )
        if self.open_jobs(user) >= s.max_open_jobs:
            raise QuotaError(
                f"user {user.name!r} already has {s.max_open_jobs} unfinished jobs, the most allowed "
                "(MAXFS_MAX_OPEN_JOBS); wait for one to finish or cancel one"
            )
        self.check_disk(spec.store_nbytes(), f"a job of {spec.k} images of {spec.height} x {spec.width}")

    def create(self, spec: JobSpec, params: JobParams, user: User) -> JobRecord:
        spec = spec.validate()
        self.check_limits(spec, user)
        job_id = uuid.uuid4().hex
        d = self.root / job_id
        try:
            JobStore.create(d, spec, params)
            rec = JobRecord(id=job_id, owner=user.name)
            save_record(d, rec)  # last: a folder without a record is an orphan
        except BaseException:
            shutil.rmtree(d, ignore_errors=True)
            raise
        return rec

    def record(self, job_id: str) -> JobRecord:
        return load_record(self.job_dir(job_id))

    def store(self, job_id: str, mode: str = "r") -> JobStore:
        return JobStore.open(self.job_dir(job_id), mode=mode)

    def spec(self, job_id: str) -> JobSpec:
        """A job's input spec (it never changes, so it is read once)."""
        if job_id not in self.specs:
            self.specs[job_id] = self.store(job_id).spec
        return self.specs[job_id]

    def list(self, user: User, everyone: bool = True) -> list[JobRecord]:
        """Jobs ``user`` may see (an admin sees all when ``everyone``), oldest first."""
        out = []
        for d in sorted(self.root.iterdir()) if self.root.exists() else []:
            try:
                rec = load_record(d)
            except StoreError:
                continue
            if rec.owner == user.name or (user.admin and everyone):
                out.append(rec)
        return sorted(out, key=lambda r: r.created_at)

    async def _write_before_start(
        self, job_id: str, what: str, write: Callable[[JobStore], None], *, image: bool
    ) -> JobRecord:
        """Run a store write while the job still takes uploads; an image marks it uploading."""
        async with self.lock(job_id):
            rec = self.record(job_id)
            if not rec.state.accepts_uploads:
                raise ConflictError(f"job {job_id} is {rec.state.value}; {what} only before start")
            await asyncio.to_thread(write, self.store(job_id, "r+"))
            if image:
                rec.state = JobState.UPLOADING
                save_record(self.job_dir(job_id), rec)
            return rec

    async def upload_image(self, job_id: str, index: int, write: Callable[[JobStore], None]) -> JobRecord:
        """Store image ``index`` with ``write(store)`` (e.g. :meth:`JobStore.write_bands`)."""
        return await self._write_before_start(job_id, "images can be uploaded", write, image=True)

    async def upload_mask(self, job_id: str, mask: NDArray[np.bool_]) -> JobRecord:
        pause = (lambda: time.sleep(60)) if self.settings.fault == "pause-mask-write" else None
        return await self._write_before_start(
            job_id, "the mask can be set", lambda store: store.write_mask(mask, pause), image=False
        )

    async def start_job(self, job_id: str, user: User) -> JobRecord:
        """Start (or resume, after cancel or failure) a job whose images are all uploaded."""
        async with self.lock(job_id):
            rec = self.access(job_id, user)
            if rec.state.active or job_id in self.runs:
                raise ConflictError(f"job {job_id} is already {rec.state.value}")
            if rec.state is JobState.DONE:
                raise ConflictError(f"job {job_id} is already done")
            store = self.store(job_id)
            missing = np.flatnonzero(~store.uploaded())
            if missing.size:
                raise ConflictError(
                    f"job {job_id} is missing {missing.size} images (first: {int(missing[0])}); "
                    "upload them first"
                )
            if store.mask_state() == "incomplete":
                raise ConflictError(
                    f"job {job_id}: the mask upload was cut short (the server stopped while writing it); "
                    "upload the mask again"
                )
            if not store.read_mask().any():
                raise InvalidInputError(f"job {job_id}: the mask selects no pixel; upload a mask with some")
            if rec.state.final and self.open_jobs(User(rec.owner)) >= self.settings.max_open_jobs:
                raise QuotaError(
                    f"user {rec.owner!r} already has {self.settings.max_open_jobs} unfinished jobs; "
                    "wait for one to finish before resuming this one"
                )
            await self.ensure_client()
            rec.state = JobState.QUEUED
            rec.error = None
            save_record(self.job_dir(job_id), rec)
            self._launch(job_id)
            return rec

    def _launch(self, job_id: str) -> None:
        assert self.client is not None, "JobManager.start() was not awaited"

        async def go() -> None:
            try:
                await run_job(
                    self.client,
                    self.job_dir(job_id),
                    progress_interval=self.settings.progress_interval,
                    retries=self.settings.tile_retries,
                )
            except asyncio.CancelledError:
                raise
            except Exception as e:  # never leave a job "running" with nothing running it
                log.exception("job %s stopped by an internal error", job_id)
                self._fail(job_id, f"internal error: {type(e).__name__}: {e}")
            finally:
                self.runs.pop(job_id, None)

        self.runs[job_id] = asyncio.create_task(go(), name=f"maxfs-job-{job_id}")

    def _fail(self, job_id: str, reason: str) -> None:
        try:
            rec = self.record(job_id)
            if rec.state.active:
                rec.state, rec.error, rec.finished_at = JobState.FAILED, reason, time.time()
                save_record(self.job_dir(job_id), rec)
        except Exception:
            log.exception("cannot record the failure of job %s", job_id)

    async def cancel(self, job_id: str, user: User) -> JobRecord:
        """Cancel a job: running tiles finish their tile, nothing else starts."""
        rec = self.access(job_id, user)
        if rec.state.final:
            raise ConflictError(f"job {job_id} is already {rec.state.value}")
        self.store(job_id, "r+").request_cancel()
        task = self.runs.get(job_id)
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        rec = self.record(job_id)
        if rec.state is not JobState.CANCELLED:  # never started (created/uploading)
            rec.state = JobState.CANCELLED
            save_record(self.job_dir(job_id), rec)
        return rec

    def zip_store(self, job_id: str) -> Path:
        """The job's whole Zarr group (plus record) as a zip file in a temp location."""
        d = self.job_dir(job_id)
        fd, tmp = tempfile.mkstemp(suffix=".zip", prefix=f"maxfs-{job_id}-")
        with open(fd, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED) as zf:
            for p in sorted(d.rglob("*")):
                if p.is_file() and not p.name.startswith(TEMP_PREFIX):
                    zf.write(p, p.relative_to(d).as_posix())
        return Path(tmp)


def npy_bytes(arr: NDArray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()
