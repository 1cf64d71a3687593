"""A shared server under hostile and careless load (issue #10), with real processes: a
uvicorn server (``maxfs serve``) and a Dask scheduler with two single-threaded workers.

Each hostile request is served while another connection polls ``/health``; the server's
peak memory is its ``VmHWM`` (reset through ``/proc/PID/clear_refs`` before the request).
The bounds asserted are generous for a loaded 2-core machine and far below what the
issue measured before the fixes (+0.9 to 1.7 GB, ``/health`` stalled 4 to 18 s).
"""

from __future__ import annotations

import io
import json
import socket
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import imagecodecs
import numpy as np
import pytest
import tifffile
from distributed import Client

from maxfs.service.cli.client import MaxfsClient
from maxfs.worker import synthetic
from tests.attacks import finished_patch_job, proc_kb
from tests.badrequests import Bad, Req, check_refused, run_setup, send
from tests.faults import fault_env
from tests.loadgen import png_bomb
from tests.procs import BIN, DaskCluster, Server, poll_until

MB = 1 << 20
#: ``/health`` must answer within this while a hostile request is served (before: 4-18 s).
HEALTH_S = 1.5

# -- measuring ---------------------------------------------------------------------------------


@dataclass
class Probe:
    """Server memory growth and ``/health`` latency while a block runs."""

    grew_mb: float = 0.0
    health: list[float] = field(default_factory=list)

    @property
    def worst(self) -> float:
        return max(self.health, default=0.0)


@contextmanager
def probe(server: Server, every: float = 0.05) -> Iterator[Probe]:
    """Reset the server's peak RSS, poll /health from another connection, and report the peak
    above the RSS before the block (MB) and the slowest /health answer (s)."""
    pid = server.proc.pid
    Path(f"/proc/{pid}/clear_refs").write_text("5")  # VmHWM := VmRSS
    before = proc_kb(pid, "VmRSS")
    out, stop = Probe(), threading.Event()

    def poll() -> None:
        with httpx.Client(base_url=server.url, timeout=60) as h:
            while not stop.is_set():
                t0 = time.perf_counter()
                assert h.get("/health").status_code == 200
                out.health.append(time.perf_counter() - t0)
                stop.wait(every)

    t = threading.Thread(target=poll, daemon=True)
    t.start()
    try:
        yield out
    finally:
        stop.set()
        t.join(timeout=60)
        out.grew_mb = (proc_kb(pid, "VmHWM") - before) / 1024


def _check(p: Probe, mb: float, what: str) -> None:
    print(
        f"{what}: server +{p.grew_mb:.0f} MB, /health worst {p.worst * 1e3:.0f} ms over {len(p.health)} polls"
    )
    assert p.grew_mb < mb, f"{what}: the server grew {p.grew_mb:.0f} MB"
    assert p.worst < HEALTH_S, f"{what}: /health took {p.worst:.2f} s"
    assert len(p.health) >= 1


# -- raw HTTP (for what httpx will not send: lies, stalls, hang-ups) ---------------------------


def _open(
    server: Server, method: str, path: str, headers: dict[str, str], body: bytes = b""
) -> socket.socket:
    """Send a request head (and ``body``, maybe only part of the declared one); keep it open."""
    host, port = server.url.removeprefix("http://").split(":")
    s = socket.create_connection((host, int(port)), timeout=60)
    head = f"{method} {path} HTTP/1.1\r\nHost: {host}\r\n" + "".join(
        f"{k}: {v}\r\n" for k, v in headers.items()
    )
    s.sendall(head.encode() + b"\r\n" + body)
    return s


def _answer(s: socket.socket, timeout: float = 60) -> tuple[int, dict]:
    """Status and JSON body of the answer on ``s`` (the server may answer before the body is sent)."""
    s.settimeout(timeout)
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    status = int(head.split()[1])
    length = next(
        (int(h.split(b":")[1]) for h in head.split(b"\r\n") if h.lower().startswith(b"content-length")), 0
    )
    while len(rest) < length:
        chunk = s.recv(65536)
        if not chunk:
            break
        rest += chunk
    s.close()
    try:
        return status, json.loads(rest[:length] or b"{}")
    except ValueError:
        return status, {}


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


# -- fixtures ----------------------------------------------------------------------------------

LIGHTS12 = synthetic.lights_uniform(12)


@pytest.fixture(scope="module")
def cluster(module_dask_cluster: DaskCluster) -> DaskCluster:
    return module_dask_cluster


@pytest.fixture(scope="module")
def server(cluster: DaskCluster, module_server_factory, tmp_path_factory: pytest.TempPathFactory) -> Server:
    tmp = tmp_path_factory.mktemp("hostile")
    (tmp / "t").mkdir()
    env = {
        "MAXFS_MIN_FREE_BYTES": "0",
        "MAXFS_MAX_OPEN_JOBS": "50",
        "MAXFS_UPLOAD_IDLE_TIMEOUT": "2",
        "MAXFS_MAX_UPLOADS_PER_USER": "4",
        "MAXFS_TILE_RETRIES": "0",
        "MAXFS_MAX_DOWNLOADS_PER_USER": "10",  # the stalled-download test holds 10 at once
        "TMPDIR": str(tmp / "t"),
    }
    s = module_server_factory(tmp / "data", cluster.address, logs=tmp, auth=True, env=env)
    s.tmp = tmp
    s.tokens = {u: s.token(u) for u in ("alice", "bob", "carol")}
    return s


def _client(server: Server, user: str) -> MaxfsClient:
    """A client for ``user``, whose token is made on first use (one user per test keeps the
    tests' jobs apart)."""
    if user not in server.tokens:
        server.tokens[user] = server.token(user)
    return MaxfsClient(server.url, token=server.tokens[user], timeout=120)


def _job(c: MaxfsClient, k: int = 6, size: int = 64, upload: bool = True, **params) -> str:
    """A job of a synthetic sphere, its images uploaded unless not ``upload``."""
    sc = synthetic.sphere(k, size)
    jid = c.create_job(
        k=k, height=size, width=size, dtype="uint8", lights=sc.lights.tolist(), eps=2.0, **params
    )["id"]
    if upload:
        for i in range(k):
            c.upload_image(jid, i, sc.images[i].astype(np.uint8))
    return jid


def _idle(cluster: DaskCluster) -> bool:
    """No task runs on any worker (the workers' view: a cancelled future leaves the scheduler's
    books at once, while its thread may still compute)."""

    def executing(dask_worker) -> int:  # in each worker's event loop, beside its busy thread
        return len(dask_worker.state.executing)

    with Client(cluster.address, timeout=30) as dc:
        return not any(dc.run(executing).values())


# -- 1. bodies are read only after the token, and only so much ---------------------------------


def test_json_body_needs_a_token_and_has_a_cap(server: Server) -> None:
    huge = 56 * MB
    with probe(server) as p:
        # no token: refused before a byte of the 56 MB body is read
        s = _open(server, "POST", "/jobs", {"Content-Type": "application/json", "Content-Length": str(huge)})
        s.sendall(b"[" + b"0," * (MB // 2))
        code, body = _answer(s)
        assert code == 401 and "API token" in body["detail"], body
        # a token, and a body declared larger than the cap: refused unread
        hdr = {
            "Content-Type": "application/json",
            "Content-Length": str(huge),
            **_bearer(server.tokens["alice"]),
        }
        code, body = _answer(_open(server, "POST", "/jobs", hdr, b"{"))
        assert code == 413 and "larger than" in body["detail"], body
        # chunked, no length: cut off at the cap
        s = _open(
            server, "POST", "/jobs", {"Transfer-Encoding": "chunked", **_bearer(server.tokens["alice"])}
        )
        piece = b"0," * (MB // 2)
        try:
            for _ in range(8):
                s.sendall(b"%x\r\n%s\r\n" % (len(piece), piece))
        except OSError:
            pass  # the server answered and closed
        code, body = _answer(s)
        assert code == 413, body
        # k over the limit: refused before the (many) lights are validated
        k = 5_000  # over MAXFS_MAX_K, under the JSON cap
        many = Req("POST", "/jobs", json={"k": k, "height": 8, "width": 8, "lights": [[0, 0, 1]] * k})
        check_refused(send(server, many), Bad("k-5000", (), many, 413, "MAX_K"))
    _check(p, 40, "56 MB JSON bodies")


# -- 2. decompression bombs ------------------------------------------------------------------


def _tiff_declaring(size: int) -> bytes:
    """A deflate TIFF whose tags declare size x size pixels (its one strip holds 64 x 64)."""
    b = io.BytesIO()
    tifffile.imwrite(b, np.zeros((64, 64), np.uint8), compression="zlib")
    data = bytearray(b.getvalue())
    with tifffile.TiffFile(io.BytesIO(bytes(data))) as t:
        tags = {tag.code: tag for tag in t.pages.first.tags}
        for code in (256, 257, 278):  # width, length, rows per strip
            tag = tags[code]
            fmt = "<H" if tag.dtype == 3 else "<I"
            data[tag.valueoffset : tag.valueoffset + struct.calcsize(fmt)] = struct.pack(fmt, size)
    return bytes(data)


def _tiff_pages_one_strip(pages: int, size: int) -> bytes:
    """A TIFF whose ``pages`` pages of size x size all point at one strip."""
    b = io.BytesIO()
    tifffile.imwrite(b, np.zeros((size, size), np.uint8))
    one = bytearray(b.getvalue())
    with tifffile.TiffFile(io.BytesIO(bytes(one))) as t:
        page = t.pages.first
        offset = page.offset
    n = struct.unpack("<H", one[offset : offset + 2])[0]
    ifd = bytes(one[offset : offset + 2 + 12 * n])
    out = bytearray(one[:offset])
    firsts = []
    for _ in range(pages):
        firsts.append(len(out))
        out += ifd + b"\x00\x00\x00\x00"
    for i, at in enumerate(firsts[:-1]):  # chain the IFDs
        out[at + 2 + 12 * n : at + 6 + 12 * n] = struct.pack("<I", firsts[i + 1])
    out[4:8] = struct.pack("<I", firsts[0])
    return bytes(out)


def _bombs() -> list[Bad]:
    """Bodies that would decode to far more than the job's image (made when a test needs them)."""
    big = png_bomb(30000, 30000)  # 0.9 GB of pixels in about 0.9 MB

    def put(path: str, body: bytes, ctype: str) -> Req:
        return Req("PUT", path, content=body, ctype=ctype, user="bomb")

    return [
        Bad("png-bomb", (), put("/jobs/{j}/images/0", big, "image/png"), 422, "has shape (30000, 30000)"),
        Bad(
            "tiff-declaring-20000",
            (),
            put("/jobs/{j}/images/0", _tiff_declaring(20000), "image/tiff"),
            422,
            "has shape (20000, 20000)",
        ),
        Bad(
            "tiff-1000-pages",
            (),
            put("/jobs/{j}/images/0", _tiff_pages_one_strip(1000, 64), "image/tiff"),
            422,
            "holds 1000 images",
        ),
        Bad("mask-png-bomb", (), put("/jobs/{j}/mask", big, "image/png"), 422, "has shape (30000, 30000)"),
    ]


def test_decompression_bombs_are_refused_before_decoding(server: Server) -> None:
    with _client(server, "bomb") as c:
        jid = _job(c, size=64, upload=False)
        hdr = {**_bearer(server.tokens["bomb"])}
        cases = _bombs()
        with probe(server) as p:
            for case in cases:
                check_refused(send(server, case.request, jid), case)
        _check(p, 60, "decompression bombs")
        # an honest PNG still goes in (decoded in a thread)
        png = imagecodecs.png_encode(np.full((64, 64), 90, np.uint8))
        r = httpx.put(
            server.url + f"/jobs/{jid}/images/0", content=png, headers={**hdr, "Content-Type": "image/png"}
        )
        assert r.status_code == 200 and r.json()["uploaded"] == 1, r.text
        c.delete(jid)


# -- 4. fair sharing between users, and cancel that frees the worker -----------------------------


def test_small_job_overtakes_a_large_one_and_cancel_frees_workers(
    server: Server, cluster: DaskCluster
) -> None:
    sc = synthetic.bump_scene(12, 128, seed=2)
    big = sc.images.astype(np.uint8)
    small = synthetic.bump_scene(12, 64, seed=3)
    with _client(server, "alice") as alice, _client(server, "bob") as bob:
        # alice: 64 MILP tiles of 16 x 16 (about a second each here)
        a = alice.create_job(
            k=12,
            height=128,
            width=128,
            dtype="uint8",
            lights=sc.lights.tolist(),
            eps=2.0,
            solver="milp",
            tile=16,
        )["id"]
        for i in range(12):
            alice.upload_image(a, i, big[i])
        alice.start(a)
        poll_until(lambda: alice.status(a)["progress"]["tiles_done"] >= 2, 120, "alice's job under way")
        # bob: k = 12, 64 x 64, four tiles; without fair priorities they would queue behind alice's
        b = bob.create_job(k=12, height=64, width=64, dtype="uint8", lights=small.lights.tolist(), eps=2.0)[
            "id"
        ]
        for i in range(12):
            bob.upload_image(b, i, small.images[i].astype(np.uint8))
        t0 = time.monotonic()
        bob.start(b)
        st = bob.wait(b, poll=0.1, timeout=120)
        took = time.monotonic() - t0
        left = alice.status(a)["progress"]
        assert st["state"] == "done", st
        assert took < 12, f"bob's small job took {took:.1f} s next to alice's large one"
        assert left["tiles_done"] < left["tiles_total"] * 0.7, f"alice's job was nearly done: {left}"
        alice.cancel(a)
        poll_until(lambda: _idle(cluster), 10, "workers idle after alice's cancel")

        # one long tile (96 x 96 MILP pixels, tens of seconds); cancel frees its worker within 5 s
        tall = synthetic.bump_scene(12, 96, seed=4)
        carol = _client(server, "carol")
        j = carol.create_job(
            k=12,
            height=96,
            width=96,
            dtype="uint8",
            lights=tall.lights.tolist(),
            eps=2.0,
            solver="milp",
            tile=96,
        )["id"]
        for i in range(12):
            carol.upload_image(j, i, tall.images[i].astype(np.uint8))
        carol.start(j)
        poll_until(
            lambda: carol.status(j)["state"] == "running" and not _idle(cluster), 60, "carol's tile running"
        )
        time.sleep(1.0)
        t0 = time.monotonic()
        assert carol.cancel(j)["state"] == "cancelled"
        poll_until(lambda: _idle(cluster), 5, "carol's worker free within 5 s of the cancel")
        freed = time.monotonic() - t0
        log = (server.data / "jobs" / j / "maxfs-runs.log").read_text()
        assert "tile=0 cancelled" in log, log
        print(f"bob's job: {took:.1f} s; carol's worker free {freed:.2f} s after cancel")
        carol.close()
        for jid, cl in ((a, alice), (b, bob)):
            cl.delete(jid)


_HUGE = {"k": 12, "height": 4096, "width": 4096, "lights": LIGHTS12.tolist(), "eps": 2.0}
HAND_SET_TILES = [
    Bad(
        "tile-640-too-much-work",
        (),
        Req("POST", "/jobs", json={**_HUGE, "tile": 640}, user="hal"),
        422,
        "more work than one task may have",
    ),
    Bad(
        "tile-160-milp",
        (),
        Req("POST", "/jobs", json={**_HUGE, "tile": 160, "solver": "milp"}, user="hal"),
        422,
        "with the MILP",
    ),
    Bad(
        "tile-16-too-many",
        (),
        Req("POST", "/jobs", json={**_HUGE, "tile": 16}, user="hal"),
        422,
        "MAXFS_MAX_TILES",
    ),
]


@pytest.mark.parametrize("case", HAND_SET_TILES, ids=lambda c: c.name)
def test_hand_set_tiles_are_bounded_in_work_and_count(server: Server, case: Bad) -> None:
    with _client(server, "hal") as c:
        check_refused(send(server, case.request, run_setup(server, case.setup)), case)
        assert not c.jobs()


# -- 5. many tiny tiles do not freeze the server ---------------------------------------------------


def test_many_tiny_tiles_do_not_stall_the_server(server: Server, cluster: DaskCluster) -> None:
    with _client(server, "tina") as c:
        jid = _job(c, size=512, tile=8)  # 4,096 tiles, the most a job may have
        mask = np.zeros((512, 512), bool)
        mask[224:288, 224:288] = True
        c.upload_mask(jid, mask)
        with probe(server) as p:
            c.start(jid)
            poll_until(lambda: c.status(jid)["progress"]["tiles_done"] >= 20, 120, "tiles under way")
        _check(p, 150, "starting 4,096 tiles")
        c.cancel(jid)
        poll_until(lambda: _idle(cluster), 30, "workers idle")
        c.delete(jid)


# -- 6. every pair of state changes, concurrently -------------------------------------------------


def _together(*calls) -> list[int]:
    """Run the calls at the same moment; their HTTP status codes."""
    codes: list[int] = [0] * len(calls)
    gate = threading.Barrier(len(calls))

    def go(i: int) -> None:
        gate.wait()
        codes[i] = calls[i]()

    ts = [threading.Thread(target=go, args=(i,)) for i in range(len(calls))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    return codes


def test_concurrent_state_changes_stay_consistent(server: Server, cluster: DaskCluster) -> None:
    c = _client(server, "rae")
    tok = server.tokens["rae"]
    with (
        c,
        httpx.Client(base_url=server.url, headers=_bearer(tok), timeout=60) as h,
    ):
        img = np.full((64, 64), 90, np.uint8).tobytes()
        # DELETE during an upload: the job ends cancelled and takes no more uploads
        jid = _job(c, upload=False)
        s = _open(
            server,
            "PUT",
            f"/jobs/{jid}/images/0",
            {"Content-Type": "application/octet-stream", "Content-Length": str(len(img)), **_bearer(tok)},
            img[:1000],
        )
        time.sleep(0.3)
        assert h.delete(f"/jobs/{jid}").json()["state"] == "cancelled"
        s.sendall(img[1000:])
        code, body = _answer(s)
        assert code == 409, body
        assert h.put(f"/jobs/{jid}/images/1", content=img).status_code == 409
        assert c.status(jid)["state"] == "cancelled"
        c.delete(jid)

        pairs = {
            "start+cancel": lambda j: (
                lambda: h.post(f"/jobs/{j}/start").status_code,
                lambda: h.delete(f"/jobs/{j}").status_code,
            ),
            "start+start": lambda j: (lambda: h.post(f"/jobs/{j}/start").status_code,) * 2,
            "cancel+cancel": lambda j: (lambda: h.delete(f"/jobs/{j}").status_code,) * 2,
            "upload+start": lambda j: (
                lambda: h.put(f"/jobs/{j}/images/0", content=img).status_code,
                lambda: h.post(f"/jobs/{j}/start").status_code,
            ),
            "start+purge": lambda j: (
                lambda: h.post(f"/jobs/{j}/start").status_code,
                lambda: h.delete(f"/jobs/{j}", params={"purge": "true"}).status_code,
            ),
        }
        for name, make in pairs.items():
            for _ in range(6 if name == "start+cancel" else 3):
                jid = _job(c)
                codes = _together(*make(jid))
                r = h.get(f"/jobs/{jid}")
                if r.status_code == 404:  # purged first: the start found no job, cleanly
                    assert name == "start+purge" and codes == [404, 200], codes
                    continue
                assert all(x in (200, 202, 409) for x in codes), (name, codes)
                st = r.json()["state"]
                if name == "start+start":
                    assert sorted(codes) == [202, 409], codes
                if name == "cancel+cancel":
                    assert sorted(codes) == [200, 409] and st == "cancelled", (codes, st)
                if name == "start+cancel":  # either order is fine: cancelled, or cancelled then resumed
                    assert codes == [202, 200] and st in ("cancelled", "queued", "running", "done"), (
                        codes,
                        st,
                    )
                # whatever happened, the job is never stuck: a cancelled one starts again
                if st == "cancelled":
                    assert h.post(f"/jobs/{jid}/start").status_code == 202, (name, codes)
                if h.get(f"/jobs/{jid}").json()["state"] in ("queued", "running"):
                    assert h.delete(f"/jobs/{jid}").json()["state"] == "cancelled"
                assert h.delete(f"/jobs/{jid}", params={"purge": "true"}).status_code == 200
        assert c.jobs() == []


# -- 7. disk space is reserved, not just checked; the zip is never copied to disk ----------------


def test_concurrent_uploads_cannot_eat_the_disk_reserve(cluster: DaskCluster, server_factory) -> None:
    from maxfs.storage.layout import JobSpec

    lights = synthetic.lights_uniform(6)
    need = JobSpec(6, 1024, 1024, None, "uint8", lights).validate().store_nbytes()
    free = need + 9 * MB  # the file system's free space, as the server is told (the reserve is 0)
    env = {
        "MAXFS_MIN_FREE_BYTES": "0",
        **fault_env(free_bytes=free),
        "MAXFS_MAX_UPLOADS_PER_USER": "100",
    }
    server = server_factory(scheduler=cluster.address, auth=True, env=env)
    tok = server.token("dan")
    with MaxfsClient(server.url, token=tok) as c:
        jid = c.create_job(k=6, height=1024, width=1024, lights=lights.tolist(), eps=2.0)["id"]
        img = np.full((1024, 1024), 90, np.uint8).tobytes()
        head = {
            "Content-Type": "application/octet-stream",
            "Content-Length": str(len(img)),
            **_bearer(tok),
        }
        socks = [_open(server, "PUT", f"/jobs/{jid}/images/{i % 6}", head) for i in range(40)]
        time.sleep(2.0)  # every head has been seen; the refused ones are answered already
        import select

        refused = [s for s in socks if select.select([s], [], [], 0)[0]]
        held = [s for s in socks if s not in refused]
        for s in refused:
            code, body = _answer(s)
            assert code == 507 and "free above its reserve" in body["detail"], body
        # each held upload reserved its body and its stored image (2 MB): no more fit than that
        fit = free // (2 * len(img))
        assert len(held) == fit < 40, f"{len(held)} of 40 uploads were let in, {fit} fit"
        for s in held:
            s.sendall(img)
            assert _answer(s)[0] == 200
        assert c.status(jid)["uploaded"] >= 1


# -- 8. large answers are streamed; previews are bounded and cached --------------------------------


def test_large_answers_stream_and_previews_are_bounded(server: Server) -> None:
    from maxfs.storage.layout import JobStore

    H = 2048
    with _client(server, "lars") as c:
        jid = finished_patch_job(c, H)
        store = JobStore.open(server.data / "jobs" / jid, mode="r")
        hdr = _bearer(server.tokens["lars"])

        # six slow readers of a 48 MB array, and four stalled downloads of the results zip
        with probe(server) as p, httpx.Client(base_url=server.url, headers=hdr, timeout=60) as h:
            streams = [h.stream("GET", f"/jobs/{jid}/results/normal.npy") for _ in range(6)]
            streams += [h.stream("GET", f"/jobs/{jid}/results.zip?inputs=true") for _ in range(4)]
            readers = [s.__enter__() for s in streams]
            for r in readers:
                assert r.status_code == 200
                next(r.iter_raw(65536))
            time.sleep(2.0)  # they stall
            assert not list((server.tmp / "t").iterdir()), "a download wrote to the temp folder"
            for s in streams:
                s.__exit__(None, None, None)
        # each stalled download holds about one piece in its transport buffer and may be reading
        # the next (service.http.streams.PIECE): 2 pieces each, and 20 MB for the rest, not 6 x 48 MB
        from maxfs.service.http.streams import PIECE

        _check(p, len(streams) * 2 * PIECE / MB + 20, "6 slow NPY readers of 48 MB and 4 stalled zips")

        # what is streamed is the array, for (H, W, 3) and (k, H, W) alike
        for name in ("normal", "inliers"):
            got = np.load(
                io.BytesIO(httpx.get(server.url + f"/jobs/{jid}/results/{name}.npy", headers=hdr).content)
            )
            np.testing.assert_array_equal(got, store.read_output(name))

        with probe(server) as p:
            t0 = time.perf_counter()
            png = httpx.get(server.url + f"/jobs/{jid}/previews/normal.png", headers=hdr, timeout=60).content
            first = time.perf_counter() - t0
        _check(p, 60, "a 2048 x 2048 preview")
        im = imagecodecs.png_decode(png)
        assert im.shape == (1024, 1024, 3), im.shape
        t0 = time.perf_counter()
        again = httpx.get(server.url + f"/jobs/{jid}/previews/normal.png", headers=hdr, timeout=60).content
        assert again == png and time.perf_counter() - t0 < first, "the preview was not cached"
        c.delete(jid)


# -- 9. status costs the same whatever k ---------------------------------------------------------


def test_status_does_not_grow_with_k(server: Server) -> None:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(1000, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.5
    lights = v / np.linalg.norm(v, axis=1, keepdims=True)

    def median_status(c: MaxfsClient, jid: str) -> float:
        times = []
        for _ in range(15):
            t0 = time.perf_counter()
            c.status(jid)
            times.append(time.perf_counter() - t0)
        return float(np.median(times))

    with _client(server, "kay") as c:
        small = _job(c, upload=False)
        big = c.create_job(k=1000, height=8, width=8, lights=lights.tolist(), eps=2.0)["id"]
        for i in range(20):
            c.upload_image(big, i, np.full((8, 8), 50 + i, np.uint8))
        st = c.status(big)
        assert st["uploaded"] == 20 and len(st["missing_images"]) == 980 and st["missing_images"][0] == 20
        t_small, t_big = median_status(c, small), median_status(c, big)
        print(f"status: k=6 {t_small * 1e3:.1f} ms, k=1000 {t_big * 1e3:.1f} ms (median of 15)")
        assert t_big < 2 * t_small + 0.02, (t_small, t_big)
        c.delete(small)
        c.delete(big)


# -- 10. delete, per-user index, retention, resumable submit; 11. the rest ------------------------


@pytest.fixture(scope="module")
def strict(cluster: DaskCluster, module_server_factory, tmp_path_factory: pytest.TempPathFactory) -> Server:
    """Two open jobs per user, jobs kept 30 s after their last change (swept every 7.5 s),
    tiles stopped after 1 s, and 12 connections at most."""
    tmp = tmp_path_factory.mktemp("strict")
    env = {
        "MAXFS_MIN_FREE_BYTES": "0",
        "MAXFS_MAX_OPEN_JOBS": "2",
        "MAXFS_RETENTION_DAYS": str(30 / 86400),
        "MAXFS_TILE_TIME_LIMIT": "1",
        "MAXFS_TILE_RETRIES": "0",
        "MAXFS_MAX_CONNECTIONS": "12",
    }
    s = module_server_factory(tmp / "data", cluster.address, logs=tmp, auth=True, env=env)
    s.tmp = tmp
    return s


def _cli(server: Server, token: str, *args: str) -> str:
    import subprocess

    out = subprocess.run(
        [str(BIN / "maxfs"), *args, "--server", server.url, "--token", token],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout + out.stderr


def test_delete_quota_index_retention_and_identity(strict: Server) -> None:
    s = strict
    eve, ann = s.token("eve"), s.token("ann")
    with MaxfsClient(s.url, token=eve) as c, MaxfsClient(s.url, token=ann) as other:
        a, b = _job(c, upload=False), _job(c, upload=False)
        mine = _job(other, upload=False)
        with pytest.raises(Exception, match="429"):
            _job(c, upload=False)
        assert "deleted" in _cli(s, eve, "delete", a)  # `maxfs delete`: the store goes, the slot is free
        assert not (s.data / "jobs" / a).exists()
        # the index: eve's create and list never read ann's record (corrupt it to prove it)
        rec = s.data / "jobs" / mine / "maxfs-job.json"
        saved = rec.read_text()
        rec.write_text("{not json")
        d = _job(c, upload=False)
        assert {j["id"] for j in c.jobs()} == {b, d}
        rec.write_text(saved)
        # a running job is not deleted; a name revoked and made again is a new person
        from maxfs.storage.tokens import TokenStore

        TokenStore(s.data / "maxfs-tokens.json").revoke("ann")
        ann2 = s.token("ann")
        with MaxfsClient(s.url, token=ann2) as again:
            assert again.jobs() == []
            with pytest.raises(Exception, match="404"):
                again.status(mine)
            fresh = _job(again, upload=False)
            # retention: jobs untouched for longer than 30 s go at the next sweep (their records
            # are made an hour old here, so a slow machine cannot expire them before this point)
            for jid in (b, d):
                path = s.data / "jobs" / jid / "maxfs-job.json"
                old = json.loads(path.read_text())
                old["updated_at"] -= 3600
                tmp = path.with_name(".maxfs-test-record")
                tmp.write_text(json.dumps(old))
                tmp.replace(path)
            poll_until(
                lambda: not (s.data / "jobs" / b).exists() and not (s.data / "jobs" / d).exists(),
                30,
                "expiry",
            )
            assert c.jobs() == []
            assert [j["id"] for j in again.jobs()] == [fresh]  # changed just now: kept
            again.delete(fresh)


def test_tile_time_limit_stops_a_tile_and_fails_the_job(strict: Server, cluster: DaskCluster) -> None:
    tok = strict.token("tim")
    sc = synthetic.bump_scene(12, 64, seed=6)
    with MaxfsClient(strict.url, token=tok) as c:
        jid = c.create_job(
            k=12, height=64, width=64, lights=sc.lights.tolist(), eps=2.0, solver="milp", tile=64
        )["id"]
        for i in range(12):
            c.upload_image(jid, i, sc.images[i].astype(np.uint8))
        t0 = time.monotonic()
        c.start(jid)
        st = c.wait(jid, poll=0.1, timeout=60)
        assert st["state"] == "failed" and "tile 0 was stopped after 1 s" in st["error"], st
        assert time.monotonic() - t0 < 15
        poll_until(lambda: _idle(cluster), 10, "the worker free")


def test_connection_cap_makes_room_from_idle_connections_and_answers_503_when_all_are_busy(
    strict: Server,
) -> None:
    """12 connections at most. Twelve that send nothing hold every slot: a newcomer gets 503 while
    they are younger than connections.GRACE, and is served after (it closes the oldest). Eleven
    requests whose bodies the server is reading (a job description arriving slowly) are busy,
    and then a newcomer gets 503 at once, not a hung accept queue."""
    host, port = strict.url.removeprefix("http://").split(":")
    idle = [socket.create_connection((host, int(port))) for _ in range(12)]
    try:
        time.sleep(0.5)
        # younger than connections.GRACE: maybe a client still sending its head, kept
        assert httpx.get(strict.url + "/health", timeout=10).status_code == 503
        time.sleep(1.0)
        assert httpx.get(strict.url + "/health", timeout=10).status_code == 200
    finally:
        for s in idle:
            s.close()
    tokens = [strict.token("busy1"), strict.token("busy2")]  # 6 and 5: under MAXFS_MAX_UPLOADS_PER_USER
    busy = []
    try:
        for i in range(11):
            head = (
                f"POST /jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {tokens[i % 2]}\r\n"
                "Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n{"
            ).encode()
            s = socket.create_connection((host, int(port)))
            s.sendall(head)
            busy.append(s)
            time.sleep(0.05)  # its head parsed: a request in progress, not an idle connection
        time.sleep(0.5)
        t0 = time.perf_counter()
        r = httpx.get(strict.url + "/health", timeout=10)
        assert r.status_code == 503 and time.perf_counter() - t0 < 2
    finally:
        for s in busy:
            s.close()
    poll_until(lambda: httpx.get(strict.url + "/health", timeout=10).status_code == 200, 10, "served again")


def test_interrupted_submit_resumes_into_the_same_job(server: Server, tmp_path: Path) -> None:
    from maxfs.storage.datasets import write_npy_folder

    sc = synthetic.sphere(6, 64)
    folder = write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask)
    sent: list[int] = []
    with _client(server, "sue") as c:
        real = c.upload_image

        def flaky(job_id: str, index: int, image: np.ndarray) -> dict:
            if len(sent) == 3:
                raise KeyboardInterrupt  # Ctrl-C after three images
            sent.append(index)
            return real(job_id, index, image)

        def flaky_batch(job_id: str, first: int, images: list[np.ndarray]) -> dict:
            # submit sends small images several to a request: cut it image by image all the same
            return [flaky(job_id, first + n, image) for n, image in enumerate(images)][-1]

        real_batch = c.upload_images
        c.upload_image = flaky  # type: ignore[method-assign]
        c.upload_images = flaky_batch  # type: ignore[method-assign]
        with pytest.raises(KeyboardInterrupt):
            c.submit_folder(folder, eps=2.0)
        (first,) = [j["id"] for j in c.jobs()]
        assert c.status(first)["uploaded"] == 3
        c.upload_image = real  # type: ignore[method-assign]
        c.upload_images = real_batch  # type: ignore[method-assign]
        jid = c.submit_folder(folder, eps=2.0)  # "run again to resume"
        assert jid == first and [j["id"] for j in c.jobs()] == [first]
        assert c.wait(jid, poll=0.2, timeout=120)["state"] == "done"
        c.delete(jid)


def test_odd_names_types_stalls_hangups_and_upload_slots(server: Server) -> None:
    c = _client(server, "odd")
    tok = server.tokens["odd"]
    hdr = _bearer(tok)
    with c, httpx.Client(base_url=server.url, headers=hdr, timeout=60) as h:
        jid = _job(c)
        c.start(jid)
        assert c.wait(jid, poll=0.2, timeout=120)["state"] == "done"
        for name in (".", "..", "%00", "normal%00"):
            r = h.get(f"/jobs/{jid}/results/{name}.npy")
            assert r.status_code == 404 and set(r.json()) == {"error", "detail"}, (name, r.text)

        j2 = _job(c, upload=False)
        img = np.full((64, 64), 90, np.uint8).tobytes()
        r = h.put(f"/jobs/{j2}/images/0", content=img, headers={"Content-Type": "Application/Octet-Stream"})
        assert r.status_code == 200, r.text
        head = {"Content-Type": "application/octet-stream", "Content-Length": str(len(img)), **hdr}
        with probe(server) as p:
            # a stalled upload is dropped after the idle timeout (2 s here), its staged file removed
            s = _open(server, "PUT", f"/jobs/{j2}/images/1", head, img[:100])
            code, body = _answer(s, timeout=30)
            assert code == 408 and "stopped arriving" in body["detail"], body
            # a client that hangs up mid-body costs one log line, no traceback
            s = _open(server, "PUT", f"/jobs/{j2}/images/1", head, img[:100])
            time.sleep(0.3)
            s.close()
            # at most 4 uploads in flight per user: the fifth and sixth are refused at once
            stalled = [
                _open(server, "PUT", f"/jobs/{j2}/images/{i}", head, img[:10]) for i in (1, 2, 3, 4, 5, 0)
            ]
            time.sleep(0.5)
            import select

            refused = [s for s in stalled if select.select([s], [], [], 0)[0]]
            answers = [_answer(s) for s in refused]
            assert [a[0] for a in answers] == [429, 429], answers
            for s in stalled:
                s.close()
        _check(p, 40, "stalled and cut-off uploads")
        time.sleep(0.5)
        assert not list((server.data / "jobs" / j2).glob(".maxfs-upload-*")), "staged uploads left behind"
        assert "Traceback" not in (server.tmp / "server.log").read_text()
        c.delete(jid)
        c.delete(j2)
