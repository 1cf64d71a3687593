"""Hostile clients shared by the tests and ``bench.load --hostile`` (real sockets on loopback)."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager


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
