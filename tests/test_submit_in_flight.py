"""``maxfs submit`` has two upload requests in flight (:data:`service.cli.client.UPLOADS_IN_FLIGHT`),
against a fake server: every image is sent once, batches go two at a time, and an older server
without the batch upload gets single images."""

from __future__ import annotations

import threading
from pathlib import Path

import httpx
import numpy as np
import pytest

from maxfs.service.cli import client as client_mod
from maxfs.service.cli.client import MaxfsClient
from maxfs.worker import synthetic


class FakeUploads:
    """A server that takes a submit's uploads: the batch upload, or (``batches=False``, an older
    server) single images only. Each batch request waits, up to 30 s, for a second one to be in
    flight with it, so a client that sends one at a time fails here instead of passing slowly."""

    def __init__(self, batches: bool = True) -> None:
        self.batches = batches
        self.lock = threading.Lock()
        self.images: list[int] = []  # every image stored, in the order stored
        self.together = threading.Barrier(2)
        self.paired = 0

    def handler(self, request: httpx.Request) -> httpx.Response:
        path, method = request.url.path, request.method
        if method == "GET" and path == "/jobs":
            return httpx.Response(200, json=[])
        if method == "POST" and path == "/jobs":
            return httpx.Response(201, json={"id": "f" * 32, "state": "created"})
        if method == "PUT" and path.endswith("/images"):
            if not self.batches:
                return httpx.Response(405, json={"error": "method_not_allowed", "detail": "no"})
            first, count = int(request.url.params["first"]), int(request.url.params["count"])
            try:
                self.together.wait(30)
                with self.lock:
                    self.paired += 1
            except threading.BrokenBarrierError:
                pass  # the last request of an odd count has no partner
            with self.lock:
                self.images += range(first, first + count)
            return httpx.Response(200, json={"state": "uploading"})
        if method == "PUT" and "/images/" in path:
            with self.lock:
                self.images.append(int(path.rsplit("/", 1)[1]))
            return httpx.Response(200, json={"state": "uploading"})
        if method == "POST" and path.endswith("/start"):
            return httpx.Response(202, json={"state": "queued"})
        return httpx.Response(404, json={"error": "not_found", "detail": path})


@pytest.mark.parametrize("batches", [True, False], ids=["batch-upload", "older-server"])
def test_a_submit_has_two_uploads_in_flight_and_sends_every_image_once(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, batches: bool
) -> None:
    from maxfs.storage.datasets import write_npy_folder

    k = 12
    images = np.random.default_rng(3).integers(0, 65535, (k, 16, 16), dtype=np.uint16)
    folder = write_npy_folder(tmp_path / "stack", images, synthetic.lights_uniform(k), None)
    three = client_mod.upload_batches
    monkeypatch.setattr(client_mod, "upload_batches", lambda m, n: three(m, n, limit=3 * n))
    fake = FakeUploads(batches)
    if not batches:
        fake.together.abort()
    c = MaxfsClient("http://fake")
    c.http = httpx.Client(base_url="http://fake", transport=httpx.MockTransport(fake.handler))
    seen: list[int] = []
    c.submit_folder(folder, eps=2.0, on_upload=lambda sent, n: seen.append(sent))
    assert sorted(fake.images) == list(range(k))  # each once
    assert seen == sorted(seen) and seen[-1] == k and len(seen) == 4  # one call per request (of 3)
    if batches:
        assert fake.paired == 4  # every batch had another in flight with it
