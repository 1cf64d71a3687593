"""Whole shards of the input stack written straight to their files.

zarr-python encodes each inner chunk of a shard as its own coroutine and thread hop: about
0.2 ms per chunk whatever its size, so storing an image of ``(W / T) x (H / T)`` tile chunks cost
more than decoding it (a 1000 x 1000 image at tile 64: 256 chunks, 50-70 ms). A band of an image
is exactly one shard (:meth:`storage.layout.JobStore.create`), so :class:`ShardWriter` encodes
it in one pass as the array's metadata says (``sharding_indexed``: inner chunks ``bytes`` little
endian then ``zstd``; index ``bytes`` little endian then ``crc32c`` at the end) and writes the
file. Any other codec chain gets no writer
(:meth:`ShardWriter.for_array` answers None) and the caller writes through zarr.
"""

from __future__ import annotations

import itertools
import os
import secrets
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import google_crc32c  # a dependency of zarr's crc32c codec, which these shards' index uses
import numpy as np
import zarr
from numcodecs import Zstd
from numpy.typing import NDArray
from zarr.codecs import BytesCodec, Crc32cCodec, ShardingCodec, ShardingCodecIndexLocation, ZstdCodec
from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding

#: Index entry of a chunk that is not stored (all fill value), as zarr writes it.
EMPTY = np.iinfo(np.uint64).max
#: Threads that encode shards for :meth:`ShardWriter.submit` (shared by every writer of the process).
ENCODERS = ThreadPoolExecutor(2, thread_name_prefix="maxfs-shards")


class ShardWriter:
    """Encodes and stores whole shards of one local Zarr v3 array (see the module docstring)."""

    def __init__(self, folder: Path, array: zarr.Array, codec: ShardingCodec, level: int) -> None:
        self.folder = Path(folder)
        self.shard = tuple(int(n) for n in array.metadata.chunk_grid.chunk_shape)
        self.chunk = tuple(int(n) for n in codec.chunk_shape)
        self.per_shard = tuple(s // c for s, c in zip(self.shard, self.chunk, strict=True))
        self.shape = tuple(int(n) for n in array.shape)
        self.dtype = np.dtype(array.dtype).newbyteorder("<")
        self.fill = array.metadata.fill_value
        self.keys = array.metadata.chunk_key_encoding
        self.zstd = Zstd(level=level)
        self.made: set[Path] = set()  # chunk folders known to exist

    @classmethod
    def for_array(cls, folder: Path, array: zarr.Array) -> ShardWriter | None:
        """A writer for ``array`` stored in ``folder`` (its local directory), or None when its
        codecs, chunk keys or data type are not the ones this module encodes."""
        meta = array.metadata
        codecs = getattr(meta, "codecs", ())
        if len(codecs) != 1 or not isinstance(codecs[0], ShardingCodec):
            return None
        sc = codecs[0]
        inner, index = sc.codecs, sc.index_codecs
        little = BytesCodec(endian="little")
        one_byte = np.dtype(array.dtype).itemsize == 1  # zarr gives single bytes no endianness
        if (
            len(inner) != 2
            or inner[0] not in (little, *([BytesCodec(endian=None)] if one_byte else []))
            or not isinstance(inner[1], ZstdCodec)
            or inner[1].checksum
            or tuple(index) != (little, Crc32cCodec())
            or sc.index_location != ShardingCodecIndexLocation.end
            or not isinstance(meta.chunk_key_encoding, DefaultChunkKeyEncoding)
            or np.dtype(array.dtype).kind not in "uif"
            or any(s % c for s, c in zip(meta.chunk_grid.chunk_shape, sc.chunk_shape, strict=True))
        ):
            return None
        return cls(folder, array, sc, int(inner[1].level))

    def path(self, coords: tuple[int, ...]) -> Path:
        return self.folder / self.keys.encode_chunk_key(coords)

    def encode(self, block: NDArray[Any]) -> bytes | None:
        """The shard file of ``block`` (the shard's values inside the array: the shard's shape, or
        less at the array's far edges, padded here with the fill value); None when every chunk
        holds only the fill value (zarr stores no file then)."""
        index = np.full((*self.per_shard, 2), EMPTY, dtype="<u8")
        parts: list[bytes] = []
        offset = 0
        for pos in np.ndindex(*self.per_shard):
            sel = tuple(slice(p * c, (p + 1) * c) for p, c in zip(pos, self.chunk, strict=True))
            chunk = block[sel]
            if chunk.size == 0 or not (chunk != self.fill).any():
                continue
            if chunk.shape != self.chunk:  # at the array's edge: zarr stores whole chunks, padded
                full = np.full(self.chunk, self.fill, dtype=self.dtype)
                full[tuple(slice(0, n) for n in chunk.shape)] = chunk
                chunk = full
            data = bytes(self.zstd.encode(np.ascontiguousarray(chunk, dtype=self.dtype)))
            index[pos] = (offset, len(data))
            parts.append(data)
            offset += len(data)
        if not parts:
            return None
        raw = index.tobytes()
        parts += [raw, np.uint32(google_crc32c.value(raw)).astype("<u4").tobytes()]
        return b"".join(parts)

    def write(self, coords: tuple[int, ...], block: NDArray[Any]) -> None:
        """Store shard ``coords`` (shard grid indices) holding ``block`` (see :meth:`encode`).

        Written in place, not through a temporary file and a rename as zarr writes (on ext4 a
        rename over a file costs three times the write): the only caller,
        :meth:`storage.layout.JobStore.write_bands`, marks the image not uploaded before its
        first shard and uploaded after its last, so a shard cut short is never read."""
        self.store(coords, self._encode_checked(coords, block))

    def submit(self, coords: tuple[int, ...], block: NDArray[Any]) -> Future[bytes | None]:
        """:meth:`encode` ``block`` on one of :data:`ENCODERS`' threads (zstd releases the GIL, so an
        image's shards are encoded two at a time); :meth:`store` the result as :meth:`write` does."""
        return ENCODERS.submit(self._encode_checked, coords, block)

    def _encode_checked(self, coords: tuple[int, ...], block: NDArray[Any]) -> bytes | None:
        expect = tuple(min(s, n - c * s) for c, s, n in zip(coords, self.shard, self.shape, strict=True))
        if tuple(block.shape) != expect:
            raise ValueError(f"shard {coords} holds {expect} values, got a block of {tuple(block.shape)}")
        return self.encode(np.asarray(block))

    def store(self, coords: tuple[int, ...], data: bytes | None) -> None:
        """Write shard ``coords``'s file of :meth:`encode`'s ``data`` (None: no file); see :meth:`write`."""
        path = self.path(coords)
        if data is None:
            path.unlink(missing_ok=True)
            return
        if path.parent not in self.made:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.made.add(path.parent)
        with open(path, "wb") as f:
            f.write(data)


def temp_path(path: Path) -> Path:
    """A hidden name beside ``path`` to write its new content under before renaming it into
    place: ``.NAME.PID-THREAD-RANDOM.partial``. The random part keeps two writers apart that share
    a pid and a thread id (processes in containers on other hosts, over a shared filesystem); the
    leading dot keeps listings (the results zip, the progress notes) from taking it for data."""
    return path.with_name(
        f".{path.name}.{os.getpid()}-{threading.get_ident()}-{secrets.token_hex(4)}.partial"
    )


class ChunkFiles:
    """Whole chunks of one local Zarr v3 array that is not sharded (codecs ``bytes`` then
    ``zstd``, as zarr's defaults make them: the outputs, ``done``, ``tile_stats``, the per-image
    ``uploaded`` and ``input_digests`` rows), encoded as zarr encodes them and written as zarr's
    LocalStore writes them.

    A finished tile writes one chunk of each output array and of its bookkeeping. Through zarr
    each is a coroutine on zarr's event loop, a thread hop for the encode and another for the
    file, and a read of the old chunk first where the tile is at the array's edge: about 8 ms of
    CPU per tile, twice the files' own cost. Here a chunk is cast to the array's dtype, padded
    with the fill value at the far edges, tested for "fill value only" as zarr tests it (then
    zarr removes the chunk's file, and so does this) and compressed by the same numcodecs Zstd;
    the file is written under a temporary name in its folder and renamed into place, so a reader
    sees the old chunk or the new one, never a part. No fsync, as zarr.
    """

    def __init__(self, folder: Path, array: zarr.Array, level: int) -> None:
        self.folder = Path(folder)
        self.chunk = tuple(int(n) for n in array.metadata.chunk_grid.chunk_shape)
        self.shape = tuple(int(n) for n in array.shape)
        self.dtype = np.dtype(array.dtype)  # zarr casts what it is given to this
        self.stored = self.dtype.newbyteorder("<")
        self.fill = np.asarray(array.metadata.fill_value, dtype=self.dtype)
        # zarr's test of a chunk of fill value only (NDBuffer.all_equal): a float fill of zero
        # compares bit patterns (a chunk of -0.0 is stored), any other by value, NaN equal to NaN
        self.bits = np.dtype(f"u{self.dtype.itemsize}") if self.dtype.kind == "f" and self.fill == 0 else None
        self.keys = array.metadata.chunk_key_encoding
        self.zstd = Zstd(level=level)

    @classmethod
    def for_array(cls, folder: Path, array: zarr.Array) -> ChunkFiles | None:
        """A writer for ``array`` stored in ``folder`` (its local directory), or None when its
        codecs, chunk keys, data type, order or settings are not the ones this class writes (the
        caller then writes through zarr)."""
        meta = array.metadata
        codecs = tuple(getattr(meta, "codecs", ()))
        one_byte = np.dtype(array.dtype).itemsize == 1
        little = (BytesCodec(endian="little"), *([BytesCodec(endian=None)] if one_byte else []))
        if (
            len(codecs) != 2
            or codecs[0] not in little
            or not isinstance(codecs[1], ZstdCodec)
            or codecs[1].checksum
            or not isinstance(meta.chunk_key_encoding, DefaultChunkKeyEncoding)
            or np.dtype(array.dtype).kind not in "buif"
            or array.config.write_empty_chunks
            or array.order != "C"
        ):
            return None
        return cls(folder, array, int(codecs[1].level))

    def chunk_at(self, region: tuple[slice, ...]) -> tuple[int, ...] | None:
        """The grid coordinates of the chunk that ``region`` (a slice per dimension, missing ones
        whole) covers exactly, or None when it is not exactly one chunk."""
        region = (*region, *(slice(None),) * (len(self.shape) - len(region)))
        coords = []
        for r, c, n in zip(region, self.chunk, self.shape, strict=True):
            a, b, step = r.indices(n)
            if step != 1 or a >= b or a % c or b != min(a + c, n):  # a >= b: empty, or past the end
                return None
            coords.append(a // c)
        return tuple(coords)

    def encode(self, coords: tuple[int, ...], value: Any) -> bytes | None:
        """The file of chunk ``coords`` holding ``value`` (its values inside the array, or a
        scalar for all of them), as zarr writes it; None when every value is the fill value
        (zarr stores no file then)."""
        inside = tuple(min(c, n - i * c) for i, c, n in zip(coords, self.chunk, self.shape, strict=True))
        # a scalar is converted as zarr converts it (an int out of the dtype's range raises)
        v = np.asarray(value, dtype=self.dtype) if np.isscalar(value) else np.asarray(value)
        if inside == self.chunk and v.shape == self.chunk:
            chunk = v.astype(self.dtype, copy=False)
        else:  # a scalar, or at the array's far edge: zarr encodes whole chunks, padded with the fill
            chunk = np.full(self.chunk, self.fill, dtype=self.dtype)
            chunk[tuple(slice(0, n) for n in inside)] = v
        if self.bits is not None:
            empty = not (chunk.view(self.bits) != self.fill.view(self.bits)).any()
        else:
            empty = np.array_equal(
                chunk, np.broadcast_to(self.fill, chunk.shape), equal_nan=self.dtype.kind == "f"
            )
        if empty:
            return None
        return bytes(self.zstd.encode(np.ascontiguousarray(chunk, dtype=self.stored)))

    def _load(self, coords: tuple[int, ...]) -> NDArray[Any] | bool | None:
        """Chunk ``coords``'s values; None: no file (the fill value); False: it does not decode."""
        path = self.folder / self.keys.encode_chunk_key(coords)
        try:
            with open(path, "rb") as f:
                data = f.read()
        except FileNotFoundError:
            return None
        try:
            raw = np.frombuffer(self.zstd.decode(data), self.stored)
            return raw.astype(self.dtype, copy=False).reshape(self.chunk)
        except (RuntimeError, ValueError):  # numcodecs' zstd errors are RuntimeErrors
            return False

    def read_region(self, region: tuple[slice, ...]) -> NDArray[Any] | None:
        """The values of ``region`` (a slice per dimension, steps of 1; dimensions left out are
        read whole) as zarr reads them, or None where zarr should read them instead (a slice with
        a step, a chunk file that does not decode). Through zarr a read is a round trip of its
        event loop and a thread hop per chunk: 3-15 ms for a tile's mask or the whole mask."""
        region = (*region, *(slice(None),) * (len(self.shape) - len(region)))
        if len(region) != len(self.shape) or not all(isinstance(r, slice) for r in region):
            return None
        idx = [r.indices(n) for r, n in zip(region, self.shape, strict=True)]
        if any(step != 1 for _, _, step in idx):
            return None
        bounds = [(a, max(a, b)) for a, b, _ in idx]
        out = np.empty([b - a for a, b in bounds], dtype=self.dtype)
        if out.size == 0:
            return out
        spans = [range(a // c, (b - 1) // c + 1) for (a, b), c in zip(bounds, self.chunk, strict=True)]
        for cc in itertools.product(*spans):
            src, dst = [], []
            for c, n, (a, b) in zip(cc, self.chunk, bounds, strict=True):
                lo, hi = max(a, c * n), min(b, (c + 1) * n)
                src.append(slice(lo - c * n, hi - c * n))
                dst.append(slice(lo - a, hi - a))
            got = self._load(cc)
            if got is False:
                return None
            out[tuple(dst)] = self.fill if got is None else got[tuple(src)]
        return out

    def put(self, coords: tuple[int, ...], data: bytes | None) -> None:
        """Write chunk ``coords``'s file of :meth:`encode`'s ``data`` (None: remove it)."""
        path = self.folder / self.keys.encode_chunk_key(coords)
        if data is None:
            path.unlink(missing_ok=True)
            return
        tmp = temp_path(path)
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0)
        try:
            fd = os.open(tmp, flags, 0o666)
        except FileNotFoundError:  # the chunk's first file in its folder (nested chunk keys)
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(tmp, flags, 0o666)
        try:
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view) :]
            finally:
                os.close(fd)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


class ShardReader:
    """Reads a region of one local Zarr v3 array straight from its shard files: what zarr-python
    reads, without its coroutine and thread hop per inner chunk (about 0.2 ms each, as for
    writing; a 240 x 240 tile of 16 images read through zarr cost 20-60 ms, of which decoding
    the chunks is 2 ms). Only arrays :meth:`ShardWriter.for_array` accepts (the same codecs,
    whoever wrote the shards); a shard whose index does not check out is left to zarr
    (:meth:`read` answers None)."""

    def __init__(self, folder: Path, array: zarr.Array, codec: ShardingCodec) -> None:
        self.folder = Path(folder)
        self.shard = tuple(int(n) for n in array.metadata.chunk_grid.chunk_shape)
        self.chunk = tuple(int(n) for n in codec.chunk_shape)
        self.per_shard = tuple(s // c for s, c in zip(self.shard, self.chunk, strict=True))
        self.shape = tuple(int(n) for n in array.shape)
        self.stored = np.dtype(array.dtype).newbyteorder("<")
        self.dtype = np.dtype(array.dtype)  # as zarr answers
        self.fill = array.metadata.fill_value
        self.keys = array.metadata.chunk_key_encoding
        self.index_bytes = int(np.prod(self.per_shard)) * 16 + 4
        self.zstd = Zstd()

    @classmethod
    def for_array(cls, folder: Path, array: zarr.Array) -> ShardReader | None:
        """A reader for ``array`` stored in ``folder`` (its local directory), or None when
        :class:`ShardWriter` would not encode it."""
        if ShardWriter.for_array(folder, array) is None:
            return None
        return cls(folder, array, array.metadata.codecs[0])

    def _index(self, f: Any, size: int) -> NDArray[np.uint64] | None:
        """The shard's (offset, length) per inner chunk, or None when it does not check out."""
        if size < self.index_bytes:
            return None
        raw = os.pread(f, self.index_bytes, size - self.index_bytes)
        body, crc = raw[:-4], raw[-4:]
        if len(raw) != self.index_bytes or google_crc32c.value(body) != int(np.frombuffer(crc, "<u4")[0]):
            return None
        return np.frombuffer(body, "<u8").reshape(*self.per_shard, 2)

    def read(self, region: tuple[slice, ...]) -> NDArray[Any] | None:
        """The values of ``region`` (a slice per dimension, steps of 1) as zarr reads them, or
        None where zarr should read them instead (a shard whose index is damaged or cut short).
        Dimensions left out are read whole."""
        got = self.read_many([region])
        return None if got is None else got[0]

    def read_many(self, regions: list[tuple[slice, ...]]) -> list[NDArray[Any]] | None:
        """:meth:`read` of several regions, each shard file opened and each inner chunk decoded
        once for all of them (the eps sample's windows: a few dozen in every image's shard); None
        where zarr should read them instead."""
        files: dict[tuple[int, ...], tuple[int, NDArray[np.uint64]] | bool | None] = {}
        decoded: dict[tuple[int, ...], NDArray[Any] | None] = {}
        try:
            out = []
            for region in regions:
                got = self._read(region, files, decoded)
                if got is None:
                    return None
                out.append(got)
            return out
        finally:
            for opened in files.values():
                if isinstance(opened, tuple):
                    os.close(opened[0])

    def _read(
        self,
        region: tuple[slice, ...],
        files: dict[tuple[int, ...], tuple[int, NDArray[np.uint64]] | bool | None],
        decoded: dict[tuple[int, ...], NDArray[Any] | None],
    ) -> NDArray[Any] | None:
        """One region of :meth:`read_many`: ``files`` holds the shard files opened so far (None: no
        file), ``decoded`` the inner chunks decoded so far (None: fill value only)."""
        region = (*region, *(slice(None),) * (len(self.shape) - len(region)))
        bounds = [r.indices(n)[:2] for r, n in zip(region, self.shape, strict=True)]
        out = np.empty([max(0, b - a) for a, b in bounds], dtype=self.dtype)
        if out.size == 0:
            return out
        spans = [range(a // c, (b - 1) // c + 1) for (a, b), c in zip(bounds, self.chunk, strict=True)]
        for cc in itertools.product(*spans):
            src, dst = self._overlap(cc, bounds)
            if cc not in decoded:
                sc = tuple(c // p for c, p in zip(cc, self.per_shard, strict=True))
                if sc not in files:
                    files[sc] = self._open(sc)
                    if files[sc] is False:
                        return None
                opened = files[sc]
                if not isinstance(opened, tuple):  # no shard file: every chunk holds the fill value
                    decoded[cc] = None
                else:
                    f, index = opened
                    at = tuple(c % p for c, p in zip(cc, self.per_shard, strict=True))
                    offset, length = (int(v) for v in index[at])
                    if offset == EMPTY and length == EMPTY:
                        decoded[cc] = None
                    else:
                        data = os.pread(f, length, offset)
                        if len(data) != length:
                            return None
                        decoded[cc] = np.frombuffer(self.zstd.decode(data), self.stored).reshape(self.chunk)
            chunk = decoded[cc]
            out[dst] = self.fill if chunk is None else chunk[src]
        return out

    def _open(self, sc: tuple[int, ...]) -> tuple[int, NDArray[np.uint64]] | bool | None:
        """Shard ``sc``'s open file and index; None when there is no file, False when its index
        does not check out (the file is closed then)."""
        try:
            f = os.open(self.folder / self.keys.encode_chunk_key(sc), os.O_RDONLY)
        except FileNotFoundError:
            return None
        index = self._index(f, os.fstat(f).st_size)
        if index is None:
            os.close(f)
            return False
        return f, index

    def _overlap(self, cc: tuple[int, ...], bounds: list[tuple[int, int]]) -> tuple[tuple[slice, ...], ...]:
        """Where inner chunk ``cc`` and the region ``bounds`` meet: (in the chunk, in the region)."""
        src, dst = [], []
        for c, n, (a, b) in zip(cc, self.chunk, bounds, strict=True):
            lo, hi = max(a, c * n), min(b, (c + 1) * n)
            src.append(slice(lo - c * n, hi - c * n))
            dst.append(slice(lo - a, hi - a))
        return tuple(src), tuple(dst)
