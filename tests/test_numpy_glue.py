"""The robust path's numpy glue, rewritten for fewer passes (issue 22, fifth round), gives the
same bits as the straightforward numpy it replaced: spelled out here as the reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from maxfs.storage.observations import ObservationModel
from maxfs.worker import synthetic
from maxfs.worker.problem import Thresholds, make_thresholds, slabs
from maxfs.worker.solve import TileResult, solve_pixels, solve_tile


def _prepare_reference(obs: ObservationModel, raw: np.ndarray):
    """ObservationModel.prepare before the rewrite."""
    k = raw.shape[0]
    vals = raw.reshape(k, -1, obs.channels or 1)
    f = vals.astype(np.float64)
    if obs.dequantize:
        f += np.where(vals > 0, 0.5, 0.0)
    f /= obs.intensities[:, None, :]
    grey = np.ascontiguousarray(f.mean(axis=2).T)
    rgb = np.ascontiguousarray(np.moveaxis(f, 0, 1)) if obs.channels is not None else None
    if obs.sensor_max is None:
        sat = np.zeros(grey.shape, dtype=bool)
    else:
        sat = (vals >= obs.sensor_max).any(axis=2).T
    return grey, rgb, sat


def _raw(rng: np.random.Generator, dtype, shape: tuple[int, ...]) -> np.ndarray:
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        raw = rng.integers(max(info.min, -300), info.max, shape, endpoint=True).astype(dtype)
        raw.flat[::7] = info.max  # saturated
        raw.flat[::5] = 0  # shadows (dequantisation leaves them at 0)
    else:
        raw = (rng.standard_normal(shape) * 100).astype(dtype)
        raw.flat[::11] = np.nan
        raw.flat[::13] = np.inf
        raw.flat[::17] = -0.0
    return raw


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.float32, np.float64])
@pytest.mark.parametrize("channels", [None, 1, 2, 3, 4, 9])
def test_prepare_matches_reference(dtype, channels) -> None:
    rng = np.random.default_rng(1)
    for dequantize in (False, True):
        for spatial in ((1,), (40,), (6, 7)):
            k = 13
            shape = (k, *spatial) + ((channels,) if channels else ())
            raw = _raw(rng, dtype, shape)
            for layout in (raw, np.concatenate([raw, raw], axis=1)[:, ::2]):  # contiguous, strided
                obs = ObservationModel.for_input(
                    dtype, k, channels, rng.uniform(0.1, 3.0, (k, channels or 1)), dequantize=dequantize
                )
                before = layout.copy()
                got = obs.prepare(layout)
                np.testing.assert_array_equal(layout, before)  # the input is not written
                _assert_prepared(got, _prepare_reference(obs, layout))
                # some positions only, in a given order (a masked tile's pixels)
                flat = layout.reshape(k, -1, *layout.shape[1 + len(spatial) :])
                pixels = rng.permutation(flat.shape[1])[: max(1, flat.shape[1] // 2)]
                _assert_prepared(obs.prepare(layout, pixels), _prepare_reference(obs, flat[:, pixels]))
                np.testing.assert_array_equal(layout, before)


def _assert_prepared(got, ref) -> None:
    for a, b in zip(got, ref, strict=True):
        if b is None:
            assert a is None
            continue
        assert a.shape == b.shape and a.dtype == b.dtype
        assert a.tobytes() == np.ascontiguousarray(b).tobytes()  # bits, NaN included
        assert a.flags.c_contiguous


def _slabs_reference(i: np.ndarray, th: Thresholds):
    """worker.problem.slabs for Thresholds before the in-place rewrite."""
    # the inputs hold NaN and +-inf on purpose: their arithmetic warnings are expected
    with np.errstate(invalid="ignore"):
        t = th.eps + th.eps_rel * i if th.eps_rel else th.eps
        floor = th.eps if th.min_shading is None else th.min_shading
        a, b = np.maximum(i - t, floor), i + t
        dark = i <= th.shadow
    a = np.where(dark, -np.inf, a)
    b = np.where(dark, np.maximum(i, 0.0) + t, b)
    return a, b


@pytest.mark.parametrize("eps_rel", [0.0, 0.05])
def test_shadow_slabs_match_reference(eps_rel: float) -> None:
    rng = np.random.default_rng(2)
    i = rng.standard_normal((50, 24)) * 10.0
    i.flat[::9] = 0.0
    i.flat[::10] = -0.0
    i.flat[::11] = np.nan
    i.flat[::13] = np.inf
    i.flat[::17] = -np.inf
    i.flat[::19] = 1.0  # on the shadow threshold below
    th = make_thresholds(24, 3.0, model="robust", response=1.0, eps_rel=eps_rel)
    assert th.shadow_slabs and th.shadow == 1.0
    for got, ref in zip(slabs(i, th), _slabs_reference(i, th), strict=True):
        assert got.tobytes() == ref.tobytes()
    grey = np.abs(i[:, :1])  # no negative value: the branch that rewrites none
    for got, ref in zip(slabs(grey, th), _slabs_reference(grey, th), strict=True):
        assert got.tobytes() == ref.tobytes()


def _assert_tiles_equal(got: TileResult, ref: TileResult) -> None:
    for f in dataclasses.fields(TileResult):
        a, b = getattr(got, f.name), getattr(ref, f.name)
        if a is None or b is None:
            assert a is None and b is None, f.name
        else:
            np.testing.assert_array_equal(a, b, err_msg=f.name)
            assert np.asarray(a).dtype == np.asarray(b).dtype, f.name


def _inactive_tile(raw, L, obs, th, solver) -> TileResult:
    """Every pixel of the tile inactive, solved (not taken from a cache)."""
    h, w = raw.shape[1:3]
    g, rgb, sat = obs.prepare(raw)
    r = solve_pixels(g, L, th, solver, rgb=rgb, active=np.zeros(h * w, bool), outlier=sat)
    return TileResult.of_pixels(r, h, w)


@pytest.mark.parametrize("solver", ["exact", "l2"])
def test_tile_outside_the_mask_is_the_inactive_fill(solver: str) -> None:
    """A tile with no masked pixel is not solved, and the masked-out pixels' values (cached per
    process and inputs) follow the inputs: grey and colour, paper and robust, in turn."""
    sc = synthetic.bump_scene(12, 16, seed=5)
    grey = sc.images.astype(np.uint8)
    cases = [
        (grey, None, make_thresholds(12, 2.0, saturation=255)),
        (np.repeat(grey[..., None], 3, axis=-1), 3, make_thresholds(12, 2.0, model="robust", response=1.0)),
        (grey, None, make_thresholds(12, 3.0, model="robust", response=1.0)),
    ]
    for raw, C, th in cases * 2:  # the second round reads the cache
        obs = ObservationModel.for_input(raw.dtype, 12, C, dequantize=C is not None)
        empty = np.zeros(raw.shape[1:3], bool)
        _assert_tiles_equal(
            solve_tile(raw, sc.lights, obs, th, solver, empty),
            _inactive_tile(raw, sc.lights, obs, th, solver),
        )
        ragged = sc.mask & (np.arange(16)[None, :] % 2 == 0)
        got = solve_tile(raw, sc.lights, obs, th, solver, ragged)
        full = solve_tile(raw, sc.lights, obs, th, solver, None)
        out = _inactive_tile(raw, sc.lights, obs, th, solver)
        # solved pixels as when the tile is solved whole; the others as the inactive ones
        for name in ("normal", "albedo", "inlier_count", "optimal", "source"):
            a, b, c = getattr(got, name), getattr(full, name), getattr(out, name)
            np.testing.assert_array_equal(a[ragged], b[ragged], err_msg=name)
            np.testing.assert_array_equal(a[~ragged], c[~ragged], err_msg=name)
