"""Decoding image files and bytes into arrays, faithfully (8/16-bit, grey/RGB).

Pillow truncates 16-bit RGB PNG to 8 bits and cannot read RGB48 TIFF, so PNG goes
through imagecodecs and TIFF through tifffile; Pillow reads the rest (TGA, BMP, JPEG).
"""

from __future__ import annotations

import io
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import imagecodecs
import numpy as np
from numpy.typing import NDArray
from PIL import Image, UnidentifiedImageError

from maxfs.storage.errors import InvalidInputError, PayloadTooLargeError
from maxfs.storage.options import DTYPES, MAX_PIXELS

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
    if str(arr.dtype) not in DTYPES:
        if np.issubdtype(arr.dtype, np.floating):
            arr = arr.astype(np.float32)
        else:
            raise InvalidInputError(f"{what}: unsupported pixel type {arr.dtype}; use 8/16-bit or float32")
    return np.ascontiguousarray(arr)


#: Most bytes one local image may decode to (MAX_PIXELS of RGB float32).
MAX_DECODED_BYTES = MAX_PIXELS * 3 * 4


def decode_bytes(data: bytes, what: str = "image") -> NDArray:
    """Decode PNG, TIFF, TGA, BMP or JPEG bytes (detected by content), with the checks of
    :func:`decode_checked` and the local limits (:data:`MAX_PIXELS`)."""
    return decode_checked(data, what, max_bytes=MAX_DECODED_BYTES, max_pixels=MAX_PIXELS)


@dataclass(frozen=True)
class ImageHeader:
    """What an encoded image declares, read from its header without decoding any pixel."""

    format: str  # "PNG", "TIFF" or Pillow's format name
    shape: tuple[int, ...]  # as :func:`decode_bytes` returns it: (H, W) or (H, W, 3)
    dtype: np.dtype  # ditto (float TIFFs become float32)
    pages: int  # images in the file (TIFF pages, animation frames)
    decoded_bytes: int  # what the decoder allocates, before alpha is dropped


def _normal_shape(shape: tuple[int, ...]) -> tuple[int, ...]:
    """:func:`_normalise`'s shape rule, on a shape."""
    if len(shape) == 3 and shape[2] in (1, 2):
        return shape[:2]
    if len(shape) == 3 and shape[2] == 4:
        return (*shape[:2], 3)
    return tuple(shape)


def _normal_dtype(dtype: np.dtype, what: str) -> np.dtype:
    if dtype in (np.uint8, np.uint16, np.float32):
        return np.dtype(dtype)
    if np.issubdtype(dtype, np.floating):
        return np.dtype(np.float32)
    raise InvalidInputError(f"{what}: unsupported pixel type {dtype}; use 8/16-bit or float32")


#: Pillow modes that :func:`_pil_array` returns as 16-bit or float (the rest as 8-bit).
_PIL_DTYPES = {"I;16": np.uint16, "I;16B": np.uint16, "I;16L": np.uint16, "I": np.uint16, "F": np.float32}
#: PNG colour type -> channels the decoder returns (palette images come out RGB, or RGBA with tRNS).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 4, 4: 2, 6: 4}


def _reason(e: Exception) -> str:
    """A decoder's complaint for a user: no object reprs (``<_io.BytesIO object at 0x...>``)."""
    if isinstance(e, UnidentifiedImageError):
        return "not a PNG, TIFF, BMP, JPEG or other image file that maxfs reads"
    text = re.sub(r"<[^<>]* at 0x[0-9a-fA-F]+>", "the data", str(e))
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def probe_bytes(data: bytes, what: str = "image") -> ImageHeader:
    """The header of PNG, TIFF or Pillow-readable bytes: size, pixel type and page count.

    Nothing is decompressed, so a small file that declares a huge image (a decompression
    bomb) costs nothing here; compare the header with what is expected before decoding.
    """
    try:
        if data.startswith(PNG_MAGIC):
            if len(data) < 33 or data[12:16] != b"IHDR":
                raise ValueError("no IHDR chunk after the PNG signature")
            w, h = struct.unpack(">II", data[16:24])
            depth, colour = data[24], data[25]
            if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16):
                raise ValueError(f"bit depth {depth} with colour type {colour} is not valid PNG")
            c = _PNG_CHANNELS[colour] if colour != 3 else 3
            dtype = np.dtype(np.uint16 if depth == 16 else np.uint8)
            raw = (h, w) if c == 1 else (h, w, c)
            # what the decoder allocates: the channels it returns (palette: RGBA at most)
            n = h * w * _PNG_CHANNELS[colour] * dtype.itemsize
            return ImageHeader("PNG", _normal_shape(raw), dtype, 1, n)
        if data[:4] in TIFF_MAGICS:
            import tifffile  # only for TIFF input (90 ms to import)

            with tifffile.TiffFile(io.BytesIO(data)) as tif:
                pages = len(tif.pages)
                page = tif.pages.first
                raw, dt = tuple(int(n) for n in page.shape), np.dtype(page.dtype)
            n = int(np.prod(raw)) * dt.itemsize
            return ImageHeader("TIFF", _normal_shape(raw), _normal_dtype(dt, what), pages, n)
        with Image.open(io.BytesIO(data)) as im:
            w, h = im.size
            mode, frames, fmt = im.mode, int(getattr(im, "n_frames", 1)), str(im.format)
        dtype = np.dtype(_PIL_DTYPES.get(mode, np.uint8))
        raw = {"L": (h, w), "LA": (h, w, 2), "RGBA": (h, w, 4)}.get(mode, (h, w, 3))
        if dtype != np.uint8:
            raw = (h, w)
        return ImageHeader(fmt, _normal_shape(raw), dtype, frames, h * w * _pil_bytes_per_pixel(mode))
    except InvalidInputError:
        raise
    except Exception as e:  # readers raise many types for corrupt headers
        raise InvalidInputError(f"{what}: cannot decode image ({_reason(e)})") from None


def decode_checked(
    data: bytes,
    what: str,
    *,
    max_bytes: int,
    shape: tuple[int, ...] | None = None,
    hw: tuple[int, int] | None = None,
    dtype: str | np.dtype | None = None,
    max_pixels: int | None = None,
) -> NDArray:
    """Decode one image only if its header fits: one page, ``shape`` (or height and width
    ``hw``), ``dtype``, at most ``max_pixels`` pixels and ``max_bytes`` decoded. The one
    reader of encoded images, for the server's uploads and the local loaders alike. A mismatch
    is refused before any pixel is decompressed; the decoder's answer is checked against the
    header again."""
    head = probe_bytes(data, what)
    if head.pages != 1:
        raise InvalidInputError(f"{what}: the file holds {head.pages} images (pages or frames); send one")
    if shape is not None and head.shape != tuple(shape):
        raise InvalidInputError(f"{what} has shape {head.shape}, the job expects {tuple(shape)}")
    if hw is not None and head.shape[:2] != tuple(hw):
        raise InvalidInputError(f"{what} has shape {head.shape}, the job's images are {hw[0]} x {hw[1]}")
    if dtype is not None and head.dtype != np.dtype(dtype):
        raise InvalidInputError(f"{what} has dtype {head.dtype}, the job expects {np.dtype(dtype)}")
    if max_pixels is not None and head.shape[0] * head.shape[1] > max_pixels:
        raise PayloadTooLargeError(
            f"{what} declares {head.shape[0]} x {head.shape[1]} pixels, more than the {max_pixels} "
            "allowed per image; crop or bin it"
        )
    if head.decoded_bytes > max_bytes:
        raise PayloadTooLargeError(
            f"{what}: decoding would take {head.decoded_bytes} bytes, more than the {max_bytes} allowed"
        )
    arr = _normalise(_decode_raw(data, head, what), what)
    if arr.shape != head.shape or arr.dtype != head.dtype:
        raise InvalidInputError(
            f"{what}: decoded to {arr.shape} {arr.dtype}, but its header says {head.shape} {head.dtype}"
        )
    return arr


def _decode_raw(data: bytes, head: ImageHeader, what: str) -> NDArray:
    """The decoder's array of checked bytes, alpha channel and all."""
    try:
        if head.format == "PNG":
            arr = imagecodecs.png_decode(data)
        elif head.format == "TIFF":
            import tifffile  # only for TIFF input (90 ms to import)

            with tifffile.TiffFile(io.BytesIO(data)) as tif:
                arr = tif.pages.first.asarray()
        else:
            with Image.open(io.BytesIO(data)) as im:
                im.load()
                arr = _pil_array(im)
    except Exception as e:  # decoders raise many types for corrupt data
        raise InvalidInputError(f"{what}: cannot decode image ({_reason(e)})") from None
    return np.asarray(arr)


def _pil_bytes_per_pixel(mode: str) -> int:
    """Bytes per pixel Pillow holds decoding an image of ``mode``, with the RGB copy
    :func:`_pil_array` makes of modes it does not return as they are."""
    try:
        bands = Image.getmodebands(mode)
    except (KeyError, ValueError):
        return 16  # an unknown mode: assume the worst Pillow has (4 bands of 32 bits)
    per_band = {"I;16": 2, "I;16B": 2, "I;16L": 2, "I": 4, "F": 4}.get(mode, 1)
    convert = 0 if mode in ("L", "RGB", "RGBA", "LA", *_PIL_DTYPES) else 3
    return bands * per_band + convert


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


def _file_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InvalidInputError(f"image file {path} does not exist") from None
    except OSError as e:
        raise InvalidInputError(f"cannot read image file {path}: {e}") from None


def read_image(path: Path) -> NDArray:
    """Read an image file (see :func:`decode_bytes`: its header is checked before decoding)."""
    path = Path(path)
    return decode_bytes(_file_bytes(path), what=str(path))


def read_mask_plane(path: Path) -> NDArray:
    """A mask file as one (H, W) plane: the maximum of its colour channels, or its alpha channel
    where the colour is all zero and the alpha varies (a mask painted as transparency over black,
    which :func:`read_image` would read as empty since it drops alpha)."""
    path = Path(path)
    data = _file_bytes(path)
    img = decode_bytes(data, what=str(path))  # the header and size checks of any image
    plane = img.max(axis=2) if img.ndim == 3 else img
    if plane.any():
        return plane
    raw = _decode_raw(data, probe_bytes(data, str(path)), str(path))
    if raw.ndim == 3 and raw.shape[2] in (2, 4) and raw[..., -1].min() != raw[..., -1].max():
        return np.ascontiguousarray(raw[..., -1])
    return plane


def load_npy(path: Path, what: str = "") -> NDArray:
    """An NPY file's array, never its pickled objects: a file that holds Python objects, or
    is no NPY at all, is an :class:`InvalidInputError` saying so (not a traceback)."""
    path = Path(path)
    what = what or str(path)
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InvalidInputError(f"{what}: no such file") from None
    except ValueError as e:
        if "allow_pickle" in str(e):
            raise InvalidInputError(
                f"{what} holds Python objects (a pickled array), which are never loaded: they can run "
                "code. Save a plain numeric array (np.save of a float or integer array)"
            ) from None
        raise InvalidInputError(f"{what} is not a readable NPY file ({e})") from None
    except (OSError, EOFError) as e:
        raise InvalidInputError(f"{what} is not a readable NPY file ({e})") from None


def encode_png(arr: NDArray, level: int | None = None) -> bytes:
    """PNG bytes of an (H, W) or (H, W, 3) uint8/uint16 array; ``level``: zlib's compression
    level (default: the encoder's)."""
    a = np.ascontiguousarray(arr)
    return bytes(imagecodecs.png_encode(a) if level is None else imagecodecs.png_encode(a, level=level))
