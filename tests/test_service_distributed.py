"""The service end to end with real processes: uvicorn server, dask scheduler, dask workers.

Each test submits a synthetic job over HTTP and checks the fetched results equal
the in-process solver bit for bit, undisturbed, with a worker killed mid-job, and
with the server killed mid-job and started again.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zarr

from maxfs.service.cli.client import MaxfsClient
from maxfs.storage.imageio import decode_bytes
from maxfs.storage.layout import JobStore
from maxfs.worker.solve import Solution
from tests.procs import DaskCluster, Server, poll_until

OUTPUTS = ("normal", "albedo", "inliers", "inlier_count", "optimal")


@dataclass(frozen=True)
class Data:
    images: np.ndarray  # (k, H, W) uint8
    lights: np.ndarray
    mask: np.ndarray
    exact_ref: Solution  # eps="auto", tile 32
    milp_ref: Solution  # eps=2, tile 16: slow tiles, so there is time to break things


@pytest.fixture(scope="module")
def data(scene, reference_solution) -> Data:
    sc = scene("bump", 12, 64, seed=3)
    images = sc.images.astype(np.uint8)
    return Data(
        images,
        sc.lights,
        sc.mask,
        # the HTTP default model is "robust" (the fixture's too); the library's default is "paper"
        reference_solution(images, sc.lights, sc.mask, eps="auto", tile=32, solver="exact"),
        reference_solution(images, sc.lights, sc.mask, eps=2.0, tile=16),  # the HiGHS MILP
    )


def _submit(c: MaxfsClient, d: Data, **params) -> str:
    k, H, W = d.images.shape
    job = c.create_job(k=k, height=H, width=W, dtype="uint8", lights=d.lights.tolist(), **params)
    assert job["state"] == "created"
    for i in range(k):
        c.upload_image(job["id"], i, d.images[i])
    c.upload_mask(job["id"], d.mask)
    started = c.start(job["id"])
    assert started["state"] == "queued"
    return job["id"]


def _wait_for(c: MaxfsClient, job_id: str, tiles: int, timeout: float = 120) -> dict:
    return poll_until(
        lambda: c.status(job_id),
        timeout,
        f"job {job_id}: {tiles} tiles done, or the job over",
        0.05,
        lambda st: st["progress"]["tiles_done"] >= tiles or st["state"] in ("done", "failed"),
    )


def _assert_equal(arrays: dict[str, np.ndarray], ref: Solution) -> None:
    for name in OUTPUTS:
        np.testing.assert_array_equal(
            arrays[name], getattr(ref, name if name != "inlier_count" else "inlier_count")
        )


@pytest.mark.smoke
def test_http_job_equals_in_process_solver(
    dask_cluster: DaskCluster, server_factory: Callable[..., Server], tmp_path: Path, data: Data
) -> None:
    server = server_factory(scheduler=dask_cluster.address)
    with MaxfsClient(server.url) as c:
        job_id = _submit(c, data, eps="auto", tile=32)
        st = c.wait(job_id, poll=0.1, timeout=180)
        assert st["state"] == "done", st
        assert st["progress"]["fraction"] == 1.0
        assert st["progress"]["certified_share"] == 1.0
        assert st["eps"] == data.exact_ref.eps and st["raw_step"] == 1  # measured when it started
        out = c.fetch_zarr(job_id, tmp_path / "fetched.zarr")
        g = zarr.open_group(out / "results.zarr", mode="r")
        _assert_equal({n: g[n][...] for n in OUTPUTS}, data.exact_ref)
        np.testing.assert_array_equal(c.fetch_array(job_id, "normal"), data.exact_ref.normal)
        png = c.http.get(f"/jobs/{job_id}/previews/normal.png").content
        assert decode_bytes(png).shape == (*data.images.shape[1:], 3)
        assert [j["id"] for j in c.jobs()] == [job_id]


def test_killed_worker_mid_job_gives_identical_results(
    dask_cluster: DaskCluster, server_factory: Callable[..., Server], tmp_path: Path, data: Data
) -> None:
    server = server_factory(scheduler=dask_cluster.address)
    with MaxfsClient(server.url) as c:
        job_id = _submit(c, data, eps=2.0, solver="milp", tile=16)
        st = _wait_for(c, job_id, tiles=2)
        assert st["state"] == "running" and st["progress"]["tiles_done"] < st["progress"]["tiles_total"]
        dask_cluster.workers[0].kill()
        st = c.wait(job_id, poll=0.1, timeout=300)
        assert st["state"] == "done", st
        store = JobStore.open(tmp_path / "data" / "jobs" / job_id, mode="r")
        _assert_equal({n: store.read_output(n) for n in OUTPUTS}, data.milp_ref)


def test_server_killed_mid_job_resumes_without_recomputing(
    dask_cluster: DaskCluster, server_factory: Callable[..., Server], tmp_path: Path, data: Data
) -> None:
    data_dir = tmp_path / "data"
    server = server_factory(data_dir, scheduler=dask_cluster.address)
    with MaxfsClient(server.url) as c:
        job_id = _submit(c, data, eps=2.0, solver="milp", tile=16)
        _wait_for(c, job_id, tiles=3)
    server.kill()
    dask_cluster.wait_idle()  # tiles in flight when the server died finish (or are dropped)
    store = JobStore.open(data_dir / "jobs" / job_id, mode="r")
    finished = np.flatnonzero(store.done_grid().ravel())
    total = len(store.tiles())
    assert 3 <= finished.size < total, "the server must die mid-job for this test to mean anything"

    server = server_factory(data_dir, scheduler=dask_cluster.address)  # resumes active jobs on start
    with MaxfsClient(server.url) as c:
        st = c.wait(job_id, poll=0.1, timeout=300)
    assert st["state"] == "done", st
    runs = store.run_counts()
    assert set(runs) == set(range(total)), "every tile was computed"
    assert all(runs[t] == 1 for t in finished), f"finished tiles were recomputed: {runs}"
    _assert_equal({n: store.read_output(n) for n in OUTPUTS}, data.milp_ref)
