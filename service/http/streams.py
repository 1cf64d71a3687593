"""Large answers made piece by piece: NPY arrays, the results zip, and bounded previews.

The server never holds a whole output array or a copy of a job folder: an NPY answer
is its header, then the array read from the store in bands of a few MiB; the zip is
written as it is sent (no temporary file, so nothing uncounted lands on the disk and
nothing is left behind by a crash); a preview is rendered from the outputs read in
row bands and decimated to at most ``max_edge`` pixels a side, then cached in the
job folder until the results change. These generators are synchronous: Starlette
runs each step in a thread, so a slow reader holds one band and no event-loop time.
"""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from maxfs.service.results.previews import render
from maxfs.storage.errors import NotFoundError
from maxfs.storage.imageio import encode_png
from maxfs.storage.layout import ArrayMeta, JobStore

#: Previews whose colours depend on each pixel alone, so they can be rendered band by band.
PER_PIXEL = frozenset({"normal", "inlier_count"})
#: Bytes of one piece of an NPY or zip answer.
PIECE = 4 << 20


def npy_header(shape: tuple[int, ...], dtype: np.dtype) -> bytes:
    """The NPY (version 1.0 or 2.0) header of a C-order array."""
    buf = io.BytesIO()
    d = {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False, "shape": shape}
    try:
        np.lib.format.write_array_header_1_0(buf, d)
    except ValueError:  # a header over 64 KiB (never for our shapes)
        buf = io.BytesIO()
        np.lib.format.write_array_header_2_0(buf, d)
    return buf.getvalue()


def _bands(
    shape: tuple[int, ...], chunks: tuple[int, ...], itemsize: int, limit: int, prefix: tuple = ()
) -> Iterator[tuple]:
    """Selections that cover an array in C order, each at most about ``limit`` bytes
    (whole chunks along the axis that is split, where a chunk fits)."""
    if not shape:
        yield prefix
        return
    row = itemsize * math.prod(shape[1:])
    if row <= limit or len(shape) == 1:
        fit = max(1, limit // max(row, 1))
        step = max(fit // chunks[0] * chunks[0], min(fit, shape[0]))
        for i in range(0, shape[0], step):
            yield (*prefix, slice(i, min(i + step, shape[0])))
    else:
        for i in range(shape[0]):
            yield from _bands(shape[1:], chunks[1:], itemsize, limit, (*prefix, i))


def job_still_there(folder: Path) -> None:
    """Stop an answer whose job was deleted while it was sent: the store's chunks are gone, and
    Zarr would go on with fill values. Raised inside a streamed answer, this ends the
    connection before the declared length, so the client sees a cut download, not a wrong one."""
    if not folder.exists():
        raise NotFoundError(f"the job at {folder.name} was deleted while its answer was being made")


def npy_pieces(store: JobStore, name: str, limit: int = PIECE) -> Iterator[bytes]:
    """An NPY file of the store's array ``name``, read band by band."""
    meta = store.array_meta(name)
    dtype = meta.dtype.newbyteorder("<") if meta.dtype.byteorder == ">" else meta.dtype
    yield npy_header(meta.shape, np.dtype(dtype))
    for sel in _bands(meta.shape, meta.chunks, np.dtype(dtype).itemsize, limit):
        try:
            band = np.ascontiguousarray(store.read_array(name, sel), dtype=dtype).tobytes()
        except (KeyError, FileNotFoundError):
            job_still_there(store.path)
            raise
        job_still_there(store.path)  # checked after the read too: a chunk read once it was gone is fill
        yield band


def npy_size(meta: ArrayMeta) -> int:
    """Bytes of :func:`npy_pieces` (for Content-Length)."""
    return len(npy_header(meta.shape, meta.dtype)) + meta.nbytes


class _Sink:
    """A write-only, unseekable file that collects what :mod:`zipfile` writes."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0

    def write(self, b: bytes) -> int:
        self.parts.append(bytes(b))
        self.size += len(b)
        return len(b)

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        out = b"".join(self.parts)
        self.parts.clear()
        self.size = 0
        return out


def zip_pieces(
    files: list[tuple[Path, str]], piece: int = PIECE, folder: Path | None = None
) -> Iterator[bytes]:
    """A zip archive (stored, ZIP64 where needed) of ``files`` = (path, name), made while it is
    sent: at most about one ``piece`` is held, nothing is written to disk. With ``folder`` (the
    job's), the answer stops if the job is deleted meanwhile (:func:`job_still_there`)."""
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:  # type: ignore[arg-type]
        for path, name in files:
            try:
                info = zipfile.ZipInfo.from_file(path, name)
                src = open(path, "rb")
            except FileNotFoundError:  # removed meanwhile (a temp file, a rewritten chunk)
                if folder is not None:
                    job_still_there(folder)
                continue
            info.compress_type = zipfile.ZIP_STORED
            with src, zf.open(info, "w", force_zip64=info.file_size > (1 << 30)) as dst:
                while chunk := src.read(piece):
                    dst.write(chunk)
                    if sink.size >= piece:
                        yield sink.take()
            if folder is not None:
                job_still_there(folder)
            if sink.size >= piece:
                yield sink.take()
    yield sink.take()


def _decimated(store: JobStore, name: str, step: int) -> NDArray[Any]:
    """``store``'s array ``name`` at ``[::step, ::step, ...]``, read in bands of whole chunk rows."""
    meta = store.array_meta(name)
    H, W = meta.shape[:2]
    out = np.empty((-(-H // step), -(-W // step), *meta.shape[2:]), dtype=meta.dtype)
    rows = max(int(meta.chunks[0]) // step, 1) * step
    for y in range(0, H, rows):
        band = store.read_array(name, (slice(y, min(y + rows, H), step), slice(None, None, step)))
        out[y // step : -(-min(y + rows, H) // step)] = band
    return out


def preview_png(store: JobStore, name: str, inputs: tuple[str, ...], max_edge: int) -> bytes:
    """PNG of preview ``name`` (:func:`service.results.previews.render`, from the outputs ``inputs``) at
    most ``max_edge`` pixels a side: every ``s``-th pixel of each output, read in row bands
    (never a whole array)."""
    H, W = store.spec.height, store.spec.width
    step = max(1, math.ceil(max(H, W) / max(max_edge, 1)))
    arrays = {n: _decimated(store, n, step) for n in store.output_names() if n in inputs}
    if name not in PER_PIXEL:  # a scale from the whole image (e.g. albedo's percentile)
        return encode_png(render(name, arrays, store.spec.k))
    rows = max(1, (1 << 16) // max(W // step, 1))  # render about 64 K pixels at a time
    n = next(iter(arrays.values())).shape[0]
    bands = [
        render(name, {k: a[y : y + rows] for k, a in arrays.items()}, store.spec.k) for y in range(0, n, rows)
    ]
    return encode_png(np.concatenate(bands, axis=0))
