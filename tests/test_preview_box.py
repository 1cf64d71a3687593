"""The previews and the depth relief are computed inside the bounding box of what they show only:
their pixels must equal the whole-image formulas (as they were computed before) everywhere."""

from __future__ import annotations

import numpy as np
import pytest

from maxfs.service.results.previews import box, normal_rgb, scale_to_uint8


def _normal_rgb_whole(normal):
    n = np.nan_to_num(np.asarray(normal, dtype=np.float64), nan=0.0)
    rgb = (n + 1.0) / 2.0
    rgb[~np.isfinite(np.asarray(normal)[..., 0])] = 0.0
    return np.clip(np.round(255 * rgb), 0, 255).astype(np.uint8)


def _scale_whole(values, top=None):
    v = np.nan_to_num(np.asarray(values, dtype=np.float64))
    if top is None:
        pos = v[v > 0]
        top = float(np.percentile(pos, 99.5)) if pos.size else 1.0
    return np.clip(np.round(255 * v / max(top, 1e-12)), 0, 255).astype(np.uint8)


def _relief_whole(depth, light=(-1.0, 1.0, 1.0)):
    z = np.asarray(depth, dtype=np.float64)
    dom = np.isfinite(z)
    zf = np.where(dom, z, 0.0)
    dzdc, dzdr = np.zeros_like(zf), np.zeros_like(zf)
    for axis, out in ((1, dzdc), (0, dzdr)):
        fwd = np.diff(zf, axis=axis)
        ok = np.diff(dom.astype(np.int8), axis=axis) == 0
        ok &= np.take(dom, range(dom.shape[axis] - 1), axis=axis)
        fwd = np.where(ok, fwd, np.nan)
        lo, hi = [(0, 0), (0, 0)], [(0, 0), (0, 0)]
        lo[axis], hi[axis] = (1, 0), (0, 1)
        back, ahead = np.pad(fwd, lo, constant_values=np.nan), np.pad(fwd, hi, constant_values=np.nan)
        count = np.isfinite(back).astype(np.int8) + np.isfinite(ahead)
        out[...] = (np.nan_to_num(back) + np.nan_to_num(ahead)) / np.maximum(count, 1)
    nx, ny = -dzdc, dzdr
    L = np.asarray(light) / np.linalg.norm(light)
    shade = (nx * L[0] + ny * L[1] + L[2]) / np.sqrt(nx**2 + ny**2 + 1.0)
    img = np.round(255 * np.clip(0.15 + 0.85 * shade, 0.0, 1.0)).astype(np.uint8)
    img[~dom] = 0
    return img


def _blob(rng, shape, where):
    """Values on a random blob inside the window ``where`` (NaN elsewhere), some of them NaN or 0."""
    a = np.full(shape, np.nan)
    win = a[where]
    win[...] = rng.normal(size=win.shape)
    win[rng.random(win.shape[:2]) < 0.2] = np.nan
    return a


@pytest.mark.parametrize("where", [np.s_[5:9, 3:20], np.s_[0:30, 0:2], np.s_[29:30, 39:40], np.s_[0:0, 0:0]])
def test_previews_equal_the_whole_image_formulas(where):
    rng = np.random.default_rng(3)
    n = _blob(rng, (30, 40, 3), where).astype(np.float32)
    np.testing.assert_array_equal(normal_rgb(n), _normal_rgb_whole(n))
    a = np.abs(_blob(rng, (30, 40), where)).astype(np.float32)
    np.testing.assert_array_equal(scale_to_uint8(a), _scale_whole(a))
    rgb = _blob(rng, (30, 40, 3), where)
    np.testing.assert_array_equal(scale_to_uint8(rgb), _scale_whole(rgb))
    counts = np.nan_to_num(np.abs(_blob(rng, (30, 40), where)) * 20).astype(np.uint16)
    np.testing.assert_array_equal(scale_to_uint8(counts, top=96.0), _scale_whole(counts, 96.0))
    from maxfs.worker.depth import relief_rgb

    z = np.cumsum(_blob(rng, (30, 40), where), axis=1)
    np.testing.assert_array_equal(relief_rgb(z), _relief_whole(z))


def test_box():
    ok = np.zeros((6, 7), bool)
    assert box(ok) is None
    ok[2, 3] = ok[4, 1] = True
    assert box(ok) == (slice(2, 5), slice(1, 4))
    assert box(np.ones(4, bool)) == (Ellipsis,)
