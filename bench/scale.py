"""Dense runs: a synthetic 16-bit stack on disk through ``maxfs run`` with 2 workers.

For each (k, size) the script writes an NPY-stack folder image by image through a
memory map (the stack is never in memory), starts a ``dask scheduler`` and two
``dask worker`` processes, runs ``maxfs run FOLDER -o OUT --scheduler ...`` and
polls the peak resident set (``VmHWM``) of the driver and of each worker.

    python -m bench.scale                      # k=200 at 1000^2 and 2000^2, k=50 at 1000^2
    python -m bench.scale --runs 200x2000 400x4000 --keep /big/disk

prints one table row per run: stack size, tile, pixels/s, certified share, peak
RSS of the driver and of each worker, and the task-memory model's estimate.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from maxfs.storage.layout import JobStore
from maxfs.storage.tiles import DEFAULT_TASK_MEMORY, tile_memory
from maxfs.worker import synthetic
from tests.harness import BIN, DaskCluster


def write_stack(folder: Path, k: int, size: int, seed: int = 0) -> Path:
    """A frame-filling bumpy sphere in 16 bits with attached shadows, highlights
    and noise, written one image at a time into ``images.npy`` (a memory map)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    u, v = (2 * x + 1) / size - 1, 1 - (2 * y + 1) / size
    r2 = u * u + v * v
    mask = r2 < 0.95
    z = np.sqrt(np.clip(1 - r2, 0.05, None))
    bump = 0.08 * np.sin(9 * u) * np.cos(7 * v)  # slope perturbation: varied normals
    n = np.stack([u + bump, v - bump, z], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    albedo = (0.5 + 0.3 * np.cos(3 * u) * np.sin(4 * v)).astype(np.float32)
    lights = synthetic.lights_uniform(k)
    view = np.array([0.0, 0.0, 1.0])
    stack = np.lib.format.open_memmap(
        folder / "images.npy", mode="w+", dtype=np.uint16, shape=(k, size, size)
    )
    for i in range(k):
        shade = np.clip(n @ lights[i].astype(np.float32), 0, None)
        h = lights[i] + view
        spec = np.clip(n @ (h / np.linalg.norm(h)).astype(np.float32), 0, None) ** 60
        img = 40000 * albedo * shade + 30000 * spec + rng.normal(0, 40, (size, size)).astype(np.float32)
        stack[i] = np.clip(np.where(mask, img, 0), 0, 65535).astype(np.uint16)
    stack.flush()
    del stack
    np.savetxt(folder / "lights.txt", lights)
    np.save(folder / "mask.npy", mask)
    return folder


def _hwm(pid: int) -> int:
    """Peak resident set of a process so far, bytes (0 once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except (FileNotFoundError, ProcessLookupError):
        pass
    return 0


class PeakWatcher(threading.Thread):
    """Polls VmHWM of some processes until stopped; keeps the largest seen."""

    def __init__(self, pids: dict[str, int]) -> None:
        super().__init__(daemon=True)
        self.pids = pids
        self.peak = dict.fromkeys(pids, 0)
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            for name, pid in self.pids.items():
                self.peak[name] = max(self.peak[name], _hwm(pid))
            time.sleep(0.1)


def run_one(k: int, size: int, root: Path, workers: int) -> dict[str, object]:
    folder = write_stack(root / f"in-{k}x{size}", k, size)
    out = root / f"out-{k}x{size}.zarr"
    logs = root / f"logs-{k}x{size}"
    logs.mkdir(exist_ok=True)
    cluster = DaskCluster(logs, n_workers=workers)
    try:
        proc = subprocess.Popen(
            [str(BIN / "maxfs"), "run", str(folder), "-o", str(out), "--scheduler", cluster.address],
            stdout=subprocess.PIPE,
            stderr=open(logs / "run.log", "wb"),
            text=True,
        )
        watch = PeakWatcher({"driver": proc.pid} | {f"w{i}": w.pid for i, w in enumerate(cluster.workers)})
        watch.start()
        stdout, _ = proc.communicate()
        watch.stop.set()
        watch.join()
    finally:
        cluster.close()
    if proc.returncode != 0:
        raise RuntimeError(f"maxfs run failed ({proc.returncode}); see {logs / 'run.log'}:\n{stdout}")
    m = re.search(r"done: (\d+) pixels in ([\d.]+) s.*tile=(\d+).*certified optimal: ([\d.]+)%", stdout)
    if m is None:
        raise RuntimeError(f"unexpected output: {stdout}")
    pixels, secs, tile, share = int(m[1]), float(m[2]), int(m[3]), float(m[4])
    store = JobStore.open(out, mode="r")
    assert store.params.tile == tile
    row = {
        "k": k,
        "size": size,
        "stack_gb": k * size * size * 2 / 1e9,
        "tile": tile,
        "pixels": pixels,
        "px_s": pixels / secs,
        "certified": share,
        "driver_mb": watch.peak["driver"] / 2**20,
        "workers_mb": [watch.peak[f"w{i}"] / 2**20 for i in range(workers)],
        "model_mb": tile_memory(tile, k, None, 2) / 2**20,
    }
    shutil.rmtree(folder)
    shutil.rmtree(out)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--runs", nargs="+", default=["50x1000", "200x1000", "200x2000"], help="KxSIZE, e.g. 200x2000"
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", type=Path, default=None, help="work folder (default: a temp folder)")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="maxfs-scale-", dir=args.keep))
    print(f"task memory budget {DEFAULT_TASK_MEMORY / 2**20:.0f} MiB (MAXFS_TASK_MEMORY); work in {root}")
    print(
        "| k | image | stack GB | tile | pixels/s | certified | driver peak MB | worker peaks MB | model MB |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    try:
        for spec in args.runs:
            k, size = (int(v) for v in spec.split("x"))
            r = run_one(k, size, root, args.workers)
            workers = " / ".join(f"{v:.0f}" for v in r["workers_mb"])
            print(
                f"| {k} | {size}x{size} | {r['stack_gb']:.2f} | {r['tile']} | {r['px_s']:.0f} "
                f"| {r['certified']:.2f}% | {r['driver_mb']:.0f} | {workers} | {r['model_mb']:.0f} |",
                flush=True,
            )
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
