"""Real processes for tests: a Dask scheduler, Dask workers and the maxfs server.

Everything binds to 127.0.0.1 on free ports; every process is killed at teardown.
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

import httpx
from distributed import Client

from storage.tokens import TokenStore

BIN = Path(sys.executable).parent


def poll_until(check: Callable[[], bool], timeout: float, what: str, interval: float = 0.1) -> None:
    """Call ``check`` until it is true; fail loudly (never silently give up) after ``timeout`` s."""
    t0 = time.monotonic()
    while not check():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for: {what}")
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


def _stop(p: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass
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
        for i in range(n_workers):
            self.add_worker(i)
        with Client(self.address, timeout=60) as c:
            c.wait_for_workers(n_workers, timeout=120)

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
            t0 = time.monotonic()
            while any(c.processing().values()):
                if time.monotonic() - t0 > timeout:
                    raise TimeoutError("workers still busy")
                time.sleep(0.1)

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
    ) -> None:
        """``scheduler=""`` starts the server's embedded cluster with ``workers`` processes;
        ``env`` sets more ``MAXFS_*`` settings."""
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.data = Path(data_dir)
        extra = ["--scheduler", scheduler] if scheduler else ["--workers", str(workers)]
        if not auth:
            extra.append("--no-auth")
        self.proc = _spawn(
            [str(BIN / "maxfs"), "serve", "--port", str(self.port), "--data-dir", str(data_dir), *extra],
            logs / "server.log",
            env={"MAXFS_PROGRESS_INTERVAL": "0.1", **(env or {})},
        )
        t0 = time.monotonic()
        while True:
            try:
                if httpx.get(f"{self.url}/health", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            if self.proc.poll() is not None or time.monotonic() - t0 > 120:
                raise RuntimeError(f"server did not start; see {logs / 'server.log'}")
            time.sleep(0.2)

    def token(self, name: str, admin: bool = False) -> str:
        """A new API token for ``name`` (the server reads the token file when it changes)."""
        return TokenStore(self.data / "maxfs-tokens.json").create(name, admin=admin)

    def kill(self) -> None:
        _stop(self.proc, signal.SIGKILL)

    def stop(self) -> None:
        _stop(self.proc, signal.SIGTERM)
