"""The one Dask client factory (service.runs.cluster): kinds, SLURM settings, and the embedded
cluster's TLS: no local process gets in through Dask, no HTTP endpoint unless asked."""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import httpx
import psutil
import pytest
from distributed.comm import connect
from distributed.security import Security

from maxfs.service.runs.cluster import (
    cluster_kind,
    open_cluster,
    slurm_job_kwargs,
    walltime_seconds,
    worker_lifetime,
)
from maxfs.service.settings import Settings
from maxfs.storage.errors import InvalidInputError
from tests.procs import Server, free_port


@dataclass(frozen=True)
class KindCase:
    cluster: str
    scheduler: str
    kind: str | None  # None: refused


@pytest.mark.parametrize(
    "case",
    [
        KindCase("", "", "local"),
        KindCase("", "tls://10.0.0.5:8786", "address"),  # MAXFS_SCHEDULER alone, as before
        KindCase("local", "tls://10.0.0.5:8786", "local"),  # --cluster local wins
        KindCase("SLURM", "", "slurm"),
        KindCase("address", "tcp://h:8786", "address"),
        KindCase("address", "", None),
        KindCase("kubernetes", "", None),
    ],
)
def test_cluster_kind(case: KindCase) -> None:
    s = Settings(cluster=case.cluster, scheduler=case.scheduler)
    if case.kind is None:
        with pytest.raises(InvalidInputError):
            cluster_kind(s)
    else:
        assert cluster_kind(s) == case.kind


@pytest.mark.parametrize(
    ("walltime", "seconds", "lifetime"),
    [
        ("30", 1800, (1620, 45)),
        ("01:00:00", 3600, (3300, 75)),
        ("1-00:00:00", 86400, (86100, 75)),
        ("2-12", 216000, (215700, 75)),
        ("1:30", 90, None),  # too short to retire early
    ],
)
def test_walltime_and_worker_lifetime(walltime: str, seconds: int, lifetime: tuple | None) -> None:
    assert walltime_seconds(walltime) == seconds
    assert worker_lifetime(walltime) == lifetime


def test_slurm_job_settings_map_to_dask_jobqueue(tmp_path: Path) -> None:
    s = Settings(
        slurm_partition="gpu",
        slurm_account="lab",
        slurm_cores=4,
        slurm_sbatch="--qos=short; --constraint=avx2",
        slurm_prologue="module load gcc",
        slurm_local_directory="$TMPDIR",
    )
    kw = slurm_job_kwargs(s, tmp_path)
    assert (kw["queue"], kw["account"], kw["cores"], kw["processes"]) == ("gpu", "lab", 4, 4)
    assert kw["memory"] == "6GiB"  # 1.5 GiB per single-threaded worker
    assert kw["job_extra_directives"] == ["--qos=short", "--constraint=avx2"]
    assert kw["job_script_prologue"][-1] == "module load gcc"
    assert kw["local_directory"] == "$TMPDIR" and kw["log_directory"] == str(tmp_path)
    assert kw["worker_extra_args"][:2] == ["--lifetime", "3300s"]
    with pytest.raises(InvalidInputError, match="MIN_JOBS"):
        slurm_job_kwargs(Settings(slurm_min_jobs=3, slurm_max_jobs=2), tmp_path)
    with pytest.raises(InvalidInputError, match="not a SLURM time limit"):
        slurm_job_kwargs(Settings(slurm_walltime="1h"), tmp_path)


def _listening_ports(pid: int) -> set[int]:
    root = psutil.Process(pid)
    pids = {root.pid} | {p.pid for p in root.children(recursive=True)}
    conns = psutil.net_connections(kind="inet")
    return {c.laddr.port for c in conns if c.status == "LISTEN" and c.pid in pids}


def _speaks_http(port: int) -> bool:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.settimeout(5)
        s.sendall(b"GET /health HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
        try:
            return s.recv(5) == b"HTTP/"
        except OSError:
            return False


async def _dask_answers(address: str, **connection_args) -> bool:
    """Whether a Dask server at ``address`` answers an ``identity`` call from this client."""
    try:  # bounded twice: connect's own timeout does not cover a peer that never answers the handshake
        comm = await asyncio.wait_for(connect(address, timeout=5, **connection_args), 10)
    except Exception:
        return False
    try:
        await comm.write({"op": "identity", "reply": True})
        reply = await asyncio.wait_for(comm.read(), 5)
        return isinstance(reply, dict) and "type" in reply
    except Exception:
        return False
    finally:
        comm.abort()


def test_embedded_cluster_refuses_other_local_clients_and_serves_no_http(
    server_factory: Callable[..., Server],
) -> None:
    """Issue #10: a local process must not reach the server's scheduler or workers (they run
    any code sent to them) nor Dask's info pages."""
    server = server_factory(workers=1)
    dask_ports = _listening_ports(server.proc.pid) - {server.port}
    assert len(dask_ports) >= 3, dask_ports  # scheduler, nanny, worker
    foreign = Security.temporary().get_connection_args("client")
    for port in sorted(dask_ports):
        assert not _speaks_http(port), f"port {port} answers HTTP"
        assert not asyncio.run(_dask_answers(f"tcp://127.0.0.1:{port}")), f"plain client got in on {port}"
        assert not asyncio.run(_dask_answers(f"tls://127.0.0.1:{port}", connection_args=foreign)), (
            f"a client with another certificate got in on {port}"
        )
    assert _speaks_http(server.port)  # the server itself, of course


@pytest.mark.slow
def test_embedded_cluster_serves_a_dashboard_only_when_asked() -> None:
    port = free_port()

    async def go() -> int:
        async with open_cluster(Settings(workers=1, dashboard=f"127.0.0.1:{port}")) as dc:
            assert dc.scheduler_address.startswith("tls://127.0.0.1:")
            assert await dc.client.submit(sum, [1, 2], pure=False) == 3  # our own client is let in
            async with httpx.AsyncClient() as h:
                return (await h.get(f"http://127.0.0.1:{port}/health")).status_code

    assert asyncio.run(go()) == 200


def _worker_settings() -> tuple[str | None, bool, bool]:
    import sys

    import dask

    return (
        os.environ.get("MALLOC_TRIM_THRESHOLD_"),
        dask.config.get("distributed.worker.profile.enabled"),
        "maxfs.worker.forkserver" in sys.modules,  # forked from the fork server, kernels loaded there
    )


@pytest.mark.slow
@pytest.mark.parametrize("dashboard", [False, True])
def test_embedded_workers_keep_freed_memory_and_profile_only_for_a_dashboard(dashboard: bool) -> None:
    """Dask's MALLOC_TRIM_THRESHOLD_ made glibc fault in every large tile array afresh (20-25 %
    more CPU per tile); its sampling profiler only feeds a dashboard. The workers are forked from
    the fork server, which loaded the solver once for all of them."""
    board = f"127.0.0.1:{free_port()}" if dashboard else ""

    async def go() -> dict:
        async with open_cluster(Settings(workers=1, dashboard=board)) as dc:
            return await dc.client.run(_worker_settings)

    (seen,) = asyncio.run(go()).values()
    assert seen == (None, dashboard, True)


def test_store_check_waits_for_a_worker_and_says_where_it_stands(
    procs, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A job's store check on a cluster with no worker yet (a SLURM worker job still queued)
    waits, logs where the check stands on the scheduler, and finishes once a worker joins."""
    import logging

    from distributed import Client

    import maxfs.service.runs.cluster as cluster

    monkeypatch.setattr(cluster, "PROBE_REPORT_SECONDS", 0.5)
    dask = procs.cluster(n_workers=0)
    job_dir = tmp_path / "job"
    job_dir.mkdir()

    async def go() -> None:
        async with Client(dask.address, asynchronous=True) as c:
            check = asyncio.ensure_future(cluster.check_store_visible(c, job_dir, "j1"))
            await asyncio.sleep(1.6)
            assert not check.done()
            dask.add_worker(0)
            await asyncio.wait_for(check, 60)  # no StoreError: the worker saw the store

    with caplog.at_level(logging.WARNING, logger="maxfs.cluster"):
        asyncio.run(go())
    waits = [r.getMessage() for r in caplog.records if "store check has waited" in r.getMessage()]
    first = waits[0] if waits else ""
    assert "'state': 'queued'" in first or "'state': 'no-worker'" in first, waits
    assert "'workers': {}" in first, waits
    assert not list(job_dir.iterdir()), "the probe files are removed"


@pytest.mark.parametrize("cancelled", ["first", "second"])
def test_cancelling_one_result_fetch_leaves_the_others(procs, cancelled: str) -> None:
    """The client batches concurrent result fetches into one request; cancelling one waiter
    (a job's run, cancelled) must not cancel the fetch of another (a second job's store check
    or tile result: it then raised CancelledError and that job stayed queued forever)."""
    import operator

    from distributed import Client

    from maxfs.service.runs.cluster import result

    dask = procs.cluster(n_workers=1)

    async def go() -> None:
        async with Client(dask.address, asynchronous=True) as c:
            for _ in range(5):  # the race is per fetch: try a few
                futs = [c.submit(operator.add, i, 1, pure=False) for i in range(2)]
                while not all(f.done() for f in futs):
                    await asyncio.sleep(0.01)
                waiting = [asyncio.ensure_future(result(f)) for f in futs]
                for _ in range(5):  # both attach to the same fetch before it is answered
                    await asyncio.sleep(0)
                victim, other = waiting if cancelled == "first" else waiting[::-1]
                victim.cancel()
                assert await asyncio.wait_for(other, 30) == (1 if other is waiting[0] else 2)
                with pytest.raises(asyncio.CancelledError):
                    await victim

    asyncio.run(go())
