"""The output table: every per-pixel array a job produces, in one place.

One row per array says its dtype, fill value, dimension names, description, whether it
has one plane per image or per colour channel, and whether it gets a preview. The table
drives store creation and tile writes (:mod:`storage.layout`), the store's size estimate,
the HTTP name enums (:mod:`service.http.openapi`) and the tests; adding an output array is
adding a row here and computing it in :func:`worker.solve.solve_tile`.

Like :mod:`storage.options` it is numpy only, at the bottom of the layers.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np


class Source(IntEnum):
    """How a pixel's normal was obtained: the ``source`` output (uint8)."""

    MASKED = 0  #: outside the mask: not solved
    CERTIFIED = 1  #: Max-FS optimum, proved (exact solver or MILP)
    BEST_FOUND = 2  #: Max-FS, best inlier set found within the budget, not proved optimal
    FIT = 3  #: least squares, nothing proved: the l2 solver, or the fallback of the robust
    #: model where Max-FS gives no normal (< 3 candidates, or rank-deficient inliers)
    UNDETERMINED = 4  #: no normal: the usable lights do not determine one (rank < 3 or
    #: badly conditioned); NaN normal, albedo 0


@dataclass(frozen=True)
class Output:
    """One per-pixel output array.

    Attributes
    ----------
    dims
        Zarr v3 ``dimension_names`` (xarray reads them).
    per
        ``None`` for one value per pixel, ``"xyz"`` for 3, ``"channel"`` for one per colour
        channel (colour input only: the array exists only then), ``"image"`` for one per
        image, stored image-first ``(k, H, W)``.
    made
        ``"tile"``: written by every tile (:meth:`storage.layout.JobStore.write_tile`);
        ``"input"``: stored with the inputs (``mask``); ``"after"``: made after the run
        from other outputs (``depth``), absent until then.
    preview
        A preview PNG is rendered from it (``service.results.previews``).
    """

    name: str
    dtype: str
    fill: Any
    dims: tuple[str, ...]
    description: str
    per: str | None = None
    made: str = "tile"
    preview: bool = False
    units: str | None = None

    def exists(self, channels: int | None) -> bool:
        """Whether a store of this colour layout has the array."""
        return self.per != "channel" or channels is not None

    def planes(self, k: int, channels: int | None) -> int:
        """Values per pixel."""
        return {None: 1, "xyz": 3, "channel": channels or 0, "image": k}[self.per]

    def shape(self, k: int, height: int, width: int, channels: int | None) -> tuple[int, ...]:
        n = self.planes(k, channels)
        if self.per is None:
            return (height, width)
        return (n, height, width) if self.per == "image" else (height, width, n)

    def bytes_per_pixel(self, k: int, channels: int | None) -> int:
        if not self.exists(channels):
            return 0
        return self.planes(k, channels) * np.dtype(self.dtype).itemsize

    def attrs(self) -> dict[str, str]:
        d = {"long_name": self.description}
        if self.units:
            d["units"] = self.units
        return d


_SOURCE_DOC = (
    "how the normal was obtained: 0 outside the mask, 1 Max-FS optimum proved, "
    "2 Max-FS best found within the budget, 3 least-squares fit (l2 solver or fallback), "
    "4 undetermined (no normal)"
)

#: Every per-pixel output, in the order clients see them.
OUTPUT_TABLE: tuple[Output, ...] = (
    Output(
        "normal",
        "float32",
        np.nan,
        ("y", "x", "xyz"),
        "unit surface normal (x right, y up, z toward the camera); NaN where unsolved",
        per="xyz",
        preview=True,
    ),
    Output(
        "albedo", "float32", 0.0, ("y", "x"), "albedo (grey), in image units; 0 where unsolved", preview=True
    ),
    Output(
        "albedo_rgb",
        "float32",
        0.0,
        ("y", "x", "channel"),
        "albedo per colour channel, in image units; 0 where unsolved",
        per="channel",
    ),
    Output(
        "inliers",
        "bool",
        False,
        ("image", "y", "x"),
        "image i obeys the Lambertian law at this pixel (the optimal inlier set)",
        per="image",
    ),
    Output(
        "inlier_count",
        "uint16",
        0,
        ("y", "x"),
        "number of inlier images (the Max-FS optimum)",
        preview=True,
        units="images",
    ),
    Output("optimal", "bool", False, ("y", "x"), "the optimum is proved"),
    Output("source", "uint8", 0, ("y", "x"), _SOURCE_DOC),
    Output("mask", "bool", True, ("y", "x"), "pixels to solve", made="input"),
    Output(
        "depth",
        "float32",
        np.nan,
        ("y", "x"),
        "z toward the camera from the normals (orthographic: height in pixels; docs/depth.md); NaN outside",
        made="after",
        preview=True,
        units="pixels",
    ),
)

OUTPUTS_BY_NAME: dict[str, Output] = {o.name: o for o in OUTPUT_TABLE}
#: Output names a client may fetch, in table order.
OUTPUT_NAMES: tuple[str, ...] = tuple(OUTPUTS_BY_NAME)
#: Arrays every tile writes.
TILE_OUTPUTS: tuple[Output, ...] = tuple(o for o in OUTPUT_TABLE if o.made == "tile")
#: Arrays with a preview PNG.
PREVIEW_NAMES: tuple[str, ...] = tuple(o.name for o in OUTPUT_TABLE if o.preview)


def output_bytes_per_pixel(k: int, channels: int | None) -> int:
    """Bytes of every output at one pixel (the store's size estimate and the tile memory model)."""
    return sum(o.bytes_per_pixel(k, channels) for o in OUTPUT_TABLE)
