"""Running a dataset folder on this machine: what ``maxfs run`` and ``maxfs demo`` do.

The output is a job store (see :mod:`storage.layout`); running again on the same
output resumes from its finished tiles. Parameters that differ from the stored
ones make every tile count as unfinished (their done markers no longer match).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import shutil
import time
from pathlib import Path

import numpy as np
from distributed import Client, LocalCluster

from service.orchestrator import ProgressFn, run_job, warm_workers
from service.previews import PREVIEW_INPUTS, PREVIEWS, render
from storage.datasets import Dataset
from storage.imageio import encode_png
from storage.layout import JobSpec, JobStore, array_digest, lights_digest
from storage.params import JobParams
from storage.records import JobRecord, JobState, load_record, save_record
from worker.errors import ConflictError, InvalidInputError, StoreError


def ingest(ds: Dataset, out: Path, params: JobParams, *, overwrite: bool = False) -> tuple[JobStore, str]:
    """Create or reopen the output store for ``ds``; copy images not yet stored.

    A store that already holds *other* inputs (images, mask, lights or intensities,
    compared by content digest) is refused unless ``overwrite``, which removes it and
    starts from scratch. Unchanged inputs are recognised from the files' fingerprint
    (paths, sizes, times) without decoding them again. Returns the store and a note
    for the user ("" when nothing notable happened).
    """
    out = Path(out)
    spec = JobSpec(ds.k, ds.height, ds.width, ds.channels, ds.dtype, ds.lights, ds.intensities).validate()
    note = ""
    if out.exists() and not out.is_dir():
        raise ConflictError(f"{out} is a file; give a folder path for the results")
    if out.exists() and any(out.iterdir()):
        if not is_job_store(out):
            raise ConflictError(
                f"{out} is not empty and holds no maxfs results; choose a new or empty output folder"
            )
        if overwrite:
            shutil.rmtree(out)
    if (out / "zarr.json").exists():
        store = JobStore.open(out)
        _check_same_inputs(store, ds, spec, out)
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
        for i in range(ds.k):
            store.write_image(i, ds.read(i))
        if ds.mask is not None:
            store.write_mask(ds.mask)
    store.source_fingerprint = ds.fingerprint()
    if not store.read_mask().any():
        raise InvalidInputError(f"the mask of {ds.name} selects no pixel; nothing to solve")
    rec.state = JobState.QUEUED
    save_record(out, rec)
    return store, note


def is_job_store(path: Path) -> bool:
    """Whether ``path`` holds a maxfs job store (of any format version)."""
    try:
        meta = json.loads((Path(path) / "zarr.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and "maxfs_format" in meta.get("attributes", {})


def _check_same_inputs(store: JobStore, ds: Dataset, spec: JobSpec, out: Path) -> None:
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
    fp = ds.fingerprint()
    if fp is not None and fp == store.source_fingerprint and store.input_identity():
        return
    stored, uploaded = store.digests(), store.uploaded()
    for i in range(ds.k):
        img = ds.read(i)
        if not uploaded[i]:
            store.write_image(i, img)
        elif array_digest(img) != stored[i]:
            raise differ(f"the images (image {i} first)")
    state = store.mask_state()
    if ds.mask is None:
        if state != "default":
            raise differ("the masks")
    elif state == "incomplete":
        store.write_mask(ds.mask)
    elif state == "default" or array_digest(np.ascontiguousarray(ds.mask, dtype=bool)) != stored[s.k]:
        raise differ("the masks")


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
        from service.research import finish_results

        finish_results(out)
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
