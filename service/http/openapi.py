"""What the routes declare for OpenAPI beyond their models: the bearer scheme, error answers, request
bodies the routes read themselves, binary answers with their media types, and enums of names."""

from __future__ import annotations

from typing import Any

from fastapi.security import HTTPBearer

from maxfs.service.http.models import ErrorBody, JobStatus
from maxfs.service.results.previews import HTTP_PREVIEWS
from maxfs.storage.outputs import OUTPUT_NAMES

#: The security scheme of every ``/jobs`` route (Swagger UI's "Authorize" button). It only documents
#: and never refuses (``auto_error=False``): :func:`service.http.auth.make_auth` checks the token.
BEARER = HTTPBearer(
    scheme_name="bearer",
    description="an API token from `maxfs token create NAME`, sent as `Authorization: Bearer <token>`",
    auto_error=False,
)

_ERRORS = {
    401: "no token, an unknown or revoked one, or not a Bearer token",
    404: "no such job (or another user's job), image index, array or preview",
    409: "the job is in the wrong state for this (e.g. results before the first start, upload after it)",
    413: "body, k or image larger than the server allows",
    422: "invalid input: a bad field, option, image, mask or light set (the detail says which)",
    429: "a per-user limit: unfinished jobs (MAXFS_MAX_OPEN_JOBS), uploads or downloads in flight",
    507: "storing this would eat into the server's free-disk reserve (MAXFS_MIN_FREE_BYTES)",
}


def job_answer(status: int = 200) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entry of a route that answers a job's status."""
    return {status: {"model": JobStatus, "description": "the job's status after the request"}}


def job_list_answer() -> dict[int | str, dict[str, Any]]:
    return {200: {"model": list[JobStatus], "description": "the jobs this token may see, oldest first"}}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entries for these error statuses, all with the :class:`ErrorBody` shape."""
    return {code: {"model": ErrorBody, "description": _ERRORS[code]} for code in codes}


def binary(media_types: dict[str, str], description: str) -> dict[int | str, dict[str, Any]]:
    """A ``200`` answer with a binary body in each of ``media_types`` (type -> what it is)."""
    return {
        200: {
            "description": description,
            "content": {
                t: {"schema": {"type": "string", "format": "binary", "description": what}}
                for t, what in media_types.items()
            },
            "headers": {
                "X-Maxfs-Partial": {
                    "description": "true while the job is not done: unfinished tiles hold fill values",
                    "schema": {"type": "string", "enum": ["true", "false"]},
                }
            },
        }
    }


def upload_body(media_types: dict[str, str]) -> dict[str, Any]:
    """``openapi_extra=`` for a route that reads its body itself: the body's content types."""
    return {
        "requestBody": {
            "required": True,
            "content": {
                t: {"schema": {"type": "string", "format": "binary", "description": what}}
                for t, what in media_types.items()
            },
        }
    }


IMAGE_BODY = upload_body(
    {
        "application/octet-stream": "raw little-endian pixels, row-major, (H, W[, C]) of the job's dtype",
        "image/png": "8- or 16-bit PNG of the job's shape",
        "image/tiff": "TIFF of the job's shape and dtype",
    }
)
IMAGES_BODY = upload_body(
    {
        "application/octet-stream": "images first..first+count-1 as raw little-endian pixels, row-major, "
        "(H, W[, C]) of the job's dtype each, one after the other",
    }
)
MASK_BODY = upload_body(
    {"application/octet-stream": "raw H*W bytes, non-zero = object", "image/png": "PNG, non-zero = object"}
)
NPY_ANSWER = binary({"application/octet-stream": "NPY (numpy.save format)"}, "the array as an NPY file")
PNG_ANSWER = binary({"image/png": "8-bit PNG"}, "the preview")
ZIP_ANSWER = binary(
    {"application/zip": "results.zarr, previews and record"}, "the job folder as a zip archive"
)

#: Path parameters whose values are a fixed set: documented as enums, while an unknown name still
#: answers 404 with the list of names (not a validation error).
RESULT_NAME_SCHEMA = {"enum": list(OUTPUT_NAMES)}
PREVIEW_NAME_SCHEMA = {"enum": list(HTTP_PREVIEWS)}
