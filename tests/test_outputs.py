"""The output table (storage.outputs) is what a store really holds and what a tile writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.outputs import OUTPUT_TABLE, TILE_OUTPUTS, output_bytes_per_pixel
from maxfs.storage.params import JobParams
from maxfs.storage.tiles import Tile
from maxfs.worker import synthetic
from maxfs.worker.problem import make_thresholds
from maxfs.worker.solve import solve_tile


def _store(tmp_path: Path, channels: int | None, mask: np.ndarray | None = None) -> JobStore:
    sc = synthetic.sphere(k=6, size=24)
    spec = JobSpec(6, 24, 24, channels, "uint8", sc.lights)
    store = JobStore.create(tmp_path / "job", spec, JobParams.build(eps=1.0, tile=16))
    if mask is not None:
        store.write_mask(mask)
    return store


@pytest.mark.parametrize("channels", [None, 3])
@pytest.mark.parametrize("out", OUTPUT_TABLE, ids=lambda o: o.name)
def test_store_arrays_follow_the_table(tmp_path: Path, channels: int | None, out) -> None:
    store = _store(tmp_path, channels)
    names = store.output_names()
    if out.made == "after" or not out.exists(channels):
        assert out.name not in names
        return
    assert out.name in names
    meta = store.group[out.name]
    assert meta.shape == out.shape(6, 24, 24, channels)
    assert str(meta.dtype) == out.dtype
    assert tuple(meta.metadata.dimension_names) == out.dims
    assert dict(meta.attrs)["long_name"] == out.description
    np.testing.assert_array_equal(np.asarray(meta.fill_value), np.asarray(out.fill, dtype=out.dtype))
    assert output_bytes_per_pixel(6, channels) >= out.bytes_per_pixel(6, channels)


@pytest.mark.parametrize("channels", [None, 3])
def test_a_tile_result_writes_every_tile_output(tmp_path: Path, channels: int | None) -> None:
    store = _store(tmp_path, channels)
    sc = synthetic.sphere(k=6, size=24)
    raw = np.clip(sc.images, 0, 255).astype(np.uint8)[:, :16, :16]
    if channels:
        raw = np.repeat(raw[..., None], 3, axis=-1)
    th = make_thresholds(6, 1.0, saturation=255)
    res = solve_tile(raw, store.spec.lights, store.observation_model, th, "exact")
    arrays = res.outputs()
    assert set(arrays) == {o.name for o in TILE_OUTPUTS if o.exists(channels)}
    t = Tile(0, 0, 0, 0, 16, 0, 16)
    store.write_tile(t, arrays, token=7, stats=(256, 256, 256))
    for name, a in arrays.items():
        got = store.group[name][:, :16, :16] if name == "inliers" else store.group[name][:16, :16]
        np.testing.assert_array_equal(got, a)
    with pytest.raises(ValueError, match="lacks normal"):
        store.write_tile(t, {k: v for k, v in arrays.items() if k != "normal"}, token=7, stats=(0, 0, 0))


def test_tiles_start_by_masked_pixel_count(tmp_path: Path) -> None:
    mask = np.zeros((24, 24), bool)
    mask[16:, 16:] = True  # tile 3 (bottom right): 64 px
    mask[:4, :16] = True  # tile 0: 64 px, ties with 3 -> raster order
    mask[20:, :2] = True  # tile 2: 8 px; tile 1: none
    store = _store(tmp_path, None, mask)
    order = [t.index for t in store.by_masked_pixels(store.tiles())]
    assert order == [0, 3, 2, 1]
