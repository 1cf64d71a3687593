"""The service end to end with real processes: uvicorn server, dask scheduler, dask workers.

Each test submits a synthetic job over HTTP and checks the fetched results equal
the in-process solver bit for bit, undisturbed, with a worker killed mid-job, and
with the server killed mid-job and started again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zarr

from service.client import MaxfsClient
from storage.imageio import decode_bytes
from storage.layout import JobStore
from tests.procs import DaskCluster, Server
from worker import synthetic
from worker.solve import Solution, solve

OUTPUTS = ("normal", "albedo", "inliers", "inlier_count", "optimal")


@dataclass(frozen=True)
class Data:
    images: np.ndarray  # (k, H, W) uint8
    lights: np.ndarray
    mask: np.ndarray
    exact_ref: Solution  # eps="auto", tile 32
    milp_ref: Solution  # eps=2, tile 16: slow tiles, so there is time to break things


@pytest.fixture(scope="module")
def data() -> Data:
    sc = synthetic.bump_scene(12, 64, seed=3)
    images = sc.images.astype(np.uint8)
    return Data(
        images,
        sc.lights,
        sc.mask,
        # the HTTP default model is "robust"; the library's default is "paper"
        solve(images, sc.lights, sc.mask, eps="auto", tile=32, model="robust"),
        solve(images, sc.lights, sc.mask, eps=2.0, solver="milp", tile=16, model="robust"),
    )


@pytest.fixture
def cluster(tmp_path: Path):
    c = DaskCluster(tmp_path, n_workers=2)
    yield c
    c.close()


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
    t0 = time.monotonic()
    while True:
        st = c.status(job_id)
        if st["progress"]["tiles_done"] >= tiles or st["state"] in ("done", "failed"):
            return st
        assert time.monotonic() - t0 < timeout, f"job stuck: {st}"
        time.sleep(0.05)


def _assert_equal(arrays: dict[str, np.ndarray], ref: Solution) -> None:
    for name in OUTPUTS:
        np.testing.assert_array_equal(
            arrays[name], getattr(ref, name if name != "inlier_count" else "inlier_count")
        )


def test_http_job_equals_in_process_solver(cluster: DaskCluster, tmp_path: Path, data: Data) -> None:
    server = Server(tmp_path / "data", cluster.address, tmp_path)
    try:
        with MaxfsClient(server.url) as c:
            job_id = _submit(c, data, eps="auto", tile=32)
            st = c.wait(job_id, poll=0.1, timeout=180)
            assert st["state"] == "done", st
            assert st["progress"]["fraction"] == 1.0
            assert st["progress"]["certified_share"] == 1.0
            assert st["eps"] == data.exact_ref.eps
            out = c.fetch_zarr(job_id, tmp_path / "fetched.zarr")
            g = zarr.open_group(out / "results.zarr", mode="r")
            _assert_equal({n: g[n][...] for n in OUTPUTS}, data.exact_ref)
            np.testing.assert_array_equal(c.fetch_array(job_id, "normal"), data.exact_ref.normal)
            png = c.http.get(f"/jobs/{job_id}/previews/normal.png").content
            assert decode_bytes(png).shape == (*data.images.shape[1:], 3)
            assert [j["id"] for j in c.jobs()] == [job_id]
    finally:
        server.kill()


def test_killed_worker_mid_job_gives_identical_results(
    cluster: DaskCluster, tmp_path: Path, data: Data
) -> None:
    server = Server(tmp_path / "data", cluster.address, tmp_path)
    try:
        with MaxfsClient(server.url) as c:
            job_id = _submit(c, data, eps=2.0, solver="milp", tile=16)
            st = _wait_for(c, job_id, tiles=2)
            assert st["state"] == "running" and st["progress"]["tiles_done"] < st["progress"]["tiles_total"]
            cluster.workers[0].kill()
            st = c.wait(job_id, poll=0.1, timeout=300)
            assert st["state"] == "done", st
            store = JobStore.open(tmp_path / "data" / "jobs" / job_id, mode="r")
            _assert_equal({n: store.read_output(n) for n in OUTPUTS}, data.milp_ref)
    finally:
        server.kill()


def test_server_killed_mid_job_resumes_without_recomputing(
    cluster: DaskCluster, tmp_path: Path, data: Data
) -> None:
    data_dir = tmp_path / "data"
    server = Server(data_dir, cluster.address, tmp_path)
    with MaxfsClient(server.url) as c:
        job_id = _submit(c, data, eps=2.0, solver="milp", tile=16)
        _wait_for(c, job_id, tiles=3)
    server.kill()
    cluster.wait_idle()  # tiles in flight when the server died finish (or are dropped)
    store = JobStore.open(data_dir / "jobs" / job_id, mode="r")
    finished = np.flatnonzero(store.done_grid().ravel())
    total = len(store.tiles())
    assert 3 <= finished.size < total, "the server must die mid-job for this test to mean anything"

    server = Server(data_dir, cluster.address, tmp_path)  # resumes active jobs on start
    try:
        with MaxfsClient(server.url) as c:
            st = c.wait(job_id, poll=0.1, timeout=300)
        assert st["state"] == "done", st
        runs = store.run_counts()
        assert set(runs) == set(range(total)), "every tile was computed"
        assert all(runs[t] == 1 for t in finished), f"finished tiles were recomputed: {runs}"
        _assert_equal({n: store.read_output(n) for n in OUTPUTS}, data.milp_ref)
    finally:
        server.kill()
