"""Cancel points inside a tile's solve: a running tile notices a cancel within seconds.

The solvers call :func:`checkpoint` between pixel batches (the exact kernel, see
:func:`worker.exact.exact_pixels`) and between pixels (the MILP). It does nothing
unless the calling thread runs inside :func:`cancel_points`, which installs a
check (e.g. "does the job's cancel flag exist?") called at most every
``interval`` seconds; when the check is true, :class:`TileCancelled` is raised and
unwinds the solve. The hook is per thread, so tile tasks on other threads of the
same worker process are not affected, and code that never installs one (the
library's :func:`worker.solve.solve`, tests) runs exactly as before.

Where the batches fall never changes a result: the exact kernel solves a batch
with the previous batches' points as its seeds, exactly as in one call.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from maxfs.storage.errors import JobCancelledError

#: Seconds of solver work between two cancel points of the exact kernel (batches adapt to it).
BATCH_SECONDS = 0.25

_local = threading.local()


class TileCancelled(JobCancelledError):
    """Raised at a cancel point of a tile whose job was cancelled (or ran past its time limit)."""


class _Hook:
    def __init__(
        self,
        check: Callable[[], str | None],
        interval: float,
        report: Callable[[int, int], None] | None,
        report_interval: float,
    ) -> None:
        self.check, self.interval, self.next = check, interval, 0.0
        # the first report after one interval: a tile that ends sooner writes no progress note
        self.report, self.report_interval = report, report_interval
        self.next_report = time.monotonic() + report_interval

    def __call__(self, done: int | None, total: int | None) -> None:
        now = time.monotonic()
        if self.report is not None and done is not None and total and now >= self.next_report:
            self.next_report = now + self.report_interval
            self.report(done, total)
        if now < self.next:
            return
        self.next = now + self.interval
        reason = self.check()
        if reason:
            raise TileCancelled(reason)


@contextmanager
def cancel_points(
    check: Callable[[], str | None],
    interval: float = 0.5,
    report: Callable[[int, int], None] | None = None,
    report_interval: float = 1.0,
) -> Iterator[None]:
    """Within this block, :func:`checkpoint` calls ``check()`` (at most every ``interval`` s)
    in this thread and raises :class:`TileCancelled` with its answer when it is not empty;
    ``report(done, total)`` hears how far the solve is (at most every ``report_interval`` s), so
    a long tile shows progress before it finishes."""
    before = getattr(_local, "hook", None)
    _local.hook = _Hook(check, interval, report, report_interval)
    try:
        yield
    finally:
        _local.hook = before


def active() -> bool:
    """Whether this thread has cancel points (the solvers batch their work only then)."""
    return getattr(_local, "hook", None) is not None


def checkpoint(done: int | None = None, total: int | None = None) -> None:
    """A cancel point: raise :class:`TileCancelled` if this thread's check says so; ``done`` of
    ``total`` pixels are solved so far (reported to the block's ``report``)."""
    hook = getattr(_local, "hook", None)
    if hook is not None:
        hook(done, total)
