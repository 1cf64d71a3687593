"""Real processes for tests, and who kills them: :class:`Procs` starts a Dask cluster, a
``maxfs serve`` or an in-process uvicorn and kills every one of them at :meth:`Procs.close`,
which the fixtures in ``tests/conftest.py`` call at teardown however the test ended.

The process classes and :func:`poll_until` live in :mod:`tests.harness` (the benchmarks
use them too, and ``bench/`` must not import ``tests/``); they are re-exported here.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import uvicorn

from tests.harness import BIN, DaskCluster, Server, free_port, poll_until

__all__ = ["BIN", "DaskCluster", "InProcessServer", "Procs", "Server", "free_port", "poll_until"]


#: every Procs not closed yet, oldest first
LIVE: list[Procs] = []


def log_tails(lines: int = 40) -> list[tuple[str, str]]:
    """``(path, last lines)`` of every log file of what live :class:`Procs` started, for the
    report of a failing test (on CI, the files go with the machine)."""
    out = []
    for p in LIVE:
        for f in dict.fromkeys(p.logs):
            try:
                text = f.read_text(errors="replace").splitlines()[-lines:]
            except OSError:
                continue
            out.append((str(f), "\n".join(text)))
    return out


class InProcessServer:
    """The app under a real uvicorn in a thread of this process (so ``tracemalloc`` sees it)."""

    def __init__(self, app: Any) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.uvicorn = uvicorn.Server(
            uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning")
        )
        self.thread = threading.Thread(target=self.uvicorn.run, daemon=True)
        self.thread.start()

        def started() -> bool:
            assert self.thread.is_alive(), "the in-process server's thread ended before it started"
            return self.uvicorn.started

        try:
            poll_until(started, 120, f"in-process uvicorn on {self.url} to start")
        except BaseException:
            self.kill()
            raise

    def kill(self) -> None:
        self.uvicorn.should_exit = True
        self.thread.join(timeout=60)


class Procs:
    """What one test (or one module) started; :meth:`close` kills it all, newest first."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = Path(tmp)
        self._started: list[Callable[[], None]] = []  # how to stop each, oldest first
        #: the log files of what was started (their tails go into a failing test's report)
        self.logs: list[Path] = []
        LIVE.append(self)

    def cluster(self, n_workers: int = 2, port: int | None = None, logs: Path | None = None) -> DaskCluster:
        """``dask scheduler`` and ``n_workers`` single-threaded workers on loopback."""
        c = DaskCluster(logs or self.tmp, n_workers=n_workers, port=port)
        self._started.append(c.close)
        self.logs += [c.logs / "scheduler.log", *(c.logs / f"worker{i}.log" for i in range(n_workers))]
        return c

    def server(
        self,
        data_dir: Path | None = None,
        scheduler: str = "",
        logs: Path | None = None,
        graceful: bool = False,
        **kw: Any,
    ) -> Server:
        """``maxfs serve`` on a free port (keywords as :class:`tests.harness.Server`); data in
        ``data_dir`` (default ``TMP/data``), its log in ``logs`` (default ``TMP``). At close it is
        SIGKILLed, or with ``graceful`` stopped by SIGTERM (so it closes its cluster; SIGKILL
        after 30 s)."""
        s = Server(data_dir or self.tmp / "data", scheduler, logs or self.tmp, **kw)
        self._started.append(s.stop if graceful else s.kill)
        self.logs.append(s.log)
        return s

    def inprocess(self, app: Any) -> InProcessServer:
        s = InProcessServer(app)
        self._started.append(s.kill)
        return s

    def close(self) -> None:
        if self in LIVE:
            LIVE.remove(self)
        errors: list[BaseException] = []
        while self._started:
            stop = self._started.pop()
            try:
                stop()
            except BaseException as e:  # kill the rest anyway
                errors.append(e)
        if errors:
            raise errors[0]
