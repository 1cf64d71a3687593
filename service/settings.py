"""One settings object, read from ``MAXFS_*`` environment variables.

A dataclass and a few lines of parsing rather than pydantic-settings: every ``maxfs`` command
reads it first, and importing pydantic-settings (with pydantic) cost 0.37 s of each command's
start, a quarter of re-running a finished job. The fields are plain str, int, float, bool and
Path; a value that does not parse is an :class:`~storage.errors.InvalidInputError` naming the
variable (a CLI message, not a traceback).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.options import MAX_PIXELS
from maxfs.storage.tiles import DEFAULT_TASK_MEMORY

LOOPBACK = ("127.0.0.1", "::1", "localhost")
#: Where tiles run (:mod:`service.runs.cluster`).
KINDS = ("local", "slurm", "address")
ENV_PREFIX = "MAXFS_"
_TRUE = frozenset({"1", "true", "t", "yes", "y", "on"})
_FALSE = frozenset({"0", "false", "f", "no", "n", "off"})
#: Fields with a lower bound: a count of processes or threads below 1 would wait for ever
#: (a Dask run with no worker) or quietly mean something else.
_AT_LEAST = {"workers": 1, "decode_slots": 1}


def _parse(kind: str, value: Any, where: str) -> Any:
    """``value`` (from the environment or a keyword) as a field of type ``kind``."""
    try:
        if kind == "bool":
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in _TRUE | _FALSE:
                return text in _TRUE
            raise ValueError
        if kind == "int":
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)  # a str may have spaces and underscores ("1_000"), not a point
        if kind == "float":
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        if kind == "Path":
            return Path(value)
        if not isinstance(value, str):
            raise ValueError
        return value
    except (TypeError, ValueError):
        expect = {"bool": "true or false", "int": "an integer", "float": "a number", "Path": "a path"}
        raise InvalidInputError(f"{where} must be {expect.get(kind, 'text')}, got {value!r}") from None


@dataclass(init=False)
class Settings:
    """Configuration of the server, the CLI and the embedded cluster.

    Every field can be set as ``MAXFS_<NAME>`` (e.g. ``MAXFS_SCHEDULER=tcp://host:8786``; the
    name in any case); keywords given to the constructor win over the environment.
    """

    #: Where job stores live (one folder per job under ``jobs/``) and the token file.
    data_dir: Path = Path("maxfs-data")
    #: Where tiles run (:mod:`service.runs.cluster`): "local" (embedded LocalCluster), "slurm" (worker
    #: jobs through dask-jobqueue) or "address" (``scheduler``); empty = "address" when
    #: ``scheduler`` is set, else "local".
    cluster: str = ""
    #: Address of an external Dask scheduler; empty = start an embedded LocalCluster.
    scheduler: str = ""
    #: Worker processes of the embedded cluster (one thread each).
    workers: int = max(1, min(4, os.cpu_count() or 1))
    #: Dask dashboard of the embedded cluster: "" = off; e.g. "127.0.0.1:8787" (loopback only by default).
    dashboard: str = ""
    #: SLURM worker jobs (``cluster="slurm"``): partition and account ("" = SLURM's defaults).
    slurm_partition: str = ""
    slurm_account: str = ""
    #: Cores per worker job: that many single-threaded worker processes.
    slurm_cores: int = 1
    #: Memory per worker job, e.g. "6GiB"; "" = 1.5 GiB per core.
    slurm_memory: str = ""
    #: Time limit of a worker job (SLURM format); workers retire a little before it.
    slurm_walltime: str = "01:00:00"
    #: Adaptive scaling between this many worker jobs (the minimum stays while idle).
    slurm_min_jobs: int = 0
    slurm_max_jobs: int = 4
    #: Seconds a worker job may idle before it is released.
    slurm_idle_timeout: float = 60.0
    #: Extra ``#SBATCH`` options, ";"-separated, e.g. "--qos=short;--constraint=avx2".
    slurm_sbatch: str = ""
    #: Shell lines run in a worker job before the worker starts, ";"-separated (e.g. "module load gcc").
    slurm_prologue: str = ""
    #: Python of the worker jobs; "" = this process's (the same installed package).
    slurm_python: str = ""
    #: Worker scratch folder on the node (e.g. "/tmp" or "$TMPDIR"); "" = Dask's default.
    slurm_local_directory: str = ""
    #: Worker job output and TLS key files, on the shared filesystem; "" = DATA_DIR/slurm-logs
    #: (``maxfs serve``) or OUT/slurm-logs (``maxfs run``).
    slurm_log_directory: str = ""
    #: Network interface of the scheduler and workers, e.g. "ib0" ("" = Dask's choice).
    slurm_interface: str = ""
    #: HTTP bind address and port for ``maxfs serve`` (loopback by default).
    host: str = "127.0.0.1"
    port: int = 8000
    #: Require a bearer token on every request (``maxfs serve --no-auth`` turns it off, loopback only).
    auth: bool = True
    #: Largest accepted request body for encoded (PNG/TIFF) images and for a batch of raw
    #: images, bytes (``maxfs submit`` sends smaller batches when refused); a single raw upload
    #: must match the job's image size exactly.
    max_upload_bytes: int = 1 << 30
    #: Largest output array served as one NPY (``/results/NAME.npy``); larger ones via results.zip.
    max_result_bytes: int = 256 << 20
    #: Most images per job.
    max_k: int = 1000
    #: Most pixels per image (H x W).
    max_pixels: int = MAX_PIXELS
    #: Most jobs per user that are not finished (created, uploading, queued or running).
    max_open_jobs: int = 8
    #: Free disk space the server keeps in reserve: a job or upload that would eat into it gets 507.
    min_free_bytes: int = 1 << 30
    #: Memory one tile task may use for its arrays; sets the automatic tile size.
    task_memory: int = DEFAULT_TASK_MEMORY
    #: ``maxfs run`` without a scheduler solves in its own process, on ``workers`` threads
    #: with the stack in memory (cut to the mask's bounding box), when the whole stack is at
    #: most this many bytes; larger stacks go to the embedded Dask cluster, which reads tiles
    #: from the store.
    in_process_bytes: int = 2 << 30
    #: Seconds between job-record saves while a job runs.
    progress_interval: float = 1.0
    #: Retries of a failed tile task before the job fails.
    tile_retries: int = 2
    #: Seconds one tile task may compute before it is stopped and its job fails, naming the
    #: tile (0 = no limit): no tile holds a worker for hours.
    tile_time_limit: float = 900.0
    #: Most tiles per job: each tile is a task (about 1 ms of scheduler time) and a chunk file
    #: in every per-tile array, so a job of tiny tiles is slow everywhere; "auto" stays far below.
    max_tiles: int = 4096
    #: Largest JSON body (``POST /jobs``): lights and intensities of 1000 images take ~130 kB.
    max_json_bytes: int = 1 << 20
    #: Seconds an upload may send nothing before it is dropped (408).
    upload_idle_timeout: float = 60.0
    #: Bytes per second a request body must average once ``upload_idle_timeout`` has passed
    #: (408 when slower): a body trickled a byte at a time never goes idle. 0 = no minimum.
    upload_min_rate: float = 10_000.0
    #: Uploads (image or mask bodies) one user may have in flight at once (429 beyond).
    max_uploads_per_user: int = 8
    #: Streamed downloads (NPY arrays, results.zip) one user may have in flight at once (429
    #: beyond): each holds a piece of its answer in memory while its reader is slow.
    max_downloads_per_user: int = 4
    #: Seconds a download's reader may take nothing before the download is dropped.
    download_idle_timeout: float = 60.0
    #: Encoded images (PNG/TIFF) decoded at once, in threads, each bounded by its job's image size.
    decode_slots: int = 2
    #: Open connections ``maxfs serve`` accepts at once; at the cap a new one closes the oldest
    #: idle one (no request yet, or a body nobody reads), and gets 503 only when every one is busy.
    max_connections: int = 1024
    #: Open connections one client address may have; beyond that a new one gets 503 and is
    #: closed before anything is read (:mod:`service.http.connections`). 0 = no limit.
    max_connections_per_client: int = 64
    #: Seconds a request head may take to arrive, from the connection's start or the previous
    #: answer; a connection that sends its head slower (or nothing) is closed. 0 = no limit.
    header_timeout: float = 10.0
    #: Longest side of a PNG preview; larger results are shown decimated.
    preview_max_edge: int = 1024
    #: Days a finished job (done, failed, cancelled), or one left created/uploading, is kept
    #: after its last change; then it is deleted. 0 = keep every job until deleted by hand.
    retention_days: float = 0.0
    #: Server URL and API token used by ``maxfs submit/status/fetch/cancel``.
    server: str = "http://127.0.0.1:8000"
    token: str = ""

    def __init__(self, **given: Any) -> None:
        fields = {f.name: f for f in dataclasses.fields(self)}
        unknown = sorted(set(given) - set(fields))
        if unknown:
            raise TypeError(f"unknown settings: {', '.join(unknown)}")
        env = {k.upper(): v for k, v in os.environ.items() if k.upper().startswith(ENV_PREFIX)}
        for name, f in fields.items():
            var = ENV_PREFIX + name.upper()
            if name in given:
                value = _parse(str(f.type), given[name], name)
            elif var in env:
                value = _parse(str(f.type), env[var], var)
            else:
                value = f.default
            low = _AT_LEAST.get(name)
            if low is not None and value < low:
                where = name if name in given else var
                raise InvalidInputError(f"{where} must be at least {low}, got {value}")
            setattr(self, name, value)

    def replace(self, **changes: Any) -> Settings:
        """A copy with ``changes`` (the environment is not read again for the other fields)."""
        return Settings(**(dataclasses.asdict(self) | changes))

    @property
    def tokens_file(self) -> Path:
        return Path(self.data_dir) / "maxfs-tokens.json"


def cluster_kind(settings: Settings) -> str:
    """The kind of cluster ``settings`` ask for: ``MAXFS_CLUSTER``, or from ``MAXFS_SCHEDULER``."""
    kind = (settings.cluster or ("address" if settings.scheduler else "local")).strip().lower()
    if kind not in KINDS:
        raise InvalidInputError(f"unknown cluster {settings.cluster!r}: use one of {', '.join(KINDS)}")
    if kind == "address" and not settings.scheduler:
        raise InvalidInputError(
            "cluster 'address' needs the scheduler's address: set MAXFS_SCHEDULER (or --scheduler) "
            "to e.g. tls://10.0.0.5:8786"
        )
    return kind


def cluster_settings(scheduler: str = "", workers: int = 2, cluster: str = "") -> Settings:
    """The ``MAXFS_*`` settings with the cluster the command line chose (see :mod:`service.runs.cluster`)."""
    return Settings().replace(scheduler=scheduler, workers=workers, cluster=cluster)


def runs_in_process(settings: Settings, nbytes: int, limit: int) -> bool:
    """Whether ``maxfs run`` solves a stack of ``nbytes`` in its own process (threads, the stack
    in memory): on the ``local`` cluster and at most ``limit`` bytes (``MAXFS_IN_PROCESS_BYTES``)."""
    return cluster_kind(settings) == "local" and nbytes <= limit
