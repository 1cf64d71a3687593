"""A Python client for the maxfs-ps HTTP API (what ``maxfs submit/status/fetch`` use)."""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, as_completed, wait
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx

from maxfs.service.http.statuses import error_for_status
from maxfs.storage.errors import ConflictError, InvalidInputError, MaxfsError
from maxfs.storage.records import FINAL_STATES, JobState

if TYPE_CHECKING:
    # imported where used: the pydantic models take ~0.3 s to build, the dataset readers ~0.3 s
    # to import and numpy ~0.15 s, on every `maxfs submit`, `status` or `fetch` that starts
    # (status, wait, fetch and jobs need none of them)
    import numpy as np
    from numpy.typing import NDArray

    from maxfs.service.http.models import JobStatus
    from maxfs.storage.datasets import Dataset

#: Response header that marks partial results (the server's :data:`service.http.models.PARTIAL_HEADER`).
PARTIAL_HEADER = "x-maxfs-partial"
#: Bytes per piece of a streamed upload.
UPLOAD_PIECE = 1 << 20
#: Images up to this size go several to a request (``PUT /jobs/{id}/images``), at most this
#: many bytes per request: a request costs ~10 ms whatever its size, a small image less.
BATCH_BYTES = 8 << 20
#: Upload requests :meth:`MaxfsClient.submit_folder` has in flight at once (each server user
#: may have ``MAXFS_MAX_UPLOADS_PER_USER``, 8 by default).
UPLOADS_IN_FLIGHT = 2
#: Seconds a status request of :meth:`MaxfsClient.wait` lets the server wait for a change.
LONG_POLL = 10.0


def submission_label(ds: Dataset, meta: dict[str, Any]) -> str | None:
    """The label that makes a submit of the same files with the same parameters resumable
    (None for a dataset without files, e.g. one made in memory)."""
    fp = ds.fingerprint()
    if fp is None:
        return None
    blob = json.dumps({"files": fp, **meta}, sort_keys=True, default=str).encode()
    return "submit-" + hashlib.sha256(blob).hexdigest()[:32]


def answer_error(status: int, detail: str) -> MaxfsError:
    """The error for an answer of HTTP ``status`` (:func:`service.http.statuses.error_for_status`); its
    ``http_status`` says the status, so the CLI tells a failed server (5xx) from a refused request."""
    err = error_for_status(status)(f"server said {status}: {detail}")
    err.http_status = status  # type: ignore[attr-defined]
    return err


def run_tile(ds: Dataset, params: dict[str, Any]) -> int:
    """The tile edge ``maxfs run`` gives ``ds`` with these options under "auto" (balanced over
    its mask, :func:`storage.tiles.balanced_edge`). A server cannot balance a job's tiles (the
    mask arrives after the job, and with it the grid), so ``maxfs submit`` sends this edge:
    the same grid as a local run, and so the same results, ties included."""
    from maxfs.service.settings import Settings
    from maxfs.storage.requests import DEFAULTS, resolve_tile
    from maxfs.storage.spec import JobSpec

    spec = JobSpec.of(ds)
    solver = str(params.get("solver") or DEFAULTS["solver"])
    return resolve_tile(spec, "auto", solver, Settings().task_memory, ds.mask)


def upload_batches(missing: list[int], nbytes: int, limit: int = BATCH_BYTES) -> list[list[int]]:
    """The requests that send images ``missing`` of ``nbytes`` bytes each: runs of consecutive
    indices of at most ``limit`` bytes (an image larger than half of it goes alone)."""
    per = max(1, limit // max(nbytes, 1)) if 2 * nbytes <= limit else 1
    out: list[list[int]] = []
    for i in missing:
        if out and len(out[-1]) < per and out[-1][-1] == i - 1:
            out[-1].append(i)
        else:
            out.append([i])
    return out


#: Tries again of a request the server never served (:meth:`MaxfsClient._call`), waiting
#: ``RETRY_WAIT * 2**n`` seconds before the n-th (0.25 .. 2 s, 3.75 s in all).
RETRIES = 4
RETRY_WAIT = 0.25


def _never_served(r: httpx.Response) -> bool:
    """Whether a 503 came from the server's connection limits rather than from a route: uvicorn's
    plain-text answer at the connection cap, or the per-address cap's ``TooManyConnections``."""
    if not r.headers.get("content-type", "").startswith("application/json"):
        return True
    try:
        return r.json().get("error") == "TooManyConnections"
    except ValueError:
        return False


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

    def _call(
        self, method: str, url: str, *, body: Callable[[], Any] | None = None, **kw: Any
    ) -> httpx.Response:
        """One request; ``body()`` makes its content afresh for each try. A request the server
        never let reach the app (its connection cap's 503, or a connection it closed before an
        answer to make room for others) is tried again after a short wait, up to
        :data:`RETRIES` times: nothing of it was done, so even a POST is safe to repeat."""
        for attempt in range(RETRIES + 1):
            if body is not None:
                kw["content"] = body()
            try:
                r = self.http.request(method, url, **kw)
            except (httpx.RemoteProtocolError, httpx.ReadError, httpx.ConnectError):
                if attempt == RETRIES:
                    raise
                time.sleep(RETRY_WAIT * 2**attempt)
                continue
            if r.status_code == 503 and _never_served(r) and attempt < RETRIES:
                time.sleep(RETRY_WAIT * 2**attempt)
                continue
            break
        if r.status_code >= 400:
            from pydantic import ValidationError

            from maxfs.service.http.models import ErrorBody

            try:  # every error the server makes is an ErrorBody; a proxy's may not be
                detail = ErrorBody.model_validate_json(r.content).detail
            except ValidationError:
                detail = r.text
            raise answer_error(r.status_code, detail)
        return r

    # -- jobs -------------------------------------------------------------------------------
    def create_job(self, **meta: Any) -> dict[str, Any]:
        return self._call("POST", "/jobs", json=meta).json()

    def upload_image(self, job_id: str, index: int, image: NDArray) -> dict[str, Any]:
        """Send one image as raw little-endian bytes, in 1 MiB pieces (no copy of the image)."""
        import numpy as np

        arr = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<"))
        view = memoryview(arr.reshape(-1)).cast("B")

        def pieces() -> Iterator[bytes]:
            for o in range(0, len(view), UPLOAD_PIECE):
                yield bytes(view[o : o + UPLOAD_PIECE])

        return self._call(
            "PUT",
            f"/jobs/{job_id}/images/{index}",
            body=pieces,
            headers={"Content-Type": "application/octet-stream", "Content-Length": str(arr.nbytes)},
        ).json()

    def upload_images(self, job_id: str, first: int, images: list[NDArray]) -> dict[str, Any]:
        """Send images ``first, first + 1, ...`` (of one shape and dtype) in one request, as raw
        little-endian bytes one after the other. A server older than the batch upload answers
        404 or 405 (:meth:`submit_folder` then sends them one by one)."""
        import numpy as np

        arrs = [np.ascontiguousarray(im, dtype=im.dtype.newbyteorder("<")) for im in images]
        return self._call(
            "PUT",
            f"/jobs/{job_id}/images",
            params={"first": first, "count": len(arrs)},
            body=lambda: (a.tobytes() for a in arrs),
            headers={
                "Content-Type": "application/octet-stream",
                "Content-Length": str(sum(a.nbytes for a in arrs)),
            },
        ).json()

    def upload_mask(self, job_id: str, mask: NDArray[np.bool_]) -> dict[str, Any]:
        import numpy as np

        data = np.ascontiguousarray(mask, dtype=np.uint8).tobytes()
        return self._call(
            "PUT", f"/jobs/{job_id}/mask", content=data, headers={"Content-Type": "application/octet-stream"}
        ).json()

    def start(self, job_id: str) -> dict[str, Any]:
        return self._call("POST", f"/jobs/{job_id}/start").json()

    def status(self, job_id: str, wait: float = 0) -> dict[str, Any]:
        """The job's status; with ``wait`` (seconds), a queued or running job's answer comes when
        its status next changes, or after ``wait`` seconds (a server older than that answers
        at once)."""
        params = {"wait": f"{wait:g}"} if wait > 0 else None
        return self._call("GET", f"/jobs/{job_id}", params=params).json()

    def job(self, job_id: str) -> JobStatus:
        """The job's status checked against, and typed as, the model the server documents
        (:meth:`status` gives the body as a dict)."""
        from maxfs.service.http.models import JobStatus

        return JobStatus.model_validate(self.status(job_id))

    def jobs(self, mine: bool = False) -> list[dict[str, Any]]:
        """The jobs this token may see (an admin's: everyone's), or with ``mine`` only its own."""
        return self._call("GET", "/jobs", params={"mine": "true"} if mine else None).json()

    def job_list(self) -> list[JobStatus]:
        """The jobs this token may see, oldest first, as typed models (:meth:`jobs`: as dicts)."""
        from maxfs.service.http.models import JobStatus

        return [JobStatus.model_validate(st) for st in self.jobs()]

    def cancel(self, job_id: str) -> dict[str, Any]:
        return self._call("DELETE", f"/jobs/{job_id}").json()

    def delete(self, job_id: str) -> dict[str, Any]:
        """Delete a job nothing runs for (cancel a queued or running one first), with its data."""
        return self._call("DELETE", f"/jobs/{job_id}", params={"purge": "true"}).json()

    def wait(
        self,
        job_id: str,
        poll: float = 0.5,
        timeout: float | None = None,
        on_status: Callable[[dict[str, Any]], None] | None = None,
    ) -> dict[str, Any]:
        """Until the job is done, failed or cancelled: its status, each change of it as the
        server sees it (``GET /jobs/{id}?wait=S``: the end is seen the moment it comes), at
        most one request per ``poll`` seconds (a server without ``wait`` answers at once, and
        is then asked every ``poll`` seconds)."""
        t0 = time.monotonic()
        while True:
            asked = time.monotonic()
            long = LONG_POLL if timeout is None else max(0.0, min(LONG_POLL, t0 + timeout - asked))
            st = self.status(job_id, wait=long)
            if on_status:
                on_status(st)
            if st["state"] in FINAL_STATES:
                return st
            if timeout is not None and time.monotonic() - t0 > timeout:
                raise TimeoutError(f"job {job_id} still {st['state']} after {timeout} s")
            time.sleep(max(0.0, poll - (time.monotonic() - asked)))

    def fetch_array(self, job_id: str, name: str) -> NDArray:
        import numpy as np

        r = self._call("GET", f"/jobs/{job_id}/results/{name}.npy")
        return np.load(io.BytesIO(r.content), allow_pickle=False)

    def fetch_zarr(
        self, job_id: str, out: Path, *, partial: bool = False, inputs: bool = False, overwrite: bool = False
    ) -> Path:
        """Download the job's results (a zip) and unpack them as the job folder ``out``
        (``out/results.zarr``, previews, record; the input stack only if ``inputs``).

        A job that is not done has partial results (unfinished tiles hold fill values):
        they are refused unless ``partial`` (use :meth:`wait` first to get complete ones).
        An existing ``out`` is replaced only with ``overwrite``, and only if it holds maxfs results
        (or nothing): the old folder goes once the new one is complete.
        """
        out = Path(out)
        if out.exists():
            from maxfs.storage.spec import is_job_folder  # here: it loads numpy, which a fetch need not

            if not overwrite:
                raise ConflictError(
                    f"{out} already exists; choose a new output folder, or add --overwrite to replace it"
                )
            if not out.is_dir() or (any(out.iterdir()) and not is_job_folder(out)):
                raise ConflictError(f"{out} holds something other than maxfs results; it is not replaced")
        if not partial:
            st = self.status(job_id)
            if st["state"] != JobState.DONE:
                p = st.get("progress", {})
                raise ConflictError(
                    f"job {job_id} is {st['state']} ({p.get('tiles_done', 0)} of {p.get('tiles_total', 0)} "
                    "tiles finished), so its results are partial; wait for it (--wait) or fetch what is "
                    "finished (--partial)"
                )
        with tempfile.TemporaryFile() as tmp:
            url = f"/jobs/{job_id}/results.zip" + ("?inputs=true" if inputs else "")
            with self.http.stream("GET", url) as r:
                if r.status_code >= 400:
                    r.read()
                    raise answer_error(r.status_code, r.text)
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
                if out.exists():  # --overwrite: the old results go only now that the new ones are here
                    old = staging.with_name(staging.name + "-old")
                    out.rename(old)
                    staging.rename(out)
                    shutil.rmtree(old, ignore_errors=True)
                else:
                    staging.rename(out)
            except BaseException:
                shutil.rmtree(staging, ignore_errors=True)
                raise
        return out

    def submit_folder(
        self,
        folder: Path | Dataset,
        *,
        name: str | None = None,
        existing: str = "new",
        on_upload: Callable[[int, int], None] | None = None,
        **params: Any,
    ) -> str:
        """Create a job from a dataset folder (or an opened :class:`Dataset`, e.g. a selection of its
        images), stream its images one by one, start it. ``name`` (default: the folder's name) is
        how the job is shown; ``on_upload(sent, k)`` is called after each request.

        Small images go several to a request (consecutive indices, at most :data:`BATCH_BYTES`
        per request, :func:`upload_batches`; one by one to a server without the batch upload),
        larger ones one per request, two requests in flight at once (:data:`UPLOADS_IN_FLIGHT`),
        each decoded on its own thread. At most two requests' decoded images are in memory at a
        time, those being sent (NPY stacks are read one image at a time).

        **Resumable**: the job is labelled with a digest of the folder's files (paths, sizes,
        times), the selection and the parameters. If this user already has an unfinished job with
        that label (a submit cut short), it is continued: only its missing images are sent, then
        it is started; one that is already queued or running is just returned. Two submits of one
        folder at once both return the job that runs, whichever of them started it.

        A *finished* job with that label (the same inputs and parameters, done) is, by ``existing``:
        ``"new"`` ignored (a new job), ``"reuse"`` returned, ``"refuse"`` a :class:`ConflictError`
        naming it (``maxfs submit`` without ``--reuse``: no silent re-upload and recompute).
        """
        import numpy as np

        from maxfs.storage.datasets import Dataset
        from maxfs.storage.inputs import load_folder

        if existing not in ("new", "reuse", "refuse"):
            raise ValueError(f"existing must be new, reuse or refuse, got {existing!r}")
        ds = folder if isinstance(folder, Dataset) else load_folder(folder)
        chosen = params.get("tile") in (None, "auto") and ds.mask is not None
        if chosen:
            params = {**params, "tile": run_tile(ds, params)}
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
        label = submission_label(ds, meta)
        # only this user's own jobs: an admin's list holds everyone's, and a job of another user
        # with the same label (the same folder) is not this submit's
        jobs = self.jobs(mine=True) if label is not None else []
        found = next((j for j in jobs if j.get("label") == label and j["state"] not in FINAL_STATES), None)
        done = next(
            (j for j in reversed(jobs) if j.get("label") == label and j["state"] == JobState.DONE), None
        )
        if found is None and done is not None and existing != "new":
            if existing == "reuse":
                return done["id"]
            raise ConflictError(
                f"job {done['id']} ({done.get('name') or 'unnamed'}) already has results for these inputs "
                f"and parameters; use it (--reuse, or `maxfs fetch {done['id']} -o FOLDER`), or delete it "
                "to compute again"
            )
        if found is not None and found["state"] in (JobState.QUEUED, JobState.RUNNING):
            return found["id"]
        if found is None:
            try:
                job_id = self.create_job(**meta, label=label, name=name or ds.name)["id"]
            except InvalidInputError as e:
                if not chosen or "tile" not in str(e):
                    raise
                # this server's task budget or tile limit is smaller: let it choose the edge
                job_id = self.create_job(**(meta | {"tile": "auto"}), label=label, name=name or ds.name)["id"]
            missing: list[int] = list(range(ds.k))
        else:
            job_id = found["id"]
            missing = list(self.status(job_id).get("missing_images", range(ds.k)))
        try:
            sent = ds.k - len(missing)
            itemsize = np.dtype(ds.dtype).itemsize
            batches = upload_batches(missing, ds.height * ds.width * (ds.channels or 1) * itemsize)
            batched = [True]  # until a server without the batch upload says otherwise
            most = [len(max(batches, key=len, default=[]))]  # images per request this server takes

            def put(batch: list[int], images: list[NDArray]) -> None:
                if len(batch) > most[0]:  # a smaller request size learnt from an earlier 413
                    put(batch[: most[0]], images[: most[0]])
                    put(batch[most[0] :], images[most[0] :])
                    return
                if len(batch) > 1 and batched[0]:
                    try:
                        self.upload_images(job_id, batch[0], images)
                        return
                    except MaxfsError as e:
                        status = getattr(e, "http_status", None)
                        if status == 413:  # this server's MAXFS_MAX_UPLOAD_BYTES is smaller: halves
                            most[0] = min(most[0], max(1, len(batch) // 2))
                            put(batch, images)
                            return
                        if status not in (404, 405):
                            raise
                        batched[0] = False  # an older server (nothing stored): one request per image
                for i, image in zip(batch, images, strict=True):
                    self.upload_image(job_id, i, image)

            def send(batch: list[int]) -> int:
                """Decode a request's images (decoders release the GIL) and send them."""
                put(batch, [ds.read(i) for i in batch])
                return len(batch)

            # UPLOADS_IN_FLIGHT requests at once, each decoded on its own thread: the server
            # stores one request's images while the next arrives, and the client decodes one
            # while it sends the other
            with ThreadPoolExecutor(UPLOADS_IN_FLIGHT, thread_name_prefix="maxfs-upload") as pool:
                pending: set[Future[int]] = set()
                todo = iter(batches)
                try:
                    for batch in todo:
                        pending.add(pool.submit(send, batch))
                        if len(pending) < UPLOADS_IN_FLIGHT:
                            continue
                        finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                        for f in finished:
                            sent += f.result()
                            if on_upload:
                                on_upload(sent, ds.k)
                    for f in as_completed(pending):
                        pending.discard(f)
                        sent += f.result()
                        if on_upload:
                            on_upload(sent, ds.k)
                finally:
                    for f in pending:  # after an error: nothing more starts; those in flight end
                        f.cancel()
            if ds.mask is not None:
                self.upload_mask(job_id, ds.mask)
            self.start(job_id)
        except ConflictError:
            # another submit of the same folder finished the uploads and started it first
            if self.status(job_id)["state"] not in (JobState.CREATED, JobState.UPLOADING):
                return job_id  # whatever it ends as, it is this submit's job too (wait reports it)
            raise
        return job_id
