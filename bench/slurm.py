"""Throughput of SLURM worker jobs (dask-jobqueue) against the embedded cluster, in one run.

Rows: the embedded LocalCluster with 1 and 2 worker processes, and ``--cluster slurm``
with 1 and 2 worker jobs of one core each (both through :func:`service.runs.cluster.open_cluster`
and :func:`service.runs.orchestrator.run_job`, as ``maxfs run --cluster ...`` runs them).
Rates count masked pixels over the compute phase of each job (first tile submitted to last
tile done), median over ``--repeat`` rounds (each configuration in turn, a fresh cluster and
store each time); "ready" is the time from asking for the cluster to having all its workers
(for SLURM: sbatch, scheduling, worker start, solver kernels loaded).

Run (root, with Debian's slurm-wlm and munge; starts the single-node SLURM of
``deploy/slurm/start-local.sh`` if it is not running)::

    python -m bench.slurm [--objects cat,rock] [--repeat 3]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from maxfs.service.runs.cluster import open_cluster
from maxfs.service.runs.local import ingest
from maxfs.service.runs.orchestrator import run_job
from maxfs.service.settings import Settings
from maxfs.storage.inputs import load_folder
from maxfs.storage.params import JobParams

REPO = Path(__file__).resolve().parents[1]
UW = REPO.parent / "shared" / "data" / "uw-psm"


def _start_slurm() -> None:
    script = REPO / "deploy/slurm/start-local.sh"
    r = subprocess.run([str(script)], capture_output=True, text=True, check=True)
    m = re.search(r"^SLURM_CONF=(.+)$", r.stdout, re.M)
    if m and not os.environ.get("SLURM_CONF"):
        os.environ["SLURM_CONF"] = m[1]


async def _measure(settings: Settings, n: int, objects: list[str], tmp: Path) -> dict:
    """One round: start the cluster, wait for its ``n`` workers, run each object once."""
    t0 = time.perf_counter()
    async with open_cluster(settings, log_dir=tmp / "slurm-logs") as dc:
        await dc.client.wait_for_workers(n, timeout=300)
        ready = time.perf_counter() - t0
        took: dict[str, float] = {}
        for obj in objects:
            out = tmp / f"{settings.cluster}-{n}-{obj}.zarr"
            ingest(load_folder(UW / obj), out, JobParams.build(tile=96))
            rec = await run_job(dc.client, out)
            assert rec.state.value == "done", rec.error
            took[obj] = rec.finished_at - rec.started_at
            shutil.rmtree(out)
    return {"ready": ready, "took": took}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="cat,rock", help="UW psm objects (../shared/data/uw-psm)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    objects = args.objects.split(",")
    _start_slurm()
    tmp = Path(tempfile.mkdtemp(prefix="maxfs-bench-slurm-"))
    base = Settings(
        slurm_interface="lo", slurm_memory="1GiB", slurm_walltime="00:30:00", slurm_idle_timeout=600
    )
    configs = [("embedded LocalCluster", n, base.replace(cluster="local", workers=n)) for n in (1, 2)] + [
        (
            "SLURM worker jobs",
            n,
            base.replace(cluster="slurm", slurm_min_jobs=n, slurm_max_jobs=n),
        )
        for n in (1, 2)
    ]
    pixels = {o: int(load_folder(UW / o).mask.sum()) for o in objects}
    rounds: list[list[dict]] = [[] for _ in configs]
    try:  # round-robin, so a shared machine's changing load falls on every configuration alike
        for r in range(args.repeat):
            for i, (name, n, settings) in enumerate(configs):
                rounds[i].append(asyncio.run(_measure(settings, n, objects, tmp)))
                print(f"round {r + 1}: {name}, {n}: {rounds[i][-1]}", file=sys.stderr, flush=True)
    finally:
        gc.collect()  # dask-jobqueue deletes its TLS key files when its cluster objects go
        shutil.rmtree(tmp, ignore_errors=True)

    print(
        f"UW psm objects (12 RGB images of 340 x 512, tile 96), median of {args.repeat} runs; "
        f"{os.cpu_count()} cores on this machine, SLURM worker jobs of 1 core on the same node.\n"
    )
    print(
        "| cluster | workers | ready (s) | "
        + " | ".join(f"{o} px/s" for o in objects)
        + " | all px/s | vs embedded, same workers |"
    )
    print("|---|---|---|" + "---|" * len(objects) + "---|---|")
    rows = []
    for (name, n, _), rs in zip(configs, rounds, strict=True):
        took = {o: statistics.median(r["took"][o] for r in rs) for o in objects}
        rates = {o: pixels[o] / took[o] for o in objects}
        rows.append(
            (
                name,
                n,
                statistics.median(r["ready"] for r in rs),
                rates,
                sum(pixels.values()) / sum(took.values()),
            )
        )
    embedded = {n: total for name, n, _, _, total in rows if name.startswith("embedded")}
    for name, n, ready, rates, total in rows:
        cells = " | ".join(f"{rates[o]:,.0f}" for o in objects)
        print(f"| {name} | {n} | {ready:.1f} | {cells} | {total:,.0f} | {total / embedded[n]:.2f}x |")


if __name__ == "__main__":
    main()
