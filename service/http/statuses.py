"""The one map from error class to HTTP status, shared by the server and the client."""

from __future__ import annotations

from maxfs.storage.errors import (
    AuthError,
    ConflictError,
    InsufficientStorageError,
    InvalidInputError,
    MaxfsError,
    NotFoundError,
    PayloadTooLargeError,
    QuotaError,
    RequestTimeoutError,
    StoreError,
)

#: Exception class -> HTTP status; the first matching base class wins.
STATUS: list[tuple[type[Exception], int]] = [
    (AuthError, 401),
    (NotFoundError, 404),
    (ConflictError, 409),
    (RequestTimeoutError, 408),
    (PayloadTooLargeError, 413),
    (InvalidInputError, 422),
    (QuotaError, 429),
    (InsufficientStorageError, 507),
    (StoreError, 500),
    (MaxfsError, 400),
]


def status_of(exc: Exception) -> int:
    """The HTTP status for an exception (500 for anything not ours)."""
    return next((code for cls, code in STATUS if isinstance(exc, cls)), 500)


def error_for_status(code: int) -> type[MaxfsError]:
    """The error class a client raises for a status: the first one mapped to it."""
    return next((cls for cls, c in STATUS if c == code and issubclass(cls, MaxfsError)), MaxfsError)
