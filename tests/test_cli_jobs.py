"""CLI verbs for server jobs (jobs, wait, start, cancel, fetch, delete, status --json, submit --wait and
its solver options), --version, plain progress."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from maxfs.storage.datasets import write_npy_folder
from maxfs.worker import synthetic
from tests.procs import Server

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _maxfs(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=timeout)


def _imports(*args: str) -> set[str]:
    """The modules a ``maxfs`` command imports (as ``python -X importtime`` lists them)."""
    r = subprocess.run(
        [sys.executable, "-X", "importtime", MAXFS, *args], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return {ln.rsplit("|", 1)[-1].strip() for ln in r.stderr.splitlines() if ln.startswith("import time:")}


def test_job_verbs_against_a_real_server(tmp_path: Path, server_factory: Callable[..., Server]) -> None:
    s = synthetic.sphere(8, 24, specular=0.0)
    folder = write_npy_folder(tmp_path / "in", s.images.astype(np.uint8), s.lights, s.mask)
    server = server_factory(workers=1, graceful=True)
    url = ["--server", server.url]
    r = _maxfs("submit", str(folder), *url, "--images", "1-6", "--eps", "1", "--wait")
    assert r.returncode == 0, r.stderr
    job_id = r.stdout.split()[0]
    assert len(job_id) == 32 and " done " in r.stdout
    assert "\r" not in r.stderr and "tiles" in r.stderr  # plain progress lines off a terminal

    r = _maxfs("jobs", *url)
    assert r.returncode == 0 and job_id in r.stdout and "done" in r.stdout
    r = _maxfs("jobs", *url, "--json")
    assert [j["id"] for j in json.loads(r.stdout)] == [job_id]
    r = _maxfs("status", job_id, *url)
    assert r.returncode == 0 and r.stdout.startswith(job_id) and "tiles 1/1 (100%)" in r.stdout
    r = _maxfs("status", job_id, *url, "--json")
    st = json.loads(r.stdout)
    assert st["state"] == "done" and st["k"] == 6 and st["progress"]["tiles_done"] == 1
    r = _maxfs("wait", job_id, *url, "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["state"] == "done"
    r = _maxfs("start", job_id, *url)
    assert r.returncode == 2 and "already done" in r.stderr and "Traceback" not in r.stderr
    r = _maxfs("wait", "0" * 32, *url)
    assert r.returncode == 2 and "Traceback" not in r.stderr

    # the client commands start light: no numpy (~0.15 s of each), no trio (~0.07 s, which httpcore
    # imports where it is installed, as the test extra does), no zarr, numba or pydantic models
    out = tmp_path / "fetched"
    for verb in (["status", job_id], ["wait", job_id], ["jobs"], ["fetch", job_id, "-o", str(out)]):
        mods = _imports(*verb, *url)
        # (trio itself is listed even when skipped: the import that fails; a real one loads trio._core)
        heavy = {m for m in mods if m.split(".")[0] in ("numpy", "zarr", "numba") or m.startswith("trio.")}
        assert not heavy, f"maxfs {verb[0]} imports {sorted(heavy)[:5]}"
    assert (out / "results.zarr").is_dir()
    # submit reads the folder (numpy) but needs neither the store's zarr nor the solver's numba
    mods = _imports("submit", str(folder), *url, "--images", "1-6", "--eps", "1", "--reuse")
    heavy = {m for m in mods if m.split(".")[0] in ("zarr", "numba") or m.startswith("trio.")}
    assert not heavy, f"maxfs submit imports {sorted(heavy)[:5]}"


def test_version() -> None:
    r = _maxfs("--version")
    assert r.returncode == 0 and r.stdout.startswith("maxfs ")


def test_plain_progress_lines_off_a_terminal() -> None:
    import io

    from maxfs.service.cli.verbs import Progress

    out = io.StringIO()
    p = Progress(stream=out)
    for i in range(101):
        p.update(i, 100, "running" if i < 100 else "done", rate=1000.0, eta=10.0)
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue() and 10 <= len(lines) <= 12 and lines[-1].startswith("100/100 tiles")


def test_submit_options_cancel_start_wait_fetch_and_delete(
    tmp_path: Path, server_factory: Callable[..., Server]
) -> None:
    """The solver options of ``submit`` reach the job; ``start --wait`` resumes a cancelled job to
    done; ``fetch --wait`` downloads it; ``delete`` removes it."""
    s = synthetic.sphere(8, 64, specular=0.0)
    folder = write_npy_folder(tmp_path / "in", s.images.astype(np.uint8), s.lights, s.mask)
    server = server_factory(workers=1, graceful=True)
    url = ["--server", server.url]
    opts = ["--solver", "milp", "--tile", "16", "--eps", "1", "--model", "paper", "--shadow", "2"]
    opts += ["--max-nodes", "5000", "--milp-time-limit", "5", "--no-fallback"]
    r = _maxfs("submit", str(folder), *url, *opts)
    assert r.returncode == 0, r.stderr
    job_id = r.stdout.split()[0]
    r = _maxfs("cancel", job_id, *url)  # 16 tiles of the MILP: seconds of work, cancelled long before
    assert r.returncode == 0 and r.stdout.strip() == "cancelled", (r.stdout, r.stderr)

    r = _maxfs("fetch", job_id, *url, "-o", str(tmp_path / "partial"))
    assert r.returncode == 2 and "--partial" in r.stderr and "Traceback" not in r.stderr
    r = _maxfs("start", job_id, *url, "--wait", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["state"] == "done"
    r = _maxfs("fetch", job_id, *url, "-o", str(tmp_path / "out.zarr"), "--wait")
    assert r.returncode == 0, r.stderr

    from maxfs.storage.layout import JobStore

    got = JobStore.open(tmp_path / "out.zarr", mode="r")
    p = got.params
    assert (p.solver, p.model, p.tile, p.eps, p.shadow) == ("milp", "paper", 16, 1.0, 2.0)
    assert (p.max_nodes, p.milp_time_limit, p.fallback) == (5000, 5.0, False)
    assert got.done_grid().all() and np.isfinite(got.read_output("normal")[s.mask]).mean() > 0.9
    # fetching into an existing folder: refused, unless --overwrite (and only over maxfs results)
    r = _maxfs("fetch", job_id, *url, "-o", str(tmp_path / "out.zarr"))
    assert r.returncode == 2 and "already exists" in r.stderr and "--overwrite" in r.stderr, r.stderr
    r = _maxfs("fetch", job_id, *url, "-o", str(tmp_path / "out.zarr"), "--overwrite")
    assert r.returncode == 0 and JobStore.open(tmp_path / "out.zarr", mode="r").done_grid().all(), r.stderr
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    r = _maxfs("fetch", job_id, *url, "-o", str(tmp_path / "mine"), "--overwrite")
    assert r.returncode == 2 and "other than maxfs results" in r.stderr
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"

    r = _maxfs("delete", job_id, *url)
    assert r.returncode == 0 and "deleted" in r.stderr, r.stderr
    assert not (server.data / "jobs" / job_id).exists()
    r = _maxfs("status", job_id, *url)
    assert r.returncode == 2 and "Traceback" not in r.stderr


def test_named_jobs_reuse_and_two_submits_of_one_folder(
    tmp_path: Path, server_factory: Callable[..., Server]
) -> None:
    """A job is called by its folder's name (or --name) in ``jobs`` and ``status``; two submits of
    one folder at once both end with the job's outcome; an identical submit after it is done is
    refused with the job's id, and ``--reuse`` returns that job."""
    import concurrent.futures

    import httpx

    s = synthetic.sphere(8, 24, specular=0.0)
    folder = write_npy_folder(tmp_path / "bear", s.images.astype(np.uint8), s.lights, s.mask)
    server = server_factory(workers=1, graceful=True)
    url = ["--server", server.url]
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        runs = list(pool.map(lambda _: _maxfs("submit", str(folder), *url, "--eps", "1", "--wait"), range(2)))
    for r in runs:
        assert r.returncode == 0 and " done " in r.stdout, (r.stdout, r.stderr)
    ids = {r.stdout.split()[0] for r in runs}
    jobs = json.loads(_maxfs("jobs", *url, "--json").stdout)
    assert {j["id"] for j in jobs} == ids and all(j["name"] == "bear" for j in jobs)
    job_id = sorted(ids)[0]
    r = _maxfs("status", job_id, *url)
    assert r.stdout.startswith(f"{job_id}  bear  done"), r.stdout

    r = _maxfs("submit", str(folder), *url, "--eps", "1")
    assert r.returncode == 2 and "already has results for these inputs" in r.stderr and "--reuse" in r.stderr
    assert "(bear)" in r.stderr
    r = _maxfs("submit", str(folder), *url, "--eps", "1", "--reuse")
    assert r.returncode == 0 and r.stdout.strip() in ids
    r = _maxfs("submit", str(folder), *url, "--eps", "2", "--name", "bear eps 2", "--wait")
    assert r.returncode == 0 and r.stdout.split()[0] not in ids  # other parameters: a new job
    assert "bear eps 2" in _maxfs("jobs", *url).stdout
    who = httpx.get(server.url + "/jobs", timeout=30).headers["X-Maxfs-User"]
    assert who == "no sign-in (auth is off)"


def test_submit_gives_the_server_the_grid_of_maxfs_run(
    tmp_path: Path, server_factory: Callable[..., Server]
) -> None:
    """A server cannot balance tiles over a mask that arrives after the job, so ``maxfs submit``
    sends the edge ``maxfs run`` chooses: the same grid, so the same normals bit for bit (ties
    are decided by the grid). A server whose task budget refuses that edge chooses its own."""
    from maxfs.service.cli.client import run_tile
    from maxfs.storage.inputs import load_folder
    from maxfs.storage.layout import JobStore
    from maxfs.storage.tiles import tile_memory

    s = synthetic.sphere(8, 160, specular=0.0)  # a disc in a frame that alone asks for one large tile
    folder = write_npy_folder(tmp_path / "in", s.images.astype(np.uint8), s.lights, s.mask)
    edge = run_tile(load_folder(folder), {})
    r = _maxfs("run", str(folder), "-o", str(tmp_path / "local"), "--eps", "1")
    assert r.returncode == 0, r.stderr
    local = JobStore.open(tmp_path / "local", mode="r")
    assert local.params.tile == edge < 160

    server = server_factory(workers=1, graceful=True)
    r = _maxfs("submit", str(folder), "--server", server.url, "--eps", "1", "--wait")
    assert r.returncode == 0, r.stderr
    r = _maxfs("fetch", r.stdout.split()[0], "--server", server.url, "-o", str(tmp_path / "remote"))
    assert r.returncode == 0, r.stderr
    remote = JobStore.open(tmp_path / "remote", mode="r")
    assert remote.params.tile == edge
    assert remote.read_output("normal").tobytes() == local.read_output("normal").tobytes()

    small = server_factory(
        data_dir=tmp_path / "small", env={"MAXFS_TASK_MEMORY": str(tile_memory(edge - 16, 8, None, 1))}
    )
    r = _maxfs("submit", str(folder), "--server", small.url, "--eps", "1")
    assert r.returncode == 0, r.stderr  # refused edge: the server's own auto edge instead
    log = small.log.read_text()
    assert '"POST /jobs HTTP/1.1" 422' in log and '"POST /jobs HTTP/1.1" 201' in log, log
