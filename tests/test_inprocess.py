"""``maxfs run`` solves small jobs on threads in its own process (issue #12): results are
bit-identical to the Dask path, and a finished job is not run again."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.layout import JobStore
from maxfs.worker import synthetic
from tests.procs import poll_until

MAXFS = str(Path(sys.executable).parent / "maxfs")
ARRAYS = (
    "normal",
    "albedo",
    "inliers",
    "inlier_count",
    "optimal",
    "tiles/tile_stats",
    "tiles/done",
    "inputs/input_digests",
)


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


@pytest.mark.slow
def test_threads_and_dask_cluster_give_identical_stores_and_finished_jobs_do_not_rerun(
    tmp_path: Path,
) -> None:
    sc = synthetic.bump_scene(10, 80, seed=5)
    mask = sc.mask.copy()
    mask[:, :40] = False  # tiles with no masked pixel are skipped, not solved
    # 12-bit values shifted into 16-bit files: both paths measure and use the raw step
    stack = sc.images.astype(np.uint8).astype(np.uint16) << 4
    folder = write_npy_folder(tmp_path / "in", stack, sc.lights, mask)
    threads = _run(folder, tmp_path / "threads.zarr", "--workers", "2")
    assert threads.returncode == 0, threads.stderr
    assert "tiles" in _phases(threads.stderr) and "cluster run (tiles)" not in _phases(threads.stderr)
    dask = _run(folder, tmp_path / "dask.zarr", "--workers", "1", MAXFS_IN_PROCESS_BYTES="0")
    assert dask.returncode == 0, dask.stderr
    # the cluster started while the images were stored and eps was estimated here, from the
    # windows kept of each image; previews and depth made while it stopped
    assert _phases(dask.stderr)[:8] == [
        "open the folder",
        "imports",
        "open or create the store",
        "eps estimate",
        "cluster start (what reading left)",
        "cluster run (tiles)",
        "previews",
        "depth and derived results",
    ]
    a, b = (zarr.open_group(tmp_path / n / "results.zarr", mode="r") for n in ("threads.zarr", "dask.zarr"))
    for name in ARRAYS:
        np.testing.assert_array_equal(a[name][...], b[name][...], err_msg=name)
    store = JobStore.open(tmp_path / "threads.zarr", mode="r")
    assert store.params == JobStore.open(tmp_path / "dask.zarr", mode="r").params
    assert store.params.quantum == 16 and "(raw values in steps of 16)" in threads.stdout
    assert store.input_identity() == JobStore.open(tmp_path / "dask.zarr", mode="r").input_identity()
    before = store.run_counts()
    # each tile with masked pixels ran once; the others are done without a task or a write
    occupied = {t.index for t in store.tiles() if mask[t.y0 : t.y1, t.x0 : t.x1].any()}
    assert before == dict.fromkeys(occupied, 1) and len(occupied) < len(store.tiles())
    assert store.done_grid().all()
    again = _run(folder, tmp_path / "threads.zarr", "--workers", "2")
    assert again.returncode == 0, again.stderr
    assert "tiles already done" in again.stderr
    phases = ["open the folder", "imports", "open or create the store", "other", "total"]
    assert _phases(again.stderr) == phases
    assert JobStore.open(tmp_path / "threads.zarr", mode="r").run_counts() == before
    # and looking at it costs no solver: numba is never imported (0.3 s and the kernels' 0.7 s)
    probe = (
        "import sys; from maxfs.service.cli.main import main; "
        "sys.argv = ['maxfs', 'run', sys.argv[1], '-o', sys.argv[2]]; rc = main(); "
        "print(rc, sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'distributed')))"
    )
    look = subprocess.run(
        [sys.executable, "-c", probe, str(folder), str(tmp_path / "threads.zarr")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert look.stdout.strip().splitlines()[-1] == "0 []", look.stdout + look.stderr


@pytest.mark.slow
@pytest.mark.parametrize("path", ["threads", "dask"])
def test_ctrl_c_prints_one_line_and_the_same_command_resumes(tmp_path: Path, path: str) -> None:
    sc = synthetic.bump_scene(12, 96, seed=2)
    folder = write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask)
    cmd = [MAXFS, "run", str(folder), "-o", str(tmp_path / "out"), "--solver", "milp", "--tile", "16"]
    env = {**os.environ, **({"MAXFS_IN_PROCESS_BYTES": "0"} if path == "dask" else {})}
    p = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as in a terminal
    )
    assert p.stderr is not None
    seen: list[str] = []

    def next_line() -> str:
        """The next line maxfs run writes to stderr (it ending before "running" fails the test)."""
        line = p.stderr.readline()
        assert line, f"maxfs run ended before solving a tile: {''.join(seen)}"
        seen.append(line)
        return line

    try:
        poll_until(
            next_line, 120, "a 'running' progress line (tiles being solved)", 0, lambda ln: "running" in ln
        )
        t0 = time.monotonic()
        p.send_signal(signal.SIGINT)
        err = p.communicate(timeout=60)[1]
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 130 and time.monotonic() - t0 < 10
    assert "interrupted; run the same command again to resume" in err and "Traceback" not in err
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert again.returncode == 0, again.stderr
    assert JobStore.open(tmp_path / "out", mode="r").done_grid().all()


def test_a_failed_kernel_load_leaves_the_verdict_to_the_tiles(tmp_path: Path, monkeypatch) -> None:
    """The up-front load is an optimisation: if it fails, the run goes on and its tiles (which
    load the kernels again) decide, so a failure ends as a failed job with a reason, not a crash."""
    import maxfs.worker.task as task
    from maxfs.service.runs.local import run_folder
    from maxfs.storage.inputs import load_folder
    from maxfs.storage.params import JobParams
    from maxfs.storage.records import JobState

    sc = synthetic.bump_scene(8, 32, seed=1)
    folder = write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask)

    def broken(on_compile=None, **kw) -> float:
        raise RuntimeError("no compiler")

    monkeypatch.setattr(task, "load_kernels", broken)
    _, rec = run_folder(load_folder(folder), tmp_path / "out", JobParams.build(eps=1.0, tile=16), workers=1)
    assert rec.state is JobState.DONE and rec.tiles_done == rec.tiles_total
