"""A finished tile's chunks written straight to their files (:class:`storage.shards.ChunkFiles`)
are the files zarr itself would have written, byte for byte and name for name, and a process
killed while it writes a tile never leaves the tile marked done."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, ZstdCodec

from maxfs.storage import shards
from maxfs.storage.layout import GROUP_DIR, JobSpec, JobStore
from maxfs.storage.outputs import TILE_OUTPUTS
from maxfs.storage.params import JobParams
from maxfs.storage.shards import ChunkFiles
from maxfs.storage.tiles import Tile
from maxfs.worker import synthetic

K = 5


def _files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by relative path, hidden ones (a write's temporary file) left out."""
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not p.name.startswith(".")
    }


def _hidden(folder: Path) -> list[Path]:
    return [p for p in folder.rglob(".*") if p.is_file()]


@pytest.mark.parametrize(
    ("dtype", "fill", "shape", "chunks"),
    [
        ("float32", np.nan, (20, 13, 3), (8, 8, 3)),
        ("float32", 0.0, (20, 13), (8, 8)),
        ("uint16", 0, (20, 13), (8, 8)),
        ("bool", False, (3, 20, 13), (3, 8, 8)),
        ("uint8", 0, (20, 13), (8, 8)),
        ("int64", 0, (3, 2, 3), (1, 1, 3)),
        ("int32", 0, (3, 2), (1, 1)),
    ],
)
@pytest.mark.parametrize("separator", ["/", "."])
def test_chunk_files_are_the_files_zarr_writes(
    tmp_path: Path, dtype: str, fill: Any, shape: tuple[int, ...], chunks: tuple[int, ...], separator: str
) -> None:
    """Every chunk of an array, edge chunks included, written with values of another dtype (zarr
    casts them), values with some and all of them the fill value (NaN for a NaN fill), -0.0
    beside a fill of +0.0, a scalar, then rewritten: the same files as zarr's own writes."""
    g = zarr.open_group(tmp_path / "g", mode="w-", zarr_format=3)
    keys = {"name": "default", "separator": separator}
    common = dict(shape=shape, chunks=chunks, dtype=dtype, fill_value=fill, chunk_key_encoding=keys)
    by_zarr, direct = g.create_array("zarr", **common), g.create_array("direct", **common)
    w = ChunkFiles.for_array(tmp_path / "g" / "direct", direct)
    assert w is not None
    rng = np.random.default_rng(3)
    grid = [range(-(-n // c)) for n, c in zip(shape, chunks, strict=True)]
    for rnd in range(3):
        for pos in np.ndindex(*(len(r) for r in grid)):
            region = tuple(
                slice(p * c, min((p + 1) * c, n)) for p, c, n in zip(pos, chunks, shape, strict=True)
            )
            inside = tuple(r.stop - r.start for r in region)
            kind = (sum(pos) + rnd) % 5
            value: Any
            if kind == 0:
                value = fill  # a scalar: the chunk's file goes
            elif kind == 1:
                value = np.full(inside, fill, dtype=dtype)
            else:
                value = rng.normal(0, 50, inside)  # float64: cast to the array's dtype as zarr casts
                if dtype == "bool":
                    value = value > 0
                elif np.dtype(dtype).kind in "ui":
                    value = np.abs(value).astype(np.int64)
                if kind == 3 and np.dtype(dtype).kind == "f":
                    value[...] = fill
                    value.flat[0] = -0.0 if fill == 0 else 1.5  # one value apart from the fill
                if kind == 4 and np.dtype(dtype).kind == "f":
                    value.flat[::2] = np.nan
            by_zarr[region] = value
            coords = w.chunk_at(region)
            assert coords == pos
            w.put(coords, w.encode(coords, value))
        made = _files(tmp_path / "g" / "zarr")
        got = _files(tmp_path / "g" / "direct")
        assert {p for p in got if p != "zarr.json"} == {p for p in made if p != "zarr.json"}, rnd
        assert all(got[p] == made[p] for p in got if p != "zarr.json"), rnd
        np.testing.assert_array_equal(direct[...], by_zarr[...])
        for pos in np.ndindex(*(len(r) for r in grid)):  # and read back as zarr reads them
            region = tuple(
                slice(p * c, min((p + 1) * c, n)) for p, c, n in zip(pos, chunks, shape, strict=True)
            )
            chunk = w.read_region(region)
            assert chunk is not None and chunk.dtype == by_zarr.dtype
            np.testing.assert_array_equal(chunk, by_zarr[region])
        for _ in range(12):  # any region, across chunks and the far edges, as zarr reads it
            ends = [np.sort(rng.integers(0, n + 1, 2)) for n in shape]
            region = tuple(slice(int(lo), int(hi)) for lo, hi in ends)
            np.testing.assert_array_equal(w.read_region(region), by_zarr[region])
    assert w.read_region((slice(0, 4, 2),)) is None  # with a step: left to zarr
    assert not _hidden(tmp_path / "g")


def test_regions_that_are_not_one_chunk_and_other_codecs_are_left_to_zarr(tmp_path: Path) -> None:
    g = zarr.open_group(tmp_path / "g", mode="w-", zarr_format=3)
    a = g.create_array("a", shape=(20, 13), chunks=(8, 8), dtype="float32")
    w = ChunkFiles.for_array(tmp_path / "g" / "a", a)
    assert w is not None
    assert w.chunk_at((slice(16, 20), slice(8, 13))) == (2, 1)
    not_one_chunk = [
        (slice(0, 4), slice(0, 8)),
        (slice(4, 12), slice(0, 8)),
        (slice(16, 19), slice(8, 13)),
        (slice(24, 32),),  # past the end
    ]
    for region in not_one_chunk:
        assert w.chunk_at(region) is None, region
    # a row past the end of a per-image array (rows of one chunk each) clamps to an empty region:
    # not the chunk after the last
    rows = ChunkFiles.for_array(
        tmp_path / "g" / "rows", g.create_array("rows", shape=(4, 32), chunks=(1, 32), dtype="uint8")
    )
    assert rows is not None and rows.chunk_at((slice(3, 4),)) == (3, 0)
    assert rows.chunk_at((slice(4, 5),)) is None
    others = {
        "blosc": g.create_array("blosc", shape=(8,), chunks=(4,), dtype="uint8", compressors=BloscCodec()),
        "checksum": g.create_array(
            "checksum", shape=(8,), chunks=(4,), dtype="uint8", compressors=ZstdCodec(level=1, checksum=True)
        ),
        "sharded": g.create_array("sharded", shape=(8,), chunks=(2,), shards=(4,), dtype="uint8"),
        "empty chunks": g.create_array(
            "empty", shape=(8,), chunks=(4,), dtype="uint8", config={"write_empty_chunks": True}
        ),
        "order F": g.create_array("f", shape=(8, 2), chunks=(4, 2), dtype="uint8", config={"order": "F"}),
    }
    for name, arr in others.items():
        assert ChunkFiles.for_array(tmp_path / "g" / name, arr) is None, name


def _store(path: Path, channels: int | None, h: int = 37, w: int = 29, tile: int = 16) -> JobStore:
    spec = JobSpec(K, h, w, channels, "uint16", synthetic.lights_uniform(K))
    return JobStore.create(path, spec, JobParams.build(eps=2.0, tile=tile).with_eps(2.0))


def _results(store: JobStore, t: Tile, seed: int) -> dict[str, np.ndarray]:
    """A tile's outputs as solve_tile hands them over: NaN normals where unsolved, some -0.0."""
    rng = np.random.default_rng(seed)
    h, w = t.shape
    out: dict[str, np.ndarray] = {}
    for o in TILE_OUTPUTS:
        if not o.exists(store.spec.channels):
            continue
        shape = o.shape(K, h, w, store.spec.channels)
        if o.dtype == "bool":
            out[o.name] = rng.random(shape) < 0.5
        elif o.dtype == "float32":
            v = rng.normal(size=shape).astype(np.float32)
            v[: h // 2] = o.fill  # the unsolved half: NaN normals, albedo 0
            v[-1, -1] = -0.0
            out[o.name] = v
        else:
            out[o.name] = rng.integers(0, 5, shape).astype(o.dtype)
    return out


@pytest.mark.parametrize("channels", [None, 3])
def test_tiles_written_directly_leave_the_store_zarr_leaves(
    tmp_path: Path, channels: int | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whole stores: tiles of results (edge tiles too), tiles without masked pixels, a tile
    written again with other results and then as an empty one, each store's done markers and
    counts: every file as zarr writes them (the reference store has no direct writer)."""
    direct, ref = _store(tmp_path / "direct", channels), _store(tmp_path / "zarr", channels)
    real = ChunkFiles.for_array
    stores = [(ref, True), (direct, False)]
    for store, use_zarr in stores:
        monkeypatch.setattr(ChunkFiles, "for_array", (lambda *a: None) if use_zarr else real)
        store._files.clear()
        tiles, token = store.tiles(), store.params.token()
        assert len(tiles) == 6
        mask = np.ones((37, 29), bool)  # its first band all True (the fill value: no file)
        mask[20:, ::3] = False
        store.write_mask(mask)
        for t in tiles:  # with other parameters' token
            if t.index == 1:
                store.write_empty_tile(t, token=token + 1)
            else:
                store.write_tile(t, _results(store, t, t.index), token=token + 1, stats=(t.index, 2, 1))
        store.write_tile(tiles[0], _results(store, tiles[0], 99), token=token, stats=(3, 2, 1))
        store.write_empty_tile(tiles[5], token=token)  # an edge tile that held results
    assert ref._files == {} or all(v is None for v in ref._files.values())
    assert direct._files and all(v is not None for v in direct._files.values())
    got, made = _files(direct.path / GROUP_DIR), _files(ref.path / GROUP_DIR)
    assert sorted(got) == sorted(made)
    assert [p for p in got if got[p] != made[p]] == []
    assert not _hidden(direct.path)
    again = JobStore.open(direct.path, mode="r")
    for name in [*again.output_names(), "done", "tile_stats"]:
        np.testing.assert_array_equal(again.read_array(name), ref.read_array(name), err_msg=name)
    assert again.done_grid().sum() == 2  # the tiles written with the current parameters' token
    for name in again.output_names():  # read straight from the files, as zarr reads them
        np.testing.assert_array_equal(again.read_output(name), ref.group[name][...], err_msg=name)
    assert again.progress() == ref.progress()
    t = again.tiles()[5]
    np.testing.assert_array_equal(again.read_tile_mask(t), ref.group["mask"][t.y0 : t.y1, t.x0 : t.x1])


#: A process that writes tile 0 of the store in ``argv[1]`` and is SIGKILLed at its ``argv[2]``-th
#: rename of a file into place (a chunk's, or the done marker's, last).
_KILLED_WRITER = """
import os, signal, sys
from pathlib import Path
from maxfs.storage.layout import JobStore
from tests.test_tile_writes import _results

store = JobStore.open(Path(sys.argv[1]))
t = store.tiles()[0]
arrays = _results(store, t, 7)
real, calls = os.replace, [0]

def replace(src, dst):
    calls[0] += 1
    if calls[0] == int(sys.argv[2]):
        os.kill(os.getpid(), signal.SIGKILL)
    real(src, dst)

os.replace = replace
store.write_tile(t, arrays, store.params.token(), (1, 1, 1))
print("written", calls[0])
"""


def test_a_process_killed_while_writing_a_tile_never_leaves_it_done(tmp_path: Path) -> None:
    """SIGKILL at each file of a tile's write, the done marker's included: the tile is not done
    (its marker still holds the parameters it had: here none), the store opens, and writing the
    tile again leaves exactly the files of an uninterrupted write."""
    ref = _store(tmp_path / "ref", 3)
    t = ref.tiles()[0]
    ref.write_tile(t, _results(ref, t, 7), ref.params.token(), (1, 1, 1))
    expected = _files(ref.path / GROUP_DIR)
    # the tile's files: each output's chunk, its counts, then the done marker
    renames = sum(o.exists(3) for o in TILE_OUTPUTS) + 2
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[1]), *sys.path])}
    for at in range(1, renames + 2):
        path = tmp_path / f"killed-{at}"
        _store(path, 3)
        p = subprocess.run(
            [sys.executable, "-c", _KILLED_WRITER, str(path), str(at)],
            env=env,
            capture_output=True,
            text=True,
        )
        again = JobStore.open(path)
        if at <= renames:
            assert p.returncode == -signal.SIGKILL, (at, p.stderr)
            assert not again.tile_done(t), at
            assert int(again.read_array("done", (0, 0))) == 0, at
            assert all(q.name.endswith(".partial") for q in _hidden(path)), at
            again.write_tile(t, _results(again, t, 7), again.params.token(), (1, 1, 1))
        else:
            assert p.returncode == 0 and p.stdout.split() == ["written", str(renames)], p.stderr
        assert again.tile_done(t), at
        assert _files(path / GROUP_DIR) == expected, at


def test_a_failed_chunk_write_leaves_no_file_and_no_marker(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A write that fails (a full disk, here an error from the write itself) removes its temporary
    file, and the tile's done marker is not written."""
    store = _store(tmp_path / "s", None)
    t = store.tiles()[0]
    real, calls = os.write, [0]

    def write(fd: int, data: Any) -> int:
        calls[0] += 1
        if calls[0] == 3:
            raise OSError(28, "No space left on device")
        return real(fd, data)

    monkeypatch.setattr(shards.os, "write", write)
    with pytest.raises(OSError, match="No space"):
        store.write_tile(t, _results(store, t, 1), store.params.token(), (1, 1, 1))
    monkeypatch.setattr(shards.os, "write", real)
    assert not store.tile_done(t)
    assert not _hidden(store.path)
    store.write_tile(t, _results(store, t, 1), store.params.token(), (1, 1, 1))
    assert store.tile_done(t)


def test_the_per_image_rows_read_directly_are_what_zarr_reads(tmp_path: Path) -> None:
    """``uploaded`` and ``input_digests`` (a chunk file per image) read straight from their files:
    rows written, recorded, never written, and a chunk file that does not decode (left to zarr,
    which raises)."""
    store = _store(tmp_path / "s", None)
    rng = np.random.default_rng(0)
    store.write_image(1, rng.integers(0, 9, (37, 29), dtype=np.uint16))
    store.record_digests({3: bytes(range(32)), 0: bytes(32 * [7])})
    store._set_row("uploaded", 4, True)
    again = JobStore.open(store.path, mode="r")
    assert again.uploaded().tolist() == np.asarray(again.group["inputs/uploaded"][...]).tolist()
    assert again.uploaded().tolist() == [False, True, False, False, True]
    want = [bytes(r) for r in np.asarray(again.group["inputs/input_digests"][...])]
    assert again.digests() == want
    assert want[0] == bytes(32 * [7]) and want[3] == bytes(range(32)) and want[2] == bytes(32)
    bad = next((tmp_path / "s" / GROUP_DIR / "inputs" / "input_digests").glob("c*3*"))
    bad.write_bytes(b"not zstd")
    with pytest.raises(Exception, match=r"(?i)zstd|decompress|frame|content"):
        JobStore.open(store.path, mode="r").digests()


def test_temporary_names_differ_for_writers_sharing_a_pid_and_thread(tmp_path: Path) -> None:
    """Two processes on two hosts can share a pid and a thread id over a shared filesystem: the
    temporary name must still differ (a shared one would interleave their bytes), stay hidden
    (dotfile) and beside the chunk (same filesystem, so the rename is atomic)."""
    chunk = tmp_path / "c.0.0"
    names = {shards.temp_path(chunk) for _ in range(1000)}
    assert len(names) == 1000
    assert all(
        n.parent == tmp_path and n.name.startswith(".c.0.0.") and n.name.endswith(".partial") for n in names
    )
