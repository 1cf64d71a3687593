"""The maxfs command line, run as a real process."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import zarr

from maxfs.storage.layout import JobStore
from tests.data import UW_OBJECTS

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _maxfs(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=timeout)


#: Share of object pixels expected to get a Max-FS normal (a consistent Lambertian set, source 1
#: or 2). The chrome sphere is a mirror (it is there to calibrate the lights): few of its pixels
#: have 3 Lambertian views; the robust model's least-squares fallback gives the others a fit.
MAXFS_SHARE = {obj: (0.95, 1.0) for obj in UW_OBJECTS} | {"chrome": (0.0, 0.3)}


# one object in the fast tier, the others with the slow one
@pytest.mark.parametrize(
    "obj", [o if o == "cat" else pytest.param(o, marks=pytest.mark.slow) for o in UW_OBJECTS]
)
def test_run_uw_object_writes_sane_outputs(tmp_path: Path, obj: str, uw_psm: Path) -> None:
    out = tmp_path / f"{obj}.zarr"
    r = _maxfs("run", str(uw_psm / obj), "-o", str(out), "--workers", "2")
    assert r.returncode == 0, r.stderr
    solved, certified = re.search(r"solved ([\d.]+)%, certified optimal ([\d.]+)%", r.stdout).groups()
    assert float(certified) <= float(solved)
    g = zarr.open_group(out / "results.zarr", mode="r")
    mask = g["mask"][...]
    normal = g["normal"][...][mask]
    solved = np.isfinite(normal[:, 0])
    lo, hi = MAXFS_SHARE[obj]
    assert lo <= np.isin(g["source"][...][mask], (1, 2)).mean() <= hi
    np.testing.assert_allclose(np.linalg.norm(normal[solved], axis=1), 1.0, atol=1e-5)
    if obj != "chrome":  # a diffuse visible surface faces the camera
        assert (normal[solved, 2] > 0).mean() > 0.97
    assert (g["inlier_count"][...][mask][solved] >= 3).all()
    assert not g["inliers"][...][:, mask][:, ~solved].any()
    assert (g["albedo_rgb"][...][mask][solved] >= 0).all()
    src = g["source"][...][mask]  # 1 proved optimum, 2 best found, 3 least-squares fallback, 4 none
    np.testing.assert_array_equal(g["optimal"][...][mask], src == 1)
    np.testing.assert_array_equal(solved, np.isin(src, (1, 2, 3)))
    if obj != "chrome":
        assert (src == 1).mean() > 0.9
    assert not np.isfinite(g["normal"][...][~mask]).any()
    for p in ("normal", "albedo", "inlier_count"):
        assert (out / "previews" / f"{p}.png").stat().st_size > 1000
    if obj == "cat":  # running again resumes: nothing is recomputed
        store = JobStore.open(out, mode="r")
        before, n = store.run_counts(), store.progress().tiles_total  # as the progress line counts
        r = _maxfs("run", str(uw_psm / obj), "-o", str(out), "--workers", "1")
        assert r.returncode == 0 and f"{n} of {n} tiles already done" in r.stderr
        assert JobStore.open(out, mode="r").run_counts() == before


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "/nonexistent/folder", "-o", "x.zarr"], "is not a folder"),
        (["run", "{uw}", "-o", "x.zarr"], "is not a recognised dataset"),
        (["run", "{uw}/cat", "-o", "x.zarr", "--eps", "-2"], "eps must be positive"),
        (["run", "{uw}/cat", "-o", "x.zarr", "--tile", "4096"], "task budget"),
        (["serve", "--no-auth", "--host", "0.0.0.0"], "refusing to serve without auth"),
        (["token", "create", "../alice", "--data-dir", "d"], "is not allowed"),
        (["token", "revoke", "nobody", "--data-dir", "d"], "no user 'nobody'"),
    ],
)
def test_cli_errors_are_messages_not_tracebacks(
    tmp_path: Path, args: list[str], message: str, request: pytest.FixtureRequest
) -> None:
    if any("{uw}" in a for a in args):  # "{uw}": ../shared/data/uw-psm
        uw = request.getfixturevalue("uw_psm")
        args = [a.format(uw=uw) for a in args]
    r = subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2
    assert message in r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "x.zarr").exists()


def test_cli_server_failures_exit_3(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    """A server that cannot be reached or answers 5xx is exit 3; its refusals (4xx) are 2, like bad input."""
    import httpx

    from maxfs.service.cli import main as cli

    r = _maxfs("status", "0" * 32, "--server", "http://127.0.0.1:9", timeout=120)
    assert r.returncode == 3 and "cannot talk to the server" in r.stderr and "Traceback" not in r.stderr

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == f"/jobs/{'1' * 32}":
            return httpx.Response(500, json={"error": "StoreError", "detail": "the job store is unreadable"})
        return httpx.Response(404, json={"error": "NotFoundError", "detail": "no job"})

    real = httpx.Client
    monkeypatch.setattr(httpx, "Client", lambda **kw: real(transport=httpx.MockTransport(answer), **kw))
    assert cli.main(["status", "1" * 32, "--server", "http://maxfs.test"]) == cli.EXIT_SERVER == 3
    assert "server said 500: the job store is unreadable" in capsys.readouterr().err
    assert cli.main(["status", "2" * 32, "--server", "http://maxfs.test"]) == cli.EXIT_USAGE == 2


def test_token_create_list_revoke(tmp_path: Path) -> None:
    from maxfs.storage.tokens import TokenStore

    d = str(tmp_path / "data")
    r = _maxfs("token", "create", "alice", "--data-dir", d)
    assert r.returncode == 0, r.stderr
    token = r.stdout.strip()
    assert token.startswith("mfs_") and len(token) > 40
    assert _maxfs("token", "create", "root", "--admin", "--data-dir", d).returncode == 0
    again = _maxfs("token", "create", "alice", "--data-dir", d)
    assert again.returncode == 2 and "already has a token" in again.stderr
    assert _maxfs("token", "list", "--data-dir", d).stdout.split("\n")[:2] == ["alice", "root  admin"]
    store = TokenStore(tmp_path / "data" / "maxfs-tokens.json")
    assert store.authenticate(token).name == "alice"
    assert token not in (tmp_path / "data" / "maxfs-tokens.json").read_text(), "token stored in clear"
    assert (tmp_path / "data" / "maxfs-tokens.json").stat().st_mode & 0o077 == 0
    assert _maxfs("token", "revoke", "alice", "--data-dir", d).returncode == 0
    assert store.authenticate(token) is None


def test_the_command_collects_its_young_generation_less_often() -> None:
    """The ``maxfs`` script's process raises the young generation's threshold (imports are not
    garbage) and keeps the older generations' as CPython has them."""
    from maxfs.service.cli.gc_policy import GC_GEN0

    probe = (
        "import gc, sys\n"
        "before = gc.get_threshold()\n"
        "import maxfs.service.cli.entry as e\n"
        "sys.argv = ['maxfs', '--help']\n"
        "try:\n    e.console()\nexcept SystemExit:\n    pass\n"
        "print(before, gc.get_threshold(), file=sys.stderr)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=dict(os.environ), timeout=60
    )
    before, after = out.stderr.strip().splitlines()[-1].split(") (")
    b = [int(v) for v in before.strip("()").split(",")]
    a = [int(v) for v in after.strip("()").split(",")]
    assert a == [GC_GEN0, b[1], b[2]] and GC_GEN0 > b[0], out.stderr


def test_the_server_keeps_cpythons_collection_thresholds(tmp_path: Path) -> None:
    """``maxfs serve`` is long-lived (a request's garbage cycles may hold an upload's buffers):
    it serves with the thresholds the process started with, not the CLI's larger young generation."""
    probe = (
        "import gc, sys\n"
        "before = gc.get_threshold()\n"
        "import maxfs.service.cli.entry as e\n"
        "import uvicorn\n"
        "def run(*a, **k):\n"
        "    print('serving', before, gc.get_threshold(), file=sys.stderr, flush=True)\n"
        "uvicorn.run = run\n"
        f"data = {str(tmp_path / 'data')!r}\n"
        "sys.argv = ['maxfs', 'serve', '--no-auth', '--data-dir', data, '--port', '0']\n"
        "e.console()\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=dict(os.environ), timeout=60
    )
    line = [x for x in out.stderr.splitlines() if x.startswith("serving")]
    assert line, out.stderr
    before, during = line[-1].removeprefix("serving ").split(") (")
    assert before + ")" == "(" + during, out.stderr


def test_the_command_keeps_blas_to_one_thread_unless_the_user_set_it() -> None:
    from maxfs.service.cli.entry import one_blas_thread

    env = {"OPENBLAS_NUM_THREADS": "4", "PATH": "/bin"}
    one_blas_thread(env)
    assert env == {
        "OPENBLAS_NUM_THREADS": "4",
        "PATH": "/bin",
        "OMP_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
    }
    # BLAS reads the count once, when numpy loads it: the entry point must set it before any numpy import
    probe = "import sys, maxfs.service.cli.entry as e; e.one_blas_thread(); print('numpy' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=dict(os.environ), timeout=60
    )
    assert out.stdout.strip() == "False", out.stderr


@pytest.mark.parametrize(
    "refusal",
    [
        lambda: httpx.Response(503, text="Service Unavailable"),  # uvicorn at the connection cap
        lambda: httpx.Response(
            503, json={"error": "TooManyConnections", "detail": "this address already has 64"}
        ),
        lambda: (_ for _ in ()).throw(
            httpx.RemoteProtocolError("Server disconnected without sending a response.")
        ),
    ],
    ids=["cap", "per-address cap", "closed to make room"],
)
def test_a_request_the_server_never_served_is_tried_again_with_its_body(monkeypatch, refusal) -> None:
    """The connection limits answer before the app (or close an idle connection to make room):
    nothing was done, so the client tries again, the upload's body made afresh; a route's own
    503 is not retried."""
    from maxfs.service.cli import client as client_module
    from maxfs.service.cli.client import MaxfsClient

    monkeypatch.setattr(client_module, "RETRY_WAIT", 0.0)
    seen: list[bytes] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.read())
        if len(seen) < 3:
            return refusal()
        return httpx.Response(200, json={"id": "j", "state": "created"})

    c = MaxfsClient("http://fake")
    c.http = httpx.Client(base_url="http://fake", transport=httpx.MockTransport(handler))
    image = np.arange(12, dtype=np.uint16).reshape(3, 4)
    assert c.upload_image("j", 0, image)["id"] == "j"
    assert seen == [image.astype("<u2").tobytes()] * 3

    def route_503(request: httpx.Request) -> httpx.Response:
        seen.append(b"")
        return httpx.Response(503, json={"error": "MaxfsError", "detail": "the cluster is starting"})

    c.http = httpx.Client(base_url="http://fake", transport=httpx.MockTransport(route_503))
    seen.clear()
    with pytest.raises(Exception, match="cluster is starting"):
        c.start("j")
    assert len(seen) == 1
