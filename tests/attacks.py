"""Hostile clients shared by the tests and ``bench.load --hostile`` (real sockets on loopback)."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from maxfs.service.cli.client import MaxfsClient
from maxfs.worker import synthetic


@contextmanager
def slow_connections(
    addr: tuple[str, int], n: int, sources: list[str], period: float
) -> Iterator[list[socket.socket]]:
    """``n`` connections to ``addr`` from the ``sources`` addresses in turn: the even ones send a
    partial request head and then one more header line every ``period`` seconds, the odd ones
    nothing. A connection the server refuses at once is left out. All are closed on exit."""
    socks: list[socket.socket] = []
    for i in range(n):
        try:
            s = socket.create_connection(addr, timeout=10, source_address=(sources[i % len(sources)], 0))
        except OSError:
            continue
        if i % 2 == 0:
            try:
                s.sendall(b"GET /jobs HTTP/1.1\r\nHost: x\r\n")
            except OSError:
                pass
        socks.append(s)
    stop = threading.Event()

    def drip() -> None:
        k = 0
        while not stop.wait(period):
            k += 1
            for s in socks[::2]:
                try:
                    s.sendall(f"X-Slow-{k}: y\r\n".encode())
                except OSError:
                    pass

    t = threading.Thread(target=drip, daemon=True)
    t.start()
    try:
        yield socks
    finally:
        stop.set()
        t.join(timeout=10)
        for s in socks:
            s.close()


def proc_kb(pid: int, key: str) -> int:
    """A ``/proc/PID/status`` memory figure in kB (``VmRSS``, ``VmHWM``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def finished_patch_job(client: MaxfsClient, size: int, timeout: float = 120) -> str:
    """A finished job of ``size`` x ``size`` pixels whose object is a 64 x 64 sphere in the middle:
    large result arrays for little solving. Returns its id (the job ended ``done``)."""
    patch = synthetic.sphere(6, 64)
    a = size // 2 - 32
    jid = client.create_job(k=6, height=size, width=size, lights=patch.lights.tolist(), eps=2.0)["id"]
    for i in range(6):
        img = np.zeros((size, size), np.uint8)
        img[a : a + 64, a : a + 64] = patch.images[i].astype(np.uint8)
        client.upload_image(jid, i, img)
    mask = np.zeros((size, size), bool)
    mask[a : a + 64, a : a + 64] = patch.mask
    client.upload_mask(jid, mask)
    client.start(jid)
    state = client.wait(jid, poll=0.2, timeout=timeout)["state"]
    assert state == "done", f"job {jid} ended {state}"
    return jid
