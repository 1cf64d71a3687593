"""The job store: one folder per job, a Zarr v3 group inside with every array created up front.

The job folder holds the group ``results.zarr/`` (nothing but Zarr, so xarray and
other Zarr tools read it as it is) and, beside it, what is not Zarr: ``maxfs-job.json``
(the record), ``maxfs-runs.log`` (one line per tile execution), ``maxfs-cancel`` (a flag
that makes tile tasks stop), ``maxfs-progress/`` (running tiles' solved pixels, while a run goes on) and
``previews/``. Arrays of ``results.zarr`` (``T`` = tile
edge, chunks are tile-aligned)::

    lights        (k, 3)          float64
    intensities   (k, C|1)        float64
    mask          (H, W)          bool                  chunks (T, W): bands of tile rows
    normal        (H, W, 3)       float32 (NaN fill)    chunks (T, T, 3)
    albedo        (H, W)          float32
    albedo_rgb    (H, W, C)       float32               colour input only
    inliers       (k, H, W)       bool                  chunks (k, T, T)
    inlier_count  (H, W)          uint16
    optimal       (H, W)          bool
    source        (H, W)          uint8                 how the normal was obtained (worker.solve.Source)
    depth         (H, W)          float32               once integrated after the run
    xyz, image, channel           coordinates: "x" "y" "z"; image numbers 1..k; "r" "g" "b" or "grey"
    inputs/images (k, H, W[, C])  uint8|uint16|float32  chunks (1, T, T[, C]) in shards (1, T, W'[, C]),
                                                        or (1, H', W'[, C]) for images of at most 1 MiB
    inputs/uploaded (k,)          bool                  chunks (1,)   set after images[i]
    inputs/input_digests (k + 1, 32) uint8              chunks (1, 32)    digest of image i; row k: mask
    tiles/done    (ny, nx)        int32                 chunks (1, 1)
    tiles/tile_stats (ny, nx, 3)  int64                 chunks (1, 1, 3)  active, solved, certified pixels

``xarray.open_zarr(FOLDER / "results.zarr")`` reads the root: the results with their coordinates
(``ds.normal.sel(xyz="z")``, ``ds.inliers.sel(image=3)``) and no bookkeeping. The input stack and
the per-tile bookkeeping are in the subgroups ``inputs`` and ``tiles`` (``group="inputs"``);
``inputs/images`` holds only the images with ``uploaded[i]`` (a local run that keeps the stack
in memory stores just their digests).

``W'`` (``H'``) is W (H) rounded up to a multiple of T. A tile task reads k chunks of ``images``
(one per image, through each shard's index); an upload writes one band of T rows
at a time, which is one whole shard, so the server never holds more than a band (or a
whole image of at most 1 MiB: one shard, one file). The per-image arrays ``images`` and
``input_digests`` name their chunk files ``c.i.y...`` in the array's folder
(:data:`FLAT_KEYS`); stores made before keep ``c/i/y/...``, which every reader follows from
the array's metadata.
An image is written as ``uploaded[i] = False``, its bands, then ``uploaded[i] =
True``, so an upload cut short (a killed server) leaves the image marked missing.

**Input identity.** Each image's digest (:mod:`storage.digests`: SHA-256 in new stores, BLAKE2b
in format 4, as the group's ``input_digest`` attribute says) is computed from the bands as they
are written (no second read) and stored in ``input_digests[i]``; the mask's in row ``k``, which holds
:data:`MASK_WRITING` while a mask is being written, so a mask cut short by a crash is
detected (:meth:`JobStore.mask_state`) and never used. :meth:`JobStore.input_identity`
combines them with the lights and intensities: a store reused for other inputs is refused.

A tile task writes whole chunks of the outputs and its pixel counts, then ``done[ty, tx] =
params.token()`` last. A tile counts as finished only if its marker equals the
token of the *current* parameters, so a job re-run with other parameters never
reuses stale tiles. A tile without masked pixels needs no marker: its outputs are fill values
whatever the parameters, so it counts as done once the job has parameters
(:meth:`JobStore.done_grid`). The store is created once, by the service or CLI, with mode
``w-``; everything after opens it ``r+``.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from numpy.typing import NDArray
from zarr.codecs import ZstdCodec
from zarr.core.sync import sync

from maxfs.storage.digests import DIGEST_BYTES, DIGESTS, LEGACY_DIGEST, ArrayHasher, array_digest
from maxfs.storage.errors import ConflictError, InvalidInputError, NotFoundError, StoreError
from maxfs.storage.observations import ObservationModel
from maxfs.storage.outputs import (
    OUTPUT_NAMES,
    OUTPUT_TABLE,
    OUTPUTS_BY_NAME,
    TILE_OUTPUTS,
)
from maxfs.storage.params import JobParams
from maxfs.storage.shards import ChunkFiles, ShardReader, ShardWriter, temp_path

# the spec and the store's place, kept in a module without zarr (see there), named here too
from maxfs.storage.spec import GROUP_DIR, JobSpec, is_job_folder, job_folder  # noqa: F401
from maxfs.storage.tiles import Tile, grid_shape, masked_per_tile, tiles


def lights_digest(spec: JobSpec) -> str:
    """Digest of a validated spec's light directions and intensities: BLAKE2b in every format
    (a few hundred bytes, recorded in the group's attributes since format 1)."""
    return (array_digest(spec.lights, LEGACY_DIGEST) + array_digest(spec.intensities, LEGACY_DIGEST)).hex()


@dataclass(frozen=True)
class ProgressCounts:
    """What the finished tiles hold (from the small per-tile arrays, never the outputs)."""

    tiles_done: int  # finished tiles among those of tiles_total
    tiles_total: int  # tiles that hold masked pixels: the tiles with work (every tile without a mask)
    pixels_done: int  # masked pixels in finished tiles
    pixels_total: int  # masked pixels of the job
    solved: int  # masked pixels in finished tiles that got a normal
    certified: int  # ... whose optimum was proved


#: The format new stores are written in. 5: the group's attributes name the hash of the input
#: digests (``input_digest``, SHA-256 for new stores); 4 named none, its digests are BLAKE2b.
FORMAT_VERSION = 5
#: Formats this maxfs opens, read and resumed alike (the layout of 4 and 5 is the same).
READ_FORMATS = (4, 5)
#: Chunk keys of the per-image input arrays: files ``c.i.y.x...`` side by side in the array's
#: folder, not a folder per image and band (``c/i/y/...``); creating a folder costs as much as
#: writing the file, 0.3-2 ms each on the reference machine's ext4, about ten per image.
FLAT_KEYS = {"name": "default", "separator": "."}
#: Images of at most this many bytes are stored as one shard each (see :meth:`JobStore.create`).
WHOLE_IMAGE_SHARD_BYTES = 1 << 20
#: Where the arrays that are not results live in the group: subgroups, so that ``xarray.open_zarr``
#: of the root shows the results alone (it reads no subgroup).
PATHS: dict[str, str] = {
    "images": "inputs/images",
    "uploaded": "inputs/uploaded",
    "input_digests": "inputs/input_digests",
    "done": "tiles/done",
    "tile_stats": "tiles/tile_stats",
}
#: Arrays that hold the input stack: left out of result downloads unless asked for.
BULK_INPUTS = frozenset({PATHS["images"]})
#: Names of the colour channels: the ``channel`` coordinate (one "grey" for grey input).
CHANNEL_NAMES = {None: ("grey",), 3: ("r", "g", "b")}  # as maxfs.Result.to_xarray names them
#: ``input_digests[k]`` while a mask is being written (a crash leaves it there).
MASK_WRITING = bytes([0xFF]) * DIGEST_BYTES
RUNS_LOG = "maxfs-runs.log"
CANCEL_FLAG = "maxfs-cancel"
#: Folder of running tiles' progress: a file per tile holding its masked pixels solved so far.
PROGRESS_DIR = "maxfs-progress"
#: Zarr v3 ``dimension_names`` of the arrays that are not outputs (``images`` gets ``channel`` last for
#: colour input); the outputs' are in :data:`storage.outputs.OUTPUT_TABLE`. So ``xarray.open_zarr``
#: reads a store as a Dataset with named dimensions.
DIMS: dict[str, tuple[str, ...]] = {
    "images": ("image", "y", "x"),
    "uploaded": ("image",),
    "lights": ("image", "xyz"),
    "intensities": ("image", "channel"),
    "done": ("tile_y", "tile_x"),
    "tile_stats": ("tile_y", "tile_x", "tile_count"),
    "input_digests": ("input", "digest_byte"),
    **{o.name: o.dims for o in OUTPUT_TABLE},
}
#: ``long_name`` attributes of the arrays that are not outputs, for xarray and other readers.
DESCRIPTIONS: dict[str, dict[str, str]] = {
    "images": {"long_name": "input images as stored (raw values)"},
    "uploaded": {"long_name": "image i is completely stored"},
    "lights": {"long_name": "unit light directions (x right, y up, z toward the camera)"},
    "intensities": {"long_name": "light intensities per image and channel"},
    "done": {"long_name": "per-tile marker: equal to the parameter token when the tile is finished"},
    "tile_stats": {"long_name": "per tile: active, solved and certified pixels"},
    "input_digests": {
        "long_name": "digest of image i (by the hash in the group's attribute input_digest); last row: mask"
    },
    **{o.name: o.attrs() for o in OUTPUT_TABLE},
}


class JobStore:
    """A job directory: its Zarr group plus record, run log and cancel flag."""

    def __init__(self, path: Path, group: zarr.Group) -> None:
        self.path = Path(path)
        self.group = group
        self._arrays: dict[str, zarr.Array] = {}
        self._writer: tuple[ShardWriter | None] | None = None  # (writer,) once looked up
        self._files: dict[str, ChunkFiles | None] = {}  # see _chunk_files
        self._reader: tuple[ShardReader | None] | None = None  # (reader,) once looked up
        self._counts: tuple[tuple[bytes, int], NDArray[np.int64]] | None = None
        attrs = dict(group.attrs)
        fmt = attrs.get("maxfs_format")
        if fmt not in READ_FORMATS:
            raise StoreError(
                f"{path} is not a maxfs job store of this version (format {fmt!r}, this maxfs writes "
                f"{FORMAT_VERSION} and reads {', '.join(map(str, READ_FORMATS))}); choose another "
                "output, or run with --overwrite to replace it"
            )
        digest = LEGACY_DIGEST if fmt == 4 else attrs["input_digest"]
        if digest not in DIGESTS:
            raise StoreError(f"{path} holds input digests of {digest!r}, which this maxfs does not know")
        self.spec = JobSpec(
            k=attrs["k"],
            height=attrs["height"],
            width=attrs["width"],
            channels=attrs["channels"],
            dtype=attrs["dtype"],
            lights=np.asarray(group["lights"][...]),
            intensities=np.asarray(group["intensities"][...]),
            digest=digest,
        )

    def _fixed(self, name: str) -> zarr.Array:
        """Array ``name``, opened once per store object: only for arrays whose metadata never
        changes after creation (each ``group[name]`` reads its zarr.json again, and a tile
        touches a dozen arrays)."""
        a = self._arrays.get(name)
        if a is None:
            a = self._arrays[name] = self.group[PATHS.get(name, name)]
        return a

    def _array(self, name: str) -> zarr.Array:
        """Array ``name`` (in its subgroup, :data:`PATHS`), its metadata read now."""
        return self.group[PATHS.get(name, name)]

    # -- creation and opening ---------------------------------------------------------------
    @classmethod
    def create(cls, path: Path, spec: JobSpec, params: JobParams) -> JobStore:
        """Create the job directory and every array. Fails if it already exists."""
        spec = spec.validate()
        spec.check_params(params)
        path = Path(path)
        if (path / GROUP_DIR / "zarr.json").exists():
            raise ConflictError(f"{path} already holds a job store; resume it instead of creating it")
        path.mkdir(parents=True, exist_ok=True)
        T = params.tile
        k, H, W, C = spec.k, spec.height, spec.width, spec.channels
        cc = () if C is None else (C,)
        img_chunks = (1, min(T, H), min(T, W), *cc)
        # a small image is one shard (one file, written in one piece); a larger one a shard per
        # band of T rows, so that an upload holds one band of it at a time
        whole = spec.image_nbytes <= WHOLE_IMAGE_SHARD_BYTES
        rows = -(-H // min(T, H)) * min(T, H) if whole else min(T, H)
        img_shards = (1, rows, -(-W // min(T, W)) * min(T, W), *cc)
        try:
            g = zarr.open_group(path / GROUP_DIR, mode="w-", zarr_format=3)
        except (zarr.errors.ContainsGroupError, zarr.errors.ContainsArrayError, FileExistsError):
            raise ConflictError(f"{path} already holds a Zarr store") from None
        tc = (min(T, H), min(T, W))
        inputs, tile_group = g.create_group("inputs"), g.create_group("tiles")
        inputs.update_attributes({"long_name": "the input stack and its digests (results are in the root)"})
        tile_group.update_attributes({"long_name": "per-tile bookkeeping: done markers and pixel counts"})
        _coordinates(g, k, C)
        inputs.create_array(
            "images",
            shape=(k, *spec.image_shape),
            chunks=img_chunks,
            shards=img_shards,
            # zstd level 1: twice the speed of the default level for 1-10 % more bytes
            compressors=ZstdCodec(level=1),
            dtype=spec.dtype,
            fill_value=0,
            chunk_key_encoding=FLAT_KEYS,
            dimension_names=DIMS["images"] + (("channel",) if C is not None else ()),
            attributes=DESCRIPTIONS["images"],
        )
        inputs.create_array(
            "uploaded",
            shape=(k,),
            chunks=(1,),
            dtype="bool",
            fill_value=False,
            dimension_names=DIMS["uploaded"],
            attributes=DESCRIPTIONS["uploaded"],
        )
        g.create_array(
            "lights", data=spec.lights, dimension_names=DIMS["lights"], attributes=DESCRIPTIONS["lights"]
        )
        g.create_array(
            "intensities",
            data=spec.intensities,
            dimension_names=DIMS["intensities"],
            attributes=DESCRIPTIONS["intensities"],
        )
        for o in OUTPUT_TABLE:
            if o.made == "after" or not o.exists(C):
                continue  # depth is made after the run (service.results.research); albedo_rgb needs colour
            shape = o.shape(k, H, W, C)
            # the mask in bands of tile rows: written once, read whole by every counting of the
            # tiles' pixels, where one chunk per tile cost a file per tile
            tx = W if o.made == "input" else tc[1]
            chunks = tuple({"y": tc[0], "x": tx}.get(d, n) for d, n in zip(o.dims, shape, strict=True))
            g.create_array(
                o.name,
                shape=shape,
                chunks=chunks,
                dtype=o.dtype,
                fill_value=o.fill,
                dimension_names=o.dims,
                attributes=DESCRIPTIONS[o.name],
            )
        tile_group.create_array(
            "done",
            shape=grid_shape(H, W, T),
            chunks=(1, 1),
            dtype="int32",
            fill_value=0,
            dimension_names=DIMS["done"],
            attributes=DESCRIPTIONS["done"],
        )
        tile_group.create_array(
            "tile_stats",
            shape=(*grid_shape(H, W, T), 3),
            chunks=(1, 1, 3),
            dtype="int64",
            fill_value=0,
            dimension_names=DIMS["tile_stats"],
            attributes=DESCRIPTIONS["tile_stats"],
        )
        inputs.create_array(
            "input_digests",
            shape=(k + 1, DIGEST_BYTES),
            chunks=(1, DIGEST_BYTES),
            dtype="uint8",
            fill_value=0,
            chunk_key_encoding=FLAT_KEYS,
            dimension_names=DIMS["input_digests"],
            attributes=DESCRIPTIONS["input_digests"],
        )
        # attrs last, in one metadata write: a store without them is detected as incomplete on open
        g.update_attributes(
            {
                "maxfs_format": FORMAT_VERSION,
                "input_digest": spec.digest,
                "k": k,
                "height": H,
                "width": W,
                "channels": C,
                "dtype": spec.dtype,
                "params": params.to_json(),
                "params_hash": params.digest() if params.resolved else None,
                "lights_digest": lights_digest(spec),
            }
        )
        return cls(path, g)

    @classmethod
    def open(cls, path: Path, mode: str = "r+") -> JobStore:
        """Open an existing store (never truncates)."""
        if mode not in ("r", "r+"):
            raise ValueError("job stores are opened 'r' or 'r+' only")
        path = job_folder(Path(path))
        if (path / "zarr.json").exists():  # format 1 and 2 kept the record inside the group
            raise StoreError(
                f"{path} was written by an older maxfs (its Zarr group is the folder itself); "
                "run again with --overwrite to replace it, or choose another output"
            )
        if not (path / GROUP_DIR / "zarr.json").exists():
            raise NotFoundError(f"no job store at {path}")
        try:
            g = zarr.open_group(path / GROUP_DIR, mode=mode, zarr_format=3)
        except (FileNotFoundError, zarr.errors.GroupNotFoundError) as e:
            raise NotFoundError(f"no job store at {path}: {e}") from None
        except (ValueError, KeyError) as e:
            raise StoreError(f"job store at {path} is unreadable: {e}") from None
        try:
            return cls(path, g)
        except KeyError as e:
            raise StoreError(f"job store at {path} is incomplete: missing {e}") from None

    # -- parameters ---------------------------------------------------------------------------
    @property
    def params(self) -> JobParams:
        return JobParams.from_json(dict(self.group.attrs["params"]))

    def set_params(self, params: JobParams) -> None:
        """Record (possibly new) parameters; tiles made with others stop counting as done."""
        self.spec.check_params(params)
        self.group.update_attributes(
            {"params": params.to_json(), "params_hash": params.digest() if params.resolved else None}
        )

    @property
    def observation_model(self) -> ObservationModel:
        s = self.spec
        p = self.params
        return ObservationModel.for_input(
            np.dtype(s.dtype), s.k, s.channels, s.intensities, dequantize=p.dequantize, quantum=p.quantum or 1
        )

    # -- inputs -------------------------------------------------------------------------------
    def check_index(self, i: int) -> None:
        k = self.spec.k
        if not 0 <= i < k:
            raise NotFoundError(f"image index {i} is out of range; this job has images 0..{k - 1}")

    @property
    def band_rows(self) -> int:
        """Rows of one image shard: the unit an upload writes."""
        return int(self._fixed("images").shards[1])

    def _shard_writer(self) -> ShardWriter | None:
        """The fast writer of whole image shards (:mod:`storage.shards`), made once; None for a
        store whose image codecs it does not encode."""
        if self._writer is None:
            folder = self.path / GROUP_DIR / PATHS["images"]
            self._writer = (ShardWriter.for_array(folder, self._fixed("images")),)
        return self._writer[0]

    def _set_row(self, name: str, i: int, value: Any) -> None:
        """``array[i] = value`` for the small per-image arrays (``uploaded``, ``input_digests``): one
        chunk file per row, written straight to it by :meth:`_write` (through zarr, each was a hop
        to its event loop and back, 1-3 ms)."""
        self._write(name, (slice(i, i + 1),), value)

    def check_image(self, i: int, image: NDArray[Any]) -> None:
        """Refuse an image whose index, shape or dtype does not fit the job."""
        s = self.spec
        self.check_index(i)
        if tuple(image.shape) != s.image_shape:
            raise InvalidInputError(
                f"image {i} has shape {tuple(image.shape)}, the job expects {s.image_shape}"
            )
        if image.dtype != np.dtype(s.dtype):
            raise InvalidInputError(f"image {i} has dtype {image.dtype}, the job expects {s.dtype}")

    def write_image(self, i: int, image: NDArray[Any]) -> None:
        """Store image ``i`` band by band (whole shards), then mark it uploaded. Idempotent."""
        s = self.spec
        self.check_image(i, image)
        B = self.band_rows
        self.write_bands(i, (image[y : y + B] for y in range(0, s.height, B)))

    def write_bands(self, i: int, bands: Iterable[NDArray[Any]], digest: bytes | None = None) -> None:
        """Store image ``i`` from consecutive bands of :attr:`band_rows` rows (the last may be
        shorter). ``uploaded[i]`` is False while the bands are written. ``digest``: the image's
        :func:`storage.digests.array_digest` when the caller made it already (an upload digests
        the body as it arrives), else it is made from the bands."""
        self.check_index(i)
        images, y = self._fixed("images"), 0
        writer, rows, H = self._shard_writer(), self.band_rows, self.spec.height
        self._set_row("uploaded", i, False)
        h = ArrayHasher(self.spec.image_shape, self.spec.dtype, self.spec.digest) if digest is None else None
        # whole shards are encoded on two threads while this one digests, at most two ahead
        encoding: deque[tuple[tuple[int, ...], Future[bytes | None]]] = deque()
        for band in bands:
            n = band.shape[0]
            if writer is not None and y % rows == 0 and (n == rows or y + n == H):
                # a whole shard: encoded in one pass (storage.shards), not chunk by chunk
                coords = (i, y // rows, *(0,) * (band.ndim - 1))
                encoding.append((coords, writer.submit(coords, band[None])))
                if len(encoding) > 2:
                    coords, data = encoding.popleft()
                    writer.store(coords, data.result())
            else:
                images[i, y : y + n] = band
            if h is not None:
                h.update(band)
            y += n
        while encoding:
            coords, data = encoding.popleft()
            assert writer is not None
            writer.store(coords, data.result())
        if y != self.spec.height:
            raise InvalidInputError(f"image {i}: got {y} rows, the job expects {self.spec.height}")
        self._set_row("input_digests", i, np.frombuffer(digest if h is None else h.digest(), np.uint8))
        self._set_row("uploaded", i, True)

    def uploaded(self) -> NDArray[np.bool_]:
        return self._read("uploaded")

    def digests(self) -> list[bytes]:
        """Recorded digests: images 0..k-1, then the mask (zeros = not written). One read of
        k + 1 chunks: callers that need several views of them take this list once."""
        return [bytes(row) for row in self._read("input_digests")]

    def write_mask(self, mask: NDArray[np.bool_]) -> None:
        """Store the mask, band by band; a crash part-way leaves :meth:`mask_state`
        "incomplete", never a silent mix of old and new."""
        s = self.spec
        if mask.shape != (s.height, s.width):
            raise InvalidInputError(
                f"mask has shape {mask.shape}, the job's images are {s.height} x {s.width}"
            )
        m = np.ascontiguousarray(mask, dtype=bool)
        row = (slice(s.k, s.k + 1),)
        self._write("input_digests", row, np.frombuffer(MASK_WRITING, np.uint8)[None])
        rows = int(self._fixed("mask").chunks[0])
        for y in range(0, s.height, rows):
            self._write("mask", (slice(y, min(y + rows, s.height)),), m[y : y + rows])
        self._write("input_digests", row, np.frombuffer(array_digest(m, s.digest), np.uint8)[None])

    def _write(self, name: str, region: tuple[slice, ...], value: Any) -> None:
        """``array[region] = value`` for an array created with the store: straight to the chunk's
        file where ``region`` is one whole chunk (:class:`storage.shards.ChunkFiles`, renamed into
        place: a reader sees the old chunk or the new one), else through zarr."""
        files = self._chunk_files(name)
        at = None if files is None else files.chunk_at(region)
        if files is None or at is None:
            self._fixed(name)[region] = value
        else:
            files.put(at, files.encode(at, value))

    @property
    def lights_digest(self) -> str:
        return str(self.group.attrs["lights_digest"])

    @property
    def source_fingerprint(self) -> str | None:
        """Fingerprint of the files the inputs were read from (:meth:`Dataset.fingerprint`)."""
        return self.group.attrs.get("source_fingerprint")

    @source_fingerprint.setter
    def source_fingerprint(self, fp: str | None) -> None:
        if fp != self.source_fingerprint:
            self.group.attrs["source_fingerprint"] = fp

    def digest_row(self, i: int) -> bytes:
        """The recorded digest ``i`` (images 0..k-1, then the mask; zeros: none)."""
        return bytes(self._read("input_digests", (slice(i, i + 1),))[0])

    def mask_state(self) -> str:
        """ "default" (none given: every pixel), "complete", or "incomplete" (a write was cut short)."""
        d = self.digest_row(self.spec.k)
        if d == MASK_WRITING:
            return "incomplete"
        return "default" if not any(d) else "complete"

    def record_digests(self, digests: Mapping[int, bytes]) -> None:
        """Record images' digests without storing their pixels (a run that keeps the stack in
        memory): the input identity holds, ``uploaded[i]`` stays False. A chunk file per image,
        written directly (:meth:`_set_row`), or through zarr in one write for all."""
        if not digests:
            return
        for i in digests:
            self.check_index(i)
        if self._chunk_files("input_digests") is not None:
            for i, d in sorted(digests.items()):
                self._set_row("input_digests", i, np.frombuffer(d, np.uint8))
            return
        idx = sorted(digests)
        rows = np.stack([np.frombuffer(digests[i], np.uint8) for i in idx])
        self._array("input_digests").set_orthogonal_selection((np.asarray(idx), slice(None)), rows)

    def known_images(self, digests: list[bytes] | None = None) -> NDArray[np.bool_]:
        """Images whose digest is recorded (stored, or digested by an in-memory run), from
        ``digests`` (:meth:`digests`, read again when not given)."""
        rows = self.digests() if digests is None else digests
        return np.array([any(d) for d in rows[: self.spec.k]], dtype=bool)

    def input_identity(self, digests: list[bytes] | None = None) -> str | None:
        """A digest of every input (images, mask, lights, intensities, shape); None while an
        image's digest is unknown or the mask is incomplete. ``digests`` as for :meth:`known_images`."""
        rows = self.digests() if digests is None else digests
        if not self.known_images(rows).all() or rows[self.spec.k] == MASK_WRITING:
            return None
        s = self.spec
        h = hashlib.sha256(f"{s.k}|{s.height}|{s.width}|{s.channels}|{s.dtype}|".encode())
        h.update(bytes.fromhex(self.group.attrs["lights_digest"]))
        for d in rows:
            h.update(d)
        return h.hexdigest()

    def read_mask(self) -> NDArray[np.bool_]:
        return self._read("mask")

    # -- tiles --------------------------------------------------------------------------------
    def tiles(self) -> list[Tile]:
        s = self.spec
        return list(tiles(s.height, s.width, self.params.tile))

    def done_grid(self) -> NDArray[np.bool_]:
        """Which tiles are finished with the current parameters: those whose marker is the
        parameters' token, and, once the job has parameters, every tile without a masked pixel
        (:meth:`masked_per_tile`): its outputs are fill values whatever the parameters, as only
        :meth:`write_empty_tile` ever writes there, so it needs no marker and no task. Reads the
        markers of the other tiles only (a chunk each)."""
        p = self.params
        if not p.resolved:
            return np.zeros(np.asarray(self._fixed("done").shape), dtype=bool)
        done = self.masked_per_tile() == 0
        ys, xs = np.nonzero(~done)
        if ys.size == done.size:
            return self._read("done") == p.token()
        if ys.size:
            done[ys, xs] = self._cells("done", ys, xs) == p.token()
        return done

    def read_tile(self, t: Tile) -> tuple[NDArray[Any], NDArray[np.bool_]]:
        """Raw images ``(k, h, w[, C])`` and mask ``(h, w)`` of one tile."""
        return self.read_tile_images(t), self.read_tile_mask(t)

    def _shard_reader(self) -> ShardReader | None:
        if self._reader is None:
            folder = self.path / GROUP_DIR / PATHS["images"]
            self._reader = (ShardReader.for_array(folder, self._fixed("images")),)
        return self._reader[0]

    def read_tile_images(self, t: Tile) -> NDArray[Any]:
        """The raw images of window ``t`` ``(k, h, w[, C])``: from the shard files directly
        (:class:`storage.shards.ShardReader`), or through zarr for other codecs."""
        region = (slice(None), slice(t.y0, t.y1), slice(t.x0, t.x1))
        reader = self._shard_reader()
        got = None if reader is None else reader.read(region)
        return np.asarray(self._fixed("images")[region]) if got is None else got

    def window_reader(self, windows: Iterable[Tile]) -> Callable[[Tile], NDArray[Any]]:
        """:meth:`read_tile_images` for many windows (the eps sample's), all read now with every
        shard file opened once (:meth:`ShardReader.read_many`; one open per window and image cost
        more than the reading); any other window is read from the store when asked for."""
        wins = {(t.y0, t.y1, t.x0, t.x1) for t in windows}
        reader = self._shard_reader()
        got = None
        if reader is not None and wins:
            order = sorted(wins)
            many = reader.read_many([(slice(None), slice(y0, y1), slice(x0, x1)) for y0, y1, x0, x1 in order])
            got = None if many is None else dict(zip(order, many, strict=True))
        kept = got or {}

        def read(t: Tile) -> NDArray[Any]:
            block = kept.get((t.y0, t.y1, t.x0, t.x1))
            return self.read_tile_images(t) if block is None else block.copy()

        return read

    def read_tile_mask(self, t: Tile) -> NDArray[np.bool_]:
        return self._read("mask", (slice(t.y0, t.y1), slice(t.x0, t.x1)))

    def write_empty_tile(self, t: Tile, token: int) -> None:
        """A tile with no masked pixel: every output at its fill value, zero stats, done marker."""
        self._write_outputs(t, {}, token, (0, 0, 0))

    def masked_per_tile(self) -> NDArray[np.int64]:
        """Masked pixels of each tile, on the tile grid ``(ny, nx)``; counted once per mask (this
        store object keeps the counts with the mask's digest, which a new mask changes)."""
        key = (self.digest_row(self.spec.k), self.params.tile)
        if self._counts is not None and self._counts[0] == key:
            return self._counts[1].copy()
        counts = masked_per_tile(self.read_mask(), self.params.tile)
        if key[0] != MASK_WRITING:
            self._counts = (key, counts)
        return counts.copy()

    def write_tile(
        self, t: Tile, arrays: Mapping[str, NDArray[Any]], token: int, stats: tuple[int, int, int]
    ) -> None:
        """Write a tile's outputs (whole chunks; ``arrays`` maps names of
        :data:`storage.outputs.TILE_OUTPUTS` to the tile's values) and ``stats`` (active,
        solved, certified pixels), then its done marker, last."""
        missing = [o.name for o in TILE_OUTPUTS if o.exists(self.spec.channels) and o.name not in arrays]
        if missing:
            raise ValueError(f"tile result lacks {', '.join(missing)}")
        self._write_outputs(t, arrays, token, stats)

    def _chunk_files(self, name: str, write: bool = True) -> ChunkFiles | None:
        """The direct reader and writer of whole chunks of array ``name``
        (:class:`storage.shards.ChunkFiles`), made once; None for an array it does not encode,
        or for writing to a store opened read-only (zarr refuses the write with its own error)."""
        if name not in self._files:
            folder = self.path / GROUP_DIR / PATHS.get(name, name)
            self._files[name] = ChunkFiles.for_array(folder, self._fixed(name))
        return None if write and self.group.store.read_only else self._files[name]

    def _read(self, name: str, region: tuple[slice, ...] = ()) -> NDArray[Any]:
        """``region`` of array ``name`` (one created with the store: see :meth:`_fixed`), read
        straight from its chunk files (:meth:`storage.shards.ChunkFiles.read_region`), or through
        zarr for other codecs or a chunk that does not decode."""
        files = self._chunk_files(name, write=False)
        got = None if files is None else files.read_region(region)
        return np.asarray(self._fixed(name)[region or ...]) if got is None else got

    def _cells(
        self, name: str, ys: NDArray[np.intp] | list[int], xs: NDArray[np.intp] | list[int]
    ) -> NDArray[Any]:
        """Tile-grid cells ``(ys[i], xs[i])`` of ``done`` or ``tile_stats`` (a chunk per tile), each
        with its trailing values: ``(len(ys), ...)``."""
        a = self._fixed(name)
        out = np.empty((len(ys), *a.shape[2:]), dtype=np.dtype(a.dtype))
        for i, (y, x) in enumerate(zip(ys, xs, strict=True)):
            out[i] = self._read(name, (slice(int(y), int(y) + 1), slice(int(x), int(x) + 1)))[0, 0]
        return out

    def _write_outputs(
        self, t: Tile, arrays: Mapping[str, NDArray[Any]], token: int, stats: tuple[int, int, int]
    ) -> None:
        ys, xs = slice(t.y0, t.y1), slice(t.x0, t.x1)
        parts: list[tuple[str, tuple[slice, ...], Any]] = []
        for o in TILE_OUTPUTS:
            if o.exists(self.spec.channels):
                region = (slice(None), ys, xs) if o.per == "image" else (ys, xs)
                parts.append((o.name, region, arrays.get(o.name, self._fixed(o.name).fill_value)))
        ty, tx = slice(t.ty, t.ty + 1), slice(t.tx, t.tx + 1)
        parts.append(("tile_stats", (ty, tx), np.asarray(stats, dtype=np.int64).reshape(1, 1, 3)))
        # each part is one whole chunk of its array (chunks are tile-aligned): encoded and written
        # here (storage.shards.ChunkFiles), the same files zarr writes; zarr for any other array
        direct: list[tuple[ChunkFiles, tuple[int, ...], bytes | None]] = []
        writes = []
        for name, region, value in parts:
            files = self._chunk_files(name)
            coords = None if files is None else files.chunk_at(region)
            if files is None or coords is None:
                writes.append(self._fixed(name).async_array.setitem(region, value))
            else:
                direct.append((files, coords, files.encode(coords, value)))
        for files, coords, data in direct:
            files.put(coords, data)
        if writes:  # in one pass of zarr's event loop, not a round trip each
            sync(_gather(writes))
        self._write("done", (ty, tx), token)  # the done marker last, once every chunk of the tile is in place

    def tile_done(self, t: Tile) -> bool:
        """Whether tile ``t`` is finished with the current parameters."""
        p = self.params
        return p.resolved and int(self._cells("done", [t.ty], [t.tx])[0]) == p.token()

    def progress(self) -> ProgressCounts:
        """Counts over the finished tiles, from the done grid and per-tile stats only."""
        counts = self.masked_per_tile()
        done = self.done_grid() & (counts > 0)
        # the stats of finished tiles with masked pixels (the others' are zeros): a chunk each
        ys, xs = np.nonzero(done)
        stats = self._cells("tile_stats", ys, xs).astype(np.int64).reshape(-1, 3)
        return ProgressCounts(
            tiles_done=int(done.sum()),
            tiles_total=int(np.count_nonzero(counts)),
            pixels_done=int(stats[:, 0].sum()),
            pixels_total=int(counts.sum()),
            solved=int(stats[:, 1].sum()),
            certified=int(stats[:, 2].sum()),
        )

    def by_masked_pixels(self, todo: Iterable[Tile], counts: NDArray[np.int64] | None = None) -> list[Tile]:
        """``todo`` by masked pixels, most first (ties in raster order): the work a tile costs,
        so the largest tiles start first and the last ones to finish are small (``counts``:
        :meth:`masked_per_tile`, if the caller has it)."""
        counts = self.masked_per_tile() if counts is None else counts
        return sorted(todo, key=lambda t: (-int(counts[t.ty, t.tx]), t.index))

    def read_output(self, name: str) -> NDArray[Any]:
        """Output ``name`` whole. A tile output is read only over the tiles that hold masked pixels
        (their bounding box): the others hold its fill value, and each of their chunks would cost
        a look-up (most of the frame, for an object in balanced small tiles)."""
        if name not in OUTPUTS_BY_NAME or name not in self.group:
            raise NotFoundError(f"no output array {name!r}; available: {', '.join(self.output_names())}")
        o = OUTPUTS_BY_NAME[name]
        if o.made == "after":  # made after the run, and again by each re-integration: metadata read now
            return np.asarray(self.group[name][...])
        a = self._fixed(name)
        if o.made != "tile":
            return self._read(name)
        ty, tx = np.nonzero(self.masked_per_tile())
        if ty.size == 0:
            return self._read(name)
        T, (H, W) = self.params.tile, (self.spec.height, self.spec.width)
        box = {
            "y": slice(int(ty.min()) * T, min((int(ty.max()) + 1) * T, H)),
            "x": slice(int(tx.min()) * T, min((int(tx.max()) + 1) * T, W)),
        }
        region = tuple(box.get(d, slice(0, n)) for d, n in zip(o.dims, a.shape, strict=True))
        if all(r == slice(0, n) for r, n in zip(region, a.shape, strict=True)):
            return self._read(name)
        out = np.full(a.shape, a.fill_value, dtype=a.dtype)
        out[region] = self._read(name, region)
        return out

    def output_names(self) -> list[str]:
        return [n for n in OUTPUT_NAMES if n in self.group]

    def download_files(self, include_inputs: bool = False) -> list[tuple[Path, str]]:
        """Files of a results download, as (path, name in the archive): the Zarr group without
        the input stack (unless ``include_inputs``), the previews and the record."""
        skip = set() if include_inputs else {self.path / GROUP_DIR / name for name in BULK_INPUTS}
        out = []
        for p in sorted(self.path.rglob("*")):
            if not p.is_file() or p.name.startswith(".") or p.name == CANCEL_FLAG:
                continue
            if p.parent.name == PROGRESS_DIR:
                continue
            if any(s == p or s in p.parents for s in skip):
                continue
            out.append((p, p.relative_to(self.path).as_posix()))
        return out

    # -- run log and cancel flag -----------------------------------------------------------------
    def log_run(self, tile_index: int, outcome: str) -> None:
        """Append one line per tile execution (O_APPEND: atomic for short lines)."""
        line = f"{time.time():.3f} {os.getpid()} tile={tile_index} {outcome}\n".encode()
        fd = os.open(self.path / RUNS_LOG, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
        finally:
            os.close(fd)

    def run_counts(self) -> dict[int, int]:
        """How many times each tile was computed (``done`` lines in the run log)."""
        counts: dict[int, int] = {}
        log = self.path / RUNS_LOG
        if log.exists():
            for line in log.read_text().splitlines():
                parts = line.split()
                if len(parts) == 4 and parts[3] == "done":
                    t = int(parts[2].removeprefix("tile="))
                    counts[t] = counts.get(t, 0) + 1
        return counts

    # -- progress inside running tiles -----------------------------------------------------------
    def note_tile_progress(self, tile_index: int, pixels: int) -> None:
        """Record that a running tile has solved ``pixels`` of its masked pixels (a small file,
        replaced atomically; any worker process may write it, the runner sums them)."""
        d = self.path / PROGRESS_DIR
        d.mkdir(exist_ok=True)
        tmp = temp_path(d / str(tile_index))
        tmp.write_text(str(int(pixels)))
        os.replace(tmp, d / str(tile_index))

    def clear_tile_progress(self, tile_index: int | None = None) -> None:
        """Forget one tile's progress note (it finished or stopped), or every tile's (a new run)."""
        d = self.path / PROGRESS_DIR
        if tile_index is not None:
            (d / str(tile_index)).unlink(missing_ok=True)
        elif d.is_dir():
            for p in d.iterdir():
                p.unlink(missing_ok=True)
            with contextlib.suppress(OSError):  # a tile still writing one: the next run clears it
                d.rmdir()

    def running_pixels(self, done: NDArray[np.bool_] | None = None) -> int:
        """Masked pixels solved so far in tiles that have not finished (``done``: the done grid,
        flattened, if the caller has it)."""
        d = self.path / PROGRESS_DIR
        if not d.is_dir():
            return 0
        grid = self.done_grid().ravel() if done is None else done
        total = 0
        for p in d.iterdir():
            if not p.name.isdigit() or int(p.name) >= grid.size or grid[int(p.name)]:
                continue
            try:
                total += int(p.read_text() or 0)
            except (OSError, ValueError):  # replaced or removed while read: it counts next time
                continue
        return total

    def request_cancel(self) -> None:
        (self.path / CANCEL_FLAG).touch()

    def clear_cancel(self) -> None:
        (self.path / CANCEL_FLAG).unlink(missing_ok=True)

    @property
    def cancel_requested(self) -> bool:
        return (self.path / CANCEL_FLAG).exists()

    # -- arrays by name, for code outside this module (only JobStore touches the group) ----------
    def has_array(self, name: str) -> bool:
        """Whether the group holds array ``name`` (``depth`` exists once it is integrated)."""
        return PATHS.get(name, name) in self.group

    def array_meta(self, name: str) -> ArrayMeta:
        """Shape, dtype, chunks and attributes of array ``name``, without reading it."""
        a = self._array(name)
        return ArrayMeta(tuple(a.shape), np.dtype(a.dtype), tuple(a.chunks), dict(a.attrs))

    def read_array(self, name: str, region: Any = ...) -> NDArray[Any]:
        """``region`` of array ``name`` (NumPy basic indexing: an index, slices, a tuple of them)."""
        return np.asarray(self._array(name)[region])

    def write_depth(self, depth: NDArray[np.floating], attrs: dict[str, Any]) -> None:
        """Store ``depth`` (H, W) as its row of the output table says, chunked like the mask,
        with ``attrs`` (replacing one)."""
        o = OUTPUTS_BY_NAME["depth"]
        arr = self.group.create_array(
            o.name,
            shape=depth.shape,
            chunks=tuple(int(c) for c in self.group["mask"].chunks),
            dtype=o.dtype,
            fill_value=o.fill,
            dimension_names=o.dims,
            overwrite=True,
        )
        arr[...] = depth
        arr.update_attributes(attrs)


async def _gather(writes: list[Any]) -> None:
    await asyncio.gather(*writes)


def _coordinates(g: zarr.Group, k: int, channels: int | None) -> None:
    """The coordinate arrays of the dimensions xarray indexes by label: ``xyz``, ``image``
    (numbered from 1, as ``--images`` and the messages number them) and ``channel``."""
    labels = {"xyz": ("x", "y", "z"), "channel": CHANNEL_NAMES[channels]}
    for dim, words in labels.items():
        a = g.create_array(dim, shape=(len(words),), dtype=str, dimension_names=(dim,))
        a[...] = np.array(words)
    g.create_array(
        "image",
        data=np.arange(1, k + 1, dtype=np.int32),
        dimension_names=("image",),
        attributes={"long_name": "image number, from 1 in the input folder's order"},
    )


@dataclass(frozen=True)
class ArrayMeta:
    """What :meth:`JobStore.array_meta` says about one array of the group."""

    shape: tuple[int, ...]
    dtype: np.dtype
    chunks: tuple[int, ...]
    attrs: dict[str, Any]

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * self.dtype.itemsize
