"""``maxfs run`` solves small jobs on threads in its own process (issue #12): results are
bit-identical to the Dask path, and a finished job is not run again."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import zarr

from storage.datasets import write_npy_folder
from storage.layout import JobStore
from worker import synthetic

MAXFS = str(Path(sys.executable).parent / "maxfs")
ARRAYS = ("normal", "albedo", "inliers", "inlier_count", "optimal", "tile_stats", "done", "images")


def _phases(stderr: str) -> list[str]:
    """Phase names of the ``--timings`` table."""
    table = stderr.split("seconds   share", 1)[1].strip().splitlines()
    names = [line.rsplit(None, 2)[0] for line in table]
    return names[: names.index("total") + 1]


def _run(folder: Path, out: Path, *extra: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [MAXFS, "run", str(folder), "-o", str(out), "--tile", "32", "--timings", *extra],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **env},
    )


def test_threads_and_dask_cluster_give_identical_stores_and_finished_jobs_do_not_rerun(
    tmp_path: Path,
) -> None:
    sc = synthetic.bump_scene(10, 80, seed=5)
    mask = sc.mask.copy()
    mask[:, :40] = False  # tiles with no masked pixel are skipped, not solved
    folder = write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, mask)
    threads = _run(folder, tmp_path / "threads.zarr", "--workers", "2")
    assert threads.returncode == 0, threads.stderr
    assert "tiles" in _phases(threads.stderr) and "cluster run (start, tiles, stop)" not in _phases(
        threads.stderr
    )
    dask = _run(folder, tmp_path / "dask.zarr", "--workers", "1", MAXFS_IN_PROCESS_BYTES="0")
    assert dask.returncode == 0, dask.stderr
    assert "cluster run (start, tiles, stop)" in _phases(dask.stderr)
    a, b = (zarr.open_group(tmp_path / n, mode="r") for n in ("threads.zarr", "dask.zarr"))
    for name in ARRAYS:
        np.testing.assert_array_equal(a[name][...], b[name][...], err_msg=name)
    store = JobStore.open(tmp_path / "threads.zarr", mode="r")
    assert store.input_identity() == JobStore.open(tmp_path / "dask.zarr", mode="r").input_identity()
    before = store.run_counts()
    assert len(before) == len(store.tiles())
    again = _run(folder, tmp_path / "threads.zarr", "--workers", "2")
    assert again.returncode == 0, again.stderr
    assert "tiles already done" in again.stderr
    assert _phases(again.stderr) == ["imports", "open the folder", "open or create the store", "total"]
    assert JobStore.open(tmp_path / "threads.zarr", mode="r").run_counts() == before
