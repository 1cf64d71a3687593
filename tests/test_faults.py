"""Faults with real processes: each ends in a true state, and the results of a job
that is then finished equal an undisturbed run bit for bit.

Covered here: a tile task that raises, the Dask scheduler lost mid-job, and the
server SIGKILLed mid-upload (plus a create cut short). A worker killed mid-tile
and the server killed mid-job are in ``test_service_distributed.py``.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest

from service.client import MaxfsClient
from storage.layout import JobStore
from storage.records import RECORD_NAME, load_record
from tests.procs import DaskCluster, Server
from worker import synthetic
from worker.solve import Solution, solve

OUTPUTS = ("normal", "albedo", "inliers", "inlier_count", "optimal")
K, SIZE, TILE, EPS = 12, 64, 16, 2.0


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray, Solution]:
    sc = synthetic.bump_scene(K, SIZE, seed=5)
    images = sc.images.astype(np.uint8)
    # the HTTP default model is "robust"; the library's default is "paper"
    return (
        images,
        sc.lights,
        solve(images, sc.lights, eps=EPS, response=1.0, solver="milp", tile=TILE, model="robust"),
    )


def _create(c: MaxfsClient, lights: np.ndarray) -> str:
    return c.create_job(
        k=K,
        height=SIZE,
        width=SIZE,
        dtype="uint8",
        lights=lights.tolist(),
        eps=EPS,
        response=1.0,
        solver="milp",
        tile=TILE,
    )["id"]


def _wait(c: MaxfsClient, job_id: str, until, timeout: float = 180) -> dict:
    t0 = time.monotonic()
    while True:
        st = c.status(job_id)
        if until(st):
            return st
        assert time.monotonic() - t0 < timeout, f"job stuck: {st}"
        time.sleep(0.05)


def _assert_equal(store: JobStore, ref: Solution) -> None:
    for name in OUTPUTS:
        np.testing.assert_array_equal(store.read_output(name), getattr(ref, name), err_msg=name)


def test_tile_task_that_raises_fails_the_job_and_resume_finishes_it(
    tmp_path: Path, scene: tuple[np.ndarray, np.ndarray, Solution]
) -> None:
    images, lights, ref = scene
    server = Server(tmp_path / "data", "", tmp_path, workers=2, env={"MAXFS_TILE_RETRIES": "1"})
    try:
        with MaxfsClient(server.url) as c:
            job_id = _create(c, lights)
            for i in range(K):
                c.upload_image(job_id, i, images[i])
            # the shard of image 3, rows 32-47: the four tiles of that band cannot read their input
            shard = tmp_path / "data" / "jobs" / job_id / "results.zarr" / "images" / "c" / "3" / "2" / "0"
            good = shard.read_bytes()
            shard.write_bytes(b"\x00not a shard" * 7)
            c.start(job_id)
            st = c.wait(job_id, poll=0.1, timeout=180)
            assert st["state"] == "failed", st
            assert "tile " in st["error"] and "failed" in st["error"], st["error"]
            store = JobStore.open(tmp_path / "data" / "jobs" / job_id, mode="r")
            assert not store.done_grid()[2].any(), "a tile with unreadable input was marked done"
            finished = np.flatnonzero(store.done_grid().ravel())

            shard.write_bytes(good)  # the operator restores the file; the user resumes
            c.start(job_id)
            st = c.wait(job_id, poll=0.1, timeout=180)
            assert st["state"] == "done" and st["error"] is None, st
            runs = store.run_counts()
            assert all(runs[t] == 1 for t in finished), f"finished tiles were recomputed: {runs}"
            _assert_equal(store, ref)
    finally:
        server.kill()


def test_scheduler_lost_mid_job_fails_with_reason_then_resumes(
    tmp_path: Path, scene: tuple[np.ndarray, np.ndarray, Solution]
) -> None:
    images, lights, ref = scene
    cluster = DaskCluster(tmp_path, n_workers=2)
    server = Server(tmp_path / "data", cluster.address, tmp_path)
    try:
        with MaxfsClient(server.url) as c:
            job_id = _create(c, lights)
            for i in range(K):
                c.upload_image(job_id, i, images[i])
            c.start(job_id)
            _wait(c, job_id, lambda st: st["progress"]["tiles_done"] >= 2)
            cluster.close()  # scheduler and workers gone
            st = _wait(c, job_id, lambda st: st["state"] != "running", timeout=60)
            assert st["state"] == "failed" and "lost the Dask scheduler" in st["error"], st
            store = JobStore.open(tmp_path / "data" / "jobs" / job_id, mode="r")
            assert store.done_grid().sum() < len(store.tiles()), "the job must be cut short"

            cluster = DaskCluster(tmp_path, n_workers=2, port=cluster.port)  # back, same address
            c.start(job_id)
            st = c.wait(job_id, poll=0.1, timeout=180)
            assert st["state"] == "done", st
            _assert_equal(store, ref)
    finally:
        server.kill()
        cluster.close()


def _partial_put(url: str, path: str, declared: int, body: bytes) -> socket.socket:
    """Send the head and part of a body, and leave the connection open."""
    host, port = url.removeprefix("http://").split(":")
    s = socket.create_connection((host, int(port)))
    head = (
        f"PUT {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/octet-stream\r\n"
        f"Content-Length: {declared}\r\n\r\n"
    )
    s.sendall(head.encode() + body)
    return s


def test_server_killed_mid_upload_restarts_in_a_true_state(
    tmp_path: Path, scene: tuple[np.ndarray, np.ndarray, Solution]
) -> None:
    images, lights, ref = scene
    data = tmp_path / "data"
    servers = [Server(data, "", tmp_path, workers=2)]
    try:
        _kill_mid_upload_then_restart(servers, data, tmp_path, images, lights, ref)
    finally:
        for s in servers:
            s.kill()


def _kill_mid_upload_then_restart(
    servers: list[Server], data: Path, tmp_path: Path, images: np.ndarray, lights: np.ndarray, ref: Solution
) -> None:
    server = servers[0]
    with MaxfsClient(server.url) as c:
        done_id = _create(c, lights)  # a finished job, which must stay finished
        for i in range(K):
            c.upload_image(done_id, i, images[i])
        c.start(done_id)
        assert c.wait(done_id, poll=0.1, timeout=180)["state"] == "done"
        job_id = _create(c, lights)
        for i in range(6):
            c.upload_image(job_id, i, images[i])
    job_dir = data / "jobs" / job_id
    half = images[6].tobytes()[: images[6].nbytes // 2]
    conn = _partial_put(server.url, f"/jobs/{job_id}/images/6", images[6].nbytes, half)
    t0 = time.monotonic()
    while not any(p.stat().st_size == len(half) for p in job_dir.glob(".maxfs-upload-6-*")):
        assert time.monotonic() - t0 < 30, "the server never staged the partial upload"
        time.sleep(0.02)
    # a create cut short between the store and its record leaves a folder without a record
    orphan = data / "jobs" / ("f" * 32)
    JobStore.create(orphan, JobStore.open(job_dir, mode="r").spec, JobStore.open(job_dir, mode="r").params)
    server.kill()
    conn.close()
    done_before = {p: p.read_bytes() for p in (data / "jobs" / done_id).rglob("*") if p.is_file()}

    server = Server(data, "", tmp_path, port=server.port, workers=2)
    servers.append(server)
    assert not list(job_dir.glob(".maxfs-*")), "staged upload left behind"
    assert not orphan.exists(), "half-created job folder left behind"
    assert load_record(data / "jobs" / done_id).state.value == "done"
    assert {p: p.read_bytes() for p in (data / "jobs" / done_id).rglob("*") if p.is_file()} == done_before
    with MaxfsClient(server.url) as c:
        st = c.status(job_id)
        assert st["state"] == "uploading" and st["uploaded"] == 6, st
        assert [j["id"] for j in c.jobs()] == [done_id, job_id]
        for i in range(6, K):
            c.upload_image(job_id, i, images[i])
        c.start(job_id)
        assert c.wait(job_id, poll=0.1, timeout=180)["state"] == "done"
    _assert_equal(JobStore.open(job_dir, mode="r"), ref)
    assert (job_dir / RECORD_NAME).exists()


def test_embedded_cluster_listens_on_loopback_only(tmp_path: Path) -> None:
    """The server, its scheduler, workers and HTTP endpoints: nothing listens beyond 127.0.0.1."""
    import psutil

    server = Server(tmp_path / "data", "", tmp_path, workers=1)
    try:
        procs = [psutil.Process(server.proc.pid), *psutil.Process(server.proc.pid).children(recursive=True)]
        pids = {p.pid for p in procs}
        listening = [
            c.laddr for c in psutil.net_connections(kind="inet") if c.status == "LISTEN" and c.pid in pids
        ]
        assert len(listening) >= 3, listening  # HTTP, scheduler, worker (at least)
        assert all(addr.ip == "127.0.0.1" for addr in listening), listening
    finally:
        server.kill()
