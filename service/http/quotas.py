"""Quota and disk checks of new and resumed jobs, made before anything is stored.

Per job: at most ``MAXFS_MAX_K`` images, ``MAXFS_MAX_PIXELS`` pixels and ``MAXFS_MAX_TILES``
tiles, and a hand-set tile no more work per task than "auto" allows; per user: at most
``MAXFS_MAX_OPEN_JOBS`` unfinished jobs; on disk: never into the reserve
(:class:`service.http.guards.DiskBudget`).
"""

from __future__ import annotations

from collections.abc import Callable

from maxfs.service.http.guards import DiskBudget
from maxfs.service.http.index import JobIndex
from maxfs.service.settings import Settings
from maxfs.storage.errors import InvalidInputError, PayloadTooLargeError, QuotaError
from maxfs.storage.layout import JobSpec
from maxfs.storage.params import JobParams
from maxfs.storage.records import JobRecord
from maxfs.storage.tiles import grid_shape
from maxfs.storage.tokens import User


class JobLimits:
    """The limits of one server: its settings, its jobs' index and its disk budget."""

    def __init__(
        self,
        settings: Settings,
        index: JobIndex,
        disk: DiskBudget,
        record_or_none: Callable[[str], JobRecord | None],
    ) -> None:
        self.settings = settings
        self.index = index
        self.disk = disk
        self.record_or_none = record_or_none

    def open_jobs(self, user: User) -> int:
        """The user's unfinished jobs (reads only the records of those that may be)."""
        return self.index.count_open(user.name, self.record_or_none)

    def check_tiles(self, spec: JobSpec, params: JobParams) -> None:
        """At most ``MAXFS_MAX_TILES`` tiles per job."""
        ny, nx = grid_shape(spec.height, spec.width, params.tile)
        most = self.settings.max_tiles
        if ny * nx > most:
            need = -(-int((spec.pixels / most) ** 0.5) // 16) * 16
            raise InvalidInputError(
                f"tile {params.tile} cuts {spec.height} x {spec.width} into {ny * nx} tiles, more than a job "
                f"may have ({most}, MAXFS_MAX_TILES); use tile {max(need, 16)} or more"
            )

    def check_disk(self, nbytes: int, what: str) -> None:
        """Refuse (507) to store ``nbytes`` more if that, with what uploads in flight have
        reserved (:class:`service.http.guards.DiskBudget`), would eat into the disk reserve."""
        self.disk.check(nbytes, what)

    def check_size(self, spec: JobSpec) -> None:
        """``MAXFS_MAX_K`` and ``MAXFS_MAX_PIXELS`` (413): before anything is computed from the
        size (the automatic tile of a huge height overflowed into a 500)."""
        s = self.settings
        if spec.k > s.max_k:
            raise PayloadTooLargeError(
                f"k={spec.k} images is more than this server allows per job ({s.max_k}, MAXFS_MAX_K); "
                "split the lights into several jobs"
            )
        if spec.pixels > s.max_pixels:
            raise PayloadTooLargeError(
                f"{spec.height} x {spec.width} = {spec.pixels} pixels is more than this server allows "
                f"({s.max_pixels}, MAXFS_MAX_PIXELS); crop or bin the images"
            )

    def check_limits(self, spec: JobSpec, user: User) -> None:
        """Per-job and per-user limits, then disk space, before anything is stored."""
        s = self.settings
        self.check_size(spec)
        if self.open_jobs(user) >= s.max_open_jobs:
            raise QuotaError(
                f"user {user.name!r} already has {s.max_open_jobs} unfinished jobs, the most allowed "
                "(MAXFS_MAX_OPEN_JOBS); wait for one to finish or cancel one"
            )
        self.check_disk(spec.store_nbytes(), f"a job of {spec.k} images of {spec.height} x {spec.width}")
