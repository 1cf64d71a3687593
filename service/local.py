"""Running a dataset folder on this machine: what ``maxfs run`` and ``maxfs demo`` do.

The output is a job store (see :mod:`storage.layout`); running again on the same
output resumes from its finished tiles. Parameters that differ from the stored
ones make every tile count as unfinished (their done markers no longer match).
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from pathlib import Path

import numpy as np
from distributed import Client, LocalCluster

from service.orchestrator import ProgressFn, run_job, warm_workers
from service.previews import PREVIEW_INPUTS, PREVIEWS, render
from storage.datasets import Dataset
from storage.imageio import encode_png
from storage.layout import JobSpec, JobStore
from storage.params import JobParams
from storage.records import JobRecord, JobState, load_record, save_record
from worker.errors import ConflictError, StoreError


def ingest(ds: Dataset, out: Path, params: JobParams) -> tuple[JobStore, str]:
    """Create or reopen the output store for ``ds``; copy images not yet stored.

    Returns the store and a note for the user ("" when nothing notable happened).
    """
    out = Path(out)
    spec = JobSpec(ds.k, ds.height, ds.width, ds.channels, ds.dtype, ds.lights, ds.intensities)
    note = ""
    if (out / "zarr.json").exists():
        store = JobStore.open(out)
        s = store.spec
        same = (s.k, s.height, s.width, s.channels, s.dtype) == (
            ds.k,
            ds.height,
            ds.width,
            ds.channels,
            ds.dtype,
        )
        if not same or not np.allclose(s.lights, spec.validate().lights):
            raise ConflictError(
                f"{out} holds results of another dataset ({s.k} images of {s.height} x {s.width}); "
                "choose another output path"
            )
        old = store.params
        comparable = dataclasses.replace(old, eps=None) if params.eps is None else old
        if comparable != params:
            store.set_params(params)
            note = f"parameters differ from the earlier run in {out}; every tile will be recomputed"
        else:
            note = (
                f"resuming {out}: {int(store.done_grid().sum())} of {len(store.tiles())} tiles already done"
            )
        try:
            rec = load_record(out)
        except StoreError:
            rec = JobRecord(id=out.name)
    else:
        store = JobStore.create(out, spec, params)
        rec = JobRecord(id=out.name)
    missing = np.flatnonzero(~store.uploaded())
    for i in missing:
        store.write_image(int(i), ds.read(int(i)))
    if ds.mask is not None and missing.size:
        store.write_mask(ds.mask)
    rec.state = JobState.QUEUED
    save_record(out, rec)
    return store, note


async def _run(out: Path, scheduler: str, workers: int, on_progress: ProgressFn | None) -> JobRecord:
    if scheduler:
        async with Client(scheduler, asynchronous=True) as client:
            await warm_workers(client)
            return await run_job(client, out, on_progress=on_progress)
    async with (
        LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            asynchronous=True,
        ) as cluster,
        Client(cluster, asynchronous=True) as client,
    ):
        await warm_workers(client)
        return await run_job(client, out, on_progress=on_progress)


def run_store(
    out: Path, *, scheduler: str = "", workers: int = 2, on_progress: ProgressFn | None = None
) -> JobRecord:
    """Run every unfinished tile of the store at ``out``; write PNG previews when done."""
    rec = asyncio.run(_run(Path(out), scheduler, workers, on_progress))
    if rec.state is JobState.DONE:
        write_previews(JobStore.open(Path(out), mode="r"))
    return rec


def write_previews(store: JobStore) -> list[Path]:
    """PNG previews under ``previews/`` in the job directory."""
    d = store.path / "previews"
    d.mkdir(exist_ok=True)
    arrays = {n: store.read_output(n) for n in store.output_names() if n in PREVIEW_INPUTS}
    paths = []
    for name in PREVIEWS:
        p = d / f"{name}.png"
        p.write_bytes(encode_png(render(name, arrays, store.spec.k)))
        paths.append(p)
    return paths


def format_progress(rec: JobRecord, width: int = 30) -> str:
    """One status line: bar, tiles, pixel rate, ETA."""
    frac = rec.tiles_done / rec.tiles_total if rec.tiles_total else 0.0
    bar = "#" * int(frac * width) + "." * (width - int(frac * width))
    rate = f"{rec.pixel_rate / 1e3:.1f}k px/s" if rec.pixel_rate else "-- px/s"
    eta = "--"
    if rec.pixel_rate and rec.pixels_total > rec.pixels_done:
        eta = time.strftime("%H:%M:%S", time.gmtime((rec.pixels_total - rec.pixels_done) / rec.pixel_rate))
    return (
        f"[{bar}] {frac:4.0%} {rec.tiles_done}/{rec.tiles_total} tiles  {rate}  ETA {eta}  {rec.state.value}"
    )
