"""Bad requests to a real server with auth and limits on: the status, the reason,
and nothing stored changes (the whole data folder is byte-identical)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from http.client import HTTPConnection
from pathlib import Path
from typing import Any

import httpx
import imagecodecs
import numpy as np
import pytest

from tests.procs import Server, poll_until
from worker import synthetic

K, H, W = 4, 8, 6
LIGHTS = synthetic.lights_uniform(K).tolist()
GOOD = {"k": K, "height": H, "width": W, "dtype": "uint8", "lights": LIGHTS, "eps": 1.0, "tile": 8}


MAX_OPEN, MAX_K, MAX_PIXELS = 3, 64, 1_000_000


def _start(tmp: Path, reserve: int) -> Server:
    env = {
        "MAXFS_MAX_OPEN_JOBS": str(MAX_OPEN),
        "MAXFS_MAX_K": str(MAX_K),
        "MAXFS_MAX_PIXELS": str(MAX_PIXELS),
        "MAXFS_MIN_FREE_BYTES": str(reserve),
    }
    s = Server(tmp / "data", "", tmp, workers=1, auth=True, env=env)
    s.tokens = {"alice": s.token("alice"), "bob": s.token("bob"), "root": s.token("root", admin=True)}
    return s


@pytest.fixture(scope="module")
def servers(tmp_path_factory: pytest.TempPathFactory):
    """The main server keeps no disk reserve, so whatever else writes to the disk meanwhile
    cannot turn its cases into 507s; the "full" server's reserve is larger than any disk,
    so every job it is asked to store gets 507."""
    main = _start(tmp_path_factory.mktemp("http"), 0)
    full = _start(tmp_path_factory.mktemp("http-full"), 1 << 62)
    yield {"main": main, "full": full}
    main.kill()
    full.kill()


def _auth(server: Server, user: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {server.tokens[user]}"}


def _snapshot(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _job(http: httpx.Client, uploaded: int = 0, started: bool = False) -> str:
    """A job of alice's in the given stage; every setup request must succeed."""
    r = http.post("/jobs", json=GOOD)
    assert r.status_code == 201, f"setup: create answered {r.status_code}: {r.text}"
    jid = r.json()["id"]
    for i in range(uploaded):
        img = np.full((H, W), 40 + 30 * i, np.uint8)
        r = http.put(f"/jobs/{jid}/images/{i}", content=img.tobytes())
        assert r.status_code == 200, f"setup: upload answered {r.status_code}: {r.text}"
    if started:
        r = http.post(f"/jobs/{jid}/start")
        assert r.status_code == 202, f"setup: start answered {r.status_code}: {r.text}"
        poll_until(lambda: http.get(f"/jobs/{jid}").json()["state"] == "done", 60, "setup job done")
    return jid


@dataclass(frozen=True)
class Bad:
    name: str
    request: Callable[[httpx.Client, str], httpx.Response]
    status: int
    reason: str
    uploaded: int = 0
    started: bool = False
    extra_jobs: int = 0  # more open jobs of the same user before the request
    server: str = "main"  # "full": the server whose disk reserve no job fits in
    setup: bool = True  # make a job first (off for cases on the "full" server)


def _create(**changes: Any) -> Callable[[httpx.Client, str], httpx.Response]:
    return lambda http, jid: http.post("/jobs", json={**GOOD, **changes})


def _as(headers: dict[str, str], method: str, path: str, **kw: Any):
    """A request with only these credentials; ``{j}`` in ``path`` is the case's job id."""
    return lambda http, jid: httpx.request(
        method, str(http.base_url).rstrip("/") + path.format(j=jid), headers=headers, timeout=60, **kw
    )


def _as_user(user: str, method: str, path: str, **kw: Any):
    """Like :func:`_as` with ``user``'s token (filled in when the case runs)."""
    return lambda http, jid: _as({"Authorization": f"Bearer {http.tokens[user]}"}, method, path, **kw)(
        http, jid
    )


def _raw_json(body: str):
    """A create request with a body httpx would not encode (NaN)."""
    return lambda http, jid: http.post("/jobs", content=body, headers={"Content-Type": "application/json"})


def _too_many_jobs(http: httpx.Client, jid: str) -> httpx.Response:
    return http.post("/jobs", json=GOOD)


def _put(index: int | str, body: bytes, ctype: str = "application/octet-stream", **headers: str):
    return lambda http, jid: http.put(
        f"/jobs/{jid}/images/{index}", content=body, headers={"Content-Type": ctype, **headers}
    )


def _lying_put(http: httpx.Client, path: str, declared: int) -> httpx.Response:
    """A PUT that declares a huge body and sends 4 bytes (httpx refuses to)."""
    url = httpx.URL(str(http.base_url))
    conn = HTTPConnection(url.host, url.port, timeout=30)
    try:
        conn.putrequest("PUT", path)
        conn.putheader("Content-Type", "application/octet-stream")
        conn.putheader("Authorization", http.headers["authorization"])
        conn.putheader("Content-Length", str(declared))
        conn.endheaders(b"\x00" * 4)
        r = conn.getresponse()
        return httpx.Response(r.status, content=r.read())
    finally:
        conn.close()


PNG_WRONG_SIZE = imagecodecs.png_encode(np.zeros((H + 1, W), np.uint8))
PNG_RGB = imagecodecs.png_encode(np.zeros((H, W, 3), np.uint8))
PNG_16 = imagecodecs.png_encode(np.zeros((H, W), np.uint16))

CASES = [
    Bad("k-below-3", _create(k=2, lights=LIGHTS[:2]), 422, "k"),
    Bad("lights-count", _create(lights=LIGHTS[:3]), 422, "3 light directions for 4 images"),
    Bad("lights-not-unit", _create(lights=[[0, 0, 2]] * K), 422, "unit vectors"),
    Bad("lights-zero", _create(lights=[[0, 0, 0]] * K), 422, "unit vectors"),
    Bad("lights-not-3d", _create(lights=[[0, 1]] * K), 422, "rows of 3"),
    Bad("eps-negative", _create(eps=-1), 422, "eps"),
    Bad("eps-word", _create(eps="loose"), 422, "eps"),
    Bad("solver-unknown", _create(solver="simplex"), 422, "solver"),
    Bad("dtype-unknown", _create(dtype="int64"), 422, "dtype"),
    Bad("channels-2", _create(channels=2), 422, "channels"),
    Bad("tile-too-small", _create(tile=2), 422, "tile"),
    Bad("height-zero", _create(height=0), 422, "height"),
    Bad("intensities-count", _create(intensities=[1.0, 1.0]), 422, "light intensities"),
    Bad("intensities-negative", _create(intensities=[1.0, -1.0, 1.0, 1.0]), 422, "positive"),
    Bad("unknown-job", lambda h, j: h.get("/jobs/" + "0" * 32), 404, "no job"),
    Bad("job-id-with-dots", lambda h, j: h.get("/jobs/..%2F..%2Fetc"), 404, "no job"),
    Bad("job-id-not-hex", lambda h, j: h.get("/jobs/zzzz"), 404, "32 hexadecimal"),
    Bad("raw-too-few-bytes", _put(0, b"\x00" * (H * W - 1)), 422, f"expected {H * W}"),
    Bad("raw-too-many-bytes", _put(0, b"\x00" * (H * W + 5)), 413, "larger than"),
    Bad("declared-too-large", lambda h, j: _lying_put(h, f"/jobs/{j}/images/0", 10**9), 413, "larger than"),
    Bad("index-out-of-range", _put(K, b"\x00" * (H * W)), 404, "out of range"),
    Bad("index-negative", _put(-1, b"\x00" * (H * W)), 422, "index"),
    Bad("corrupt-png", _put(0, b"\x89PNG\r\n\x1a\n" + b"junk" * 10, "image/png"), 422, "cannot decode"),
    Bad("png-wrong-size", _put(0, PNG_WRONG_SIZE, "image/png"), 422, "has shape"),
    Bad("png-rgb-for-grey-job", _put(0, PNG_RGB, "image/png"), 422, "has shape"),
    Bad("png-16bit-for-8bit-job", _put(0, PNG_16, "image/png"), 422, "dtype"),
    Bad("start-missing-images", lambda h, j: h.post(f"/jobs/{j}/start"), 409, "missing 2 images", uploaded=2),
    Bad(
        "mask-wrong-bytes",
        lambda h, j: h.put(
            f"/jobs/{j}/mask", content=b"\x01" * 3, headers={"Content-Type": "application/octet-stream"}
        ),
        422,
        "mask",
    ),
    Bad("upload-after-done", _put(0, b"\x00" * (H * W)), 409, "done", uploaded=K, started=True),
    Bad(
        "start-twice", lambda h, j: h.post(f"/jobs/{j}/start"), 409, "already done", uploaded=K, started=True
    ),
    Bad(
        "cancel-finished", lambda h, j: h.delete(f"/jobs/{j}"), 409, "already done", uploaded=K, started=True
    ),
    Bad(
        "unknown-result",
        lambda h, j: h.get(f"/jobs/{j}/results/secrets.npy"),
        404,
        "no output array",
        uploaded=K,
        started=True,
    ),
    Bad("unknown-preview", lambda h, j: h.get(f"/jobs/{j}/previews/x.png"), 404, "no preview"),
    Bad(
        "lights-nan",
        _raw_json(json.dumps({**GOOD, "lights": [[float("nan"), 0, 1], *LIGHTS[1:]]})),
        422,
        "finite",
    ),
    Bad("tile-over-task-memory", _create(tile=4096), 422, "task budget"),
    Bad("index-with-path", _put("..%2F0", b"\x00" * (H * W)), 404, "no job or route"),
    Bad("result-name-with-path", lambda h, j: h.get(f"/jobs/{j}/results/..%2Fmaxfs-job.npy"), 404, "no"),
    # auth: no token, a wrong one, another scheme; other users' jobs do not exist for them
    Bad("no-token", _as({}, "GET", "/jobs/{j}"), 401, "needs an API token"),
    Bad("wrong-token", _as({"Authorization": "Bearer mfs_x"}, "GET", "/jobs/{j}"), 401, "not valid"),
    Bad("basic-scheme", _as({"Authorization": "Basic YTpi"}, "GET", "/jobs/{j}"), 401, "Bearer"),
    Bad("no-token-create", _as({}, "POST", "/jobs", json=GOOD), 401, "API token"),
    Bad("other-user-status", _as_user("bob", "GET", "/jobs/{j}"), 404, "no job"),
    Bad(
        "other-user-upload",
        _as_user("bob", "PUT", "/jobs/{j}/images/0", content=b"\x00" * (H * W)),
        404,
        "no job",
    ),
    Bad("other-user-start", _as_user("bob", "POST", "/jobs/{j}/start"), 404, "no job", uploaded=K),
    Bad("other-user-cancel", _as_user("bob", "DELETE", "/jobs/{j}"), 404, "no job"),
    Bad(
        "other-user-result",
        _as_user("bob", "GET", "/jobs/{j}/results/normal.npy"),
        404,
        "no job",
        uploaded=K,
        started=True,
    ),
    Bad(
        "other-user-zip",
        _as_user("bob", "GET", "/jobs/{j}/results.zip"),
        404,
        "no job",
        uploaded=K,
        started=True,
    ),
    # limits
    Bad("too-many-open-jobs", _too_many_jobs, 429, "unfinished jobs", extra_jobs=MAX_OPEN - 1),
    Bad(
        "k-over-limit",
        _create(k=MAX_K + 1, lights=synthetic.lights_uniform(MAX_K + 1).tolist()),
        413,
        "MAX_K",
    ),
    Bad("pixels-over-limit", _create(height=2000, width=1000), 413, "MAX_PIXELS"),
    Bad("disk-full", _create(), 507, "free above its reserve", server="full", setup=False),
    # one validator: every bad option is a 422 before anything is stored (issue #9)
    Bad("saturation-below-shadow", _create(saturation=2.0, shadow=5.0), 422, "must be above shadow"),
    Bad("saturation-below-eps", _create(saturation=0.2), 422, "must be above the default shadow threshold"),
    Bad("shadow-infinite", _raw_json(json.dumps({**GOOD, "shadow": float("inf")})), 422, "finite"),
    Bad("box-factor-infinite", _raw_json(json.dumps({**GOOD, "box_factor": float("inf")})), 422, "finite"),
    Bad("box-factor-below-1", _create(box_factor=0.5), 422, "box_factor"),
    Bad("eps-infinite", _raw_json(json.dumps({**GOOD, "eps": float("inf")})), 422, "eps"),
    Bad("max-nodes-past-int64", _create(max_nodes=2**70), 422, "max_nodes must be between"),
    Bad("max-nodes-zero", _create(max_nodes=0), 422, "max_nodes"),
    Bad("milp-time-zero", _create(milp_time_limit=0), 422, "milp_time_limit"),
    Bad("lights-ragged", _create(lights=[[0, 0, 1], [0, 1], *LIGHTS[2:]]), 422, "rows of 3 numbers"),
    Bad("intensities-ragged", _create(intensities=[[1, 1], [1], [1, 1], [1, 1]]), 422, "light intensities"),
    Bad("unknown-field", _create(epsilon=3), 422, "epsilon: Extra inputs are not permitted"),
    Bad(
        "lights-coplanar",
        _create(lights=[[0, 0, 1], [0, 0.6, 0.8], [0, -0.6, 0.8], [0, 0.8, 0.6]]),
        422,
        "singular values",
    ),
    Bad("lights-repeated", _create(lights=[[0, 0, 1]] * K), 422, "rank < 3"),
    # results exist only once a job has run (issue #9)
    Bad("result-before-start", lambda h, j: h.get(f"/jobs/{j}/results/normal.npy"), 409, "has not run yet"),
    Bad("preview-before-start", lambda h, j: h.get(f"/jobs/{j}/previews/normal.png"), 409, "not run yet"),
    Bad("zip-before-start", lambda h, j: h.get(f"/jobs/{j}/results.zip"), 409, "not run yet", uploaded=K),
]


def _close_open_jobs(server: Server) -> None:
    """Cancel every unfinished job (as admin), so each case starts under the job limit."""
    with httpx.Client(base_url=server.url, headers=_auth(server, "root"), timeout=60) as admin:
        for job in admin.get("/jobs").json():
            if job["state"] not in ("done", "failed", "cancelled"):
                assert admin.delete(f"/jobs/{job['id']}").status_code == 200


def test_catalogue_is_large_enough() -> None:
    assert len(CASES) >= 25 and len({c.name for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_bad_request(servers: dict[str, Server], case: Bad) -> None:
    server = servers[case.server]
    with httpx.Client(base_url=server.url, headers=_auth(server, "alice"), timeout=60) as http:
        http.tokens = server.tokens
        try:
            jid = _job(http, case.uploaded, case.started) if case.setup else "0" * 32
            for _ in range(case.extra_jobs):
                _job(http)
            before = _snapshot(server.data)
            r = case.request(http, jid)
            assert r.status_code == case.status, r.text
            body = r.json()
            assert set(body) == {"error", "detail"}
            assert case.reason in body["detail"], body
            if r.status_code == 401:
                assert r.headers["www-authenticate"] == "Bearer"
            assert _snapshot(server.data) == before, "a rejected request changed stored data"
        finally:
            _close_open_jobs(server)
