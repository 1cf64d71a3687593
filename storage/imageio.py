"""Decoding image files and bytes into arrays, faithfully (8/16-bit, grey/RGB).

Pillow truncates 16-bit RGB PNG to 8 bits and cannot read RGB48 TIFF, so PNG goes
through imagecodecs and TIFF through tifffile; Pillow reads the rest (TGA, BMP, JPEG).
"""

from __future__ import annotations

import io
from pathlib import Path

import imagecodecs
import numpy as np
import tifffile
from numpy.typing import NDArray
from PIL import Image

from worker.errors import InvalidInputError

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def _normalise(arr: NDArray, what: str) -> NDArray:
    """Drop alpha; keep (H, W) grey or (H, W, 3) colour; reject other shapes."""
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim == 3 and arr.shape[2] == 4:
        arr = arr[..., :3]
    if arr.ndim == 3 and arr.shape[2] == 2:  # grey + alpha
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise InvalidInputError(f"{what}: expected a grey or RGB image, got array shape {arr.shape}")
    if arr.dtype not in (np.uint8, np.uint16, np.float32):
        if np.issubdtype(arr.dtype, np.floating):
            arr = arr.astype(np.float32)
        else:
            raise InvalidInputError(f"{what}: unsupported pixel type {arr.dtype}; use 8/16-bit or float32")
    return np.ascontiguousarray(arr)


def decode_bytes(data: bytes, what: str = "image") -> NDArray:
    """Decode PNG, TIFF, TGA, BMP or JPEG bytes (detected by content)."""
    try:
        if data.startswith(PNG_MAGIC):
            arr = imagecodecs.png_decode(data)
        elif data[:4] in TIFF_MAGICS:
            arr = tifffile.imread(io.BytesIO(data))
        else:
            with Image.open(io.BytesIO(data)) as im:
                im.load()
                arr = _pil_array(im)
    except InvalidInputError:
        raise
    except Exception as e:  # decoders raise many types for corrupt data
        raise InvalidInputError(f"{what}: cannot decode image ({type(e).__name__}: {e})") from None
    return _normalise(np.asarray(arr), what)


def _pil_array(im: Image.Image) -> NDArray:
    if im.mode in ("I;16", "I;16B", "I;16L"):
        return np.asarray(im, dtype=np.uint16)
    if im.mode == "I":
        return np.asarray(im).astype(np.uint16)
    if im.mode == "F":
        return np.asarray(im, dtype=np.float32)
    if im.mode not in ("L", "RGB", "RGBA", "LA"):
        im = im.convert("RGB")
    return np.asarray(im)


def read_image(path: Path) -> NDArray:
    """Read an image file (see :func:`decode_bytes`)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InvalidInputError(f"image file {path} does not exist") from None
    except OSError as e:
        raise InvalidInputError(f"cannot read image file {path}: {e}") from None
    return decode_bytes(data, what=str(path))


def encode_png(arr: NDArray) -> bytes:
    """PNG bytes of an (H, W) or (H, W, 3) uint8/uint16 array."""
    return bytes(imagecodecs.png_encode(np.ascontiguousarray(arr)))
