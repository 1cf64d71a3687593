"""A dataset's whole stack, decoded on threads in the background.

``maxfs run`` starts one as soon as the folder is open, so that decoding (PNG and TIFF
decoders release the GIL) overlaps with importing the solver and creating the store; numpy
and hashlib only, so starting it costs nothing of that import.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.datasets import Dataset
from maxfs.storage.digests import array_digest


class StackReader:
    """Decode every image of ``ds`` into one ``(k, H, W[, C])`` array on ``threads`` threads,
    with each image's digest (:func:`storage.digests.array_digest`)."""

    def __init__(self, ds: Dataset, threads: int) -> None:
        shape = (ds.height, ds.width) if ds.channels is None else (ds.height, ds.width, ds.channels)
        self.images: NDArray = np.empty((ds.k, *shape), dtype=ds.dtype)
        self.digests: list[bytes] = [b""] * ds.k
        self._ds = ds
        self._pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="maxfs-read")
        self._futures: list[Future[None]] = [self._pool.submit(self._one, i) for i in range(ds.k)]

    def _one(self, i: int) -> None:
        self.images[i] = self._ds.read(i)
        self.digests[i] = array_digest(self.images[i])

    def result(self) -> tuple[NDArray, list[bytes]]:
        """The stack and its digests, once every image is decoded (the first error is raised)."""
        try:
            for f in self._futures:
                f.result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)
        return self.images, self.digests

    def cancel(self) -> None:
        """Stop decoding (images not started are skipped) and wait for the ones running."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> StackReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()
