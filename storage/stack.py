"""A dataset's stack, decoded on threads in the background, held only where the mask is.

``maxfs run`` starts one as soon as the folder is open, so that decoding (PNG and TIFF
decoders release the GIL) overlaps with importing the solver and creating the store; numpy
and hashlib only, so starting it costs nothing of that import.

Only the mask's bounding box of each image is kept (:class:`HeldStack`): a tile reads
images only where it has masked pixels, and so does every other reader of a run (the eps
sample and the calibration checks pick masked pixels), so the rest of the frame is never
needed. Each image's digest is still of the whole image, as the store records it.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.datasets import Dataset
from maxfs.storage.digests import DIGEST, array_digest
from maxfs.storage.tiles import Tile


def mask_box(mask: NDArray[np.bool_] | None, height: int, width: int) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)``: the smallest window that holds every pixel of ``mask`` (the whole
    frame without a mask, or with an empty one, which a run refuses later with its own error)."""
    if mask is None or not mask.any():
        return 0, height, 0, width
    ys, xs = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1


@dataclass(frozen=True)
class HeldStack:
    """The images ``(k, H, W[, C])`` of a frame ``height x width``, held over the window
    ``box = (y0, y1, x0, x1)`` only (``data``: ``(k, y1 - y0, x1 - x0[, C])``)."""

    data: NDArray
    box: tuple[int, int, int, int]
    height: int
    width: int

    def window(self, y0: int, y1: int, x0: int, x1: int) -> NDArray:
        """The images over rows ``y0:y1`` and columns ``x0:x1`` of the frame: a view where the
        window lies inside the held box, else a copy that is 0 outside it (pixels no mask
        selects, which nothing solves)."""
        by0, by1, bx0, bx1 = self.box
        if by0 <= y0 and y1 <= by1 and bx0 <= x0 and x1 <= bx1:
            return self.data[:, y0 - by0 : y1 - by0, x0 - bx0 : x1 - bx0]
        out = np.zeros((self.data.shape[0], y1 - y0, x1 - x0, *self.data.shape[3:]), self.data.dtype)
        oy0, oy1, ox0, ox1 = max(y0, by0), min(y1, by1), max(x0, bx0), min(x1, bx1)
        if oy0 < oy1 and ox0 < ox1:
            held = self.data[:, oy0 - by0 : oy1 - by0, ox0 - bx0 : ox1 - bx0]
            out[:, oy0 - y0 : oy1 - y0, ox0 - x0 : ox1 - x0] = held
        return out

    def tile(self, t: Tile) -> NDArray:
        """The images of tile ``t`` (``(k, h, w[, C])``), as :meth:`window`."""
        return self.window(t.y0, t.y1, t.x0, t.x1)


class StackReader:
    """Decode every image of ``ds`` on ``threads`` threads into a :class:`HeldStack` over the
    mask's box, with each whole image's digest (:func:`storage.digests.array_digest` of
    ``digest``: a new store's hash unless the store is known to record another)."""

    def __init__(self, ds: Dataset, threads: int, digest: str = DIGEST) -> None:
        self.digest = digest
        self.box = mask_box(ds.mask, ds.height, ds.width)
        y0, y1, x0, x1 = self.box
        shape = (y1 - y0, x1 - x0) if ds.channels is None else (y1 - y0, x1 - x0, ds.channels)
        self.images: NDArray = np.empty((ds.k, *shape), dtype=ds.dtype)
        self.digests: list[bytes] = [b""] * ds.k
        self._ds = ds
        self._pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="maxfs-read")
        self._futures: list[Future[None]] = [self._pool.submit(self._one, i) for i in range(ds.k)]

    def _one(self, i: int) -> None:
        img = self._ds.read(i)
        y0, y1, x0, x1 = self.box
        self.images[i] = img[y0:y1, x0:x1]
        self.digests[i] = array_digest(img, self.digest)

    def result(self) -> tuple[HeldStack, list[bytes]]:
        """The held stack and the digests, once every image is decoded (the first error is raised)."""
        try:
            for f in self._futures:
                f.result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)
        return HeldStack(self.images, self.box, self._ds.height, self._ds.width), self.digests

    def cancel(self) -> None:
        """Stop decoding (images not started are skipped) and wait for the ones running."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> StackReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()
