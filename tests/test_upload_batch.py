"""``PUT /jobs/{id}/images?first=&count=``: several raw images in one request, against a real
``maxfs serve``. It stores exactly what single uploads store, refuses what they refuse (with a
JSON reason, storing nothing), and a body cut short keeps the whole images before the cut.
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest

from maxfs.service.cli.client import MaxfsClient, upload_batches
from maxfs.storage.layout import JobStore
from maxfs.worker import synthetic
from tests.procs import Server, poll_until

K, H, W = 6, 37, 50
LIGHTS = synthetic.lights_uniform(K)
IMAGES = np.random.default_rng(7).integers(0, 65535, (K, H, W), dtype=np.uint16)
NBYTES = H * W * 2


@pytest.fixture(scope="module")
def server(module_server_factory: Callable[..., Server], tmp_path_factory: pytest.TempPathFactory) -> Server:
    return module_server_factory(tmp_path_factory.mktemp("batch"), workers=1)


@pytest.fixture
def http(server: Server):
    with httpx.Client(base_url=server.url, timeout=60) as h:
        yield h
        for job in h.get("/jobs").json():  # each test's jobs go: the server limits open jobs per user
            if job["state"] in ("queued", "running"):
                h.delete(f"/jobs/{job['id']}")
            h.delete(f"/jobs/{job['id']}", params={"purge": "true"})


def _create(http: httpx.Client) -> str:
    body = {"k": K, "height": H, "width": W, "dtype": "uint16", "lights": LIGHTS.tolist(), "eps": 2.0}
    r = http.post("/jobs", json=body)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _batch(http: httpx.Client, job: str, first: int, count: int, **kw) -> httpx.Response:
    body = kw.pop("content", IMAGES[first : first + count].astype("<u2").tobytes())
    headers = {"Content-Type": "application/octet-stream"} | kw.pop("headers", {})
    return http.put(
        f"/jobs/{job}/images", params={"first": first, "count": count}, content=body, headers=headers
    )


def _staged(server: Server, job: str) -> list[str]:
    return [p.name for p in (server.data / "jobs" / job).iterdir() if p.name.startswith(".maxfs-")]


def test_a_batch_stores_what_single_uploads_store(server: Server, http: httpx.Client) -> None:
    one, many = _create(http), _create(http)
    for i in range(K):
        assert (
            http.put(f"/jobs/{one}/images/{i}", content=IMAGES[i].astype("<u2").tobytes()).status_code == 200
        )
    r = _batch(http, many, 0, 4)
    assert r.status_code == 200, r.text
    assert r.json()["uploaded"] == 4 and r.json()["missing_images"] == [4, 5]
    assert r.json()["state"] == "uploading"
    with MaxfsClient(server.url) as c:  # the client's batch upload, its images as arrays
        st = c.upload_images(many, 4, list(IMAGES[4:]))
    assert st["uploaded"] == K and st["missing_images"] == []
    a = JobStore.open(server.data / "jobs" / one, mode="r")
    b = JobStore.open(server.data / "jobs" / many, mode="r")
    assert a.uploaded().all() and b.uploaded().all()
    assert a.digests() == b.digests()
    np.testing.assert_array_equal(b.read_array("images"), IMAGES)
    assert not _staged(server, many)


@pytest.mark.parametrize(
    ("first", "count", "kw", "status", "reason"),
    [
        (5, 2, {}, 404, "out of range"),
        (0, 0, {"content": b""}, 422, "count"),
        (0, 2, {"headers": {"Content-Type": "image/png"}}, 422, "raw little-endian"),
        (0, 2, {"content": b"\x00" * (2 * NBYTES - 1)}, 422, "declares"),
        (0, 2, {"content": b"\x00" * (2 * NBYTES + 1)}, 413, "larger than"),
    ],
)
def test_a_bad_batch_is_refused_and_stores_nothing(
    server: Server, http: httpx.Client, first: int, count: int, kw: dict, status: int, reason: str
) -> None:
    job = _create(http)
    r = _batch(http, job, first, count, **kw)
    assert r.status_code == status and reason in r.json()["detail"], r.text
    assert http.get(f"/jobs/{job}").json()["uploaded"] == 0
    assert not JobStore.open(server.data / "jobs" / job, mode="r").uploaded().any()
    assert not _staged(server, job)


def test_a_cancelled_job_takes_no_batch(http: httpx.Client) -> None:
    job = _create(http)
    assert http.delete(f"/jobs/{job}").json()["state"] == "cancelled"
    r = _batch(http, job, 0, 2)
    assert r.status_code == 409 and "cancelled" in r.json()["detail"], r.text


def test_a_batch_cut_short_keeps_the_whole_images_before_the_cut(server: Server, http: httpx.Client) -> None:
    job = _create(http)
    body = IMAGES[1:4].astype("<u2").tobytes()
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
        s.sendall(
            (
                f"PUT /jobs/{job}/images?first=1&count=3 HTTP/1.1\r\nHost: x\r\n"
                f"Content-Type: application/octet-stream\r\nContent-Length: {len(body)}\r\n\r\n"
            ).encode()
            + body[: NBYTES + NBYTES // 2]  # image 1, and half of image 2
        )
        # image 1 is stored while image 2's first half waits in the server's memory (small images
        # of a batch are gathered there, not in a staging file)
        poll_until(
            lambda: JobStore.open(server.data / "jobs" / job, mode="r").uploaded()[1],
            30,
            "image 1 to be stored",
        )
        assert not _staged(server, job)
    # the client hung up: image 1 stays (and is recorded), image 2's half goes
    poll_until(
        lambda: (
            http.get(f"/jobs/{job}").json()["missing_images"] == [0, 2, 3, 4, 5] and not _staged(server, job)
        ),
        30,
        "image 1 to be recorded and image 2's staging file removed",
    )
    store = JobStore.open(server.data / "jobs" / job, mode="r")
    assert store.uploaded().tolist() == [False, True, False, False, False, False]
    np.testing.assert_array_equal(store.read_array("images", 1), IMAGES[1])
    # resumed: the rest, as the status lists it
    assert _batch(http, job, 2, 4).json()["missing_images"] == [0]


def test_a_batch_of_large_images_is_staged_and_a_cut_keeps_the_whole_ones(
    server: Server, http: httpx.Client
) -> None:
    """Images above :data:`service.http.uploads.IN_MEMORY_IMAGE_BYTES` go through a staging file
    each, as a single upload's body does: stored as sent, and a body cut short keeps the whole
    images before the cut and leaves no staging file."""
    from maxfs.service.http.uploads import IN_MEMORY_IMAGE_BYTES

    k, h, w = 3, 768, 768
    nbytes = h * w * 2
    assert nbytes > IN_MEMORY_IMAGE_BYTES
    big = np.random.default_rng(11).integers(0, 65535, (k, h, w), dtype=np.uint16)
    meta = {"k": k, "height": h, "width": w, "dtype": "uint16", "eps": 2.0}
    meta["lights"] = synthetic.lights_uniform(k).tolist()
    job = http.post("/jobs", json=meta).json()["id"]
    body = big[:2].astype("<u2").tobytes()
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
        s.sendall(
            (
                f"PUT /jobs/{job}/images?first=0&count=2 HTTP/1.1\r\nHost: x\r\n"
                f"Content-Type: application/octet-stream\r\nContent-Length: {len(body)}\r\n\r\n"
            ).encode()
            + body[: nbytes + nbytes // 2]  # image 0, and half of image 1
        )
        poll_until(lambda: _staged(server, job), 30, "image 1 to be staged")
    poll_until(
        lambda: http.get(f"/jobs/{job}").json()["missing_images"] == [1, 2] and not _staged(server, job),
        30,
        "image 0 to be recorded and image 1's staging file removed",
    )
    r = http.put(
        f"/jobs/{job}/images",
        params={"first": 1, "count": 2},
        content=big[1:].astype("<u2").tobytes(),
        headers={"Content-Type": "application/octet-stream"},
    )
    assert r.status_code == 200, r.text
    assert r.json()["missing_images"] == []
    store = JobStore.open(server.data / "jobs" / job, mode="r")
    for i in range(k):
        np.testing.assert_array_equal(store.read_array("images", i), big[i])


def test_submit_batches_small_consecutive_images() -> None:
    assert upload_batches([0, 1, 2, 3, 4], 3 << 20) == [[0, 1], [2, 3], [4]]  # 8 MiB per request
    assert upload_batches([0, 1, 3, 4, 5], 1 << 20, limit=2 << 20) == [[0, 1], [3, 4], [5]]
    assert upload_batches([0, 1, 2], 5 << 20) == [[0], [1], [2]]  # larger than half a batch: alone
    assert upload_batches([], 100) == []


def test_submit_folder_sends_batches(server: Server, http: httpx.Client, tmp_path: Path) -> None:
    from maxfs.storage.datasets import write_npy_folder

    folder = write_npy_folder(tmp_path / "stack", IMAGES, LIGHTS, None)
    with MaxfsClient(server.url) as c:
        seen: list[int] = []
        job = c.submit_folder(folder, eps=2.0, on_upload=lambda sent, k: seen.append(sent))
        assert seen == [K]  # six small images: one request
        store = JobStore.open(server.data / "jobs" / job, mode="r")
        np.testing.assert_array_equal(store.read_array("images"), IMAGES)
        assert c.wait(job, poll=0.1, timeout=120)["state"] == "done"


def test_submit_sends_smaller_requests_to_a_server_that_takes_less(
    module_server_factory: Callable[..., Server], tmp_path: Path
) -> None:
    """A server whose MAXFS_MAX_UPLOAD_BYTES is below a batch (here 2 of the 6 images) answers
    413; the client halves its requests until they fit, and every image arrives as sent."""
    from maxfs.storage.datasets import write_npy_folder

    small = module_server_factory(
        tmp_path / "data", workers=1, env={"MAXFS_MAX_UPLOAD_BYTES": str(2 * NBYTES + 100)}
    )
    folder = write_npy_folder(tmp_path / "stack", IMAGES, LIGHTS, None)
    with MaxfsClient(small.url) as c:
        seen: list[int] = []
        job = c.submit_folder(folder, eps=2.0, on_upload=lambda sent, k: seen.append(sent))
        assert seen[-1] == K
        store = JobStore.open(small.data / "jobs" / job, mode="r")
        np.testing.assert_array_equal(store.read_array("images"), IMAGES)
        assert c.wait(job, poll=0.1, timeout=120)["state"] == "done"
