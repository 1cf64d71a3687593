"""Digests of input arrays: what makes a store's inputs recognisable (numpy and hashlib only,
so a reader can digest images while the heavier modules are still being imported)."""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: BLAKE2b digest size of every input digest.
DIGEST_BYTES = 32


class ArrayHasher:
    """BLAKE2b-256 of an array's shape, dtype and little-endian C-order bytes, fed in
    consecutive row bands, so a digest is made while the bands are written."""

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype | str) -> None:
        self.dtype = np.dtype(dtype).newbyteorder("<")
        self.h = hashlib.blake2b(digest_size=DIGEST_BYTES)
        self.h.update(f"{tuple(shape)}|{self.dtype.str}|".encode())

    def update(self, band: NDArray[Any]) -> None:
        a = np.ascontiguousarray(band).astype(self.dtype, copy=False)
        self.h.update(memoryview(a.reshape(-1)).cast("B"))

    def digest(self) -> bytes:
        return self.h.digest()


def array_digest(arr: NDArray[Any]) -> bytes:
    """The :class:`ArrayHasher` digest of a whole array."""
    h = ArrayHasher(arr.shape, arr.dtype)
    h.update(arr)
    return h.digest()
