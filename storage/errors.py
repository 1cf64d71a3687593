"""The one error hierarchy of maxfs-ps.

The root subclasses :class:`ValueError`; each leaf also subclasses the builtin
that matches its meaning (a "not found" error is also a :class:`LookupError`),
so callers that only know builtins still catch the right thing. ``service``
maps each class to one HTTP status.
"""

from __future__ import annotations


class MaxfsError(ValueError):
    """Root of every error raised on purpose by maxfs-ps."""


class InvalidInputError(MaxfsError):
    """Input data has the wrong shape, type, range or content."""


class DatasetError(InvalidInputError):
    """An input folder cannot be read as a photometric stereo dataset."""


class NotFoundError(MaxfsError, LookupError):
    """A job, array or file that was asked for does not exist."""


class ConflictError(MaxfsError):
    """The request does not fit the current state (e.g. starting a job twice)."""


class StoreError(MaxfsError, OSError):
    """The job store is missing, corrupt, or was written with other parameters."""


class JobCancelledError(MaxfsError):
    """A job was cancelled while it was running."""


class PayloadTooLargeError(InvalidInputError):
    """A request body is larger than allowed or than the job expects."""


class AuthError(MaxfsError):
    """The request carries no API token, or one the server does not know."""


class QuotaError(MaxfsError):
    """A per-user limit is reached (e.g. open jobs); retry when a job has finished."""


class InsufficientStorageError(MaxfsError, OSError):
    """The server's disk cannot hold what the request would store."""


class RequestTimeoutError(MaxfsError, TimeoutError):
    """A request body stopped arriving (no data for the server's idle timeout)."""


class ClientGoneError(MaxfsError, ConnectionError):
    """The client closed the connection before its request was complete."""


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` is a write refused by a full disk or an exhausted quota (not one of ours)."""
    import errno

    return (
        isinstance(exc, OSError)
        and not isinstance(exc, MaxfsError)
        and exc.errno in (errno.ENOSPC, errno.EDQUOT)
    )
