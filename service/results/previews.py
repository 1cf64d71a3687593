"""PNG previews of results, coloured as in the paper."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.outputs import PREVIEW_NAMES, TILE_OUTPUTS


def box(ok: NDArray[np.bool_]) -> tuple[slice, ...] | None:
    """The bounding box of ``ok`` over its first two axes (rows, columns; any further axis counts
    where any of it is ``ok``) as slices, or None when nothing is ``ok``; fewer than two axes: the
    whole array. A preview is computed inside it only (an object on 5 % of the image costs 5 % of
    the float passes) and is 0 outside, exactly as computed everywhere."""
    if ok.ndim < 2:
        return (Ellipsis,)
    if ok.ndim > 2:
        ok = ok.reshape(*ok.shape[:2], -1).any(axis=2)
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    if not rows.size:
        return None
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def normal_rgb(normal: NDArray[np.floating]) -> NDArray[np.uint8]:
    """255 * (n + 1) / 2 for all three components (the field's convention); black where undefined."""
    normal = np.asarray(normal)
    out = np.zeros(normal.shape, dtype=np.uint8)
    defined = np.isfinite(normal[..., 0])
    b = box(defined)
    if b is None:
        return out
    n = np.nan_to_num(np.asarray(normal[b], dtype=np.float64), nan=0.0)
    rgb = (n + 1.0) / 2.0
    rgb[~defined[b]] = 0.0
    out[b] = np.clip(np.round(255 * rgb), 0, 255).astype(np.uint8)
    return out


def scale_to_uint8(values: NDArray[np.floating], top: float | None = None) -> NDArray[np.uint8]:
    """Linear 0..top to 0..255 (``top`` defaults to the 99.5th percentile of positive values)."""
    values = np.asarray(values)
    out = np.zeros(values.shape, dtype=np.uint8)
    pos = values > 0  # where nan_to_num(values) > 0; every other value maps to 0
    b = box(pos)
    if b is None:
        return out
    v = np.nan_to_num(np.asarray(values[b], dtype=np.float64))
    if top is None:
        p = v[v > 0]
        top = float(np.percentile(p, 99.5)) if p.size else 1.0
    out[b] = np.clip(np.round(255 * v / max(top, 1e-12)), 0, 255).astype(np.uint8)
    return out


#: zlib level of the preview files ``maxfs run`` writes: level 1 encodes them about twice as fast
#: as the default (6) for files about 25 % larger (a 512 x 612 normal map: 28 kB instead of 22 kB).
PNG_LEVEL = 1
#: Previews rendered from the tiles' outputs (the table's previewable tile outputs).
PREVIEWS = tuple(o.name for o in TILE_OUTPUTS if o.preview)
#: Output arrays the previews read (never ``inliers``, which is k times larger; the albedo
#: preview is in colour where ``albedo_rgb`` exists).
PREVIEW_INPUTS = (*PREVIEWS, "albedo_rgb")
#: Previews the server renders: the above, and ``depth`` (a shaded relief) once the store has a depth.
HTTP_PREVIEWS = PREVIEW_NAMES


def inputs_of(name: str) -> tuple[str, ...]:
    """The output arrays the preview ``name`` reads."""
    return {"normal": ("normal",), "albedo": ("albedo", "albedo_rgb"), "depth": ("depth",)}.get(name, (name,))


def render(name: str, arrays: dict[str, NDArray], k: int) -> NDArray[np.uint8]:
    """The preview image of one output (``normal``, ``albedo``, ``inlier_count`` or ``depth``)."""
    if name == "normal":
        return normal_rgb(arrays["normal"])
    if name == "albedo":
        if arrays.get("albedo_rgb") is not None:
            return scale_to_uint8(arrays["albedo_rgb"])
        return scale_to_uint8(arrays["albedo"])
    if name == "inlier_count":
        return scale_to_uint8(arrays["inlier_count"], top=float(k))
    if name == "depth":
        from maxfs.worker.depth import relief_rgb  # the relief `maxfs run` writes as previews/depth.png

        return relief_rgb(arrays["depth"])
    raise KeyError(name)


def legend_strip(width: int, k: int) -> NDArray[np.uint8]:
    """A grey legend for the inlier-count preview, as wide as it: a ramp from black (0 images)
    to white (all ``k``), and under it "0" at the left and "k images" at the right."""
    from PIL import Image, ImageDraw, ImageFont

    ramp = np.tile(np.round(np.linspace(0, 255, max(width, 1))).astype(np.uint8), (6, 1))
    text = Image.new("L", (max(width, 1), 14), 0)
    draw = ImageDraw.Draw(text)
    font = ImageFont.load_default()
    right = f"{k} images"
    draw.text((1, 1), "0", fill=255, font=font)
    draw.text((max(width - 1 - draw.textlength(right, font=font), 12), 1), right, fill=255, font=font)
    return np.vstack([np.zeros((2, ramp.shape[1]), np.uint8), ramp, np.asarray(text)])


def with_legend(name: str, image: NDArray[np.uint8], k: int) -> NDArray[np.uint8]:
    """The preview file as written beside the results: ``inlier_count`` gets its legend below
    (its greys mean image counts); the others are self-explaining colour maps."""
    if name != "inlier_count":
        return image
    return np.vstack([image, legend_strip(image.shape[1], k)])
