"""Real local processes for the tests and the benchmarks: a Dask scheduler, Dask workers and
``maxfs serve``, and the one polling helper they wait with.

Everything binds to 127.0.0.1 on free ports. The caller kills what it starts (the tests'
fixtures in ``tests/conftest.py`` do it at teardown, whatever the test did). Neither
``tests/`` nor ``bench/`` is imported from here; both import this module.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import httpx
from distributed import Client

from maxfs.storage.tokens import TokenStore

BIN = Path(sys.executable).parent
T = TypeVar("T")


def poll_until(
    check: Callable[[], T],
    timeout: float,
    what: str,
    interval: float = 0.1,
    until: Callable[[T], bool] = bool,
) -> T:
    """Call ``check`` every ``interval`` s until ``until(value)`` holds, and return that value.

    After ``timeout`` s it raises :class:`AssertionError` naming ``what`` and the last value
    ``check`` returned: a wait never gives up silently. An exception from ``check`` goes
    up at once (so ``check`` can stop the wait early, e.g. when a process it waits on died).
    """
    t0 = time.monotonic()
    while True:
        value = check()
        if until(value):
            return value
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for: {what} (last value: {value!r})")
        time.sleep(interval)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(args: list[str], log: Path, env: dict[str, str] | None = None) -> subprocess.Popen:
    fh = open(log, "ab")
    return subprocess.Popen(
        args, stdout=fh, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})}, start_new_session=True
    )


def _signal_group(p: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(p.pid, sig)
    except ProcessLookupError:
        pass


def _stop(p: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    """Signal ``p``'s process group and reap it; what a SIGTERM leaves after 30 s is SIGKILLed."""
    if p.poll() is None:
        _signal_group(p, sig)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            _signal_group(p, signal.SIGKILL)
            p.wait(timeout=30)


class DaskCluster:
    """``dask scheduler`` plus ``n`` single-threaded ``dask worker`` processes (no nanny)."""

    def __init__(self, logs: Path, n_workers: int = 2, port: int | None = None) -> None:
        self.port = port or free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.logs = logs
        self.scheduler = _spawn(
            [
                str(BIN / "dask"),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--no-dashboard",
            ],
            logs / "scheduler.log",
        )
        self.workers: list[subprocess.Popen] = []
        try:
            for i in range(n_workers):
                self.add_worker(i)
            with Client(self.address, timeout=60) as c:
                if n_workers:  # none: a scheduler alone, its workers added later
                    c.wait_for_workers(n_workers, timeout=120)
        except BaseException:  # nothing is left running when the cluster does not come up
            self.close()
            raise

    def add_worker(self, i: int) -> subprocess.Popen:
        w = _spawn(
            [
                str(BIN / "dask"),
                "worker",
                self.address,
                "--nthreads",
                "1",
                "--no-nanny",
                "--no-dashboard",
                "--host",
                "127.0.0.1",
                "--name",
                f"w{i}-{time.monotonic_ns()}",
            ],
            self.logs / f"worker{i}.log",
        )
        self.workers.append(w)
        return w

    def wait_idle(self, timeout: float = 120) -> None:
        """Until no task is processing anywhere (in-flight tiles finished)."""
        with Client(self.address, timeout=30) as c:
            busy = lambda: {w: keys for w, keys in c.processing().items() if keys}  # noqa: E731
            poll_until(busy, timeout, "no task processing on any worker", until=lambda b: not b)

    def close(self) -> None:
        for w in self.workers:
            _stop(w)
        _stop(self.scheduler)


class Server:
    """``maxfs serve`` (uvicorn) on a free loopback port."""

    def __init__(
        self,
        data_dir: Path,
        scheduler: str,
        logs: Path,
        port: int | None = None,
        workers: int = 1,
        auth: bool = False,
        env: dict[str, str] | None = None,
        bin_dir: Path = BIN,
    ) -> None:
        """``scheduler=""`` starts the server's embedded cluster with ``workers`` processes;
        ``env`` sets more ``MAXFS_*`` settings; ``bin_dir`` holds the ``maxfs`` to run (another
        checkout's, for a benchmark's before and after)."""
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.data = Path(data_dir)
        self.log = logs / "server.log"
        extra = ["--scheduler", scheduler] if scheduler else ["--workers", str(workers)]
        if not auth:
            extra.append("--no-auth")
        self.proc = _spawn(
            [str(bin_dir / "maxfs"), "serve", "--port", str(self.port), "--data-dir", str(data_dir), *extra],
            self.log,
            env={"MAXFS_PROGRESS_INTERVAL": "0.1", **(env or {})},
        )
        try:
            poll_until(
                self._health,
                120,
                f"{self.url}/health to answer 200 (see {self.log})",
                0.2,
                lambda v: v == 200,
            )
        except BaseException:  # nothing is left running when the server does not come up
            self.kill()
            raise

    def _health(self) -> int | str:
        """``/health``'s status code, or why there is none; raises once the server process is gone."""
        if self.proc.poll() is not None:
            raise AssertionError(f"maxfs serve exited with {self.proc.returncode}; see {self.log}")
        try:
            return httpx.get(f"{self.url}/health", timeout=2).status_code
        except httpx.HTTPError as e:
            return f"{type(e).__name__}: {e}"

    def token(self, name: str, admin: bool = False) -> str:
        """A new API token for ``name`` (the server reads the token file when it changes)."""
        return TokenStore(self.data / "maxfs-tokens.json").create(name, admin=admin)

    def kill(self) -> None:
        _stop(self.proc, signal.SIGKILL)

    def stop(self) -> None:
        _stop(self.proc, signal.SIGTERM)
