"""Faults with real processes: each ends in a true state, and the results of a job
that is then finished equal an undisturbed run bit for bit.

Covered here: a tile task that raises, the Dask scheduler lost mid-job, and the
server SIGKILLed mid-upload (plus a create cut short). A worker killed mid-tile
and the server killed mid-job are in ``test_service_distributed.py``.
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from maxfs.service.cli.client import MaxfsClient
from maxfs.storage.layout import JobStore
from maxfs.storage.records import RECORD_NAME, load_record
from maxfs.worker.solve import Solution
from tests.faults import fault_env
from tests.procs import Procs, Server, poll_until

OUTPUTS = ("normal", "albedo", "inliers", "inlier_count", "optimal")
K, SIZE, TILE, EPS = 12, 64, 16, 2.0


@pytest.fixture(scope="module")
def job(scene, reference_solution) -> tuple[np.ndarray, np.ndarray, Solution]:
    """The 12 images and lights of the job every test here submits, and its HiGHS reference."""
    sc = scene("bump", K, SIZE, seed=5)
    images = sc.images.astype(np.uint8)
    # the HiGHS reference, with the HTTP default model ("robust"; the library's default is "paper")
    return images, sc.lights, reference_solution(images, sc.lights, eps=EPS, response=1.0, tile=TILE)


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


def _wait(c: MaxfsClient, job_id: str, until, what: str, timeout: float = 180) -> dict:
    return poll_until(lambda: c.status(job_id), timeout, f"job {job_id}: {what}", 0.05, until)


def _assert_equal(store: JobStore, ref: Solution) -> None:
    for name in OUTPUTS:
        np.testing.assert_array_equal(store.read_output(name), getattr(ref, name), err_msg=name)


def test_tile_task_that_raises_fails_the_job_and_resume_finishes_it(
    tmp_path: Path, job: tuple[np.ndarray, np.ndarray, Solution], server_factory: Callable[..., Server]
) -> None:
    images, lights, ref = job
    # the tiles of rows 32-47 (tiles 8-11 of the 4 x 4 grid) raise while the fault file exists
    fault = tmp_path / "fail-tiles"
    fault.write_text("8,9,10,11")
    env = {"MAXFS_TILE_RETRIES": "1", **fault_env(fail_tiles=fault)}
    server = server_factory(workers=2, env=env)
    with MaxfsClient(server.url) as c:
        job_id = _create(c, lights)
        for i in range(K):
            c.upload_image(job_id, i, images[i])
        c.start(job_id)
        st = c.wait(job_id, poll=0.1, timeout=180)
        assert st["state"] == "failed", st
        assert "tile " in st["error"] and "failed" in st["error"], st["error"]
        assert "failure injected by the test" in st["error"], st["error"]
        store = JobStore.open(tmp_path / "data" / "jobs" / job_id, mode="r")
        assert not store.done_grid()[2].any(), "a tile that raised was marked done"
        finished = np.flatnonzero(store.done_grid().ravel())

        fault.unlink()  # the fault is gone; the user resumes
        c.start(job_id)
        st = c.wait(job_id, poll=0.1, timeout=180)
        assert st["state"] == "done" and st["error"] is None, st
        runs = store.run_counts()
        assert all(runs[t] == 1 for t in finished), f"finished tiles were recomputed: {runs}"
        _assert_equal(store, ref)


def test_scheduler_lost_mid_job_fails_with_reason_then_resumes(
    tmp_path: Path, job: tuple[np.ndarray, np.ndarray, Solution], procs: Procs
) -> None:
    images, lights, ref = job
    cluster = procs.cluster(n_workers=2)
    server = procs.server(scheduler=cluster.address)
    with MaxfsClient(server.url) as c:
        job_id = _create(c, lights)
        for i in range(K):
            c.upload_image(job_id, i, images[i])
        c.start(job_id)
        _wait(c, job_id, lambda st: st["progress"]["tiles_done"] >= 2, "2 tiles done")
        cluster.close()  # scheduler and workers gone
        st = _wait(c, job_id, lambda st: st["state"] != "running", "the job to stop running", timeout=60)
        assert st["state"] == "failed" and "lost the Dask scheduler" in st["error"], st
        store = JobStore.open(tmp_path / "data" / "jobs" / job_id, mode="r")
        assert store.done_grid().sum() < len(store.tiles()), "the job must be cut short"

        procs.cluster(n_workers=2, port=cluster.port)  # back, same address
        c.start(job_id)
        st = c.wait(job_id, poll=0.1, timeout=180)
        assert st["state"] == "done", st
        _assert_equal(store, ref)


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
    tmp_path: Path, job: tuple[np.ndarray, np.ndarray, Solution], server_factory: Callable[..., Server]
) -> None:
    images, lights, ref = job
    data = tmp_path / "data"
    server = server_factory(data, workers=2)
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
    poll_until(
        lambda: {p.name: p.stat().st_size for p in job_dir.glob(".maxfs-upload-6-*")},
        30,
        f"the server to stage the first {len(half)} bytes of the partial upload",
        0.02,
        lambda staged: len(half) in staged.values(),
    )
    # a create cut short between the store and its record leaves a folder without a record
    orphan = data / "jobs" / ("f" * 32)
    JobStore.create(orphan, JobStore.open(job_dir, mode="r").spec, JobStore.open(job_dir, mode="r").params)
    server.kill()
    conn.close()
    done_before = {p: p.read_bytes() for p in (data / "jobs" / done_id).rglob("*") if p.is_file()}

    server = server_factory(data, port=server.port, workers=2)
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


def test_embedded_cluster_listens_on_loopback_only(server_factory: Callable[..., Server]) -> None:
    """The server, its scheduler, workers and HTTP endpoints: nothing listens beyond 127.0.0.1."""
    import psutil

    server = server_factory(workers=1)
    procs = [psutil.Process(server.proc.pid), *psutil.Process(server.proc.pid).children(recursive=True)]
    pids = {p.pid for p in procs}
    listening = [
        c.laddr for c in psutil.net_connections(kind="inet") if c.status == "LISTEN" and c.pid in pids
    ]
    assert len(listening) >= 3, listening  # HTTP, scheduler, worker (at least)
    assert all(addr.ip == "127.0.0.1" for addr in listening), listening
