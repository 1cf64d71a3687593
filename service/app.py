"""The HTTP API (FastAPI). Build it with :func:`create_app`; serve it with uvicorn.

Every error is JSON ``{"error": <class>, "detail": <what is wrong and how to fix it>}``
with the status from :data:`service.statuses.STATUS` (one map from exception class to code).

Every ``/jobs`` route needs ``Authorization: Bearer <token>`` unless the server
runs with auth off; a job of another user answers 404, exactly like a job that
does not exist. Image uploads are checked (owner, state, index, declared size,
disk space) before the body is read, streamed to a staging file in the job
folder, validated whole, then written to the store one shard band at a time: the
server holds one band of one image per request, whatever k is, and a rejected
upload leaves the store as it was.
"""

from __future__ import annotations

import asyncio
import hashlib
from collections.abc import Iterator
from contextlib import asynccontextmanager
from pathlib import Path as FsPath
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, FastAPI, Path, Request, Security
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from service import openapi as api
from service.dashboard import check_dashboard
from service.docs import install_docs
from service.guards import RequestGuard, check_declared, mask_of, media_type, read_body, stage_body
from service.jobs import TEMP_PREFIX, JobManager
from service.models import Health
from service.page import install_page
from service.previews import HTTP_PREVIEWS, inputs_of
from service.settings import Settings
from service.statuses import status_of
from service.streams import npy_pieces, npy_size, preview_png, zip_pieces
from storage.errors import (
    AuthError,
    ConflictError,
    InvalidInputError,
    MaxfsError,
    NotFoundError,
    PayloadTooLargeError,
)
from storage.layout import JobSpec, JobStore
from storage.params import JobParams
from storage.records import JobRecord, JobState
from storage.tokens import LOCAL_USER, TokenStore, User

#: Header on result answers: "true" while the job is not done (unfinished tiles hold fill values).
PARTIAL_HEADER = "X-Maxfs-Partial"


class CreateJob(BaseModel):
    """A new job: the stack's shape, the lights, and the solver parameters.

    Only types are checked here; values are checked by the one validator the library
    and the CLI use too (:meth:`JobSpec.validate`, :func:`worker.problem.check_options`).
    Unknown fields are refused, so a misspelt option is never silently ignored.
    """

    model_config = ConfigDict(extra="forbid")

    k: int = Field(description="number of images (at least 3)")
    height: int = Field(description="image height in pixels")
    width: int = Field(description="image width in pixels")
    channels: Literal[1, 3] = Field(1, description="1 = grey, 3 = RGB")
    dtype: Literal["uint8", "uint16", "float32"] = "uint8"
    lights: list[list[float]] = Field(description="k unit light directions (x right, y up, z toward camera)")
    intensities: list[float] | list[list[float]] | None = Field(
        None, description="light intensities: k values, or k x channels"
    )
    eps: float | Literal["auto"] = "auto"
    solver: Literal["exact", "milp", "l2"] = "exact"
    tile: int | Literal["auto"] = Field(
        "auto", description="tile edge in pixels (8-4096), or auto: from k and the server's task memory"
    )
    shadow: float | None = Field(None, description="intensities <= this are shadows (default: eps)")
    saturation: float | None = Field(None, description="float input only: values >= this are saturated")
    box_factor: float = Field(10.0, description="box on n as a multiple of the brightest value (>= 1)")
    max_nodes: int = Field(200_000, description="exact solver's node budget per pixel (1 to 1e9)")
    milp_time_limit: float = Field(30.0, description="MILP seconds per pixel (0 to 3600)")
    label: str | None = Field(
        None,
        max_length=200,
        description="your name for the submission; `maxfs submit` finds an unfinished job by it to resume",
    )
    model: Literal["robust", "paper"] = Field(
        "robust", description="robust (default) or paper (Yu, Seo, Lee 2010 as published); see worker.problem"
    )
    response: float | Literal["auto"] | None = Field(
        None, description="g of I = (L.n)^g, or auto (default of robust; paper: 1)"
    )
    eps_rel: float | None = Field(None, description="tolerance eps + eps_rel * I (default 0)")
    drop_bright: float | None = Field(
        None, description="share of each pixel's brightest candidates that are outliers (robust: 0.3)"
    )
    dequantize: bool | None = Field(None, description="integer input: read v > 0 as v + 0.5 (robust: true)")
    fallback: bool | None = Field(
        None, description="least squares where Max-FS gives no normal (robust: true)"
    )


def status_body(
    rec: JobRecord, base: str, uploaded: int | None = None, k: int | None = None
) -> dict[str, Any]:
    body = rec.to_json()
    body.pop("uploaded_images", None)  # the indices; "uploaded" (count) and "missing_images" say it
    frac = rec.tiles_done / rec.tiles_total if rec.tiles_total else 0.0
    remaining = max(rec.pixels_total - rec.pixels_done, 0)
    eta = remaining / rec.pixel_rate if rec.pixel_rate and rec.state.active else None
    body["progress"] = {
        "fraction": frac,
        "tiles_done": rec.tiles_done,
        "tiles_total": rec.tiles_total,
        "pixels_done": rec.pixels_done,
        "pixels_total": rec.pixels_total,
        "pixels_per_second": rec.pixel_rate,
        "eta_seconds": eta,
        "solved_share": rec.solved_share,
        "certified_share": rec.certified_share,
    }
    body["warnings"] = rec.warnings()
    # results are complete only when done; before the first start there are none at all
    body["results"] = {"available": rec.started_at is not None, "partial": rec.state is not JobState.DONE}
    if uploaded is not None:
        body["uploaded"] = uploaded
        body["k"] = k
    body["links"] = {
        "self": f"{base}/jobs/{rec.id}",
        "start": f"{base}/jobs/{rec.id}/start",
        "zip": f"{base}/jobs/{rec.id}/results.zip",
    }
    return body


def raw_bands(path: FsPath, spec: JobSpec, rows: int) -> Iterator[np.ndarray]:
    """Bands of ``rows`` rows of a raw little-endian image file."""
    wire = np.dtype(spec.dtype).newbyteorder("<")
    row_shape = spec.image_shape[1:]
    per_row = int(np.prod(row_shape))
    with open(path, "rb") as f:
        for y in range(0, spec.height, rows):
            n = min(rows, spec.height - y)
            band = np.fromfile(f, dtype=wire, count=n * per_row).reshape(n, *row_shape)
            yield band.astype(spec.dtype, copy=False)


def make_auth(settings: Settings, tokens: TokenStore):
    """The dependency that puts the request's :class:`User` in ``request.state.user``."""

    async def authenticate(request: Request) -> None:
        if not settings.auth:
            request.state.user = LOCAL_USER
            return
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            raise AuthError(
                "this server needs an API token: send 'Authorization: Bearer <token>' "
                "(an administrator makes one with `maxfs token create NAME`)"
            )
        user = tokens.authenticate(token.strip())
        if user is None:
            raise AuthError("the API token is not valid (mistyped or revoked); ask for a new one")
        request.state.user = user

    return authenticate


def _user(request: Request) -> User:
    return request.state.user


class JobRoutes:
    """Routes for jobs, built around one :class:`JobManager`."""

    def __init__(self, manager: JobManager, settings: Settings, tokens: TokenStore) -> None:
        self.m = manager
        self.s = settings
        # the bearer scheme documents the auth (Swagger UI's "Authorize"); make_auth enforces it
        bearer = [Security(api.BEARER)] if settings.auth else []
        self.router = APIRouter(
            prefix="/jobs",
            tags=["jobs"],
            dependencies=[Depends(make_auth(settings, tokens)), *bearer],
            responses=api.errors(401) if settings.auth else {},
        )
        r = self.router
        # JSON answers are documented by service.models (tests check live bodies against them) but
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
        r.add_api_route(
            "", self.list, methods=["GET"], summary="List jobs", **doc, responses=api.job_list_answer()
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
            self.zip,
            methods=["GET"],
            summary="Download the results as a zip",
            **binary,
            responses=api.ZIP_ANSWER | api.errors(404, 409, 422),
        )
        r.add_api_route(
            "/{job_id}/results/{name}.npy",
            self.result,
            methods=["GET"],
            summary="Download an output array (NPY)",
            **binary,
            responses=api.NPY_ANSWER | api.errors(404, 409, 413, 422),
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
        rec = self.m.access(job_id, _user(request))
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
        params = JobParams.build(
            eps=req.eps,
            solver=req.solver,
            tile=self.m.resolve_tile(spec, req.tile, req.solver),
            shadow=req.shadow,
            saturation=req.saturation,
            box_factor=req.box_factor,
            max_nodes=req.max_nodes,
            milp_time_limit=req.milp_time_limit,
            model=req.model,
            response=req.response,
            eps_rel=req.eps_rel,
            drop_bright=req.drop_bright,
            dequantize=req.dequantize,
            fallback=req.fallback,
        )
        rec = self.m.create(spec, params, _user(request), label=req.label)
        body = self._body(request, rec.id)
        return JSONResponse(body, status_code=201, headers={"Location": body["links"]["self"]})

    async def list(self, request: Request) -> list[dict[str, Any]]:
        """All jobs, oldest first."""
        base = str(request.base_url).rstrip("/")
        return [status_body(r, base) for r in self.m.list(_user(request))]

    async def status(self, job_id: str, request: Request) -> dict[str, Any]:
        """State, progress (tiles, pixels/s, ETA, certified share) and error reason of a job."""
        return self._body(request, job_id)

    def _before_upload(self, request: Request, job_id: str, what: str) -> JobStore:
        """Owner and state checks that need no body, so a doomed upload is refused unread."""
        rec = self.m.access(job_id, _user(request))
        if not rec.state.accepts_uploads:
            raise ConflictError(f"job {job_id} is {rec.state.value}; {what} only before start")
        return self.m.store(job_id)

    async def upload_image(
        self, job_id: str, index: Annotated[int, Path(ge=0)], request: Request
    ) -> dict[str, Any]:
        """Upload image ``index``: raw little-endian bytes (application/octet-stream) or PNG/TIFF.

        Idempotent: uploading the same index again replaces it, until the job starts.
        """
        store = self._before_upload(request, job_id, "images can be uploaded")
        spec = store.spec
        store.check_index(index)
        raw = media_type(request, "application/octet-stream") == "application/octet-stream"
        limit = spec.image_nbytes if raw else min(self.s.max_upload_bytes, 2 * spec.image_nbytes + (1 << 20))
        check_declared(request, limit)
        user, s = _user(request), self.s
        # the staged body (at most its declared length) and the stored image are reserved
        # before a byte is written
        declared = request.headers.get("content-length", "")
        staged = min(limit, int(declared)) if declared.isdigit() else limit
        with self.m.uploads.take(user.name), self.m.disk.hold(spec.image_nbytes + staged, f"image {index}"):
            part = await stage_body(
                request, self.m.job_dir(job_id), f"{TEMP_PREFIX}upload-{index}-", limit, s.upload_idle_timeout
            )
            try:
                size = part.stat().st_size
                if raw:
                    if size != spec.image_nbytes:
                        raise InvalidInputError(
                            f"image {index}: got {size} bytes, expected {spec.image_nbytes} "
                            f"({' x '.join(map(str, spec.image_shape))} {spec.dtype}, little-endian, "
                            "row-major)"
                        )

                    def write(st: JobStore) -> None:
                        st.write_bands(index, raw_bands(part, spec, st.band_rows))

                else:  # header checked before any pixel is decoded; decoded in a thread
                    img = await self.m.decoder.decode_file(
                        part,
                        f"image {index}",
                        max_bytes=2 * spec.image_nbytes + (1 << 20),
                        shape=spec.image_shape,
                        dtype=spec.dtype,
                    )

                    def write(st: JobStore) -> None:
                        st.write_image(index, img)

                await self.m.upload_image(job_id, index, write)
            finally:
                part.unlink(missing_ok=True)
        return self._body(request, job_id)

    async def upload_mask(self, job_id: str, request: Request) -> dict[str, Any]:
        """Upload the object mask: PNG (non-zero = object) or raw H*W bytes."""
        spec = self._before_upload(request, job_id, "the mask can be set").spec
        HW = spec.height * spec.width
        with self.m.uploads.take(_user(request).name), self.m.disk.hold(2 * HW, "the mask"):
            data = await read_body(request, 2 * HW + (1 << 20), self.s.upload_idle_timeout)
            if media_type(request) == "application/octet-stream":
                if len(data) != HW:
                    raise InvalidInputError(f"mask: got {len(data)} bytes, expected {HW}")
                mask = np.frombuffer(data, dtype=np.uint8).reshape(spec.height, spec.width) > 0
            else:  # header checked first (a small file cannot declare a huge mask); decoded in a thread
                m = await self.m.decoder.decode(
                    data, "mask", max_bytes=4 * 4 * HW + (1 << 20), hw=(spec.height, spec.width)
                )
                mask = mask_of(m)
            del data
            await self.m.upload_mask(job_id, mask)
        return self._body(request, job_id)

    async def start(self, job_id: str, request: Request) -> dict[str, Any]:
        """Start, or resume a cancelled/failed job from its finished tiles."""
        await self.m.start_job(job_id, _user(request))
        body = self._body(request, job_id)
        body["status_url"] = body["links"]["self"]
        return body

    async def cancel(self, job_id: str, request: Request, purge: bool = False) -> Any:
        """Cancel: nothing more starts and running tiles stop within seconds; start again to
        resume. With ``purge=true``: delete a job nothing runs for (created, uploading, done,
        failed, cancelled) with everything stored for it, which frees its quota slot."""
        if purge:
            rec = await self.m.delete(job_id, _user(request))
            return JSONResponse({"id": rec.id, "state": "deleted", "owner": rec.owner})
        await self.m.cancel(job_id, _user(request))
        return self._body(request, job_id)

    def _results_of(self, request: Request, job_id: str) -> tuple[JobStore, dict[str, str]]:
        """The store of a job that has results, and the headers that say whether they are
        partial; a job never started has none (409)."""
        rec = self.m.access(job_id, _user(request))
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
        """One output array as NPY (normal, albedo, albedo_rgb, inliers, inlier_count, optimal, mask).

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
        # streamed from the store in bands (service.streams): a slow reader holds one band
        return StreamingResponse(
            npy_pieces(store, name),
            media_type="application/octet-stream",
            headers={
                "Content-Disposition": f'attachment; filename="{name}.npy"',
                "Content-Length": str(npy_size(meta)),
            }
            | headers,
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
            self.m.access(job_id, _user(request))
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
        ``MAXFS_PREVIEW_MAX_EDGE`` a side (:func:`service.streams.preview_png`), in a thread
        (as many at once as decodes), and cached in the job folder until the results change."""
        rec = self.m.access(job_id, _user(request))
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
            for old in folder.glob(f"{TEMP_PREFIX}preview-{name}-*.png"):
                old.unlink(missing_ok=True)
            tmp = folder / f"{TEMP_PREFIX}preview-{name}-{tag}.part"
            tmp.write_bytes(png)
            tmp.replace(cached)
        return png

    async def zip(self, job_id: str, request: Request, inputs: bool = False) -> StreamingResponse:
        """The job folder as a zip archive: ``results.zarr`` without the input stack (with it when
        ``inputs=true``), previews and record (``X-Maxfs-Partial`` as for results)."""
        _, headers = self._results_of(request, job_id)
        store = self.m.store(job_id)
        files = await asyncio.to_thread(store.download_files, inputs)
        # made while it is sent (service.streams): no temporary copy on any disk, one piece in memory
        return StreamingResponse(
            zip_pieces(files),
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{job_id}.zarr.zip"'} | headers,
        )


def _error_response(exc: Exception) -> JSONResponse:
    code = status_of(exc)
    headers = {"WWW-Authenticate": "Bearer"} if code == 401 else None
    return JSONResponse({"error": type(exc).__name__, "detail": str(exc)}, status_code=code, headers=headers)


def create_app(settings: Settings | None = None, manager: JobManager | None = None) -> FastAPI:
    """Build the application; the manager (and its Dask client) starts in the lifespan."""
    settings = settings or Settings()
    check_dashboard(settings)  # loopback only; warns when bokeh (the [dashboard] extra) is missing
    manager = manager or JobManager(settings)
    tokens = TokenStore(settings.tokens_file)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        await manager.start()
        try:
            yield
        finally:
            await manager.close()

    app = FastAPI(
        title="maxfs-ps",
        version="0.1.0",
        description="Robust photometric stereo by exact maximum feasible Lambertian subsystems.",
        lifespan=lifespan,
        docs_url=None,  # served with local assets by install_docs: no CDN
        redoc_url=None,
    )
    app.state.manager = manager
    app.include_router(JobRoutes(manager, settings, tokens).router)
    # the token before any body is read; JSON bodies capped (service.guards)
    app.add_middleware(RequestGuard, settings=settings, tokens=tokens)
    install_docs(app)
    install_page(app)

    @app.get("/health", tags=["service"], response_model=Health)
    async def health() -> dict[str, Any]:
        """Liveness, without a token; says nothing about anyone's jobs."""
        return {"status": "ok", "auth": settings.auth}

    @app.exception_handler(MaxfsError)
    async def maxfs_error(_: Request, exc: MaxfsError) -> JSONResponse:
        return _error_response(exc)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        # routing errors (no such path or method) get the same JSON shape as ours
        if exc.status_code == 404:
            body = {"error": "NotFoundError", "detail": "no job or route here; see /docs for the API"}
        else:
            body = {"error": "HTTPError", "detail": str(exc.detail)}
        return JSONResponse(body, status_code=exc.status_code)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'][1:]) or 'body'}: {e['msg']}" for e in exc.errors()
        )
        return JSONResponse({"error": "InvalidInputError", "detail": problems}, status_code=422)

    return app
