"""A Python client for the maxfs-ps HTTP API (what ``maxfs submit/status/fetch`` use)."""

from __future__ import annotations

import io
import shutil
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from numpy.typing import NDArray

from service.statuses import error_for_status
from storage.datasets import Dataset, load_folder
from worker.errors import ConflictError, MaxfsError

FINAL_STATES = ("done", "failed", "cancelled")
#: Response header that marks partial results (the server's :data:`service.app.PARTIAL_HEADER`).
PARTIAL_HEADER = "x-maxfs-partial"
#: Bytes per piece of a streamed upload.
UPLOAD_PIECE = 1 << 20


class MaxfsClient:
    """Talks to one server. Errors come back as the server's :class:`MaxfsError` classes."""

    def __init__(self, base_url: str, token: str | None = None, timeout: float = 120.0) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> MaxfsClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, method: str, url: str, **kw: Any) -> httpx.Response:
        r = self.http.request(method, url, **kw)
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise error_for_status(r.status_code)(f"server said {r.status_code}: {detail}")
        return r

    # -- jobs -------------------------------------------------------------------------------
    def create_job(self, **meta: Any) -> dict[str, Any]:
        return self._call("POST", "/jobs", json=meta).json()

    def upload_image(self, job_id: str, index: int, image: NDArray) -> dict[str, Any]:
        """Send one image as raw little-endian bytes, in 1 MiB pieces (no copy of the image)."""
        arr = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<"))
        view = memoryview(arr.reshape(-1)).cast("B")

        def pieces() -> Iterator[bytes]:
            for o in range(0, len(view), UPLOAD_PIECE):
                yield bytes(view[o : o + UPLOAD_PIECE])

        return self._call(
            "PUT",
            f"/jobs/{job_id}/images/{index}",
            content=pieces(),
            headers={"Content-Type": "application/octet-stream", "Content-Length": str(arr.nbytes)},
        ).json()

    def upload_mask(self, job_id: str, mask: NDArray[np.bool_]) -> dict[str, Any]:
        data = np.ascontiguousarray(mask, dtype=np.uint8).tobytes()
        return self._call(
            "PUT", f"/jobs/{job_id}/mask", content=data, headers={"Content-Type": "application/octet-stream"}
        ).json()

    def start(self, job_id: str) -> dict[str, Any]:
        return self._call("POST", f"/jobs/{job_id}/start").json()

    def status(self, job_id: str) -> dict[str, Any]:
        return self._call("GET", f"/jobs/{job_id}").json()

    def jobs(self) -> list[dict[str, Any]]:
        return self._call("GET", "/jobs").json()

    def cancel(self, job_id: str) -> dict[str, Any]:
        return self._call("DELETE", f"/jobs/{job_id}").json()

    def wait(
        self,
        job_id: str,
        poll: float = 0.5,
        timeout: float | None = None,
        on_status: Callable[[dict[str, Any]], None] | None = None,
    ) -> dict[str, Any]:
        """Poll until the job is done, failed or cancelled."""
        t0 = time.monotonic()
        while True:
            st = self.status(job_id)
            if on_status:
                on_status(st)
            if st["state"] in FINAL_STATES:
                return st
            if timeout is not None and time.monotonic() - t0 > timeout:
                raise TimeoutError(f"job {job_id} still {st['state']} after {timeout} s")
            time.sleep(poll)

    def fetch_array(self, job_id: str, name: str) -> NDArray:
        r = self._call("GET", f"/jobs/{job_id}/results/{name}.npy")
        return np.load(io.BytesIO(r.content), allow_pickle=False)

    def fetch_zarr(self, job_id: str, out: Path, *, partial: bool = False) -> Path:
        """Download the job's Zarr group (zip) and unpack it at ``out``.

        A job that is not done has partial results (unfinished tiles hold fill values):
        they are refused unless ``partial`` (use :meth:`wait` first to get complete ones).
        """
        out = Path(out)
        if out.exists():
            raise ConflictError(f"{out} already exists; choose a new output path")
        if not partial:
            st = self.status(job_id)
            if st["state"] != "done":
                p = st.get("progress", {})
                raise ConflictError(
                    f"job {job_id} is {st['state']} ({p.get('tiles_done', 0)} of {p.get('tiles_total', 0)} "
                    "tiles finished), so its results are partial; wait for it (--wait) or fetch what is "
                    "finished (--partial)"
                )
        with tempfile.TemporaryFile() as tmp:
            with self.http.stream("GET", f"/jobs/{job_id}/results.zip") as r:
                if r.status_code >= 400:
                    r.read()
                    raise error_for_status(r.status_code)(f"server said {r.status_code}: {r.text}")
                if r.headers.get(PARTIAL_HEADER) == "true" and not partial:
                    raise ConflictError(f"job {job_id} was restarted while fetching; its results are partial")
                for chunk in r.iter_bytes():
                    tmp.write(chunk)
            tmp.seek(0)
            staging = Path(
                tempfile.mkdtemp(prefix=".maxfs-fetch-", dir=out.parent if out.parent.exists() else None)
            )
            try:
                with zipfile.ZipFile(tmp) as zf:
                    for name in zf.namelist():
                        if name.startswith("/") or ".." in Path(name).parts:
                            raise MaxfsError(f"refusing unsafe path {name!r} in the archive")
                    zf.extractall(staging)
                staging.rename(out)
            except BaseException:
                shutil.rmtree(staging, ignore_errors=True)
                raise
        return out

    def submit_folder(self, folder: Path | Dataset, **params: Any) -> str:
        """Create a job from a dataset folder (or an opened :class:`Dataset`, e.g. a selection of its
        images), stream its images one by one, start it.

        Only one decoded image is in memory at a time (NPY stacks are memory-mapped).
        """
        ds = folder if isinstance(folder, Dataset) else load_folder(folder)
        meta: dict[str, Any] = {
            "k": ds.k,
            "height": ds.height,
            "width": ds.width,
            "channels": ds.channels or 1,
            "dtype": ds.dtype,
            "lights": ds.lights.tolist(),
            "intensities": None if ds.intensities is None else np.asarray(ds.intensities).tolist(),
            **{k: v for k, v in params.items() if v is not None},
        }
        job = self.create_job(**meta)
        for i in range(ds.k):
            self.upload_image(job["id"], i, ds.read(i))
        if ds.mask is not None:
            self.upload_mask(job["id"], ds.mask)
        self.start(job["id"])
        return job["id"]
