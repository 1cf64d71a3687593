"""One settings object, read from ``MAXFS_*`` environment variables."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Configuration of the server, the CLI and the embedded cluster.

    Every field can be set as ``MAXFS_<NAME>`` (e.g. ``MAXFS_SCHEDULER=tcp://host:8786``).
    """

    model_config = SettingsConfigDict(env_prefix="MAXFS_")

    #: Where job stores live (one folder per job under ``jobs/``).
    data_dir: Path = Path("maxfs-data")
    #: Address of an external Dask scheduler; empty = start an embedded LocalCluster.
    scheduler: str = ""
    #: Worker processes of the embedded cluster (one thread each).
    workers: int = max(1, min(4, os.cpu_count() or 1))
    #: Dask dashboard of the embedded cluster: "" = off; e.g. "127.0.0.1:8787" (loopback only by default).
    dashboard: str = ""
    #: HTTP bind address and port for ``maxfs serve`` (loopback by default).
    host: str = "127.0.0.1"
    port: int = 8000
    #: Largest accepted request body (one image upload), bytes.
    max_upload_bytes: int = 1 << 30
    #: Seconds between job-record saves while a job runs.
    progress_interval: float = 1.0
    #: Retries of a failed tile task before the job fails.
    tile_retries: int = 2
    #: Server URL used by ``maxfs submit/status/fetch/cancel``.
    server: str = "http://127.0.0.1:8000"
