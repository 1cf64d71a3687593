"""Issue #24's attacks on a running ``maxfs serve``, each measured from another client:
slow and silent connections, stalled downloads, a disk that fills mid-run.

Used by ``python -m bench.load --hostile``; each function returns one table row (a dict).
"""

from __future__ import annotations

import os
import socket
import subprocess
import time
from pathlib import Path

import httpx
import numpy as np

from maxfs.service.cli.client import MaxfsClient
from maxfs.worker import synthetic
from tests.attacks import finished_patch_job, proc_kb, slow_connections
from tests.faults import fault_env


def _addr(url: str) -> tuple[str, int]:
    host, port = url.removeprefix("http://").split(":")
    return host, int(port)


def _pct(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def slow_clients(url: str, token: str, n: int, addresses: int, header_timeout: float) -> dict:
    """``n`` connections from ``addresses`` loopback addresses (127.0.0.2, ...): half send a
    request head one line a second, half nothing. Meanwhile 50 authenticated requests from
    127.0.0.1, each on a new connection; then how long until the server closed them all."""
    sources = [f"127.0.0.{2 + a}" for a in range(addresses)]
    with slow_connections(_addr(url), n, sources, 1.0) as socks:
        opened = time.monotonic()
        took, codes = [], []
        for _ in range(50):
            t0 = time.perf_counter()
            r = httpx.get(url + "/jobs", headers={"Authorization": f"Bearer {token}"}, timeout=60)
            took.append(time.perf_counter() - t0)
            codes.append(r.status_code)
            time.sleep(0.02)
        # how long until the server has closed every one (a read returns b"" or its 503 answer)
        last, still = 0.0, 0
        for s in socks:
            s.settimeout(max(0.1, header_timeout + 10 - (time.monotonic() - opened)))
            try:
                while s.recv(4096):
                    pass
            except TimeoutError:
                still += 1
                continue
            except OSError:
                pass
            last = max(last, time.monotonic() - opened)
    return {
        "attack": f"{len(socks)} slow/silent connections from {addresses} address(es)",
        "other client": f"{codes.count(200)}/50 answered 200; p50 {_pct(took, 50) * 1e3:.0f} ms, "
        f"p99 {_pct(took, 99) * 1e3:.0f} ms",
        "server": f"all closed within {last:.1f} s" if not still else f"{still} still open",
    }


def stalled_downloads(url: str, pid: int, owner: str, other: str, n: int) -> dict:
    """One user opens ``n`` downloads of a 12 MiB array and never reads; /health and another
    user's list are timed meanwhile, with the server's memory growth."""
    with MaxfsClient(url, token=owner, timeout=300) as c:
        jid = finished_patch_job(c, 1024, timeout=300)
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    before = proc_kb(pid, "VmRSS")
    head = (
        f"GET /jobs/{jid}/results/normal.npy HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {owner}\r\n\r\n"
    ).encode()
    socks, codes = [], []
    for _ in range(n):
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.bind(("127.0.0.3", 0))  # not the measuring client's address (MAXFS_MAX_CONNECTIONS_PER_CLIENT)
        s.connect(_addr(url))
        s.sendall(head)
        socks.append(s)
    for s in socks:
        s.settimeout(30)
        try:
            codes.append(int(s.recv(12)[9:12]))
        except (OSError, ValueError):
            codes.append(0)
    took = []
    with MaxfsClient(url, token=other, timeout=60) as o:
        for _ in range(20):
            t0 = time.perf_counter()
            httpx.get(url + "/health", timeout=60)
            o.jobs()
            took.append(time.perf_counter() - t0)
    grew = (proc_kb(pid, "VmHWM") - before) / 1024
    for s in socks:
        s.close()
    return {
        "attack": f"{n} never-read downloads of a 12 MiB array, one user",
        "other client": f"/health + another user's list: max {max(took) * 1e3:.0f} ms",
        "server": f"{codes.count(200)} served, {codes.count(429)} answered 429, {codes.count(503)} 503 "
        f"(per-address cap); +{grew:.0f} MB",
    }


def full_disk(start_server, tmp: Path) -> dict:
    """A 24 MB tmpfs as the data folder, filled while a 16-tile MILP job runs; then freed and
    the job started again. Needs root (mount); otherwise the row says so."""
    if os.geteuid() != 0:
        return {"attack": "disk filled mid-run", "other client": "-", "server": "not run (mount needs root)"}
    mnt = tmp / "disk"
    mnt.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(mnt)], check=True)
    server = None
    try:
        # the disk budget is told of a huge disk, so the writes themselves meet the full disk
        env = {"MAXFS_MIN_FREE_BYTES": "0", "MAXFS_TILE_RETRIES": "0", **fault_env(free_bytes=1 << 40)}
        server = start_server(mnt / "data", env)
        with MaxfsClient(server.url, token=server.token("dora"), timeout=120) as c:
            sc = synthetic.bump_scene(12, 64, seed=3)
            meta = {"k": 12, "height": 64, "width": 64, "lights": sc.lights.tolist(), "eps": 2.0}
            jid = c.create_job(**meta, solver="milp", tile=16)["id"]
            later = c.create_job(**meta)["id"]
            for i in range(12):
                c.upload_image(jid, i, sc.images[i].astype(np.uint8))
            c.start(jid)
            while not c.status(jid)["tiles_done"]:
                time.sleep(0.1)
            filler = mnt / "filler"
            with open(filler, "wb", buffering=0) as f:
                try:
                    while True:
                        f.write(b"\0" * (1 << 16))
                except OSError:
                    pass
            t0 = time.monotonic()
            while (st := c.status(jid))["state"] in ("queued", "running") and time.monotonic() - t0 < 60:
                time.sleep(0.1)
            stopped = time.monotonic() - t0
            r = httpx.put(
                f"{server.url}/jobs/{later}/images/0",
                content=sc.images[0].astype(np.uint8).tobytes(),
                headers={"Authorization": c.http.headers["Authorization"]},
                timeout=60,
            )
            filler.unlink()
            c.start(jid)
            end = c.wait(jid, poll=0.2, timeout=300)
        return {
            "attack": "24 MB data disk filled mid-run (16-tile MILP job)",
            "other client": f"upload on the full disk: {r.status_code} {r.json().get('error', '')}",
            "server": f"job {st['state']} {stopped:.1f} s after; resumed when freed: {end['state']} "
            f"({end['tiles_done']}/{end['tiles_total']} tiles)",
        }
    finally:
        if server is not None:
            server.kill()
        subprocess.run(["umount", "-l", str(mnt)], check=False)
