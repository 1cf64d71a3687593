"""Tiles on a real SLURM cluster through dask-jobqueue (``--cluster slurm``).

The cluster is a single-node ``slurmctld`` + ``slurmd`` with munge on this machine,
started by ``deploy/slurm/start-local.sh`` (idempotent) from the fixture; worker jobs
are real SLURM batch jobs, so ``scancel`` and the controller's job completion log are
the real thing. Each run is compared bit for bit with the plain local ``maxfs run``.
Without SLURM installed (or not root) the tests skip, except where
``MAXFS_REQUIRE_SLURM=1`` (CI) makes that a failure.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from maxfs.service.cli.client import MaxfsClient
from maxfs.storage.inputs import load_folder
from maxfs.storage.layout import JobStore
from tests.procs import Server, poll_until

pytestmark = pytest.mark.slurm

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
MAXFS = str(BIN / "maxfs")
OUTPUTS = ("normal", "albedo", "albedo_rgb", "inliers", "inlier_count", "optimal")


@pytest.fixture(scope="module", autouse=True)
def cat(uw_psm: Path) -> Path:
    """Every test here runs on the UW psm cat: without ``../shared/data`` they skip, saying so."""
    return uw_psm / "cat"


@dataclass(frozen=True)
class Slurm:
    conf: Path

    @property
    def dir(self) -> Path:
        return self.conf.parent

    def env(self, **settings: str) -> dict[str, str]:
        """The environment of a maxfs process using this cluster (1 core, 1 GiB per worker job)."""
        return {
            **os.environ,
            "SLURM_CONF": str(self.conf),
            "MAXFS_SLURM_INTERFACE": "lo",
            "MAXFS_SLURM_MEMORY": "1GiB",
            "MAXFS_SLURM_WALLTIME": "00:30:00",
            **settings,
        }

    def jobcomp(self) -> dict[int, str]:
        """Job id -> state of every finished job, from the controller's job completion log."""
        log = self.dir / "jobcomp.log"
        text = log.read_text() if log.exists() else ""
        return {
            int(m[1]): m[3]
            for m in re.finditer(r"JobId=(\d+) .*?Name=(\S+) JobState=(\S+)", text)
            if m[2] == "maxfs-worker"
        }

    def queued(self) -> set[int]:
        """Ids of maxfs worker jobs SLURM still has pending or running."""
        r = subprocess.run(
            ["squeue", "-h", "-n", "maxfs-worker", "-o", "%i"],
            capture_output=True,
            text=True,
            env={**os.environ, "SLURM_CONF": str(self.conf)},
            check=True,
        )
        return {int(x) for x in r.stdout.split()}


@pytest.fixture(scope="module")
def slurm() -> Slurm:
    if shutil.which("sbatch") is None or os.geteuid() != 0:
        why = "needs SLURM (apt-get install slurm-wlm munge) and root for deploy/slurm/start-local.sh"
        if os.environ.get("MAXFS_REQUIRE_SLURM") == "1":
            pytest.fail(why)
        pytest.skip(why)
    r = subprocess.run(
        [str(REPO / "deploy/slurm/start-local.sh")], capture_output=True, text=True, timeout=180
    )
    assert r.returncode == 0, r.stderr
    m = re.search(r"^SLURM_CONF=(.+)$", r.stdout, re.M)
    assert m, r.stdout
    return Slurm(Path(m[1]))


@pytest.fixture(scope="module")
def local_ref(tmp_path_factory: pytest.TempPathFactory, cat: Path) -> dict[str, np.ndarray]:
    """The cat solved by a plain ``maxfs run`` on this machine."""
    out = tmp_path_factory.mktemp("local") / "cat.zarr"
    r = subprocess.run([MAXFS, "run", str(cat), "-o", str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return _arrays(out)


def _arrays(out: Path) -> dict[str, np.ndarray]:
    store = JobStore.open(out, mode="r")
    return {n: store.read_output(n) for n in OUTPUTS}


def _assert_bit_identical(got: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> None:
    for n in OUTPUTS:
        assert got[n].dtype == ref[n].dtype and got[n].shape == ref[n].shape, n
        assert got[n].tobytes() == ref[n].tobytes(), f"{n} differs from the local run"


def _job_ids(log_dir: Path) -> set[int]:
    """SLURM ids of the worker jobs whose output is in ``log_dir`` (maxfs-worker-<id>.err)."""
    return {int(p.stem.rsplit("-", 1)[1]) for p in log_dir.glob("maxfs-worker-*.err")}


def _wait_released(slurm: Slurm, ids: set[int], timeout: float = 60) -> None:
    """Until every one of ``ids`` has left the queue and is in the job completion log."""
    poll_until(
        lambda: not (slurm.queued() & ids) and ids <= set(slurm.jobcomp()),
        timeout,
        f"SLURM to release and account jobs {sorted(ids)}",
        interval=0.5,
    )


def test_run_on_slurm_equals_local_run_and_slurm_accounts_the_jobs(
    slurm: Slurm,
    local_ref: dict[str, np.ndarray],
    tmp_path: Path,
    cat: Path,
) -> None:
    out = tmp_path / "cat.zarr"
    r = subprocess.run(
        [MAXFS, "run", str(cat), "-o", str(out), "--cluster", "slurm"],
        capture_output=True,
        text=True,
        timeout=300,
        env=slurm.env(MAXFS_SLURM_MAX_JOBS="1"),
    )
    assert r.returncode == 0, r.stderr
    _assert_bit_identical(_arrays(out), local_ref)
    ids = _job_ids(out / "slurm-logs")
    assert len(ids) == 1, ids
    # the tiles ran in the worker job's process, not in this machine's maxfs process
    (job,) = ids
    assert "Registered to:" in (out / "slurm-logs" / f"maxfs-worker-{job}.err").read_text()
    _wait_released(slurm, ids)  # closing the cluster scancels its worker jobs
    # started by the main scheduler, or by backfill when it had to wait for cores
    started = rf"(sched: Allocate|backfill: Started) JobId={job}\b"
    log = slurm.dir / "slurmctld.log"
    poll_until(lambda: re.search(started, log.read_text()) is not None, 30, f"job {job} in {log}", 0.5)


def test_scancel_of_a_worker_job_mid_run_loses_no_tile_and_changes_no_bit(
    slurm: Slurm,
    local_ref: dict[str, np.ndarray],
    tmp_path: Path,
    cat: Path,
) -> None:
    out = tmp_path / "cat.zarr"
    log = open(tmp_path / "run.log", "wb")
    proc = subprocess.Popen(
        [MAXFS, "run", str(cat), "-o", str(out), "--cluster", "slurm"],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=slurm.env(MAXFS_SLURM_MIN_JOBS="2", MAXFS_SLURM_MAX_JOBS="2"),
    )
    try:
        runs = out / "maxfs-runs.log"

        def done_lines() -> list[list[str]]:
            text = runs.read_text() if runs.exists() else ""
            return [ln.split() for ln in text.splitlines() if ln.endswith(" done")]

        poll_until(lambda: bool(done_lines()) or proc.poll() is not None, 180, "a first finished tile", 0.02)
        first = done_lines()
        assert first, f"maxfs run ended before any tile: {(tmp_path / 'run.log').read_text()}"
        pid = int(first[0][1])  # the worker process that finished the first tile; its SLURM job:
        env = dict(
            kv.split("=", 1) for kv in Path(f"/proc/{pid}/environ").read_text().split("\0") if "=" in kv
        )
        job = int(env["SLURM_JOB_ID"])
        subprocess.run(["scancel", str(job)], env=slurm.env(), check=True)
        before = {int(t[2].removeprefix("tile=")) for t in done_lines()}
        assert proc.wait(timeout=240) == 0, (tmp_path / "run.log").read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
        log.close()
    store = JobStore.open(out, mode="r")
    occupied = store.masked_per_tile().ravel() > 0  # tiles without masked pixels get no task
    total = int(occupied.sum())
    assert len(before) < total, "the run finished before the worker job was cancelled"
    counts = store.run_counts()
    assert all(counts[t] == 1 for t in before), "a tile finished before the kill was computed again"
    assert set(counts) == {t.index for t in store.tiles() if occupied[t.index]}
    assert bool(store.done_grid().all())
    late = {int(ln.split()[1]) for ln in runs.read_text().splitlines()[len(first) :]}
    assert late - {pid}, "no other worker took over the tiles"
    _assert_bit_identical(_arrays(out), local_ref)
    _wait_released(slurm, _job_ids(out / "slurm-logs"))
    assert slurm.jobcomp()[job] == "CANCELLED"


def test_serve_on_slurm_runs_an_http_job_end_to_end_and_releases_idle_workers(
    slurm: Slurm,
    local_ref: dict[str, np.ndarray],
    tmp_path: Path,
    cat: Path,
    server_factory: Callable[..., Server],
) -> None:
    env = slurm.env(MAXFS_CLUSTER="slurm", MAXFS_SLURM_MAX_JOBS="1", MAXFS_SLURM_IDLE_TIMEOUT="2")
    server = server_factory(env=env, graceful=True)  # SIGTERM at teardown: it closes its SLURM cluster
    with MaxfsClient(server.url) as c:
        job_id = c.submit_folder(load_folder(cat))
        st = c.wait(job_id, poll=0.2, timeout=240)
        assert st["state"] == "done", st
        got = {n: c.fetch_array(job_id, n) for n in OUTPUTS}
    _assert_bit_identical(got, local_ref)
    ids = _job_ids(tmp_path / "data" / "slurm-logs")
    assert ids, "no SLURM worker job ran the tiles"
    _wait_released(slurm, ids, timeout=60)  # idle 2 s: released while the server runs on
    assert server.proc.poll() is None


def test_slurm_settings_it_refuses_fail_at_start_with_slurms_words(
    slurm: Slurm, tmp_path: Path, cat: Path
) -> None:
    r = subprocess.run(
        [MAXFS, "run", str(cat), "-o", str(tmp_path / "cat.zarr"), "--cluster", "slurm"],
        capture_output=True,
        text=True,
        timeout=120,
        env=slurm.env(MAXFS_SLURM_PARTITION="no-such-partition"),
    )
    assert r.returncode != 0
    assert "SLURM refuses the worker job" in r.stderr and "no-such-partition" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_store_the_workers_cannot_see_fails_the_job_with_a_clear_message(
    slurm: Slurm,
    tmp_path: Path,
    cat: Path,
) -> None:
    """Worker jobs whose node mounts something else at the output's path (a tmpfs here)."""
    out = tmp_path / "cat.zarr"
    out.mkdir()
    wrapper = tmp_path / "python-on-another-node"
    hide = f'mount -t tmpfs tmpfs "{out}" && exec {sys.executable} "$@"'
    wrapper.write_text(f"#!/bin/sh\nexec unshare -m sh -c '{hide}' sh \"$@\"\n")
    wrapper.chmod(0o755)
    r = subprocess.run(
        [MAXFS, "run", str(cat), "-o", str(out), "--cluster", "slurm"],
        capture_output=True,
        text=True,
        timeout=180,
        env=slurm.env(
            MAXFS_SLURM_PYTHON=str(wrapper),
            MAXFS_SLURM_MAX_JOBS="1",
            MAXFS_SLURM_LOG_DIRECTORY=str(tmp_path / "logs"),
        ),
    )
    assert r.returncode != 0
    assert f"the Dask workers cannot see the job store {out}" in r.stderr, r.stderr
    assert "mount at the same path" in r.stderr
    # no tile was computed (tiles without a masked pixel count as done once eps is known, which
    # maxfs run now estimates itself while the cluster starts)
    store = JobStore.open(out, mode="r")
    assert not (store.done_grid() & (store.masked_per_tile() > 0)).any()


def test_batch_script_runs_maxfs_inside_one_allocation(
    slurm: Slurm,
    local_ref: dict[str, np.ndarray],
    tmp_path: Path,
    cat: Path,
) -> None:
    out = tmp_path / "cat.zarr"
    env = slurm.env()
    env["PATH"] = f"{BIN}:{env['PATH']}"
    r = subprocess.run(
        [
            "sbatch",
            "--wait",
            "--ntasks=2",
            "--mem-per-cpu=1G",
            f"--output={tmp_path / 'batch.log'}",
            str(REPO / "deploy/slurm/maxfs-run.sbatch"),
            str(cat),
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        cwd=tmp_path,
    )
    log = (tmp_path / "batch.log").read_text() if (tmp_path / "batch.log").exists() else ""
    assert r.returncode == 0, r.stderr + log
    assert "done:" in log, log
    _assert_bit_identical(_arrays(out), local_ref)
    assert not list(tmp_path.glob(".maxfs-tls-*")), "the job's TLS files were left behind"
