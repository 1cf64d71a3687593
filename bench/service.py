"""Throughput of the service paths against the in-process solver, in one run.

Rows: the in-process solver (one process, no Dask); the ``maxfs run`` path
(job store + Dask tile tasks on an embedded cluster) with 1 and 2 workers; and
the HTTP path (``maxfs serve`` with 2 embedded workers: upload, start, poll).
Rates count masked-in pixels over the compute phase (job start to last tile;
cluster start-up and upload are excluded and reported separately).

Run: ``python -m bench.service`` (``--size``, ``--k``, ``--tile`` to change the job).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from maxfs.service.cli.client import MaxfsClient
from maxfs.service.runs.local import ingest, run_store
from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.inputs import load_folder
from maxfs.storage.params import JobParams
from maxfs.worker import synthetic
from maxfs.worker.solve import solve
from tests.harness import Server


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, default=24)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--tile", type=int, default=64)
    ap.add_argument("--eps", type=float, default=1.0)
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="maxfs-bench-"))
    try:
        sc = synthetic.bump_scene(args.k, args.size)
        images = sc.images.astype(np.uint8)
        folder = write_npy_folder(tmp / "input", images, sc.lights, sc.mask)
        px = int(sc.mask.sum())
        solve(images[:, :8, :8], sc.lights, eps=args.eps)  # JIT warm-up
        t0 = time.perf_counter()
        solve(images, sc.lights, sc.mask, eps=args.eps, tile=args.tile)
        rows = [("in-process solve()", 1, px / (time.perf_counter() - t0), float("nan"))]

        params = JobParams.build(eps=args.eps, tile=args.tile)
        for workers in (1, 2):
            out = tmp / f"run{workers}.zarr"
            ingest(load_folder(folder), out, params)
            t0 = time.perf_counter()
            rec = run_store(out, workers=workers)
            wall = time.perf_counter() - t0
            compute = rec.finished_at - rec.started_at
            rows.append((f"maxfs run, {workers} worker(s)", workers, px / compute, wall - compute))

        logs = tmp / "logs"
        logs.mkdir()
        server = Server(tmp / "data", "", logs, workers=2)
        try:
            with MaxfsClient(server.url) as c:
                t0 = time.perf_counter()
                job = c.create_job(
                    k=args.k,
                    height=args.size,
                    width=args.size,
                    dtype="uint8",
                    lights=sc.lights.tolist(),
                    eps=args.eps,
                    tile=args.tile,
                )
                for i in range(args.k):
                    c.upload_image(job["id"], i, images[i])
                c.upload_mask(job["id"], sc.mask)
                upload = time.perf_counter() - t0
                c.start(job["id"])
                st = c.wait(job["id"], poll=0.2)
                assert st["state"] == "done", st
                rows.append(
                    ("HTTP (maxfs serve), 2 workers", 2, px / (st["finished_at"] - st["started_at"]), upload)
                )
        finally:
            server.kill()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    base = rows[0][2]
    one = rows[1][2]
    print(
        f"bump scene k={args.k}, {args.size}x{args.size} ({px} object pixels), "
        f"tile {args.tile}, eps {args.eps}\n"
    )
    print(
        "| path | workers | pixels/s | per worker vs in-process | vs 1 worker "
        "| overhead outside compute (s) |"
    )
    print("|---|---|---|---|---|---|")
    for name, w, rate, extra in rows:
        over = "-" if np.isnan(extra) else f"{extra:.1f}"
        print(f"| {name} | {w} | {rate:,.0f} | {rate / w / base:.2f}x | {rate / one:.2f}x | {over} |")


if __name__ == "__main__":
    main()
