"""Image shards written by :class:`storage.shards.ShardWriter` read back through zarr exactly as
written, and as zarr itself would have stored them: every dtype and colour layout the stores
hold, edge shards and chunks, chunks of fill value only, images replaced."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, ZstdCodec

from maxfs.storage import layout
from maxfs.storage.layout import GROUP_DIR, PATHS, JobSpec, JobStore
from maxfs.storage.params import JobParams
from maxfs.storage.shards import ShardReader, ShardWriter
from maxfs.worker import synthetic


def _store(path: Path, k: int, h: int, w: int, channels: int | None, dtype: str, tile: int) -> JobStore:
    spec = JobSpec(k, h, w, channels, dtype, synthetic.lights_uniform(k))
    return JobStore.create(path, spec, JobParams.build(eps=2.0, tile=tile))


#: How stores lay out their image shards: this version's (small images one shard each, chunk keys
#: ``c.i.y.x`` side by side) and the earlier one (a shard per band of tile rows, keys ``c/i/y/x``),
#: which stores made before still have.
LAYOUTS = {"flat-whole": (layout.FLAT_KEYS, layout.WHOLE_IMAGE_SHARD_BYTES), "nested-bands": (None, 0)}


@pytest.fixture(params=sorted(LAYOUTS))
def shard_layout(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    keys, whole = LAYOUTS[request.param]
    monkeypatch.setattr(layout, "FLAT_KEYS", keys)
    monkeypatch.setattr(layout, "WHOLE_IMAGE_SHARD_BYTES", whole)
    return request.param


def _shard_files(folder: Path) -> list[Path]:
    """The shard files of an images array's folder, whatever its chunk key separator."""
    return sorted(
        p for p in folder.rglob("*") if p.is_file() and p.relative_to(folder).as_posix()[:2] in ("c/", "c.")
    )


def _shard_coords(folder: Path, shard: Path) -> tuple[int, ...]:
    rel = shard.relative_to(folder).as_posix()
    return tuple(int(n) for n in rel.replace("/", ".").split(".")[1:])


def _images(k: int, shape: tuple[int, ...], dtype: str, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if dtype == "float32":
        a = rng.random((k, *shape), dtype=np.float32)
    else:
        a = rng.integers(0, np.iinfo(dtype).max, (k, *shape), dtype=dtype)
    a[0] = 0  # an image of fill value only: no shard file at all
    a[1, : shape[0] // 2] = 0  # whole chunks and shards of fill value beside stored ones
    return a


@pytest.mark.parametrize(
    ("h", "w", "channels", "dtype", "tile"),
    [
        (70, 45, None, "uint16", 16),
        (33, 64, 3, "uint8", 16),
        (20, 21, None, "float32", 8),
        (16, 16, 3, "uint16", 16),
    ],
)
def test_shards_read_back_as_zarr_writes_them(
    tmp_path: Path, h: int, w: int, channels: int | None, dtype: str, tile: int, shard_layout: str
) -> None:
    k = 4
    shape = (h, w) if channels is None else (h, w, channels)
    images = _images(k, shape, dtype, seed=h * w)
    fast = _store(tmp_path / "fast", k, h, w, channels, dtype, tile)
    assert fast._shard_writer() is not None, "the stores this version creates get the fast writer"
    slow = _store(tmp_path / "slow", k, h, w, channels, dtype, tile)
    slow._writer = (None,)  # through zarr's own codec pipeline
    for i in range(k):
        fast.write_image(i, images[i])
        slow.write_image(i, images[i])
    again = JobStore.open(tmp_path / "fast", mode="r")
    assert again.uploaded().all()
    assert again.digests() == JobStore.open(tmp_path / "slow", mode="r").digests()
    for i in range(k):
        np.testing.assert_array_equal(again.read_array("images", i), images[i])
    # the files are zarr's: the same set of shards (none where all is fill value), each decoding
    # to the same values as zarr's own, read a tile at a time as tile tasks read them
    root = Path(GROUP_DIR) / PATHS["images"]
    files = [p.relative_to(tmp_path / "fast").as_posix() for p in _shard_files(tmp_path / "fast" / root)]
    assert files and files == [
        p.relative_to(tmp_path / "slow").as_posix() for p in _shard_files(tmp_path / "slow" / root)
    ]
    coords = [_shard_coords(tmp_path / "fast" / root, tmp_path / "fast" / f) for f in files]
    assert not any(c[0] == 0 for c in coords), "an image of zeros stores no shard"
    whole = shard_layout == "flat-whole"
    assert {c[1] for c in coords} == ({0} if whole else set(range(-(-h // min(tile, h)))))
    for t in again.tiles():
        np.testing.assert_array_equal(again.read_tile_images(t), images[:, t.y0 : t.y1, t.x0 : t.x1])


def test_an_image_replaced_by_another_reads_as_the_new_one(tmp_path: Path) -> None:
    store = _store(tmp_path / "s", 3, 40, 30, None, "uint16", 16)
    old, new = _images(2, (40, 30), "uint16", seed=1)[::-1], _images(2, (40, 30), "uint16", seed=2)
    for i in range(2):
        store.write_image(i, old[i])
    for i in range(2):
        store.write_image(i, new[i])  # image 0 becomes all fill value, image 1 half of it
    store = JobStore.open(tmp_path / "s", mode="r")
    for i in range(2):
        np.testing.assert_array_equal(store.read_array("images", i), new[i])


def test_arrays_of_other_codecs_get_no_writer_and_are_written_by_zarr(tmp_path: Path) -> None:
    g = zarr.open_group(tmp_path / "g", mode="w-", zarr_format=3)
    common = dict(shape=(2, 32, 32), chunks=(1, 16, 16), shards=(1, 16, 32), dtype="uint16", fill_value=0)
    for name, comp in [("blosc", BloscCodec()), ("checksum", ZstdCodec(level=1, checksum=True))]:
        a = g.create_array(name, compressors=comp, **common)
        assert ShardWriter.for_array(tmp_path / "g" / name, a) is None, name
    plain = g.create_array("plain", chunks=(1, 16, 16), shape=(2, 32, 32), dtype="uint16")  # no shards
    assert ShardWriter.for_array(tmp_path / "g" / "plain", plain) is None
    ok = g.create_array("ok", compressors=ZstdCodec(level=3), **common)
    w = ShardWriter.for_array(tmp_path / "g" / "ok", ok)
    assert w is not None
    block = np.arange(16 * 32, dtype=np.uint16).reshape(1, 16, 32)
    w.write((1, 1, 0), block)
    np.testing.assert_array_equal(ok[1, 16:], block[0])
    with pytest.raises(ValueError, match="holds"):
        w.write((1, 0, 0), block[:, :8])


@pytest.mark.parametrize(("channels", "dtype"), [(None, "uint16"), (3, "uint8"), (None, "float32")])
def test_shard_reader_reads_any_window_as_zarr_does(
    tmp_path: Path, channels: int | None, dtype: str, shard_layout: str
) -> None:
    """Tile tasks read their images straight from the shard files (ShardReader): the same values
    and dtype as zarr's own reads, for windows on and off the tile grid, over chunks and shards of
    fill value only, in stores written by ShardWriter or by zarr; a damaged shard index is left
    to zarr (the reader answers None)."""
    k, h, w, tile = 4, 70, 45, 16
    shape = (h, w) if channels is None else (h, w, channels)
    images = _images(k, shape, dtype, seed=7)
    for name, writer in (("fast", True), ("slow", False)):
        store = _store(tmp_path / name, k, h, w, channels, dtype, tile)
        if not writer:
            store._writer = (None,)
        for i in range(k - 1):  # the last image never stored: no shard files at all
            store.write_image(i, images[i])
        store = JobStore.open(tmp_path / name, mode="r")
        z = store._fixed("images")
        reader = ShardReader.for_array(tmp_path / name / GROUP_DIR / PATHS["images"], z)
        assert reader is not None
        rng = np.random.default_rng(3)
        windows = [(t.y0, t.y1, t.x0, t.x1) for t in store.tiles()] + [
            (y0, min(h, y0 + dy), x0, min(w, x0 + dx))
            for y0, x0, dy, dx in rng.integers([0, 0, 1, 1], [h, w, 40, 40], size=(60, 4))
        ]
        for y0, y1, x0, x1 in windows:
            got = reader.read((slice(None), slice(y0, y1), slice(x0, x1)))
            want = np.asarray(z[:, y0:y1, x0:x1])
            assert got is not None and got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(reader.read((slice(2, 3), slice(5, 60), slice(0, 45))), z[2:3, 5:60])
        # all windows at once (each shard opened, each chunk decoded once), as the eps sample reads
        many = reader.read_many([(slice(None), slice(y0, y1), slice(x0, x1)) for y0, y1, x0, x1 in windows])
        assert many is not None and len(many) == len(windows)
        for (y0, y1, x0, x1), got in zip(windows, many, strict=True):
            np.testing.assert_array_equal(got, z[:, y0:y1, x0:x1])
        tiles = store.tiles()
        read = store.window_reader(tiles[:3])
        for t in tiles:  # the windows read up front and any other one alike
            np.testing.assert_array_equal(read(t), z[:, t.y0 : t.y1, t.x0 : t.x1])
    folder = tmp_path / "fast" / GROUP_DIR / PATHS["images"]
    reader = ShardReader.for_array(folder, JobStore.open(tmp_path / "fast", mode="r")._fixed("images"))
    assert reader is not None
    shard = _shard_files(folder)[0]
    data = bytearray(shard.read_bytes())
    data[-6] ^= 0xFF  # in the index: its checksum no longer matches
    shard.write_bytes(bytes(data))
    i, y = _shard_coords(folder, shard)[:2]
    y *= z.shards[1] // tile  # the first tile row of the shard
    assert reader.read((slice(i, i + 1), slice(y * tile, y * tile + 1), slice(0, w))) is None
    assert reader.read_many([(slice(None), slice(0, h), slice(0, w))]) is None


@pytest.mark.parametrize(
    ("h", "w", "dtype", "whole"),
    [(320, 296, "uint8", True), (512, 1024, "uint16", True), (513, 1024, "uint16", False)],
)
def test_new_stores_keep_small_images_whole_and_name_their_chunks_flat(
    tmp_path: Path, h: int, w: int, dtype: str, whole: bool
) -> None:
    """An image of at most 1 MiB is one shard (one file per upload), a larger one a shard per band
    of tile rows (an upload holds one band); either way its files (and its digest's) sit side by
    side in the array's folder, no folder per image."""
    store = _store(tmp_path / "s", 3, h, w, None, dtype, 64)
    images = store._fixed("images")
    assert images.shards[1] == (-(-h // 64) * 64 if whole else 64)
    for name in ("images", "input_digests"):
        assert store._fixed(name).metadata.chunk_key_encoding.separator == "."
    img = _images(3, (h, w), dtype, seed=5)[2]
    store.write_image(2, img)
    folder = tmp_path / "s" / GROUP_DIR / PATHS["images"]
    names = sorted(p.name for p in folder.iterdir() if p.name != "zarr.json")
    assert names == (["c.2.0.0"] if whole else [f"c.2.{y}.0" for y in range(-(-h // 64))])
    assert not any(p.is_dir() for p in (tmp_path / "s" / GROUP_DIR / PATHS["input_digests"]).iterdir())
    np.testing.assert_array_equal(JobStore.open(tmp_path / "s", mode="r").read_array("images", 2), img)
