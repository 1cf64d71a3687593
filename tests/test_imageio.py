"""Image bodies: honest files of every format decode within the server's bound; bombs do not.

The server lets a PNG/TIFF/other body decode to at most ``2 * image_nbytes + 1 MiB``
(``service``'s upload route); the header's estimate of the decoded size must therefore be
close to the real one, or honest camera frames are refused as too large.
"""

from __future__ import annotations

import io

import imagecodecs
import numpy as np
import pytest
import tifffile
from PIL import Image

from maxfs.storage.errors import InvalidInputError, PayloadTooLargeError
from maxfs.storage.imageio import decode_checked, probe_bytes


def _encode(fmt: str, a: np.ndarray) -> bytes:
    if fmt == "PNG":
        return imagecodecs.png_encode(a)
    if fmt == "TIFF":
        b = io.BytesIO()
        tifffile.imwrite(b, a, compression="deflate")
        return b.getvalue()
    b = io.BytesIO()
    Image.fromarray(a).save(b, format=fmt)
    return b.getvalue()


CASES = [
    ("PNG", (1024, 1024), np.uint8),
    ("PNG", (600, 600), np.uint16),
    ("PNG", (640, 512, 3), np.uint8),
    ("PNG", (512, 512, 3), np.uint16),
    ("TIFF", (700, 700), np.uint16),
    ("BMP", (700, 700), np.uint8),
    ("BMP", (1024, 1024, 3), np.uint8),
    ("JPEG", (1024, 1024), np.uint8),
    ("JPEG", (512, 640, 3), np.uint8),
]


@pytest.mark.parametrize(("fmt", "shape", "dtype"), CASES, ids=lambda v: str(getattr(v, "__name__", v)))
def test_honest_images_decode_within_the_server_bound(fmt: str, shape: tuple[int, ...], dtype) -> None:
    a = (np.random.default_rng(1).random(shape) * 200).astype(dtype)
    data = _encode(fmt, a)
    bound = 2 * a.nbytes + (1 << 20)
    head = probe_bytes(data)
    assert head.decoded_bytes <= bound
    got = decode_checked(data, "image 0", max_bytes=bound, shape=shape, dtype=dtype)
    assert got.shape == shape and got.dtype == dtype
    if fmt != "JPEG":  # lossless formats give the pixels back
        np.testing.assert_array_equal(got, a)


def test_a_bomb_is_refused_from_its_header() -> None:
    small = imagecodecs.png_encode(np.zeros((8, 8), np.uint8))
    # an honest header for the 8 x 8 image, then one that declares 30000 x 30000
    bomb = bytearray(imagecodecs.png_encode(np.zeros((30000, 1), np.uint8)))
    bomb[16:24] = (30000).to_bytes(4, "big") * 2
    with pytest.raises(InvalidInputError, match="shape"):
        decode_checked(bytes(bomb), "image 0", max_bytes=1 << 20, shape=(8, 8))
    with pytest.raises(PayloadTooLargeError, match="decoding would take"):
        decode_checked(bytes(bomb), "image 0", max_bytes=1 << 20)
    assert decode_checked(small, "image 0", max_bytes=1 << 20, shape=(8, 8)).shape == (8, 8)


def test_mask_images_follow_non_zero_is_object() -> None:
    from maxfs.service.http.guards import mask_of

    m = np.array([[0.0, -1.0], [np.nan, 0.5]], np.float32)
    np.testing.assert_array_equal(mask_of(m), [[False, True], [False, True]])
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[1, 0, 2] = 7
    np.testing.assert_array_equal(mask_of(rgb), [[False, False], [True, False]])
