"""The job manager: creates job stores, takes uploads, runs and cancels jobs.

It owns the asynchronous Dask client (an embedded LocalCluster, or an external
scheduler from settings) and one asyncio task per running job. On start it
resumes every job whose record says queued or running: a restarted server loses
no finished tile and finishes what was in flight.
"""

from __future__ import annotations

import asyncio
import io
import shutil
import tempfile
import uuid
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from distributed import Client, LocalCluster
from numpy.typing import NDArray

from service.orchestrator import run_job, warm_workers
from service.settings import Settings
from storage.layout import JobSpec, JobStore
from storage.params import JobParams
from storage.records import JobRecord, JobState, load_record, save_record
from worker.errors import ConflictError, NotFoundError, StoreError


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
        self.cluster: LocalCluster | None = None
        self.runs: dict[str, asyncio.Task] = {}
        self.locks: dict[str, asyncio.Lock] = {}

    # -- life cycle ---------------------------------------------------------------------------
    async def start(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        s = self.settings
        if s.scheduler:
            self.client = await Client(s.scheduler, asynchronous=True)
        else:
            self.cluster = await LocalCluster(
                n_workers=s.workers,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address=s.dashboard or None,
                asynchronous=True,
            )
            self.client = await Client(self.cluster, asynchronous=True)
        await warm_workers(self.client)
        for job_dir in sorted(self.root.iterdir()):
            try:
                rec = load_record(job_dir)
            except StoreError:
                continue
            if rec.state.active:
                self._launch(rec.id)

    async def close(self) -> None:
        runs = list(self.runs.values())
        for task in runs:
            task.cancel()
        await asyncio.gather(*runs, return_exceptions=True)
        if self.client is not None:
            await self.client.close()
        if self.cluster is not None:
            await self.cluster.close()

    # -- jobs ---------------------------------------------------------------------------------
    def job_dir(self, job_id: str) -> Path:
        d = self.root / _check_id(job_id)
        if not d.is_dir():
            raise NotFoundError(f"no job {job_id}")
        return d

    def lock(self, job_id: str) -> asyncio.Lock:
        return self.locks.setdefault(job_id, asyncio.Lock())

    def create(self, spec: JobSpec, params: JobParams, owner: str = "local") -> JobRecord:
        spec = spec.validate()
        job_id = uuid.uuid4().hex
        d = self.root / job_id
        try:
            JobStore.create(d, spec, params)
            rec = JobRecord(id=job_id, owner=owner)
            save_record(d, rec)
        except BaseException:
            shutil.rmtree(d, ignore_errors=True)
            raise
        return rec

    def record(self, job_id: str) -> JobRecord:
        return load_record(self.job_dir(job_id))

    def store(self, job_id: str, mode: str = "r") -> JobStore:
        return JobStore.open(self.job_dir(job_id), mode=mode)

    def list(self) -> list[JobRecord]:
        out = []
        for d in sorted(self.root.iterdir()) if self.root.exists() else []:
            try:
                out.append(load_record(d))
            except StoreError:
                continue
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

    async def upload_image(self, job_id: str, index: int, image: NDArray) -> JobRecord:
        return await self._write_before_start(
            job_id, "images can be uploaded", lambda store: store.write_image(index, image), image=True
        )

    async def upload_mask(self, job_id: str, mask: NDArray[np.bool_]) -> JobRecord:
        return await self._write_before_start(
            job_id, "the mask can be set", lambda store: store.write_mask(mask), image=False
        )

    async def start_job(self, job_id: str) -> JobRecord:
        """Start (or resume, after cancel or failure) a job whose images are all uploaded."""
        async with self.lock(job_id):
            rec = self.record(job_id)
            if rec.state.active or job_id in self.runs:
                raise ConflictError(f"job {job_id} is already {rec.state.value}")
            if rec.state is JobState.DONE:
                raise ConflictError(f"job {job_id} is already done")
            missing = np.flatnonzero(~self.store(job_id).uploaded())
            if missing.size:
                raise ConflictError(
                    f"job {job_id} is missing {missing.size} images (first: {int(missing[0])}); "
                    "upload them first"
                )
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
            finally:
                self.runs.pop(job_id, None)

        self.runs[job_id] = asyncio.create_task(go(), name=f"maxfs-job-{job_id}")

    async def cancel(self, job_id: str) -> JobRecord:
        """Cancel a job: running tiles finish their tile, nothing else starts."""
        rec = self.record(job_id)
        if rec.state in (JobState.DONE, JobState.FAILED, JobState.CANCELLED):
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
                if p.is_file() and not p.name.startswith(".maxfs-job-"):
                    zf.write(p, p.relative_to(d).as_posix())
        return Path(tmp)


def npy_bytes(arr: NDArray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()
