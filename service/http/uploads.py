"""Upload staging: an image or mask upload from the checks before its body to the store.

Owner, state, index, declared size and disk space are checked before the body is read
(:meth:`Uploads.before_upload`, :func:`service.http.guards.check_declared`); a raw image body is
streamed to a staging file in the job folder (digested as it arrives), validated whole, then
written to the store one shard band at a time (:func:`raw_bands`), so the server holds one band
of one image per request (a whole image of at most 1 MiB, which is one shard), whatever k is, and
a rejected upload leaves the store as it was. A
PNG or TIFF body (at most twice the image plus 1 MiB) is read into memory, as its decoder
needs it whole. A batch of raw images (:meth:`Uploads.images`) is one raw upload per image,
back to back in one body; its images of at most 1 MiB are gathered in memory, not staged.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from fastapi import Request

from maxfs.service.http.auth import user_of
from maxfs.service.http.guards import body_chunks, check_declared, is_raw, mask_of, read_body, stage_body
from maxfs.service.http.jobs import TEMP_PREFIX, JobManager
from maxfs.service.settings import Settings
from maxfs.storage.digests import ArrayHasher
from maxfs.storage.errors import ConflictError, InvalidInputError, NotFoundError, PayloadTooLargeError
from maxfs.storage.layout import JobSpec, JobStore


def raw_bands(source: Path | BinaryIO, spec: JobSpec, rows: int) -> Iterator[np.ndarray]:
    """Bands of ``rows`` rows of a raw little-endian image: a staged file, or one gathered in
    memory (read from its current position)."""
    wire = np.dtype(spec.dtype).newbyteorder("<")
    row_shape = spec.image_shape[1:]
    per_row = int(np.prod(row_shape))
    with open(source, "rb") if isinstance(source, Path) else contextlib.nullcontext(source) as f:
        for y in range(0, spec.height, rows):
            n = min(rows, spec.height - y)
            band = np.frombuffer(f.read(n * per_row * wire.itemsize), dtype=wire).reshape(n, *row_shape)
            yield band.astype(spec.dtype, copy=False)


#: Images of a batch upload (:meth:`Uploads.images`) of at most this many bytes are gathered in
#: memory instead of a staging file: the size up to which an image is one shard, held whole by
#: its upload anyway (:data:`storage.layout.WHOLE_IMAGE_SHARD_BYTES`).
IN_MEMORY_IMAGE_BYTES = 1 << 20


class Uploads:
    """Takes image and mask uploads for the jobs of one :class:`JobManager`."""

    def __init__(self, manager: JobManager, settings: Settings) -> None:
        self.m = manager
        self.s = settings

    def before_upload(self, request: Request, job_id: str, what: str) -> JobSpec:
        """Owner and state checks that need no body, so a doomed upload is refused unread; the
        job's spec (read once per job, not a store opened per request)."""
        rec = self.m.access(job_id, user_of(request))
        if not rec.state.accepts_uploads:
            raise ConflictError(f"job {job_id} is {rec.state.value}; {what} only before start")
        return self.m.spec(job_id)

    async def image(self, request: Request, job_id: str, index: int) -> None:
        """Store image ``index`` from the request body: raw little-endian bytes, or PNG/TIFF."""
        try:
            await self._image(request, job_id, index)
        except FileNotFoundError:
            if self.m.job_dir(job_id).exists():
                raise
            # deleted (purge or retention) while the body arrived: its staging file went too
            raise NotFoundError(f"job {job_id} was deleted during the upload") from None

    async def _image(self, request: Request, job_id: str, index: int) -> None:
        spec = self.before_upload(request, job_id, "images can be uploaded")
        if not 0 <= index < spec.k:
            raise NotFoundError(f"image index {index} is out of range; this job has images 0..{spec.k - 1}")
        raw = is_raw(request)
        limit = spec.image_nbytes if raw else min(self.s.max_upload_bytes, 2 * spec.image_nbytes + (1 << 20))
        check_declared(request, limit)
        user, s = user_of(request), self.s
        # the staged body (at most its declared length) and the stored image are reserved
        # before a byte is written
        declared = request.headers.get("content-length", "")
        staged = min(limit, int(declared)) if declared.isdigit() else limit
        with self.m.uploads.take(user.name), self.m.disk.hold(spec.image_nbytes + staged, f"image {index}"):
            if not raw:
                await self._encoded_image(request, job_id, index, spec, limit)
                return
            # the digest is made as the body arrives (the body is the image's little-endian
            # bytes, what the digest reads), not from a second pass over the stored bands
            hasher = ArrayHasher(spec.image_shape, spec.dtype, spec.digest)
            part = await stage_body(
                request,
                self.m.job_dir(job_id),
                f"{TEMP_PREFIX}upload-{index}-",
                limit,
                s.upload_idle_timeout,
                feed=hasher.h.update,
                min_rate=s.upload_min_rate,
            )
            try:
                size = part.stat().st_size
                if size != spec.image_nbytes:
                    raise InvalidInputError(
                        f"image {index}: got {size} bytes, expected {spec.image_nbytes} "
                        f"({' x '.join(map(str, spec.image_shape))} {spec.dtype}, little-endian, "
                        "row-major); for a PNG or TIFF file send Content-Type: image/png or image/tiff"
                    )
                await self._store_raw(job_id, index, spec, part, hasher.digest())
            finally:
                part.unlink(missing_ok=True)

    async def images(self, request: Request, job_id: str, first: int, count: int) -> None:
        """Store images ``first .. first + count - 1`` from one raw body: their little-endian
        bytes one after the other (see :meth:`_images`)."""
        try:
            await self._images(request, job_id, first, count)
        except FileNotFoundError:
            if self.m.job_dir(job_id).exists():
                raise
            raise NotFoundError(f"job {job_id} was deleted during the upload") from None

    async def _images(self, request: Request, job_id: str, first: int, count: int) -> None:
        """A batch of small images in one request (one request per image costs more than the
        image when images are small). The checks of a single raw upload, for the whole body
        before it is read; then each image is staged, checked and stored as soon as its bytes
        are in, exactly as a single upload stores it, and the job record is saved once for the
        batch. A body cut short or too long keeps the whole images that came before the fault
        (resumable: the status lists the images still missing)."""
        spec = self.before_upload(request, job_id, "images can be uploaded")
        last = first + count - 1
        if count < 1 or not 0 <= first <= last < spec.k:
            raise NotFoundError(
                f"images {first}..{last} are out of range; this job has images 0..{spec.k - 1}"
            )
        if not is_raw(request):
            raise InvalidInputError(
                "a batch of images is raw little-endian bytes (Content-Type: application/octet-stream), "
                "one image after the other; send a PNG or TIFF file alone to PUT /jobs/{id}/images/{index}"
            )
        size = spec.image_nbytes
        limit = count * size
        if limit > self.s.max_upload_bytes:
            raise PayloadTooLargeError(
                f"{count} images of {size} bytes are {limit} bytes, more than one request may carry "
                f"({self.s.max_upload_bytes}, MAXFS_MAX_UPLOAD_BYTES); send fewer images per request"
            )
        check_declared(request, limit)
        declared = request.headers.get("content-length", "")
        if declared.isdigit() and int(declared) != limit:
            raise InvalidInputError(
                f"images {first}..{last}: the body declares {declared} bytes, {count} images need "
                f"{limit} ({count} x {size}: {' x '.join(map(str, spec.image_shape))} {spec.dtype}, "
                "little-endian, row-major, one after the other)"
            )
        folder, stored = self.m.job_dir(job_id), []
        # a small image is gathered in memory (at most one at a time per request), a larger one
        # staged to a file as a single upload is: creating, reading back and removing a file
        # per image cost more than storing a small image
        in_memory = size <= IN_MEMORY_IMAGE_BYTES
        # every image of the batch stored, and the one being staged, reserved before a byte is written
        hold = self.m.disk.hold(limit + size, f"images {first}..{last}")
        with self.m.uploads.take(user_of(request).name), hold:
            part: Path | None = None
            f: Any = None
            try:
                got = 0
                async for chunk in body_chunks(
                    request, limit, self.s.upload_idle_timeout, self.s.upload_min_rate
                ):
                    view = memoryview(chunk)
                    while view:
                        index = first + len(stored)
                        if f is None:
                            if in_memory:
                                f = io.BytesIO()
                            else:
                                fd, name = tempfile.mkstemp(
                                    prefix=f"{TEMP_PREFIX}upload-{index}-", suffix=".part", dir=folder
                                )
                                part, f = Path(name), os.fdopen(fd, "wb", buffering=0)
                            hasher, got = ArrayHasher(spec.image_shape, spec.dtype, spec.digest), 0
                        piece, view = view[: size - got], view[size - got :]
                        f.write(piece)
                        hasher.h.update(piece)
                        got += len(piece)
                        if got < size:
                            continue
                        source: Path | BinaryIO
                        if in_memory:
                            f.seek(0)
                            source = f
                        else:
                            f.close()
                            source = part
                        f = None
                        await self._store_raw(job_id, index, spec, source, hasher.digest(), record=False)
                        if part is not None:
                            part.unlink(missing_ok=True)
                        stored.append(index)
                if len(stored) != count:
                    received = len(stored) * size + (got if f is not None else 0)
                    raise InvalidInputError(
                        f"images {first}..{last}: got {received} bytes, expected {limit} ({count} x {size}); "
                        f"the {len(stored)} whole images that came first are stored"
                    )
            finally:
                if f is not None:
                    f.close()
                if part is not None:
                    part.unlink(missing_ok=True)
                await self.m.record_uploads(job_id, stored)

    async def _store_raw(
        self,
        job_id: str,
        index: int,
        spec: JobSpec,
        part: Path | BinaryIO,
        digest: bytes,
        *,
        record: bool = True,
    ) -> None:
        """Store image ``index`` from its raw bytes (a staged file, or a small image of a batch
        gathered in memory; :func:`raw_bands`) and the digest made as it arrived;
        ``record=False`` in a batch, whose caller saves the job record once for all its images."""

        def write(st: JobStore) -> None:
            st.write_bands(index, raw_bands(part, spec, st.band_rows), digest=digest)

        await self.m.upload_image(job_id, index, write, record=record)

    async def _encoded_image(
        self, request: Request, job_id: str, index: int, spec: JobSpec, limit: int
    ) -> None:
        """A PNG or TIFF body: read into memory (the decoder wants it whole; at most ``limit``
        bytes, what a staged file was read back as), its header checked before any pixel is
        decoded, decoded in a thread, stored."""
        data = await read_body(request, limit, self.s.upload_idle_timeout, self.s.upload_min_rate)
        if not self.m.job_dir(job_id).exists():
            raise FileNotFoundError(job_id)  # deleted while the body arrived (see image())
        img = await self.m.decoder.decode(
            data,
            f"image {index}",
            max_bytes=2 * spec.image_nbytes + (1 << 20),
            shape=spec.image_shape,
            dtype=spec.dtype,
        )
        del data

        def write(st: JobStore) -> None:
            st.write_image(index, img)

        await self.m.upload_image(job_id, index, write)

    async def mask(self, request: Request, job_id: str) -> None:
        """Store the object mask from the request body: PNG (non-zero = object) or raw H*W bytes."""
        spec = self.before_upload(request, job_id, "the mask can be set")
        HW = spec.height * spec.width
        with self.m.uploads.take(user_of(request).name), self.m.disk.hold(2 * HW, "the mask"):
            data = await read_body(
                request, 2 * HW + (1 << 20), self.s.upload_idle_timeout, self.s.upload_min_rate
            )
            if is_raw(request):
                if len(data) != HW:
                    raise InvalidInputError(
                        f"mask: got {len(data)} bytes, expected {HW} (one byte per pixel, non-zero = "
                        "object); for a PNG or TIFF file send Content-Type: image/png or image/tiff"
                    )
                mask = np.frombuffer(data, dtype=np.uint8).reshape(spec.height, spec.width) > 0
            else:  # header checked first (a small file cannot declare a huge mask); decoded in a thread
                m = await self.m.decoder.decode(
                    data, "mask", max_bytes=4 * 4 * HW + (1 << 20), hw=(spec.height, spec.width)
                )
                mask = mask_of(m)
            del data
            await self.m.upload_mask(job_id, mask)
