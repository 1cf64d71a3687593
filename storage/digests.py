"""Digests of input arrays: what makes a store's inputs recognisable (numpy and hashlib only,
so a reader can digest images while the heavier modules are still being imported).

A store records which hash its input digests use (:data:`DIGEST` for new stores); stores of
format 4 record none and used :data:`LEGACY_DIGEST`. Both are 32 bytes.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Size of every input digest.
DIGEST_BYTES = 32
#: The hash of new stores' input digests: SHA-256, which hashlib runs on the CPU's SHA extensions
#: where it has them (x86 since 2017-2019, ARMv8): half BLAKE2b's CPU on the reference machine
#: (0.10 against 0.19 s for 96 16-bit 612 x 512 RGB images).
DIGEST = "sha256"
#: The hash of stores that record none (format 4).
LEGACY_DIGEST = "blake2b"
#: Every hash a store may record, with its name in the store's descriptions.
DIGESTS: dict[str, str] = {"sha256": "SHA-256", "blake2b": "BLAKE2b-256"}


def new_hash(algorithm: str) -> Any:
    """A fresh hashlib object of ``algorithm`` (a key of :data:`DIGESTS`), DIGEST_BYTES long."""
    if algorithm == "sha256":
        return hashlib.sha256()
    if algorithm == "blake2b":
        return hashlib.blake2b(digest_size=DIGEST_BYTES)
    raise ValueError(f"unknown input digest {algorithm!r}; this maxfs knows {', '.join(DIGESTS)}")


class ArrayHasher:
    """The ``algorithm`` digest of an array's shape, dtype and little-endian C-order bytes, fed in
    consecutive row bands, so a digest is made while the bands are written."""

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype | str, algorithm: str) -> None:
        self.dtype = np.dtype(dtype).newbyteorder("<")
        self.h = new_hash(algorithm)
        self.h.update(f"{tuple(shape)}|{self.dtype.str}|".encode())

    def update(self, band: NDArray[Any]) -> None:
        a = np.ascontiguousarray(band).astype(self.dtype, copy=False)
        self.h.update(memoryview(a.reshape(-1)).cast("B"))

    def digest(self) -> bytes:
        return self.h.digest()


def array_digest(arr: NDArray[Any], algorithm: str) -> bytes:
    """The :class:`ArrayHasher` digest of a whole array."""
    h = ArrayHasher(arr.shape, arr.dtype, algorithm)
    h.update(arr)
    return h.digest()
