"""Careless and hostile requests at the edges of the HTTP API, against a real ``maxfs serve``.

Each case was seen to misbehave (a 500, a 400 without a reason, an honest upload refused, a
download completed with fill values after its job was deleted); each must now get the right
answer with a JSON body that says why, and leave nothing stored behind.
"""

from __future__ import annotations

import io
import socket
from collections.abc import Callable

import httpx
import imagecodecs
import numpy as np
import pytest
from PIL import Image

from maxfs.service.cli.client import MaxfsClient
from maxfs.worker import synthetic
from tests.procs import Server, poll_until

LIGHTS = synthetic.lights_uniform(6)


@pytest.fixture(scope="module")
def server(module_server_factory: Callable[..., Server], tmp_path_factory: pytest.TempPathFactory) -> Server:
    return module_server_factory(tmp_path_factory.mktemp("edges"), workers=1)


@pytest.fixture
def http(server: Server):
    with httpx.Client(base_url=server.url, timeout=60) as h:
        yield h


def _create(http: httpx.Client, size: int = 64, **params) -> str:
    body = {"k": 6, "height": size, "width": size, "dtype": "uint8", "lights": LIGHTS.tolist(), "eps": 2.0}
    r = http.post("/jobs", json=body | params)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _jobs_on_disk(server: Server) -> list[str]:
    jobs = server.data / "jobs"
    return sorted(p.name for p in jobs.iterdir()) if jobs.exists() else []


def _raw_post(server: Server, body: bytes) -> tuple[int, bytes]:
    """POST /jobs with ``body`` as it is (no client-side JSON), the answer's status and body."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as s:
        head = (
            f"POST /jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
        ).encode()
        s.sendall(head + body)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    status = int(data.split(b" ", 2)[1])
    return status, data.split(b"\r\n\r\n", 1)[1]


@pytest.mark.parametrize(
    ("name", "body", "reason"),
    [
        ("nested-open", b"[" * 100_000, "nests too deeply"),
        ("nested-closed", b"[" * 5000 + b"]" * 5000, "nests too deeply"),
        ("bad-utf8", b'{"k": "\xff\xfe"}', "not valid JSON"),
        ("huge-integer", b'{"k": ' + b"9" * 5000 + b"}", "not valid JSON"),
        ("truncated", b'{"k": 6, "lights": [[0, 0', "not valid JSON"),
        ("empty", b"", "not valid JSON"),
    ],
)
def test_bodies_that_are_not_json_get_422_with_the_reason(
    server: Server, name: str, body: bytes, reason: str
):
    before = (
        sorted(p.name for p in (server.data / "jobs").iterdir()) if (server.data / "jobs").exists() else []
    )
    status, answer = _raw_post(server, body)
    assert status == 422, (name, status, answer[:200])
    assert reason in answer.decode(), answer[:300]
    assert b"Traceback" not in answer
    after = (
        sorted(p.name for p in (server.data / "jobs").iterdir()) if (server.data / "jobs").exists() else []
    )
    assert after == before
    assert httpx.get(f"{server.url}/health", timeout=5).status_code == 200


def _encoded(fmt: str, a: np.ndarray) -> bytes:
    if fmt == "PNG":
        return imagecodecs.png_encode(a)
    b = io.BytesIO()
    Image.fromarray(a).save(b, format=fmt)
    return b.getvalue()


@pytest.mark.parametrize(
    ("fmt", "ctype"), [("PNG", "image/png"), ("BMP", "image/bmp"), ("JPEG", "image/jpeg")]
)
def test_honest_image_files_are_taken(http: httpx.Client, fmt: str, ctype: str) -> None:
    size = 768  # 0.6 MP grey: its decoded size was over-estimated 4x (16x for BMP) and refused
    jid = _create(http, size=size)
    img = (np.random.default_rng(0).random((size, size)) * 200).astype(np.uint8)
    r = http.put(f"/jobs/{jid}/images/0", content=_encoded(fmt, img), headers={"Content-Type": ctype})
    assert r.status_code == 200, r.text
    assert http.get(f"/jobs/{jid}").json()["uploaded"] == 1


@pytest.mark.parametrize("ctype", [None, "application/x-www-form-urlencoded", "Application/Octet-Stream"])
def test_raw_masks_and_images_need_no_exact_content_type(http: httpx.Client, ctype: str | None) -> None:
    jid = _create(http, size=32)
    headers = {} if ctype is None else {"Content-Type": ctype}
    mask = np.zeros((32, 32), np.uint8)
    mask[8:24, 8:24] = 1
    r = http.put(f"/jobs/{jid}/mask", content=mask.tobytes(), headers=headers)
    assert r.status_code == 200, r.text
    img = np.full((32, 32), 50, np.uint8)
    assert http.put(f"/jobs/{jid}/images/0", content=img.tobytes(), headers=headers).status_code == 200
    # a PNG sent as raw bytes is refused with a hint, and no decoder object's repr
    r = http.put(f"/jobs/{jid}/mask", content=imagecodecs.png_encode(mask), headers=headers)
    assert r.status_code == 422 and "Content-Type: image/png" in r.json()["detail"], r.text
    r = http.put(f"/jobs/{jid}/mask", content=b"not an image", headers={"Content-Type": "image/png"})
    assert r.status_code == 422 and " at 0x" not in r.json()["detail"], r.text


@pytest.mark.parametrize(
    ("params", "reason"),
    [
        ({"eps": 1e308}, "eps = 1e+308 is above the brightest value"),
        ({"shadow": 1e9}, "shadow = 1e+09 is above the brightest value"),
        ({"eps_rel": 1e308}, "eps_rel must be between 0 and 1"),
        ({"intensities": [1e-300] * 6}, "light intensities must be between"),
        ({"intensities": [1e308] * 6}, "light intensities must be between"),
        ({"eps": True}, "a number, not true or false"),
        ({"height": True}, "a number, not true or false"),
        ({"max_nodes": True}, "a number, not true or false"),
        ({"dequantize": 0}, "true or false"),
        ({"lights": [[0, 0, True]] * 6}, "a number, not true or false"),
    ],
)
def test_values_that_cannot_mean_anything_are_refused(http: httpx.Client, params: dict, reason: str) -> None:
    body = {"k": 6, "height": 32, "width": 32, "dtype": "uint8", "lights": LIGHTS.tolist()} | params
    r = http.post("/jobs", json=body)
    assert r.status_code == 422 and reason in r.json()["detail"], r.text


def test_an_upload_whose_job_is_deleted_meanwhile_answers_404(server: Server, http: httpx.Client) -> None:
    jid = _create(http, size=256)
    img = np.full((256, 256), 7, np.uint8).tobytes()
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as s:
        s.sendall(
            (
                f"PUT /jobs/{jid}/images/0 HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n"
                f"Content-Length: {len(img)}\r\nConnection: close\r\n\r\n"
            ).encode()
            + img[: len(img) // 2]
        )
        poll_until(
            lambda: any(p.name.startswith(".maxfs-upload") for p in (server.data / "jobs" / jid).iterdir()),
            30,
            "the upload to be staged",
        )
        assert http.delete(f"/jobs/{jid}", params={"purge": "true"}).status_code == 200
        s.sendall(img[len(img) // 2 :])
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    assert data.split(b" ", 2)[1] == b"404", data[:300]
    assert b"NotFoundError" in data and b"Traceback" not in data
    assert http.get(f"/jobs/{jid}").status_code == 404


@pytest.mark.parametrize("what", ["results/normal.npy", "results.zip?inputs=true"])
def test_a_download_whose_job_is_deleted_meanwhile_is_cut(
    server: Server, http: httpx.Client, what: str
) -> None:
    """Never a complete-looking answer: Zarr reads a deleted chunk as fill values and the zip
    skipped files that had gone, so both answers must stop instead."""
    c = MaxfsClient(server.url)
    size = 1536  # normals 27 MB, images 14 MB (noise: Zarr cannot compress it): several 4 MiB pieces
    rng = np.random.default_rng(3)
    jid = _create(http, size=size, solver="l2")
    for i in range(6):
        c.upload_image(jid, i, rng.integers(1, 250, (size, size), dtype=np.uint8))
    mask = np.zeros((size, size), np.uint8)
    mask[760:776, 760:776] = 1  # a small object: the job is quick, its arrays are full size
    assert http.put(f"/jobs/{jid}/mask", content=mask.tobytes()).status_code == 200
    assert http.post(f"/jobs/{jid}/start").status_code == 202
    poll_until(
        lambda: http.get(f"/jobs/{jid}").json()["state"], 120, "the job to finish", 0.2, lambda s: s == "done"
    )
    got = 0
    logged = server.log.stat().st_size
    with pytest.raises(httpx.HTTPError), http.stream("GET", f"/jobs/{jid}/{what}") as r:
        assert r.status_code == 200
        for piece in r.iter_raw(1 << 16):
            if not got:
                assert http.delete(f"/jobs/{jid}", params={"purge": "true"}).status_code == 200
            got += len(piece)
    assert got > 0
    # an expected end, told in one line: no traceback for the operator to chase
    with server.log.open("rb") as f:
        f.seek(logged)
        tail = f.read().decode(errors="replace")
    assert "was deleted while its answer was being made" in tail and "Traceback" not in tail, tail[-2000:]


def test_starting_a_job_cancelled_before_its_uploads_says_what_to_do(http: httpx.Client) -> None:
    jid = _create(http, size=32)
    assert http.delete(f"/jobs/{jid}").json()["state"] == "cancelled"
    r = http.post(f"/jobs/{jid}/start")
    assert r.status_code == 409 and "purge=true" in r.json()["detail"], r.text


def _trickled(chunk: bytes, every: float, count: int):
    """A starlette Request whose body arrives as ``count`` pieces ``chunk``, one every ``every`` s."""
    import asyncio

    from starlette.requests import Request

    sent = 0

    async def receive() -> dict:
        nonlocal sent
        await asyncio.sleep(every)
        sent += 1
        return {"type": "http.request", "body": chunk, "more_body": sent < count}

    scope = {"type": "http", "method": "PUT", "path": "/", "headers": [], "query_string": b""}
    return Request(scope, receive)


@pytest.mark.parametrize(
    ("chunk", "too_slow"),
    [(b"x" * 10, True), (b"x" * 200, False)],  # 33 and 667 bytes per second against a minimum of 100
    ids=["a trickle is cut", "a steady body arrives"],
)
def test_a_body_must_average_the_minimum_rate_once_the_idle_timeout_has_passed(
    chunk: bytes, too_slow: bool
) -> None:
    """Never idle for 0.5 s, yet 33 bytes per second: 408 once 0.5 s + n / 100 s have passed;
    667 bytes per second arrives whole."""
    import asyncio

    from maxfs.service.http.guards import body_chunks
    from maxfs.storage.errors import RequestTimeoutError

    async def read() -> int:
        n = 0
        async for piece in body_chunks(_trickled(chunk, 0.3, 12), 1 << 20, 0.5, min_rate=100.0):
            n += len(piece)
        return n

    if too_slow:
        with pytest.raises(RequestTimeoutError, match=r"too slowly.*MAXFS_UPLOAD_MIN_RATE"):
            asyncio.run(read())
    else:
        assert asyncio.run(read()) == 12 * len(chunk)
