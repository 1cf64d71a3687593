"""The tile grid: the unit of work, of checkpointing, and of solver seeding.

The exact solver seeds each pixel with its predecessor's solution in raster
order *within a tile*, so where several optima tie, which one is returned
depends on the grid. Every path (in-process :func:`worker.solve.solve`, Dask
tile tasks) walks the same grid, so results agree bit for bit for equal
parameters; the tile size is a job parameter for that reason.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy only where a mask is counted: the settings import this module
    import numpy as np
    from numpy.typing import NDArray

#: Default tile edge in pixels.
DEFAULT_TILE = 128


@dataclass(frozen=True)
class Tile:
    """One tile: its index in the grid and its pixel window."""

    index: int
    ty: int
    tx: int
    y0: int
    y1: int
    x0: int
    x1: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.y1 - self.y0, self.x1 - self.x0)


def grid_shape(height: int, width: int, tile: int) -> tuple[int, int]:
    """Number of tile rows and columns covering an image."""
    return (-(-height // tile), -(-width // tile))


def tiles(height: int, width: int, tile: int) -> Iterator[Tile]:
    """All tiles in row-major order; edge tiles are smaller."""
    ny, nx = grid_shape(height, width, tile)
    for ty in range(ny):
        for tx in range(nx):
            y0, x0 = ty * tile, tx * tile
            yield Tile(ty * nx + tx, ty, tx, y0, min(y0 + tile, height), x0, min(x0 + tile, width))


#: Bytes one tile task may hold in arrays (the service's ``MAXFS_TASK_MEMORY``).
DEFAULT_TASK_MEMORY = 512 << 20
#: Upper bound on pixels x images per tile, so a task lasts seconds, not minutes.
WORK_PER_TILE = 1 << 22
#: Work of one pixel-image relative to the exact solver: the MILP is about a hundred times
#: slower per pixel, so its tiles hold a sixteenth of the pixel-images (a quarter of the edge).
WORK_COST: dict[str, int] = {"exact": 1, "l2": 1, "milp": 16}
MIN_TILE, MAX_TILE, TILE_STEP = 32, 512, 16
#: Auto tiles are small enough that an image has at least this many (work to spread).
MIN_TILES = 16
#: With the mask known, auto tiles are small enough that none holds more than 1 / MASKED_SHARE of
#: the masked pixels: a tile is one thread's or worker's work, so the largest one is the critical
#: path, and 8 keeps 4 workers busy to the end (an object in one corner of the frame otherwise
#: sits in one or two tiles whatever the worker count).
MASKED_SHARE = 8
#: ... but not so small that the frame has more tiles than this (the server's default
#: ``MAXFS_MAX_TILES``): each tile is a chunk of every output, read by the previews and the depth.
MAX_AUTO_TILES = 4096


def tile_bytes_per_pixel(k: int, channels: int | None, itemsize: int) -> int:
    """Peak bytes a tile task holds per pixel.

    Counted from the arrays of one task: the raw block (``k*C*itemsize``), the
    float64 copies made by ``ObservationModel.prepare`` and the per-channel
    albedo refit (three of ``k*C*8``), the grey intensities and the solver's
    per-pixel copies (four of ``k*8``), and the boolean masks. ``bench/scale.py``
    checks the model against the measured RSS of workers.
    """
    C = channels or 1
    return k * (C * itemsize + 24 * C + 48) + 256


def auto_tile(
    k: int,
    channels: int | None,
    itemsize: int,
    memory: int = DEFAULT_TASK_MEMORY,
    pixels: int | None = None,
    solver: str = "exact",
    mask: NDArray[np.bool_] | None = None,
) -> int:
    """Tile edge for a job: the largest multiple of 16 that fits the memory budget,
    keeps ``tile**2 * k * WORK_COST[solver] <= WORK_PER_TILE``, gives an image of
    ``pixels`` pixels at least :data:`MIN_TILES` tiles and, given the job's ``mask``, puts no
    more than 1 / :data:`MASKED_SHARE` of its pixels in one tile (:func:`balanced_edge`), within
    [32, 512]. It depends only on the job (its shape, type and mask), never on the cluster or the
    worker count, because the tile size is part of the result (see above)."""
    by_memory = (memory / tile_bytes_per_pixel(k, channels, itemsize)) ** 0.5
    by_work = (WORK_PER_TILE / (max(k, 1) * WORK_COST.get(str(solver), 1))) ** 0.5
    by_count = (pixels / MIN_TILES) ** 0.5 if pixels else float("inf")
    edge = int(min(by_memory, by_work, by_count)) // TILE_STEP * TILE_STEP
    edge = max(MIN_TILE, min(MAX_TILE, edge))
    return edge if mask is None else balanced_edge(mask, edge)


def masked_per_tile(mask: NDArray[np.bool_], tile: int) -> NDArray[np.int64]:
    """Masked pixels of each tile of the grid, ``(ny, nx)``."""
    import numpy as np

    m = np.asarray(mask, dtype=bool)
    ny, nx = grid_shape(*m.shape, tile)
    padded = np.zeros((ny * tile, nx * tile), dtype=bool)
    padded[: m.shape[0], : m.shape[1]] = m
    return padded.reshape(ny, tile, nx, tile).sum(axis=(1, 3), dtype=np.int64)


def balanced_edge(mask: NDArray[np.bool_], largest: int) -> int:
    """The largest tile edge, a multiple of :data:`TILE_STEP` in [:data:`MIN_TILE`, ``largest``],
    whose grid holds at most 1 / :data:`MASKED_SHARE` of the masked pixels in any tile; the
    smallest edge when none does (an object under about ``MASKED_SHARE * MIN_TILE**2`` pixels,
    cheap to solve anyway), where the smallest gives the frame at most :data:`MAX_AUTO_TILES`
    tiles. A mask that selects nothing keeps ``largest``."""
    import numpy as np

    total = int(np.count_nonzero(mask))
    if total == 0:
        return largest
    smallest = MIN_TILE
    while smallest < largest and np.prod(grid_shape(*np.shape(mask), smallest)) > MAX_AUTO_TILES:
        smallest += TILE_STEP
    edge = largest
    while edge > smallest and masked_per_tile(mask, edge).max() * MASKED_SHARE > total:
        edge = max(smallest, (edge - 1) // TILE_STEP * TILE_STEP)
    return edge


def tile_memory(tile: int, k: int, channels: int | None, itemsize: int) -> int:
    """Estimated peak bytes of one task for a tile edge (see :func:`tile_bytes_per_pixel`)."""
    return tile * tile * tile_bytes_per_pixel(k, channels, itemsize)
