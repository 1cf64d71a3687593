"""What keeps one careless or hostile request from hurting everyone else on a shared server.

- Request bodies are read only after the token is checked, never past a size cap,
  and never waiting more than ``MAXFS_UPLOAD_IDLE_TIMEOUT`` seconds for the next piece
  (:func:`body_chunks`); a client that hangs up is one log line, not a traceback.
- Each user may have ``MAXFS_MAX_UPLOADS_PER_USER`` uploads and ``MAXFS_MAX_DOWNLOADS_PER_USER``
  streamed downloads in flight (:class:`UploadSlots`, :class:`HeldStream`); a download whose
  reader takes nothing for ``MAXFS_DOWNLOAD_IDLE_TIMEOUT`` seconds is dropped.
- Disk space is reserved before it is written (:class:`DiskBudget`): concurrent uploads
  cannot together eat into the reserve that each alone would have respected.
- Encoded images are decoded off the event loop, at most ``MAXFS_DECODE_SLOTS`` at once,
  after their header was checked (:meth:`Decoder.decode`, :func:`storage.imageio.decode_checked`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import tempfile
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from starlette.requests import ClientDisconnect, Request
from starlette.responses import StreamingResponse

from maxfs.service.http.error_handlers import error_response
from maxfs.storage.errors import (
    AuthError,
    ClientGoneError,
    InsufficientStorageError,
    InvalidInputError,
    NotFoundError,
    PayloadTooLargeError,
    QuotaError,
    RequestTimeoutError,
)
from maxfs.storage.imageio import decode_checked

log = logging.getLogger("maxfs.guards")


def media_type(request: Request, default: str = "") -> str:
    """The request's media type, lower case, without parameters (``Application/Octet-Stream;
    charset=x`` is ``application/octet-stream``)."""
    value = request.headers.get("content-type", default)
    return value.split(";", 1)[0].strip().lower()


#: Media types of raw bodies (little-endian pixels): octet-stream, none at all, and what curl
#: sends by default (``-d``/``--data-binary``); anything else is an image file to decode.
RAW_TYPES = frozenset({"", "application/octet-stream", "application/x-www-form-urlencoded"})


def is_raw(request: Request) -> bool:
    """Whether an image or mask body is raw bytes (:data:`RAW_TYPES`) rather than a PNG/TIFF file."""
    return media_type(request) in RAW_TYPES


def check_declared(request: Request, limit: int) -> None:
    """Refuse (413) a body declared larger than ``limit`` before reading any of it."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise PayloadTooLargeError(
            f"body of {declared} bytes is larger than the {limit} bytes this request allows"
        )


async def body_chunks(
    request: Request, limit: int, idle_timeout: float, min_rate: float = 0.0
) -> AsyncIterator[bytes]:
    """The body in the pieces it arrives in: 413 past ``limit`` bytes, 408 when nothing
    arrives for ``idle_timeout`` seconds or when, after those first seconds, the body has
    averaged fewer than ``min_rate`` bytes per second since it began (more than ``n`` bytes are
    due ``max(idle_timeout, n / min_rate)`` seconds after the start: a byte every few seconds is
    never idle, and would hold a connection and an upload slot for days),
    :class:`ClientGoneError` when the client hangs up."""
    check_declared(request, limit)
    stream = request.stream().__aiter__()
    loop = asyncio.get_running_loop()
    start = last = loop.time()
    n = 0
    while True:
        wait = idle_timeout
        if min_rate > 0:  # the time by which more than n bytes must have arrived
            wait = min(wait, start + max(idle_timeout, n / min_rate) - loop.time())
        try:
            # a timeout scope per piece, not wait_for's task per piece (a 2 MB body comes in
            # 30-40 pieces)
            async with asyncio.timeout(max(wait, 0.0)):
                chunk = await stream.__anext__()
        except StopAsyncIteration:
            return
        except TimeoutError:
            if loop.time() - last < 0.99 * idle_timeout:  # bytes came lately, but too few
                raise RequestTimeoutError(
                    f"the body arrives too slowly: {n} bytes in {loop.time() - start:.0f} s, less "
                    f"than {min_rate:g} bytes per second (MAXFS_UPLOAD_MIN_RATE); send it again "
                    "over a faster link"
                ) from None
            raise RequestTimeoutError(
                f"the body stopped arriving: nothing for {idle_timeout:g} s "
                f"after {n} bytes (MAXFS_UPLOAD_IDLE_TIMEOUT); send it again"
            ) from None
        except ClientDisconnect:
            raise ClientGoneError(f"the client closed the connection after {n} bytes of the body") from None
        n += len(chunk)
        last = loop.time()
        if n > limit:
            raise PayloadTooLargeError(f"body is larger than the {limit} bytes this request allows")
        yield chunk


async def read_body(request: Request, limit: int, idle_timeout: float, min_rate: float = 0.0) -> bytes:
    """A small request body, in memory (see :func:`body_chunks`)."""
    buf = bytearray()
    async for chunk in body_chunks(request, limit, idle_timeout, min_rate):
        buf += chunk
    return bytes(buf)


async def stage_body(
    request: Request,
    folder: Path,
    prefix: str,
    limit: int,
    idle_timeout: float,
    feed: Callable[[bytes], object] | None = None,
    min_rate: float = 0.0,
) -> Path:
    """Stream the body to a new file in ``folder`` whose name starts with ``prefix`` (removed
    by the caller, or as an orphan on the next start), as :func:`body_chunks` allows; each
    piece is also given to ``feed`` (e.g. a digest's ``update``) as it arrives."""
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".part", dir=folder)
    path = Path(tmp)
    try:
        with os.fdopen(fd, "wb", buffering=0) as f:  # unbuffered: what arrived is on disk
            async for chunk in body_chunks(request, limit, idle_timeout, min_rate):
                f.write(chunk)
                if feed is not None:
                    feed(chunk)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return path


class UploadSlots:
    """At most ``per_user`` request bodies (or, with ``what="downloads"``, answers) in flight
    per user (429 beyond)."""

    def __init__(
        self, per_user: int, what: str = "uploads", setting: str = "MAXFS_MAX_UPLOADS_PER_USER"
    ) -> None:
        self.per_user, self.what, self.setting = per_user, what, setting
        self.busy: dict[str, int] = {}

    def full(self, user: str) -> bool:
        """Whether ``user`` has no slot left (:meth:`take` would refuse)."""
        return self.busy.get(user, 0) >= self.per_user

    @contextmanager
    def take(self, user: str) -> Iterator[None]:
        n = self.busy.get(user, 0)
        if n >= self.per_user:
            raise QuotaError(
                f"user {user!r} already has {n} {self.what} in progress, the most allowed "
                f"({self.setting}); wait for one to finish"
            )
        self.busy[user] = n + 1
        try:
            yield
        finally:
            self.busy[user] -= 1
            if not self.busy[user]:
                del self.busy[user]


class HeldStream(StreamingResponse):
    """A streamed answer that holds one of its user's download slots until it ends, however
    it ends, and is dropped when the client reads nothing for ``idle_timeout`` seconds (a
    stalled reader would otherwise hold its slot, and a piece of the answer, for ever)."""

    def __init__(
        self, content: Any, *, slots: UploadSlots, user: str, idle_timeout: float, **kw: Any
    ) -> None:
        self.slot = slots.take(user)
        self.slot.__enter__()  # 429 here, before any answer starts
        super().__init__(content, **kw)
        self.idle_timeout = idle_timeout

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        async def timed_send(message: Any) -> None:
            try:
                await asyncio.wait_for(send(message), self.idle_timeout)
            except TimeoutError:
                raise ClientGoneError(
                    f"the client read nothing for {self.idle_timeout:g} s (MAXFS_DOWNLOAD_IDLE_TIMEOUT); "
                    "download dropped"
                ) from None

        try:
            await super().__call__(scope, receive, timed_send)
        except Exception as e:
            gone = e.exceptions if isinstance(e, BaseExceptionGroup) else (e,)
            # a reader that left, or a job deleted while its answer streamed (job_still_there):
            # expected, one log line; the answer stays incomplete and the server closes the
            # connection, so the client sees a cut download, never fill values
            if not all(isinstance(x, ClientGoneError | NotFoundError) for x in gone):
                raise
            log.info("%s %s: cut: %s", scope.get("method"), scope.get("path"), gone[0])
        finally:
            self.slot.__exit__(None, None, None)


class DiskBudget:
    """Free disk above the reserve, minus what requests in flight have reserved."""

    def __init__(self, root: Path, reserve: int) -> None:
        self.root, self.reserve = Path(root), reserve
        self.reserved = 0

    def free(self) -> int:
        return shutil.disk_usage(self.root).free

    def check(self, nbytes: int, what: str) -> None:
        """Refuse (507) to store ``nbytes`` more if that would eat into the reserve."""
        left = self.free() - self.reserved - self.reserve
        if nbytes > left:
            raise InsufficientStorageError(
                f"{what} needs up to {nbytes / 2**30:.2f} GiB but the server has "
                f"{max(left, 0) / 2**30:.2f} GiB free above its reserve; "
                "delete old jobs (`maxfs delete`) or ask the administrator for space"
            )

    @contextmanager
    def hold(self, nbytes: int, what: str) -> Iterator[None]:
        """Reserve ``nbytes`` while the block writes them (507 if they do not fit)."""
        self.check(nbytes, what)
        self.reserved += nbytes
        try:
            yield
        finally:
            self.reserved -= nbytes


class Decoder:
    """Decodes encoded images in threads, ``slots`` at a time, each bounded in size."""

    def __init__(self, slots: int) -> None:
        self.sem = asyncio.Semaphore(max(1, slots))

    async def decode(self, data: bytes, what: str, *, max_bytes: int, **expect: Any) -> NDArray[Any]:
        async with self.sem:
            return await asyncio.to_thread(decode_checked, data, what, max_bytes=max_bytes, **expect)

    async def decode_file(self, path: Path, what: str, *, max_bytes: int, **expect: Any) -> NDArray[Any]:
        async with self.sem:
            return await asyncio.to_thread(
                lambda: decode_checked(path.read_bytes(), what, max_bytes=max_bytes, **expect)
            )


def mask_of(decoded: NDArray[Any]) -> NDArray[np.bool_]:
    """An object mask from a decoded image: non-zero in any channel (NaN is not an object)."""
    m = np.nan_to_num(np.asarray(decoded), nan=0.0) != 0
    return m.any(axis=2) if m.ndim == 3 else m


class RequestGuard:
    """ASGI middleware in front of every ``/jobs`` route: the token is checked before any
    byte of the body is read, and a ``POST /jobs`` body is read here, at most
    ``MAXFS_MAX_JSON_BYTES``, with its ``k`` checked against ``MAXFS_MAX_K`` before the
    lights are validated; the app then gets the same body.

    FastAPI parses a JSON body before it runs a route's dependencies (our auth), so without
    this a request with no token could make the server parse a body of any size.
    """

    def __init__(self, app: Any, *, settings: Any, tokens: Any) -> None:
        self.app, self.settings, self.tokens = app, settings, tokens
        # job descriptions being read, per user: each holds a connection while it arrives, and
        # a busy connection is never closed to make room (service.http.connections)
        self.reading = UploadSlots(settings.max_uploads_per_user, "job descriptions arriving")

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or not (scope["path"] == "/jobs" or scope["path"].startswith("/jobs/")):
            return await self.app(scope, receive, send)
        request = Request(scope, receive)
        try:
            if self.settings.auth:
                scheme, _, token = request.headers.get("authorization", "").partition(" ")
                if scheme.lower() != "bearer" or not token.strip():
                    raise AuthError(
                        "this server needs an API token: send 'Authorization: Bearer <token>' "
                        "(an administrator makes one with `maxfs token create NAME`)"
                    )
                user = self.tokens.authenticate(token.strip())
                if user is None:
                    raise AuthError("the API token is not valid (mistyped or revoked); ask for a new one")
            if scope["method"] == "POST" and scope["path"].rstrip("/") == "/jobs":
                s = self.settings
                with self.reading.take(user.name if self.settings.auth else ""):
                    body = await read_body(
                        request, s.max_json_bytes, s.upload_idle_timeout, s.upload_min_rate
                    )
                # parsed in a thread: a large or deeply nested body must not stall other requests
                await asyncio.to_thread(_check_k, body, s.max_k)
                receive = _replay(body, receive)
        except (AuthError, InvalidInputError, RequestTimeoutError, ClientGoneError, QuotaError) as e:
            if isinstance(e, ClientGoneError):
                log.info("%s %s: %s", scope["method"], scope["path"], e)
            return await error_response(e)(scope, receive, send)
        return await self.app(scope, receive, send)


def _check_k(body: bytes, max_k: int) -> None:
    """Refuse (413) a job of more than ``max_k`` images before its lights are looked at, and
    (422) a body that is not JSON at all, with the reason: not UTF-8, malformed, nested past
    Python's recursion limit, a number of more digits than Python converts. A JSON value that
    is not a job is left to the route's own validation."""
    hint = "send a JSON object with k, height, width and lights (see /docs)"
    try:
        obj = json.loads(body)
    except RecursionError:
        raise InvalidInputError(f"the body nests too deeply to be a job; {hint}") from None
    except ValueError as e:  # also UnicodeDecodeError
        raise InvalidInputError(f"the body is not valid JSON ({e}); {hint}") from None
    k = obj.get("k") if isinstance(obj, dict) else None
    rows = obj.get("lights") if isinstance(obj, dict) else None
    n = max(
        k if isinstance(k, int) and not isinstance(k, bool) else 0, len(rows) if isinstance(rows, list) else 0
    )
    if n > max_k:
        raise PayloadTooLargeError(
            f"k={n} images is more than this server allows per job ({max_k}, MAXFS_MAX_K); "
            "split the lights into several jobs"
        )


def _replay(body: bytes, receive: Any) -> Any:
    """A ``receive`` that hands the app the body already read, then the client's events."""
    sent = False

    async def again() -> dict:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return again


class NoSniff:
    """ASGI middleware: ``X-Content-Type-Options: nosniff`` on every answer (static assets,
    JSON, NPY, zip, PNG alike), so no browser runs a body as another type than it is sent as."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_nosniff(message: dict) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                if not any(k.lower() == b"x-content-type-options" for k, _ in headers):
                    headers.append((b"x-content-type-options", b"nosniff"))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_nosniff)
