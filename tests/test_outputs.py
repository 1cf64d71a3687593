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
    store = JobStore.create(tmp_path / "job", spec, JobParams.build(eps=1.0, tile=16).with_eps(1.0))
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


def test_tiles_without_masked_pixels_are_done_without_a_marker_once_the_job_has_eps(tmp_path: Path) -> None:
    mask = np.zeros((24, 24), bool)
    mask[16:, 16:] = True  # only tile 3 holds masked pixels
    sc = synthetic.sphere(k=6, size=24)
    spec = JobSpec(6, 24, 24, None, "uint8", sc.lights)
    waiting = JobStore.create(tmp_path / "auto", spec, JobParams.build(eps="auto", tile=16))
    waiting.write_mask(mask)
    assert not waiting.done_grid().any()  # eps not estimated yet: nothing is done
    store = _store(tmp_path, None, mask)
    np.testing.assert_array_equal(store.masked_per_tile(), [[0, 0], [0, 64]])
    np.testing.assert_array_equal(store.done_grid(), [[True, True], [True, False]])
    assert not store.group["tiles/done"][...].any()  # no marker written for them
    p = store.progress()
    assert (p.tiles_done, p.tiles_total, p.pixels_done, p.pixels_total) == (0, 1, 0, 64)  # tiles with work
    t = store.tiles()[3]
    res = solve_tile(
        np.zeros((6, 8, 8), np.uint8),
        sc.lights,
        store.observation_model,
        make_thresholds(6, 1.0),
        "exact",
        mask[16:, 16:],
    )
    store.write_tile(t, res.outputs(), store.params.token(), (64, 60, 50))
    assert store.done_grid().all() and store.tile_done(t)
    p = store.progress()
    assert (p.tiles_done, p.pixels_done, p.solved, p.certified) == (1, 64, 60, 50)
    for o in TILE_OUTPUTS:  # read over the occupied tiles only: the same as reading every chunk
        if o.exists(None):
            got, every = store.read_output(o.name), np.asarray(store.group[o.name][...])
            np.testing.assert_array_equal(got, every, err_msg=o.name)
            assert got.dtype == every.dtype


def test_a_new_mask_is_counted_again_by_the_same_store_object(tmp_path: Path) -> None:
    store = _store(tmp_path, None)
    assert store.masked_per_tile().tolist() == [[256, 128], [128, 64]]  # no mask: every pixel
    mask = np.zeros((24, 24), bool)
    mask[:3, :3] = True
    store.write_mask(mask)  # an upload after the job was made: the counts follow it
    assert store.masked_per_tile().tolist() == [[9, 0], [0, 0]]
    assert store.done_grid().tolist() == [[False, True], [True, True]]


def test_auto_tiles_put_at_most_an_eighth_of_the_masked_pixels_in_one_tile() -> None:
    from maxfs.storage.requests import job_params
    from maxfs.storage.tiles import MASKED_SHARE, MIN_TILE, TILE_STEP, balanced_edge, masked_per_tile

    # a 160-pixel disc in a 612 x 512 frame, as a DiLiGenT object: the frame alone asks for 128-pixel
    # tiles, where one tile would hold over half of the object
    spec = JobSpec(96, 512, 612, 3, "uint16", synthetic.lights_uniform(96))
    yy, xx = np.mgrid[:512, :612]
    mask = np.hypot(yy - 250, xx - 320) < 72
    frame = job_params(spec, {}, 512 << 20).tile
    assert masked_per_tile(mask, frame).max() > mask.sum() / 2
    edge = job_params(spec, {}, 512 << 20, mask).tile
    assert edge % TILE_STEP == 0 and MIN_TILE <= edge < frame
    assert masked_per_tile(mask, edge).max() * MASKED_SHARE <= mask.sum()
    assert masked_per_tile(mask, edge + TILE_STEP).max() * MASKED_SHARE > mask.sum()  # the largest that does
    assert job_params(spec, {"tile": 96}, 512 << 20, mask).tile == 96  # a tile given by hand stays
    # an object filling the frame keeps the frame's edge; a tiny one gets the smallest tiles
    assert balanced_edge(np.ones((512, 612), bool), frame) == frame
    tiny = np.zeros((512, 612), bool)
    tiny[:10, :10] = True
    assert balanced_edge(tiny, frame) == MIN_TILE


def test_balanced_tiles_keep_a_large_frame_under_the_tile_limit() -> None:
    from maxfs.storage.tiles import MAX_AUTO_TILES, balanced_edge, grid_shape

    frame = np.zeros((3000, 4000), bool)
    frame[1400:1500, 1900:2000] = True  # a small object in a 12-megapixel frame
    edge = balanced_edge(frame, 512)
    ny, nx = grid_shape(3000, 4000, edge)
    assert ny * nx <= MAX_AUTO_TILES < np.prod(grid_shape(3000, 4000, edge - 16))
