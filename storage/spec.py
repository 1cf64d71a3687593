"""A job's input spec and where its store lives: what a client needs before any store exists.

Kept apart from :mod:`storage.layout` (which re-exports every name here) because that module
imports zarr, 0.3-0.4 s of CPU that ``maxfs submit`` (choosing the tile edge from the spec) and
``maxfs fetch`` (checking an output folder) spent on every start for nothing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.digests import DIGEST, DIGESTS
from maxfs.storage.errors import InvalidInputError
from maxfs.storage.observations import ObservationModel
from maxfs.storage.options import DTYPES, check_lights
from maxfs.storage.outputs import output_bytes_per_pixel
from maxfs.storage.params import JobParams
from maxfs.storage.tiles import auto_tile, tile_memory

if TYPE_CHECKING:
    from maxfs.storage.datasets import Dataset

#: The Zarr group's folder inside a job folder.
GROUP_DIR = "results.zarr"


@dataclass(frozen=True)
class JobSpec:
    """Shape and metadata of a job's inputs."""

    k: int
    height: int
    width: int
    channels: int | None  # None = grey
    dtype: str
    lights: NDArray[np.float64]
    intensities: NDArray[np.float64] | None = None
    #: the hash of the store's input digests (:mod:`storage.digests`): a new store's is
    #: :data:`~storage.digests.DIGEST`, an opened store's the one it records
    digest: str = DIGEST

    @classmethod
    def of(cls, ds: Dataset) -> JobSpec:
        """The validated spec of an opened dataset's stack."""
        return cls(ds.k, ds.height, ds.width, ds.channels, ds.dtype, ds.lights, ds.intensities).validate()

    def validate(self) -> JobSpec:
        if self.k < 3:
            raise InvalidInputError(f"photometric stereo needs at least 3 images, got k={self.k}")
        if self.height < 1 or self.width < 1:
            raise InvalidInputError(
                f"image height and width must be positive, got height={self.height}, width={self.width}"
            )
        if self.channels not in (None, 3):
            raise InvalidInputError(f"channels must be 1 (grey) or 3 (RGB), got {self.channels}")
        if self.dtype not in DTYPES:
            raise InvalidInputError(f"dtype must be one of {', '.join(DTYPES)}, got {self.dtype!r}")
        lights = check_lights(self.lights, self.k)
        inten = self.intensities
        if inten is not None:
            try:
                inten = np.asarray(inten, dtype=np.float64)
            except (ValueError, TypeError):
                raise InvalidInputError(
                    f"light intensities must be {self.k} numbers, or {self.k} rows of one number per "
                    "channel, all rows the same length"
                ) from None
        obs = ObservationModel.for_input(np.dtype(self.dtype), self.k, self.channels, inten)
        if self.digest not in DIGESTS:
            raise InvalidInputError(f"unknown input digest {self.digest!r}; one of {', '.join(DIGESTS)}")
        return JobSpec(
            self.k, self.height, self.width, self.channels, self.dtype, lights, obs.intensities, self.digest
        )

    @property
    def image_shape(self) -> tuple[int, ...]:
        hw = (self.height, self.width)
        return hw if self.channels is None else (*hw, self.channels)

    @property
    def image_nbytes(self) -> int:
        return int(np.prod(self.image_shape)) * np.dtype(self.dtype).itemsize

    @property
    def itemsize(self) -> int:
        return np.dtype(self.dtype).itemsize

    @property
    def pixels(self) -> int:
        return self.height * self.width

    def check_params(self, params: JobParams) -> None:
        """Refuse thresholds that no value of these images can reach: for integer input, an
        eps or shadow threshold above the brightest grey value the dtype can hold (after the
        light intensities) makes every observation fit or every one a shadow, and the result
        meaningless. Float input has no such bound."""
        dt = np.dtype(self.dtype)
        if not np.issubdtype(dt, np.integer) or self.intensities is None:
            return
        top = float(np.iinfo(dt).max) / float(np.min(self.intensities)) + 1.0
        asked = None if params.eps_request == "auto" else float(params.eps_request)
        for name, v in (("eps", params.eps if params.eps is not None else asked), ("shadow", params.shadow)):
            if v is not None and v > top:
                raise InvalidInputError(
                    f"{name} = {v:g} is above the brightest value {self.dtype} images can hold here "
                    f"({top:g}, after the light intensities): every observation would "
                    f"{'fit' if name == 'eps' else 'be a shadow'}; give a value in the data's range, or "
                    f"{'eps=auto' if name == 'eps' else 'leave it unset'}"
                )

    def store_nbytes(self) -> int:
        """Upper bound of the job's size on disk (images and outputs, uncompressed)."""
        return self.k * self.image_nbytes + self.pixels * output_bytes_per_pixel(self.k, self.channels)

    def auto_tile(self, memory: int, solver: str = "exact", mask: NDArray[np.bool_] | None = None) -> int:
        """Tile edge for this stack, a per-task memory budget, a solver and, where it is known
        when the job is made, the mask (see :func:`storage.tiles.auto_tile`)."""
        return auto_tile(self.k, self.channels, self.itemsize, memory, self.pixels, solver, mask)

    def resolve_tile(
        self, tile: int | str, memory: int, solver: str = "exact", mask: NDArray[np.bool_] | None = None
    ) -> int:
        """``"auto"`` to :meth:`auto_tile`; a tile edge given by hand must fit ``memory``."""
        if tile == "auto":
            return self.auto_tile(memory, solver, mask)
        self.check_tile(int(tile), memory)
        return int(tile)

    def check_tile(self, tile: int, memory: int) -> None:
        """Refuse a tile edge whose task would need more than ``memory`` bytes."""
        need = tile_memory(tile, self.k, self.channels, self.itemsize)
        if need > memory:
            raise InvalidInputError(
                f"tile {tile} needs about {need / 2**20:.0f} MiB per task with k={self.k}, more than the "
                f"{memory / 2**20:.0f} MiB task budget; use tile {self.auto_tile(memory)} or 'auto'"
            )


def job_folder(path: Path) -> Path:
    """The job folder of ``path``, which may name the folder or its ``results.zarr``."""
    path = Path(path)
    return path.parent if path.name == GROUP_DIR and (path / "zarr.json").exists() else path


def is_job_folder(path: Path) -> bool:
    """Whether ``path`` holds a maxfs job store, of this or an older format."""
    for meta in (Path(path) / GROUP_DIR / "zarr.json", Path(path) / "zarr.json"):
        try:
            attrs = json.loads(meta.read_text()).get("attributes", {})
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(attrs, dict) and "maxfs_format" in attrs:
            return True
    return False
