"""Where tiles run: the one place that builds the Dask client, for every kind of cluster.

Three kinds (``MAXFS_CLUSTER``, ``--cluster``):

``local``
    An embedded ``LocalCluster`` of ``MAXFS_WORKERS`` single-threaded processes on
    127.0.0.1. Every connection is mutual TLS with a temporary certificate that only
    this process holds (:func:`temporary_security`; the workers get it through their
    nanny's pipe, never from disk), so another local process can neither submit code
    to the scheduler nor talk to a worker. No Dask HTTP endpoint listens unless
    ``MAXFS_DASHBOARD`` names one (then only the scheduler's).
``slurm``
    A ``dask_jobqueue.SLURMCluster``: the scheduler runs in this process, the workers
    are SLURM batch jobs (``MAXFS_SLURM_*`` settings) that run this same installed
    package (``sys.executable``), scaled adaptively between a minimum and a maximum
    number of jobs; a job idle for ``MAXFS_SLURM_IDLE_TIMEOUT`` seconds is released,
    and a job that ends (``scancel``, walltime) is replaced while work remains. Also
    mutual TLS with a temporary certificate, which the worker jobs read from 0600 files
    in the (shared) log directory.
``address``
    An external scheduler at ``MAXFS_SCHEDULER``; TLS then comes from Dask's own
    configuration (``distributed.comm.tls.*``, e.g. ``DASK_DISTRIBUTED__COMM__TLS__...``).

Every worker of every kind must see the job store at the same path: before the first
tile of a job, :func:`check_store_visible` asks a worker to read a probe file that this
process wrote and answer with one of its own; a store it cannot see fails the job
with a message that says so.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import re
import shlex
import socket
import subprocess
import sys
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from distributed import Client
from distributed.diagnostics.plugin import WorkerPlugin
from distributed.security import Security

from maxfs.service.settings import Settings, cluster_kind
from maxfs.storage.errors import ConflictError, InvalidInputError, StoreError

log = logging.getLogger("maxfs.cluster")

#: SLURM job name of every worker job (what ``squeue``/``sacct`` show).
SLURM_JOB_NAME = "maxfs-worker"
#: Prefix of probe files (the job manager's temp-file prefix: removed on restart, never zipped).
PROBE_PREFIX = ".maxfs-probe-"


class _WorkerSetup(WorkerPlugin):
    """On every worker, also ones that join later: no HTTP endpoint, solver kernels loaded."""

    name = "maxfs-worker-setup"

    async def setup(self, worker: Any) -> None:
        if worker.http_server is not None:
            worker.http_server.stop()
        from maxfs.worker.task import warm_up

        await asyncio.get_running_loop().run_in_executor(None, warm_up)


@dataclass
class DaskCluster:
    """A connected Dask client and what it runs on; :meth:`close` releases both."""

    kind: str
    client: Client
    settings: Settings
    #: the LocalCluster or SLURMCluster this process started (None for ``address``)
    cluster: Any = None
    security: Security | None = None
    _closed: bool = field(default=False, repr=False)

    @property
    def scheduler_address(self) -> str:
        return self.client.scheduler.address

    async def reconnect(self) -> Client:
        """A new client when the old one lost an external scheduler; else the current one."""
        if self.kind != "address" or self.client.status not in ("closed", "closing", "failed"):
            return self.client
        address = self.settings.scheduler
        try:
            self.client = await Client(address, asynchronous=True, timeout=10)
        except OSError as e:
            raise ConflictError(
                f"the Dask scheduler {address} cannot be reached ({e}); start the job again once it is back"
            ) from None
        await warm_workers(self.client)
        return self.client

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            await self.client.close()
        finally:
            if self.cluster is not None:
                await self.cluster.close()


async def start_cluster(settings: Settings, *, log_dir: Path | None = None) -> DaskCluster:
    """Start (or connect to) the cluster ``settings`` ask for; the caller closes it.

    ``log_dir`` is where SLURM worker jobs write their output (``MAXFS_SLURM_LOG_DIRECTORY``
    wins; default ``MAXFS_DATA_DIR/slurm-logs``); it must be on the shared filesystem.
    """
    kind = cluster_kind(settings)
    if kind == "address":
        client = await Client(settings.scheduler, asynchronous=True)
        dc = DaskCluster(kind, client, settings)
    elif kind == "local":
        return await _start_local(settings)  # its workers loaded the kernels before they joined
    else:
        dc = await _start_slurm(settings, log_dir)
    try:
        await warm_workers(dc.client)
    except BaseException:
        await dc.close()
        raise
    return dc


@asynccontextmanager
async def open_cluster(settings: Settings, *, log_dir: Path | None = None) -> AsyncIterator[DaskCluster]:
    """``async with open_cluster(settings) as dc:`` use ``dc.client``; closed on exit."""
    dc = await start_cluster(settings, log_dir=log_dir)
    try:
        yield dc
    finally:
        await dc.close()


async def _no_scheduler_http(dc: DaskCluster, *, workers: bool = True) -> None:
    """Stop the in-process scheduler's HTTP server (Dask always starts one) unless a dashboard
    was asked for, and (``workers``) the workers' ones, now and when they join: the embedded
    cluster's workers get :class:`_WorkerSetup` as they start instead (:func:`_start_local`)."""
    if not dc.settings.dashboard:
        dc.cluster.scheduler.http_server.stop()
    if workers:
        await dc.client.register_plugin(_WorkerSetup())


def temporary_security() -> Security:
    """:meth:`Security.temporary` (one self-signed certificate, in memory, for every role) with
    an elliptic-curve key (P-256) instead of RSA 2048: made in 0.2 ms instead of 0.2-0.35 s of
    this process's CPU, spent while the embedded cluster's workers are loading, on 2 cores."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    key_pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    ).decode()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "dask-internal")])
    now = datetime.datetime.now(tz=datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .add_extension(x509.SubjectAlternativeName([x509.DNSName("dask-internal")]), critical=False)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=365))
        .sign(key, hashes.SHA256())
    )
    cert_pem = cert.public_bytes(serialization.Encoding.PEM).decode()
    return Security(
        require_encryption=True,
        tls_ca_file=cert_pem,
        tls_client_key=key_pem,
        tls_client_cert=cert_pem,
        tls_scheduler_key=key_pem,
        tls_scheduler_cert=cert_pem,
        tls_worker_key=key_pem,
        tls_worker_cert=cert_pem,
    )


#: Dask settings of the embedded cluster's workers (the nannies pass them on to the worker
#: processes they spawn). Dask exports ``MALLOC_TRIM_THRESHOLD_=65536`` to its workers so that
#: freed memory goes back to the system at once; glibc then maps and faults in afresh every large
#: array a tile allocates, which cost 20-25 % more CPU per tile than the same code in one
#: process. Its sampling profiler walks every thread's stack 100 times a second, for a dashboard
#: that is off unless ``MAXFS_DASHBOARD`` is set.
LOCAL_WORKER_CONFIG: dict[str, Any] = {
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
}


def local_worker_config(dashboard: str) -> dict[str, Any]:
    """:data:`LOCAL_WORKER_CONFIG`, with the profiler on when a dashboard shows it."""
    return LOCAL_WORKER_CONFIG | {
        "distributed.worker.profile.enabled": bool(dashboard),
        "distributed.worker.multiprocessing-method": "forkserver",
    }


def start_forkserver() -> None:
    """Start this process's fork server (:mod:`service.runs.forkserver`, unless ``maxfs run`` did
    already), the parent of the embedded cluster's worker processes.

    A worker spawned afresh imports Dask, NumPy, numba and the solver and loads the kernels from
    numba's cache: 2-4 s of CPU per worker. Forked from the fork server (a single-threaded process,
    started once per process and kept), it has them already: paid once, not once per worker, and
    not again for a later cluster of this process. Dask's own preload list (which also imports
    pandas, here in this process) is not used."""
    from distributed import utils

    from maxfs.service.runs import forkserver

    forkserver.launch()
    utils._forkserver_preload_set = True  # Dask's get_mp_context keeps the list of launch()


async def _start_local(settings: Settings) -> DaskCluster:
    import dask
    from distributed import LocalCluster

    await asyncio.to_thread(start_forkserver)
    security = temporary_security()
    with dask.config.set(local_worker_config(settings.dashboard)):  # read as the nannies are made
        cluster = await LocalCluster(
            n_workers=settings.workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=settings.dashboard or None,
            # Dask listens for HTTP even without a dashboard: on a random loopback port, stopped below
            scheduler_kwargs={} if settings.dashboard else {"dashboard_address": "127.0.0.1:0"},
            security=security,
            asynchronous=True,
            # set up as each worker starts, before it joins: no round of messages once all have joined
            plugins={_WorkerSetup()},
        )
    try:
        client = await Client(cluster, asynchronous=True)
    except BaseException:
        await cluster.close()
        raise
    dc = DaskCluster("local", client, settings, cluster, security)
    try:
        await _no_scheduler_http(dc, workers=False)
    except BaseException:
        await dc.close()
        raise
    return dc


# -- SLURM ------------------------------------------------------------------------------------------


def walltime_seconds(walltime: str) -> int:
    """Seconds of a SLURM time limit: ``M``, ``M:S``, ``H:M:S``, ``D-H``, ``D-H:M``, ``D-H:M:S``."""
    m = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", walltime.strip())
    if not m:
        raise InvalidInputError(
            f"MAXFS_SLURM_WALLTIME={walltime!r} is not a SLURM time limit (e.g. 60, 01:00:00, 1-00:00:00)"
        )
    days, a, b, c = (int(g) if g is not None else None for g in m.groups())
    if days is None:
        h, mi, s = (a, b, c) if c is not None else (0, a, b or 0)
    else:
        h, mi, s = a, b or 0, c or 0
    return (((days or 0) * 24 + h) * 60 + mi) * 60 + s


def worker_lifetime(walltime: str) -> tuple[int, int] | None:
    """(lifetime, stagger) seconds for ``dask worker --lifetime``: a worker retires and hands
    its tiles back before SLURM's walltime kills it (5 minutes or a tenth of the walltime
    early, whichever is less). None for walltimes under two minutes."""
    total = walltime_seconds(walltime)
    if total < 120:
        return None
    early = min(300, total // 10)
    return total - early, max(1, early // 4)


def slurm_job_kwargs(settings: Settings, log_dir: Path) -> dict[str, Any]:
    """Keyword arguments of ``SLURMCluster`` from the ``MAXFS_SLURM_*`` settings."""
    s = settings
    if s.slurm_cores < 1:
        raise InvalidInputError(f"MAXFS_SLURM_CORES must be at least 1, got {s.slurm_cores}")
    if not 0 <= s.slurm_min_jobs <= s.slurm_max_jobs or s.slurm_max_jobs < 1:
        raise InvalidInputError(
            f"need 0 <= MAXFS_SLURM_MIN_JOBS ({s.slurm_min_jobs}) <= MAXFS_SLURM_MAX_JOBS "
            f"({s.slurm_max_jobs}) and at least one job"
        )
    memory = s.slurm_memory or f"{1.5 * s.slurm_cores:g}GiB"
    python = s.slurm_python or sys.executable
    prologue = [f"export PATH={shlex.quote(str(Path(python).parent))}:$PATH"]
    prologue += [line.strip() for line in s.slurm_prologue.split(";") if line.strip()]
    extra_args: list[str] = []
    lifetime = worker_lifetime(s.slurm_walltime)
    if lifetime:
        extra_args += ["--lifetime", f"{lifetime[0]}s", "--lifetime-stagger", f"{lifetime[1]}s"]
    kw: dict[str, Any] = dict(
        cores=s.slurm_cores,
        processes=s.slurm_cores,  # one single-threaded worker process per core, as everywhere
        memory=memory,
        walltime=s.slurm_walltime,
        queue=s.slurm_partition or None,
        account=s.slurm_account or None,
        job_name=SLURM_JOB_NAME,
        job_extra_directives=[d.strip() for d in s.slurm_sbatch.split(";") if d.strip()],
        job_script_prologue=prologue,
        python=python,
        log_directory=str(log_dir),
        shared_temp_directory=str(log_dir),
        local_directory=s.slurm_local_directory or None,
        interface=s.slurm_interface or None,
        worker_extra_args=extra_args,
    )
    return kw


def _check_sbatch(cluster: Any) -> None:
    """``sbatch --test-only`` the worker job script: a wrong partition, account or resource
    request is refused now, with SLURM's words, instead of leaving jobs queued forever."""
    script = cluster.job_script()
    try:
        r = subprocess.run(
            ["sbatch", "--test-only"], input=script, capture_output=True, text=True, timeout=60
        )
    except FileNotFoundError:
        raise InvalidInputError(
            "cluster 'slurm' needs the SLURM client commands (sbatch, scancel) on this machine's PATH"
        ) from None
    if r.returncode != 0:
        words = " ".join((r.stderr or r.stdout).split())
        raise InvalidInputError(f"SLURM refuses the worker job ({words}); check the MAXFS_SLURM_* settings")


async def _start_slurm(settings: Settings, log_dir: Path | None) -> DaskCluster:
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError:
        raise InvalidInputError(
            "cluster 'slurm' needs dask-jobqueue: pip install 'maxfs-ps[slurm]'"
        ) from None
    s = settings
    log_dir = Path(s.slurm_log_directory or log_dir or Path(s.data_dir) / "slurm-logs").absolute()
    log_dir.mkdir(parents=True, exist_ok=True)
    kw = slurm_job_kwargs(s, log_dir)
    security = Security.temporary()
    cluster = await SLURMCluster(
        **kw,
        security=security,
        scheduler_options={"dashboard": bool(s.dashboard), "dashboard_address": s.dashboard or "127.0.0.1:0"},
        asynchronous=True,
    )
    try:
        await asyncio.to_thread(_check_sbatch, cluster)
        client = await Client(cluster, asynchronous=True)
    except BaseException:
        await cluster.close()
        raise
    dc = DaskCluster("slurm", client, settings, cluster, security)
    try:
        await _no_scheduler_http(dc)
        idle = max(1.0, s.slurm_idle_timeout)
        cluster.adapt(
            minimum_jobs=s.slurm_min_jobs,
            maximum_jobs=s.slurm_max_jobs,
            interval="1s",
            wait_count=max(1, math.ceil(idle)),
        )
    except BaseException:
        await dc.close()
        raise
    log.info(
        "SLURM cluster: scheduler %s, %d-%d worker jobs of %d cores, logs in %s",
        cluster.scheduler_address,
        s.slurm_min_jobs,
        s.slurm_max_jobs,
        s.slurm_cores,
        log_dir,
    )
    return dc


# -- the shared-filesystem check -------------------------------------------------------------------


#: Seconds between two log lines while a store check waits for a worker.
PROBE_REPORT_SECONDS = 30.0


def _task_on_scheduler(dask_scheduler: Any, key: str) -> dict[str, Any]:
    """On the scheduler: where task ``key`` stands, and how busy each worker is."""
    ts = dask_scheduler.tasks.get(key)
    return {
        "state": None if ts is None else ts.state,
        "on": None if ts is None or ts.processing_on is None else ts.processing_on.address,
        "workers": {w.address: len(w.processing) for w in dask_scheduler.workers.values()},
    }


async def _probe_answer(
    client: Client, job_dir: Path, name: str, nonce: str, job_id: str, priority: int = 0
) -> str | None:
    """Run :func:`probe_store` on a worker and return its answer, however long a worker takes
    to come (a SLURM worker job may wait in the queue). Every ``PROBE_REPORT_SECONDS`` the log
    says where the check stands on the scheduler; a check the scheduler has never heard of (its
    submission was lost) is submitted again."""
    attempt, waited = 0, 0.0
    while True:
        key = f"maxfs-probe-{job_id}-{nonce[:8]}-{attempt}"
        fut = client.submit(probe_store, str(job_dir), name, nonce, key=key, pure=False, priority=priority)
        waiter = asyncio.ensure_future(result(fut))
        try:
            while True:
                done, _ = await asyncio.wait({waiter}, timeout=PROBE_REPORT_SECONDS)
                if done:
                    return waiter.result()
                waited += PROBE_REPORT_SECONDS
                try:
                    where = await asyncio.wait_for(client.run_on_scheduler(_task_on_scheduler, key=key), 10)
                except Exception as e:  # the scheduler did not answer: say so, keep waiting
                    where = {"state": "unknown", "error": f"{type(e).__name__}: {e}"}
                log.warning(
                    "job %s: the store check has waited %g s for a worker (client %s; on the scheduler: %s)",
                    job_id,
                    waited,
                    client.status,
                    where,
                )
                if where.get("state") is None:  # the scheduler never got it: submit it again
                    break
        finally:
            waiter.cancel()
            fut.release()
        attempt += 1


async def warm_workers(client: Client) -> None:
    """Load the solver kernels on every current worker (see :func:`worker.task.warm_up`)."""
    from maxfs.worker.task import warm_up

    await client.run(warm_up)


async def result(fut: Any) -> Any:
    """The result of a Dask future, fetched so that cancelling the caller cancels only the caller.

    The client batches concurrent result fetches into one shared request, and awaiting it
    directly lets a cancelled waiter cancel that request for every other waiter: cancelling one
    job's run made another job's fetch raise ``CancelledError`` (that job then stayed queued
    with nothing running it). Shielded, the shared fetch finishes for the others.
    """
    fetch = asyncio.ensure_future(_fetch(fut))
    fetch.add_done_callback(_retrieved)  # a caller cancelled meanwhile never reads its outcome
    return await asyncio.shield(fetch)


async def _fetch(fut: Any) -> Any:
    return await fut


def _retrieved(task: asyncio.Future) -> None:
    if not task.cancelled():
        task.exception()


def probe_store(job_dir: str, name: str, token: str) -> str | None:
    """On a worker: read the probe file ``name`` in ``job_dir`` and answer beside it.

    Returns None when the probe holds ``token`` and the answer was written, else what
    this worker sees instead (so the error can say it).
    """
    where = f"worker on {socket.gethostname()} (pid {os.getpid()})"
    d = Path(job_dir)
    if not d.is_dir():
        return f"{where}: no folder {job_dir}"
    try:
        seen = (d / name).read_text()
    except OSError as e:
        return f"{where}: {job_dir} exists but is another folder (no probe file: {type(e).__name__})"
    if seen != token:
        return f"{where}: {job_dir} holds another copy of the store (probe mismatch)"
    try:
        (d / f"{name}.answer").write_text(token)
    except OSError as e:
        return f"{where}: cannot write in {job_dir} ({e})"
    return None


async def check_store_visible(client: Client, job_dir: Path, job_id: str, priority: int = 0) -> None:
    """Before the first tile: a worker must read and write the job store this process made.

    Raises :class:`StoreError` with what the worker saw otherwise. Waits for a worker (a
    SLURM worker job may wait in the queue first).
    """
    job_dir = Path(job_dir)  # the very path the tile tasks get
    nonce = uuid.uuid4().hex
    name = f"{PROBE_PREFIX}{nonce}"
    probe, answer = job_dir / name, job_dir / f"{name}.answer"
    probe.write_text(nonce)
    try:
        seen = await _probe_answer(client, job_dir, name, nonce, job_id, priority)
        if seen is None and not (answer.is_file() and answer.read_text() == nonce):
            seen = "a worker wrote its answer where this process cannot read it"
        if seen is not None:
            if not job_dir.is_absolute():
                seen += f"; the path is relative to this process's folder {Path.cwd()}: make it absolute"
            raise StoreError(
                f"the Dask workers cannot see the job store {job_dir} ({seen}). Put it on a filesystem "
                "that this process and every worker node mount at the same path (NFS, Lustre, ...): "
                "MAXFS_DATA_DIR for the server, the output folder for maxfs run"
            )
    finally:
        probe.unlink(missing_ok=True)
        answer.unlink(missing_ok=True)
