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
