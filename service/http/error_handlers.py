"""Exceptions to JSON answers: every error is ``{"error": <class>, "detail": <what and how to fix>}``.

The status of each error class of :mod:`storage.errors` comes from the one table,
:data:`service.http.statuses.STATUS` (the client maps statuses back with the same table);
:func:`install_error_handlers` gives routing and validation errors the same shape.
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import JSONResponse

from maxfs.service.http.statuses import status_of
from maxfs.storage.errors import InsufficientStorageError, MaxfsError, is_disk_full


def error_response(exc: Exception) -> JSONResponse:
    """The JSON error answer ``{"error", "detail"}`` for ``exc``, with its status."""
    code = status_of(exc)
    headers = {"WWW-Authenticate": "Bearer"} if code == 401 else None
    return JSONResponse({"error": type(exc).__name__, "detail": str(exc)}, status_code=code, headers=headers)


def install_error_handlers(app: FastAPI) -> None:
    """Answer our errors by the table, and routing and validation errors in the same JSON shape."""

    @app.exception_handler(MaxfsError)
    async def maxfs_error(_: Request, exc: MaxfsError) -> JSONResponse:
        return error_response(exc)

    @app.exception_handler(OSError)
    async def os_error(_: Request, exc: OSError) -> JSONResponse:
        if not is_disk_full(exc):
            raise exc  # any other OSError is a bug: the server's 500
        return error_response(
            InsufficientStorageError(
                "the server's disk is full: what this request sent was not stored. Delete old jobs "
                "(`maxfs delete`) or ask the administrator for space, then send it again"
            )
        )

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
