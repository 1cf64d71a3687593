"""The load scenario of ``python -m bench.load`` and ``tests/test_load.py``: several users
submit jobs to one server at once while others poll status, and (with a hostile token) a
careless or hostile user attacks the server meanwhile (issue #10's catalogue).

Each user (one thread) creates its jobs, uploads every image, starts them, and waits; a
poller thread per user reads the status of that user's jobs in a loop and records each
request's latency. At the end every user tries to read, fetch and cancel every other
user's jobs (all must answer 404) and lists its own jobs. Here, in the package, so that
the benchmark and the test share it without importing each other.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field

import httpx
import numpy as np

from maxfs.service.cli.client import MaxfsClient
from maxfs.worker import synthetic


@dataclass
class LoadResult:
    """What happened under load."""

    states: dict[str, str] = field(default_factory=dict)  # job id -> final state
    owner: dict[str, str] = field(default_factory=dict)  # job id -> user
    latencies: list[float] = field(default_factory=list)  # seconds per status request
    denied: int = 0  # cross-user requests answered 404
    leaked: list[str] = field(default_factory=list)  # cross-user requests that were not
    listed_ok: bool = True  # every user's list held exactly its own jobs
    wall: float = 0.0
    hostile: Counter = field(default_factory=Counter)  # "what: status" -> count

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.latencies, q)) if self.latencies else float("nan")


def png_bomb(w: int, h: int) -> bytes:
    """A valid grey PNG of w x h zeros in about w * h / 1000 bytes (deflate blocks repeated)."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    rows = 100
    block = b"\x00" * ((w + 1) * rows)
    z = zlib.compressobj(9, zlib.DEFLATED, -15)
    piece = z.compress(block) + z.flush(zlib.Z_FULL_FLUSH)
    adler = 1
    for _ in range(h // rows):
        adler = zlib.adler32(block, adler)
    stream = b"\x78\xda" + piece * (h // rows) + zlib.compressobj(9, zlib.DEFLATED, -15).flush()
    stream += struct.pack(">I", adler)
    ihdr = struct.pack(">IIBBBBB", w, h // rows * rows, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", stream) + chunk(b"IEND", b"")


def _raw(url: str, head: str, body: bytes, timeout: float = 120) -> socket.socket:
    host, port = url.removeprefix("http://").split(":")
    s = socket.create_connection((host, int(port)), timeout=timeout)
    try:
        s.sendall(head.encode() + b"\r\n" + body)
    except OSError:  # the server answered (and closed) before the body was sent: read its answer
        pass
    return s


def _status_of(s: socket.socket) -> int:
    try:
        line = s.recv(64).split(b"\r\n", 1)[0]
        return int(line.split()[1]) if line else 0
    except (OSError, IndexError, ValueError):
        return 0
    finally:
        s.close()


def hostile_user(url: str, token: str, res: LoadResult, lock: threading.Lock, stop: threading.Event) -> None:
    """Issue #10's hostile and careless requests, in a loop until ``stop``."""
    auth = {"Authorization": f"Bearer {token}"}
    bomb = png_bomb(30000, 30000)
    lights = synthetic.lights_uniform(6).tolist()

    def count(what: str, code: int) -> None:
        with lock:
            res.hostile[f"{what}: {code}"] += 1

    with httpx.Client(base_url=url, headers=auth, timeout=120) as h:
        job = h.post("/jobs", json={"k": 6, "height": 64, "width": 64, "lights": lights, "eps": 2.0}).json()[
            "id"
        ]
        storm = h.post("/jobs", json={"k": 6, "height": 64, "width": 64, "lights": lights, "eps": 2.0}).json()
        img = synthetic.sphere(6, 64).images.astype(np.uint8)
        for i in range(6):
            h.put(f"/jobs/{storm['id']}/images/{i}", content=img[i].tobytes())
        while not stop.is_set():
            # 56 MB of JSON without a token (4 MB of it sent before the answer)
            s = _raw(
                url,
                f"POST /jobs HTTP/1.1\r\nHost: x\r\nContent-Length: {56 << 20}\r\n",
                b"[" + b"0," * (2 << 20),
            )
            count("56 MB JSON, no token", _status_of(s))
            r = h.put(f"/jobs/{job}/images/0", content=bomb, headers={"Content-Type": "image/png"})
            count("PNG bomb 30000^2", r.status_code)
            r = h.put(f"/jobs/{job}/mask", content=bomb, headers={"Content-Type": "image/png"})
            count("mask PNG bomb", r.status_code)
            stalled = [
                _raw(
                    url,
                    f"PUT /jobs/{job}/images/{i} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                    f"Content-Type: application/octet-stream\r\nContent-Length: 4096\r\n",
                    b"\x00" * 100,
                )
                for i in range(1, 3)
            ]
            r = h.post("/jobs", json={"k": 6, "height": 4096, "width": 4096, "lights": lights, "tile": 8})
            count("65,536 tiny tiles", r.status_code)
            for _ in range(3):
                count("start", h.post(f"/jobs/{storm['id']}/start").status_code)
                count("cancel", h.delete(f"/jobs/{storm['id']}").status_code)
            for name in ("..", ".", "%00"):
                count("result name " + name, h.get(f"/jobs/{storm['id']}/results/{name}.npy").status_code)
            for s in stalled:
                count("stalled upload", _status_of(s))
        for jid in (job, storm["id"]):
            h.delete(f"/jobs/{jid}")
            h.delete(f"/jobs/{jid}", params={"purge": "true"})


def run_load(
    url: str,
    tokens: dict[str, str],
    jobs_per_user: int = 3,
    k: int = 12,
    size: int = 64,
    timeout: float = 600,
    hostile_token: str | None = None,
) -> LoadResult:
    """Run the scenario against a server at ``url`` with one token per user (and, with
    ``hostile_token``, a hostile user besides them)."""
    res = LoadResult()
    lock = threading.Lock()
    scene = synthetic.bump_scene(k, size, seed=1)
    images = scene.images.astype(np.uint8)
    mine: dict[str, list[str]] = {u: [] for u in tokens}
    stop = threading.Event()
    errors: list[BaseException] = []

    def submit(user: str) -> None:
        try:
            with MaxfsClient(url, token=tokens[user]) as c:
                for _ in range(jobs_per_user):
                    job = c.create_job(
                        k=k, height=size, width=size, dtype="uint8", lights=scene.lights.tolist(), eps=1.0
                    )
                    for i in range(k):
                        c.upload_image(job["id"], i, images[i])
                    c.upload_mask(job["id"], scene.mask)
                    c.start(job["id"])
                    with lock:
                        mine[user].append(job["id"])
                        res.owner[job["id"]] = user
                for jid in list(mine[user]):
                    res.states[jid] = c.wait(jid, poll=0.2, timeout=timeout)["state"]
        except BaseException as e:  # reported by the caller
            errors.append(e)

    def poll(user: str) -> None:
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {tokens[user]}"}) as http:
            while not stop.is_set():
                with lock:
                    ids = list(mine[user])
                for jid in ids:
                    t0 = time.perf_counter()
                    r = http.get(f"/jobs/{jid}")
                    dt = time.perf_counter() - t0
                    if r.status_code != 200:
                        errors.append(RuntimeError(f"status of own job {jid}: {r.status_code} {r.text}"))
                    with lock:
                        res.latencies.append(dt)
                time.sleep(0.01)

    t0 = time.perf_counter()
    submitters = [threading.Thread(target=submit, args=(u,)) for u in tokens]
    pollers = [threading.Thread(target=poll, args=(u,), daemon=True) for u in tokens]
    if hostile_token:
        hstop = threading.Event()
        attacker = threading.Thread(
            target=hostile_user, args=(url, hostile_token, res, lock, hstop), daemon=True
        )
        pollers.append(attacker)
    for t in submitters + pollers:
        t.start()
    for t in submitters:
        t.join()
    stop.set()
    if hostile_token:
        hstop.set()
    for t in pollers:
        t.join(timeout=60)
    res.wall = time.perf_counter() - t0
    if errors:
        raise errors[0]

    for user, token in tokens.items():
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}) as http:
            listed = {j["id"] for j in http.get("/jobs").json()}
            res.listed_ok &= listed == set(mine[user])
            for jid, owner in res.owner.items():
                if owner == user:
                    continue
                for method, path in (
                    ("GET", f"/jobs/{jid}"),
                    ("GET", f"/jobs/{jid}/results/normal.npy"),
                    ("GET", f"/jobs/{jid}/results.zip"),
                    ("DELETE", f"/jobs/{jid}"),
                ):
                    r = http.request(method, path)
                    if r.status_code == 404:
                        res.denied += 1
                    else:
                        res.leaked.append(f"{user} {method} {path}: {r.status_code}")
    return res
