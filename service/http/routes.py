"""The ``/jobs`` routes: create, list, status, upload, start, cancel or delete, and fetch results.

Every route needs ``Authorization: Bearer <token>`` unless the server runs with auth off
(:mod:`service.http.auth`); a job of another user answers 404, exactly like a job that does not
exist. Uploads go through :mod:`service.http.uploads`; results are streamed from the store
(:mod:`service.http.streams`) and say in ``X-Maxfs-Partial`` whether they are partial.
"""

from __future__ import annotations

import asyncio
import hashlib
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request, Security
from fastapi.responses import JSONResponse, Response, StreamingResponse

from maxfs.service.http import openapi as api
from maxfs.service.http.auth import make_auth, user_of
from maxfs.service.http.guards import HeldStream
from maxfs.service.http.jobs import MAX_STATUS_WAIT, TEMP_PREFIX, JobManager
from maxfs.service.http.models import PARTIAL_HEADER, CreateJob, solve_options, status_body
from maxfs.service.http.streams import job_still_there, npy_pieces, npy_size, preview_png, zip_pieces
from maxfs.service.http.uploads import Uploads
from maxfs.service.results.previews import HTTP_PREVIEWS, inputs_of
from maxfs.service.settings import Settings
from maxfs.storage.errors import ConflictError, NotFoundError, PayloadTooLargeError
from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.records import JobState
from maxfs.storage.requests import job_params
from maxfs.storage.tokens import TokenStore, User

#: The header of ``GET /jobs`` that says whose jobs these are.
USER_HEADER = "X-Maxfs-User"


def signed_in_as(user: User, auth: bool) -> str:
    """'alice', 'root (admin)', or what a server without auth says: everyone is the local user."""
    if not auth:
        return "no sign-in (auth is off)"
    return user.name + (" (admin)" if user.admin else "")


class JobRoutes:
    """Routes for jobs, built around one :class:`JobManager`."""

    def __init__(self, manager: JobManager, settings: Settings, tokens: TokenStore) -> None:
        self.m = manager
        self.s = settings
        self.uploads = Uploads(manager, settings)
        # the bearer scheme documents the auth (Swagger UI's "Authorize"); make_auth enforces it
        bearer = [Security(api.BEARER)] if settings.auth else []
        self.router = APIRouter(
            prefix="/jobs",
            tags=["jobs"],
            dependencies=[Depends(make_auth(settings, tokens)), *bearer],
            responses=api.errors(401) if settings.auth else {},
        )
        r = self.router
        # JSON answers are documented by service.http.models (tests check live bodies against them) but
        # not filtered through them: a field added to the job record reaches clients unchanged
        job, binary = api.job_answer, {"response_class": Response}  # binary: no JSON 200
        doc = {"response_model": None}  # no model inferred from the return annotation either
        r.add_api_route(
            "",
            self.create,
            methods=["POST"],
            summary="Create a job",
            status_code=201,
            **doc,
            responses=job(201) | api.errors(413, 422, 429, 507),
        )
        r.add_api_route(  # name: the operationId stays list_jobs_get
            "",
            self.list_jobs,
            methods=["GET"],
            name="list",
            summary="List jobs",
            **doc,
            responses=api.job_list_answer() | api.errors(422),
        )
        r.add_api_route(
            "/{job_id}",
            self.status,
            methods=["GET"],
            summary="Status of a job",
            **doc,
            responses=job() | api.errors(404, 422),
        )
        r.add_api_route(
            "/{job_id}",
            self.cancel,
            methods=["DELETE"],
            summary="Cancel a job",
            **doc,
            responses=job() | api.errors(404, 409, 422),
        )
        r.add_api_route(
            "/{job_id}/images/{index}",
            self.upload_image,
            methods=["PUT"],
            summary="Upload an image",
            **doc,
            responses=job() | api.errors(404, 409, 413, 422, 507),
            openapi_extra=api.IMAGE_BODY,
        )
        r.add_api_route(
            "/{job_id}/images",
            self.upload_images,
            methods=["PUT"],
            summary="Upload several images in one request",
            **doc,
            responses=job() | api.errors(404, 409, 413, 422, 507),
            openapi_extra=api.IMAGES_BODY,
        )
        r.add_api_route(
            "/{job_id}/mask",
            self.upload_mask,
            methods=["PUT"],
            summary="Upload the mask",
            **doc,
            responses=job() | api.errors(404, 409, 413, 422),
            openapi_extra=api.MASK_BODY,
        )
        r.add_api_route(
            "/{job_id}/start",
            self.start,
            methods=["POST"],
            summary="Start or resume a job",
            status_code=202,
            **doc,
            responses=job(202) | api.errors(404, 409, 422, 429),
        )
        r.add_api_route(
            "/{job_id}/results.zip",
            self.results_zip,
            methods=["GET"],
            name="zip",  # the operationId stays zip_jobs__job_id__results_zip_get
            summary="Download the results as a zip",
            **binary,
            responses=api.ZIP_ANSWER | api.errors(404, 409, 422, 429),
        )
        r.add_api_route(
            "/{job_id}/results/{name}.npy",
            self.result,
            methods=["GET"],
            summary="Download an output array (NPY)",
            **binary,
            responses=api.NPY_ANSWER | api.errors(404, 409, 413, 422, 429),
        )
        r.add_api_route(
            "/{job_id}/previews/{name}.png",
            self.preview,
            methods=["GET"],
            summary="Preview of an output (PNG)",
            **binary,
            responses=api.PNG_ANSWER | api.errors(404, 409, 422),
        )

    def _body(self, request: Request, job_id: str) -> dict[str, Any]:
        rec = self.m.access(job_id, user_of(request))
        k = self.m.spec(job_id).k
        # what was uploaded is in the record (one small file), whatever k is; a started job has all
        done = set(rec.uploaded_images)
        uploaded = k if rec.started_at is not None or rec.state.active else len(done)
        body = status_body(rec, str(request.base_url).rstrip("/"), uploaded, k)
        if rec.state.accepts_uploads:
            body["missing_images"] = [i for i in range(k) if i not in done]
        return body

    async def create(self, req: CreateJob, request: Request) -> JSONResponse:
        """Create a job (metadata only); upload images next."""
        spec = JobSpec(
            k=req.k,
            height=req.height,
            width=req.width,
            channels=None if req.channels == 1 else req.channels,
            dtype=req.dtype,
            lights=req.lights,
            intensities=req.intensities,
        ).validate()
        self.m.limits.check_size(spec)  # before the automatic tile is computed from the size
        params = job_params(spec, solve_options(req), self.s.task_memory)
        rec = self.m.create(spec, params, user_of(request), label=req.label, name=req.name)
        body = self._body(request, rec.id)
        return JSONResponse(body, status_code=201, headers={"Location": body["links"]["self"]})

    async def list_jobs(
        self,
        request: Request,
        mine: Annotated[bool, Query(description="only the caller's own jobs (for an admin too)")] = False,
    ) -> JSONResponse:
        """The caller's jobs (an admin's: everyone's, unless ``mine=true``), oldest first.
        ``X-Maxfs-User`` names who the token belongs to (the job page says who is signed in)."""
        base = str(request.base_url).rstrip("/")
        user = user_of(request)
        body = [status_body(r, base) for r in self.m.list_jobs(user, everyone=not mine)]
        return JSONResponse(body, headers={USER_HEADER: signed_in_as(user, self.s.auth)})

    async def status(
        self,
        job_id: str,
        request: Request,
        wait: Annotated[
            float,
            Query(
                ge=0,
                le=MAX_STATUS_WAIT,
                description="seconds to wait, for a queued or running job, until its status changes "
                "(progress, state) before answering; 0: answer at once",
            ),
        ] = 0,
    ) -> dict[str, Any]:
        """State, progress (tiles, pixels/s, ETA, certified share) and error reason of a job.

        With ``wait``, a queued or running job's status comes when it next changes (or after
        ``wait`` seconds): a client waiting for the end sees it the moment it comes, without
        polling often."""
        if wait > 0:
            await self.m.wait_change(job_id, user_of(request), wait)
        return self._body(request, job_id)

    async def upload_image(
        self, job_id: str, index: Annotated[int, Path(ge=0)], request: Request
    ) -> dict[str, Any]:
        """Upload image ``index``: raw little-endian bytes (application/octet-stream) or PNG/TIFF.

        Idempotent: uploading the same index again replaces it, until the job starts.
        """
        await self.uploads.image(request, job_id, index)
        return self._body(request, job_id)

    async def upload_images(
        self,
        job_id: str,
        request: Request,
        first: Annotated[int, Query(ge=0, description="index of the first image in the body")],
        count: Annotated[int, Query(ge=1, description="how many images the body holds")],
    ) -> dict[str, Any]:
        """Upload images ``first`` .. ``first + count - 1`` in one raw body, one after the other
        (application/octet-stream; PNG and TIFF files go one per request).

        For many small images, where a request per image costs more than the image. Each image
        is checked and stored as its bytes arrive, as a single upload stores it: a body cut
        short keeps the whole images before the cut (the status lists those still missing).
        """
        await self.uploads.images(request, job_id, first, count)
        return self._body(request, job_id)

    async def upload_mask(self, job_id: str, request: Request) -> dict[str, Any]:
        """Upload the object mask: PNG (non-zero = object) or raw H*W bytes."""
        await self.uploads.mask(request, job_id)
        return self._body(request, job_id)

    async def start(self, job_id: str, request: Request) -> dict[str, Any]:
        """Start, or resume a cancelled/failed job from its finished tiles."""
        await self.m.start_job(job_id, user_of(request))
        body = self._body(request, job_id)
        body["status_url"] = body["links"]["self"]
        return body

    async def cancel(self, job_id: str, request: Request, purge: bool = False) -> Any:
        """Cancel: nothing more starts and running tiles stop within seconds; start again to
        resume. With ``purge=true``: delete a job nothing runs for (created, uploading, done,
        failed, cancelled) with everything stored for it, which frees its quota slot."""
        if purge:
            rec = await self.m.delete(job_id, user_of(request))
            return JSONResponse({"id": rec.id, "state": "deleted", "owner": rec.owner})
        await self.m.cancel(job_id, user_of(request))
        return self._body(request, job_id)

    def _results_of(self, request: Request, job_id: str) -> tuple[JobStore, dict[str, str]]:
        """The store of a job that has results, and the headers that say whether they are
        partial; a job never started has none (409)."""
        rec = self.m.access(job_id, user_of(request))
        if rec.started_at is None:
            raise ConflictError(
                f"job {job_id} is {rec.state.value} and has not run yet, so it has no results; "
                "upload its images and start it"
            )
        partial = rec.state is not JobState.DONE
        headers = {PARTIAL_HEADER: "true" if partial else "false"}
        return self.m.store(job_id), headers

    async def result(
        self,
        job_id: str,
        name: Annotated[str, Path(description="output array", json_schema_extra=api.RESULT_NAME_SCHEMA)],
        request: Request,
    ) -> Response:
        """One output array as NPY (a name of ``storage.outputs.OUTPUT_NAMES``).

        While the job is not done the answer is partial (unfinished tiles hold fill values)
        and says so in the ``X-Maxfs-Partial`` header."""
        store, headers = self._results_of(request, job_id)
        names = store.output_names()
        if name not in names:  # before the store is asked: ".", "..", NUL are just unknown names
            raise NotFoundError(f"no output array {name!r}; available: {', '.join(names)}")
        meta = store.array_meta(name)
        if meta.nbytes > self.s.max_result_bytes:
            raise PayloadTooLargeError(
                f"{name} is {meta.nbytes / 2**20:.0f} MiB, more than one NPY answer may be "
                f"({self.s.max_result_bytes / 2**20:.0f} MiB); fetch results.zip (`maxfs fetch`) instead"
            )
        # streamed from the store in bands (service.http.streams): a slow reader holds one band
        return self._stream(
            request,
            npy_pieces(store, name),
            media_type="application/octet-stream",
            headers={
                "Content-Disposition": f'attachment; filename="{name}.npy"',
                "Content-Length": str(npy_size(meta)),
            }
            | headers,
        )

    def _stream(self, request: Request, pieces: Any, **kw: Any) -> HeldStream:
        """A streamed answer in one of the user's download slots (429 when all are taken)."""
        return HeldStream(
            pieces,
            slots=self.m.downloads,
            user=user_of(request).name,
            idle_timeout=self.s.download_idle_timeout,
            **kw,
        )

    async def preview(
        self,
        job_id: str,
        name: Annotated[str, Path(description="preview", json_schema_extra=api.PREVIEW_NAME_SCHEMA)],
        request: Request,
    ) -> Response:
        """PNG preview: normal (paper colouring), albedo, inlier_count; depth (shaded relief) once the
        job is done and its depth integrated."""
        if name not in HTTP_PREVIEWS:
            self.m.access(job_id, user_of(request))
            raise NotFoundError(f"no preview {name!r}; available: {', '.join(HTTP_PREVIEWS)}")
        store, headers = self._results_of(request, job_id)
        if name == "depth" and not store.has_array("depth"):
            raise NotFoundError(f"job {job_id} has no depth yet: it is integrated after the job is done")
        png = await self._preview_png(request, job_id, store, name, inputs_of(name))
        return Response(png, media_type="image/png", headers=headers)

    async def _preview_png(
        self, request: Request, job_id: str, store: JobStore, name: str, inputs: tuple[str, ...]
    ) -> bytes:
        """The preview, rendered from outputs read in row bands and decimated to at most
        ``MAXFS_PREVIEW_MAX_EDGE`` a side (:func:`service.http.streams.preview_png`), in a thread
        (as many at once as decodes), and cached in the job folder until the results change."""
        rec = self.m.access(job_id, user_of(request))
        edge = self.s.preview_max_edge
        key = f"{rec.state.value}-{rec.tiles_done}-{rec.started_at}-{rec.finished_at}-{edge}"
        tag = hashlib.sha256(key.encode()).hexdigest()[:16]
        folder = self.m.job_dir(job_id)
        cached = folder / f"{TEMP_PREFIX}preview-{name}-{tag}.png"
        if cached.exists():
            return cached.read_bytes()
        async with self.m.decoder.sem:
            if cached.exists():  # made while this request waited
                return cached.read_bytes()
            png = await asyncio.to_thread(preview_png, store, name, inputs, self.s.preview_max_edge)
            job_still_there(folder)  # deleted while it was rendered: what was read may be fill values
            for old in folder.glob(f"{TEMP_PREFIX}preview-{name}-*.png"):
                old.unlink(missing_ok=True)
            tmp = folder / f"{TEMP_PREFIX}preview-{name}-{tag}.part"
            tmp.write_bytes(png)
            tmp.replace(cached)
        return png

    async def results_zip(self, job_id: str, request: Request, inputs: bool = False) -> StreamingResponse:
        """The job folder as a zip archive: ``results.zarr`` without the input stack (with it when
        ``inputs=true``), previews and record (``X-Maxfs-Partial`` as for results)."""
        _, headers = self._results_of(request, job_id)
        store = self.m.store(job_id)
        files = await asyncio.to_thread(store.download_files, inputs)
        # made while it is sent (service.http.streams): no temporary copy on any disk, one piece in memory
        return self._stream(
            request,
            zip_pieces(files, folder=store.path),
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{job_id}.zarr.zip"'} | headers,
        )
