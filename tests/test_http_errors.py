"""Bad requests to a real server with auth and limits on: the status, the reason,
and nothing stored changes (the whole data folder is byte-identical)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import imagecodecs
import numpy as np
import pytest

from maxfs.worker import synthetic
from tests.badrequests import Bad, Req, Step, check_refused, run_setup, send
from tests.procs import Server

K, H, W = 4, 8, 6
LIGHTS = synthetic.lights_uniform(K).tolist()
GOOD = {"k": K, "height": H, "width": W, "dtype": "uint8", "lights": LIGHTS, "eps": 1.0, "tile": 8}


MAX_OPEN, MAX_K, MAX_PIXELS = 3, 64, 1_000_000


def _start(factory: Callable[..., Server], tmp: Path, reserve: int) -> Server:
    env = {
        "MAXFS_MAX_OPEN_JOBS": str(MAX_OPEN),
        "MAXFS_MAX_K": str(MAX_K),
        "MAXFS_MAX_PIXELS": str(MAX_PIXELS),
        "MAXFS_MIN_FREE_BYTES": str(reserve),
    }
    s = factory(tmp / "data", logs=tmp, workers=1, auth=True, env=env)
    s.tokens = {"alice": s.token("alice"), "bob": s.token("bob"), "root": s.token("root", admin=True)}
    return s


@pytest.fixture(scope="module")
def servers(module_server_factory, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Server]:
    """The main server keeps no disk reserve, so whatever else writes to the disk meanwhile
    cannot turn its cases into 507s; the "full" server's reserve is larger than any disk,
    so every job it is asked to store gets 507."""
    return {
        "main": _start(module_server_factory, tmp_path_factory.mktemp("http"), 0),
        "full": _start(module_server_factory, tmp_path_factory.mktemp("http-full"), 1 << 62),
    }


def _auth(server: Server, user: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {server.tokens[user]}"}


def _snapshot(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# -- setup steps: a job of alice's in a given stage -----------------------------------------------

CREATE = Step(Req("POST", "/jobs", json=GOOD), 201, keep_id=True)
ANOTHER_JOB = Step(Req("POST", "/jobs", json=GOOD), 201)  # one more open job of alice's


def _uploads(n: int) -> tuple[Step, ...]:
    return tuple(
        Step(
            Req("PUT", f"/jobs/{{j}}/images/{i}", content=np.full((H, W), 40 + 30 * i, np.uint8).tobytes()),
            200,
        )
        for i in range(n)
    )


JOB = (CREATE,)  # created, nothing uploaded
ALL_UPLOADED = (CREATE, *_uploads(K))
DONE = (
    *ALL_UPLOADED,
    Step(Req("POST", "/jobs/{j}/start"), 202),
    Step(Req("GET", "/jobs/{j}"), 200, until="done"),
)

# -- requests ----------------------------------------------------------------------------------


def _create(**changes: Any) -> Req:
    return Req("POST", "/jobs", json={**GOOD, **changes})


def _raw_json(body: str) -> Req:
    """A create request with a body httpx would not encode (NaN, infinity)."""
    return Req("POST", "/jobs", content=body.encode(), ctype="application/json")


def _put(index: int | str, body: bytes, ctype: str = "application/octet-stream") -> Req:
    return Req("PUT", f"/jobs/{{j}}/images/{index}", content=body, ctype=ctype)


def _get(path: str, user: str | None = "alice", **headers: str) -> Req:
    return Req("GET", path, user=user, headers=headers)


PNG_WRONG_SIZE = imagecodecs.png_encode(np.zeros((H + 1, W), np.uint8))
PNG_RGB = imagecodecs.png_encode(np.zeros((H, W, 3), np.uint8))
PNG_16 = imagecodecs.png_encode(np.zeros((H, W), np.uint16))
RAW = b"\x00" * (H * W)

# name, setup, request, status, reason substring (and the server: "full" keeps a reserve no job fits in)
CASES = [
    Bad("k-below-3", JOB, _create(k=2, lights=LIGHTS[:2]), 422, "k"),
    Bad("lights-count", JOB, _create(lights=LIGHTS[:3]), 422, "3 light directions for 4 images"),
    Bad("lights-not-unit", JOB, _create(lights=[[0, 0, 2]] * K), 422, "unit vectors"),
    Bad("lights-zero", JOB, _create(lights=[[0, 0, 0]] * K), 422, "unit vectors"),
    Bad("lights-not-3d", JOB, _create(lights=[[0, 1]] * K), 422, "rows of 3"),
    Bad("eps-negative", JOB, _create(eps=-1), 422, "eps"),
    Bad("eps-word", JOB, _create(eps="loose"), 422, "eps"),
    Bad("solver-unknown", JOB, _create(solver="simplex"), 422, "solver"),
    Bad("dtype-unknown", JOB, _create(dtype="int64"), 422, "dtype"),
    Bad("channels-2", JOB, _create(channels=2), 422, "channels"),
    Bad("tile-too-small", JOB, _create(tile=2), 422, "tile"),
    Bad("height-zero", JOB, _create(height=0), 422, "height"),
    Bad("intensities-count", JOB, _create(intensities=[1.0, 1.0]), 422, "light intensities"),
    Bad("intensities-negative", JOB, _create(intensities=[1.0, -1.0, 1.0, 1.0]), 422, "positive"),
    Bad("unknown-job", JOB, _get("/jobs/" + "0" * 32), 404, "no job"),
    Bad("job-id-with-dots", JOB, _get("/jobs/..%2F..%2Fetc"), 404, "no job"),
    Bad("job-id-not-hex", JOB, _get("/jobs/zzzz"), 404, "32 hexadecimal"),
    Bad("raw-too-few-bytes", JOB, _put(0, b"\x00" * (H * W - 1)), 422, f"expected {H * W}"),
    Bad("raw-too-many-bytes", JOB, _put(0, b"\x00" * (H * W + 5)), 413, "larger than"),
    Bad(
        "declared-too-large",
        JOB,
        Req(
            "PUT", "/jobs/{j}/images/0", content=b"\x00" * 4, ctype="application/octet-stream", declared=10**9
        ),
        413,
        "larger than",
    ),
    Bad("index-out-of-range", JOB, _put(K, RAW), 404, "out of range"),
    Bad("index-negative", JOB, _put(-1, RAW), 422, "index"),
    Bad("corrupt-png", JOB, _put(0, b"\x89PNG\r\n\x1a\n" + b"junk" * 10, "image/png"), 422, "cannot decode"),
    Bad("png-wrong-size", JOB, _put(0, PNG_WRONG_SIZE, "image/png"), 422, "has shape"),
    Bad("png-rgb-for-grey-job", JOB, _put(0, PNG_RGB, "image/png"), 422, "has shape"),
    Bad("png-16bit-for-8bit-job", JOB, _put(0, PNG_16, "image/png"), 422, "dtype"),
    Bad(
        "start-missing-images",
        (CREATE, *_uploads(2)),
        Req("POST", "/jobs/{j}/start"),
        409,
        "missing 2 images",
    ),
    Bad(
        "mask-wrong-bytes",
        JOB,
        Req("PUT", "/jobs/{j}/mask", content=b"\x01" * 3, ctype="application/octet-stream"),
        422,
        "mask",
    ),
    Bad("upload-after-done", DONE, _put(0, RAW), 409, "done"),
    Bad("start-twice", DONE, Req("POST", "/jobs/{j}/start"), 409, "already done"),
    Bad("cancel-finished", DONE, Req("DELETE", "/jobs/{j}"), 409, "already done"),
    Bad("unknown-result", DONE, _get("/jobs/{j}/results/secrets.npy"), 404, "no output array"),
    Bad("unknown-preview", JOB, _get("/jobs/{j}/previews/x.png"), 404, "no preview"),
    Bad(
        "lights-nan",
        JOB,
        _raw_json(json.dumps({**GOOD, "lights": [[float("nan"), 0, 1], *LIGHTS[1:]]})),
        422,
        "finite",
    ),
    Bad("tile-over-task-memory", JOB, _create(tile=4096), 422, "task budget"),
    Bad("index-with-path", JOB, _put("..%2F0", RAW), 404, "no job or route"),
    Bad("result-name-with-path", JOB, _get("/jobs/{j}/results/..%2Fmaxfs-job.npy"), 404, "no"),
    # auth: no token, a wrong one, another scheme; other users' jobs do not exist for them
    Bad("no-token", JOB, _get("/jobs/{j}", user=None), 401, "needs an API token"),
    Bad("wrong-token", JOB, _get("/jobs/{j}", None, Authorization="Bearer mfs_x"), 401, "not valid"),
    Bad("basic-scheme", JOB, _get("/jobs/{j}", None, Authorization="Basic YTpi"), 401, "Bearer"),
    Bad("no-token-create", JOB, Req("POST", "/jobs", json=GOOD, user=None), 401, "API token"),
    Bad("other-user-status", JOB, _get("/jobs/{j}", user="bob"), 404, "no job"),
    Bad("other-user-upload", JOB, Req("PUT", "/jobs/{j}/images/0", content=RAW, user="bob"), 404, "no job"),
    Bad("other-user-start", ALL_UPLOADED, Req("POST", "/jobs/{j}/start", user="bob"), 404, "no job"),
    Bad("other-user-cancel", JOB, Req("DELETE", "/jobs/{j}", user="bob"), 404, "no job"),
    Bad("other-user-result", DONE, _get("/jobs/{j}/results/normal.npy", user="bob"), 404, "no job"),
    Bad("other-user-zip", DONE, _get("/jobs/{j}/results.zip", user="bob"), 404, "no job"),
    # limits
    Bad("too-many-open-jobs", (CREATE, *[ANOTHER_JOB] * (MAX_OPEN - 1)), _create(), 429, "unfinished jobs"),
    Bad(
        "k-over-limit",
        JOB,
        _create(k=MAX_K + 1, lights=synthetic.lights_uniform(MAX_K + 1).tolist()),
        413,
        "MAX_K",
    ),
    Bad("pixels-over-limit", JOB, _create(height=2000, width=1000), 413, "MAX_PIXELS"),
    Bad("disk-full", (), _create(), 507, "free above its reserve", server="full"),
    # one validator: every bad option is a 422 before anything is stored (issue #9)
    Bad("saturation-below-shadow", JOB, _create(saturation=2.0, shadow=5.0), 422, "must be above shadow"),
    Bad("saturation-below-eps", JOB, _create(saturation=0.2), 422, "above the default shadow threshold"),
    Bad("shadow-infinite", JOB, _raw_json(json.dumps({**GOOD, "shadow": float("inf")})), 422, "finite"),
    Bad(
        "box-factor-infinite", JOB, _raw_json(json.dumps({**GOOD, "box_factor": float("inf")})), 422, "finite"
    ),
    Bad("box-factor-below-1", JOB, _create(box_factor=0.5), 422, "box_factor"),
    Bad("eps-infinite", JOB, _raw_json(json.dumps({**GOOD, "eps": float("inf")})), 422, "eps"),
    Bad("max-nodes-past-int64", JOB, _create(max_nodes=2**70), 422, "max_nodes must be between"),
    Bad("max-nodes-zero", JOB, _create(max_nodes=0), 422, "max_nodes"),
    Bad("milp-time-zero", JOB, _create(milp_time_limit=0), 422, "milp_time_limit"),
    Bad("lights-ragged", JOB, _create(lights=[[0, 0, 1], [0, 1], *LIGHTS[2:]]), 422, "rows of 3 numbers"),
    Bad(
        "intensities-ragged",
        JOB,
        _create(intensities=[[1, 1], [1], [1, 1], [1, 1]]),
        422,
        "light intensities",
    ),
    Bad("unknown-field", JOB, _create(epsilon=3), 422, "epsilon: Extra inputs are not permitted"),
    Bad(
        "lights-coplanar",
        JOB,
        _create(lights=[[0, 0, 1], [0, 0.6, 0.8], [0, -0.6, 0.8], [0, 0.8, 0.6]]),
        422,
        "singular values",
    ),
    Bad("lights-repeated", JOB, _create(lights=[[0, 0, 1]] * K), 422, "rank < 3"),
    # results exist only once a job has run (issue #9)
    Bad("result-before-start", JOB, _get("/jobs/{j}/results/normal.npy"), 409, "has not run yet"),
    Bad("preview-before-start", JOB, _get("/jobs/{j}/previews/normal.png"), 409, "not run yet"),
    Bad("zip-before-start", ALL_UPLOADED, _get("/jobs/{j}/results.zip"), 409, "not run yet"),
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
    try:
        jid = run_setup(server, case.setup)
        before = _snapshot(server.data)
        check_refused(send(server, case.request, jid), case)
        assert _snapshot(server.data) == before, "a rejected request changed stored data"
    finally:
        _close_open_jobs(server)
