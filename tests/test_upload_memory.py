"""Uploads stream: the server's memory per image upload does not grow with k and
stays under the size of one image, and the stored bytes equal the files sent.

The server is a real uvicorn in a thread of this process, so ``tracemalloc`` sees
its allocations; the client streams each image from a file on disk, so it adds
only its 64 KiB read buffer. numpy and zarr buffers are traced too.
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import httpx
import numpy as np
import pytest

from maxfs.service.http.app import create_app
from maxfs.service.settings import Settings
from maxfs.storage.layout import JobStore
from maxfs.worker import synthetic
from tests.procs import Procs

H, W = 1024, 1024
TILE = 64  # one shard band = 64 rows = 1/16 of an image


@pytest.fixture(scope="module")
def server(module_procs: Procs, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """The app under uvicorn in this process (stopped at the module's teardown)."""
    data = tmp_path_factory.mktemp("mem") / "data"
    srv = module_procs.inprocess(create_app(Settings(data_dir=data, workers=1, auth=False)))
    return srv.url, data


def _upload_peaks(url: str, data: Path, k: int, folder: Path) -> tuple[list[int], str]:
    """Upload k random 16-bit images from files; return the traced peak of each request."""
    rng = np.random.default_rng(k)
    lights = synthetic.lights_uniform(k).tolist()
    meta = {"k": k, "height": H, "width": W, "dtype": "uint16", "lights": lights, "eps": 5.0, "tile": TILE}
    peaks = []
    with httpx.Client(base_url=url, timeout=120) as http:
        job = http.post("/jobs", json=meta).json()["id"]
        folder.mkdir()
        for i in range(k):
            f = folder / f"{i}.raw"
            f.write_bytes(rng.integers(0, 65535, (H, W), dtype=np.uint16).astype("<u2").tobytes())
            tracemalloc.reset_peak()
            base = tracemalloc.get_traced_memory()[0]
            with open(f, "rb") as fh:
                r = http.put(
                    f"/jobs/{job}/images/{i}",
                    content=fh,
                    headers={"Content-Type": "application/octet-stream"},
                )
            assert r.status_code == 200, r.text
            peaks.append(tracemalloc.get_traced_memory()[1] - base)
    store = JobStore.open(data / "jobs" / job, mode="r")
    assert store.uploaded().all()
    for i in range(k):
        stored = store.read_array("images", i)
        assert stored.astype("<u2").tobytes() == (folder / f"{i}.raw").read_bytes(), f"image {i} differs"
    return peaks, job


def test_upload_memory_does_not_grow_with_k(server: tuple[str, Path], tmp_path: Path) -> None:
    url, data = server
    image_bytes = H * W * 2
    tracemalloc.start()
    try:
        small, _ = _upload_peaks(url, data, 4, tmp_path / "k4")
        large, _ = _upload_peaks(url, data, 12, tmp_path / "k12")
    finally:
        tracemalloc.stop()
    # the first request of a job warms caches; compare the steady state
    small_peak, large_peak = max(small[1:]), max(large[1:])
    assert large_peak <= 1.25 * small_peak + (64 << 10), (small_peak, large_peak)
    # a few shard bands (zarr's encode buffers) plus fixed overhead: less than the one image
    assert large_peak < image_bytes, f"an upload held {large_peak} bytes of a {image_bytes}-byte image"
