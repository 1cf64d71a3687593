"""Reading the input folders labs already have, one loader for all layouts.

Layouts (detected in this order):

* **DiLiGenT**: ``filenames.txt``, ``light_directions.txt`` (k x 3),
  optional ``light_intensities.txt`` (k x 3 RGB), optional ``mask.png``;
  8/16-bit PNG or TIFF, grey or RGB.
* **NPY stack**: ``images.npy`` (k, H, W[, C]) plus ``lights.txt`` or
  ``lights.npy`` (k x 3); optional ``mask.npy``/``mask.png`` and
  ``intensities.txt``/``intensities.npy``.
* **UW psm** (CSE 455 ``psmImages``): the object folder ``OBJ/`` whose parent
  holds ``lights.txt`` (a count line, then k directions) and ``OBJ.txt`` (a count
  line, then the image paths, then the mask path; paths may start with
  ``psmImages/``); ``OBJ.mask.tga`` is a soft mask, thresholded at 128.

Images are read one at a time (:meth:`Dataset.read`), never as a whole stack.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.errors import DatasetError, InvalidInputError
from maxfs.storage.imageio import load_npy
from maxfs.storage.imageio import read_image as _decode_file
from maxfs.storage.options import DTYPES, check_lights


@dataclass(frozen=True)
class Dataset:
    """A photometric stereo dataset on disk, read lazily."""

    name: str
    layout: str
    k: int
    height: int
    width: int
    channels: int | None
    dtype: str
    lights: NDArray[np.float64]
    intensities: NDArray[np.float64] | None
    mask: NDArray[np.bool_] | None
    _reader: Callable[[int], NDArray]
    #: Files the dataset is read from (images, mask, lights): their fingerprint lets a
    #: re-run recognise unchanged inputs without decoding them again.
    files: tuple[Path, ...] = ()
    #: What looks wrong about the folder's calibration files (:func:`folder_notes`): an expected
    #: file missing, or text files the layout does not read (a misnamed intensities file).
    notes: tuple[str, ...] = ()
    #: How the user knows image ``i``: "image 10 (010.png)", numbered from 1 like ``--images``
    #: (empty: "image N" alone, for stacks in one file).
    image_labels: tuple[str, ...] = ()

    def label(self, i: int) -> str:
        """Image ``i`` (0-based) as the user knows it: 1-based number and file name."""
        return self.image_labels[i] if i < len(self.image_labels) else f"image {i + 1}"

    @property
    def nbytes(self) -> int:
        """Bytes of the whole stack in memory."""
        return self.k * self.height * self.width * (self.channels or 1) * np.dtype(self.dtype).itemsize

    def fingerprint(self) -> str | None:
        """Digest of the listed files' paths, sizes and modification times (None without files)."""
        if not self.files:
            return None
        h = hashlib.sha256()
        for p in self.files:
            try:
                st = Path(p).stat()
            except OSError:
                return None
            h.update(f"{Path(p).resolve()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
        return h.hexdigest()

    def read(self, i: int) -> NDArray:
        """Image ``i`` as stored (uint8/uint16/float32; (H, W) or (H, W, 3))."""
        img = self._reader(i)
        expect = (
            (self.height, self.width) if self.channels is None else (self.height, self.width, self.channels)
        )
        if img.shape != expect:
            raise DatasetError(
                f"{self.name}: {self.label(i)} has shape {img.shape} but {self.label(0)} has {expect}; "
                "all images must have the same size"
            )
        if str(img.dtype) != self.dtype:
            raise DatasetError(
                f"{self.name}: {self.label(i)} is {img.dtype} but {self.label(0)} is {self.dtype}"
            )
        return img


def read_image(path: Path) -> NDArray:
    """An image file of a dataset; unreadable files are :class:`DatasetError`."""
    try:
        return _decode_file(path)
    except DatasetError:
        raise
    except InvalidInputError as e:
        raise DatasetError(str(e)) from None


def _inside(root: Path, name: str, listing: Path) -> Path:
    """``root / name``, refusing names that are absolute or climb out with ``..``."""
    p = Path(name)
    if p.is_absolute() or ".." in p.parts:
        raise DatasetError(
            f"{listing}: entry {name!r} points outside the dataset folder; list images by paths "
            "relative to it, without '..'"
        )
    return root / p


def _read_matrix(path: Path, cols: int, what: str, count_line: bool = False) -> NDArray[np.float64]:
    try:
        lines = [ln for ln in path.read_text().split("\n") if ln.strip()]
    except FileNotFoundError:
        raise DatasetError(f"missing {what}: {path}") from None
    if count_line:
        try:
            n = int(lines[0].split()[0])
        except (IndexError, ValueError):
            raise DatasetError(f"{path}: first line must be the number of rows") from None
        lines = lines[1:]
        if len(lines) != n:
            raise DatasetError(f"{path}: says {n} rows but has {len(lines)}")
    try:
        arr = np.array([[float(v) for v in ln.replace(",", " ").split()] for ln in lines])
    except ValueError as e:
        raise DatasetError(f"{path}: not a table of numbers ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise DatasetError(f"{path}: expected {cols} numbers per line, got shape {arr.shape}")
    return arr


def _lights(arr: NDArray[np.float64], k: int, where: Path) -> NDArray[np.float64]:
    if arr.shape[0] != k:
        raise DatasetError(f"{where}: {arr.shape[0]} light directions for {k} images; give one per image")
    try:
        return check_lights(arr, k)
    except InvalidInputError as e:
        raise DatasetError(f"{where}: {e}") from None


def _mask_from(path: Path) -> NDArray[np.bool_]:
    m = read_image(path)
    if m.ndim == 3:
        m = m.max(axis=2)
    thresh = 0.5 if m.dtype == np.float32 else np.iinfo(m.dtype).max / 2
    return m > thresh


def _existing(paths: list[Path], folder: Path, *names: str) -> tuple[Path, ...]:
    """``paths`` plus those of ``names`` in ``folder`` that exist."""
    return (*paths, *(folder / n for n in names if (folder / n).exists()))


#: Text files no layout reads but a dataset folder may well hold.
_HARMLESS_TEXT = ("readme", "license", "licence", "notes", "citation")


def folder_notes(folder: Path, known: tuple[str, ...], expected: tuple[str, ...] = ()) -> tuple[str, ...]:
    """Calibration files that look wrong in ``folder``: ``*.txt`` files the layout does not read
    (``known`` are those it reads; a README or LICENSE is fine) and ``expected`` files missing."""
    notes = []
    for n in expected:
        if not (folder / n).is_file():
            notes.append(
                f"{folder.name} has no {n}: every light is taken as equally bright; the DiLiGenT layout "
                f"gives each light's intensity there (k lines of R G B); add it unless the lights "
                "really are equal"
            )
    unknown = sorted(
        p.name
        for p in folder.glob("*.txt")
        if p.name not in known and not p.name.lower().startswith(_HARMLESS_TEXT)
    )
    if unknown:
        notes.append(
            f"{folder.name} holds {', '.join(unknown)}, which maxfs does not read (it reads "
            f"{', '.join(known)}); if it holds light intensities or directions, rename it"
        )
    return tuple(notes)


def labels(paths: list[Path]) -> tuple[str, ...]:
    """``image N (file name)`` for each of ``paths``, N from 1 (see :meth:`Dataset.label`)."""
    return tuple(f"image {i + 1} ({p.name})" for i, p in enumerate(paths))


def _probe(name: str, layout: str, k: int, reader: Callable[[int], NDArray], **kw) -> Dataset:
    first = reader(0)
    h, w = first.shape[:2]
    ch = None if first.ndim == 2 else first.shape[2]
    mask = kw.pop("mask", None)
    if mask is not None and mask.shape != (h, w):
        raise DatasetError(f"{name}: mask is {mask.shape[0]} x {mask.shape[1]} but images are {h} x {w}")
    return Dataset(name, layout, k, h, w, ch, str(first.dtype), _reader=reader, mask=mask, **kw)


#: The text files of the DiLiGenT layout.
DILIGENT_TEXT = ("filenames.txt", "light_directions.txt", "light_intensities.txt")


def diligent(folder: Path) -> Dataset:
    names = [ln.strip() for ln in (folder / "filenames.txt").read_text().splitlines() if ln.strip()]
    if len(names) < 3:
        raise DatasetError(f"{folder}/filenames.txt lists {len(names)} images; at least 3 are needed")
    paths = [_inside(folder, n, folder / "filenames.txt") for n in names]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise DatasetError(f"{folder}: {len(missing)} listed images are missing, e.g. {missing[0]}")
    lights = _lights(_read_matrix(folder / "light_directions.txt", 3, "light directions"), len(paths), folder)
    inten = None
    if (folder / "light_intensities.txt").exists():
        inten = _read_matrix(folder / "light_intensities.txt", 3, "light intensities")
        if inten.shape[0] != len(paths):
            raise DatasetError(f"{folder}: {inten.shape[0]} light intensities for {len(paths)} images")
    mask = _mask_from(folder / "mask.png") if (folder / "mask.png").exists() else None
    ds = _probe(
        folder.name,
        "diligent",
        len(paths),
        lambda i: read_image(paths[i]),
        lights=lights,
        intensities=inten,
        mask=mask,
        files=_existing(paths, folder, "mask.png", "light_directions.txt", "light_intensities.txt"),
        notes=folder_notes(folder, DILIGENT_TEXT, expected=("light_intensities.txt",)),
        image_labels=labels(paths),
    )
    if inten is not None and ds.channels is None:
        # grey images with RGB intensities: use their mean
        ds = Dataset(**{**ds.__dict__, "intensities": inten.mean(axis=1, keepdims=True)})
    return ds


class _NpyImages:
    """Images of an ``images.npy`` stack, read one at a time with plain file reads.

    Not a memory map: mapped pages of a large stack count toward the reader's
    resident memory, which would then grow with k.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            with open(path, "rb") as f:
                version = np.lib.format.read_magic(f)
                read_header = {
                    (1, 0): np.lib.format.read_array_header_1_0,
                    (2, 0): np.lib.format.read_array_header_2_0,
                }.get(version)
                if read_header is None:
                    raise ValueError(f"NPY format version {version} is not supported; save with np.save")
                shape, fortran, dtype = read_header(f)
                self.offset = f.tell()
        except (ValueError, OSError) as e:
            raise DatasetError(f"{path} is not a readable NPY file: {e}") from None
        if fortran:
            raise DatasetError(f"{path} is stored in Fortran order; save it with np.save(C-ordered array)")
        self.shape, self.dtype, self.ndim = tuple(shape), np.dtype(dtype), len(shape)

    def __getitem__(self, i: int) -> NDArray:
        count = int(np.prod(self.shape[1:]))
        with open(self.path, "rb") as f:
            f.seek(self.offset + i * count * self.dtype.itemsize)
            img = np.fromfile(f, dtype=self.dtype, count=count)
        if img.size != count:
            raise DatasetError(f"{self.path} is truncated: image {i + 1} is incomplete")
        return img.reshape(self.shape[1:])


def npy_stack(folder: Path) -> Dataset:
    stack = _NpyImages(folder / "images.npy")
    if stack.ndim not in (3, 4) or (stack.ndim == 4 and stack.shape[3] != 3):
        raise DatasetError(f"{folder}/images.npy must be (k, H, W) or (k, H, W, 3), got {stack.shape}")
    if str(stack.dtype) not in DTYPES:
        raise DatasetError(f"{folder}/images.npy has dtype {stack.dtype}; use one of {', '.join(DTYPES)}")
    k = stack.shape[0]
    if (folder / "lights.npy").exists():
        raw = load_npy(folder / "lights.npy").astype(np.float64)
    else:
        raw = _read_matrix(folder / "lights.txt", 3, "light directions")
    lights = _lights(raw, k, folder)
    inten = None
    for nm in ("intensities.npy", "intensities.txt"):
        p = folder / nm
        if p.exists():
            inten = load_npy(p) if nm.endswith(".npy") else np.loadtxt(p, ndmin=2)
    mask = None
    if (folder / "mask.npy").exists():
        mask = load_npy(folder / "mask.npy").astype(bool)
    elif (folder / "mask.png").exists():
        mask = _mask_from(folder / "mask.png")
    return _probe(
        folder.name,
        "npy",
        k,
        lambda i: stack[i],
        lights=lights,
        intensities=inten,
        mask=mask,
        files=_existing(
            [folder / "images.npy"],
            folder,
            "lights.npy",
            "lights.txt",
            "intensities.npy",
            "intensities.txt",
            "mask.npy",
            "mask.png",
        ),
        notes=folder_notes(folder, ("lights.txt", "intensities.txt")),
    )


def uw_psm(folder: Path) -> Dataset:
    root = folder.parent
    listing = root / f"{folder.name}.txt"
    lines = [ln.strip() for ln in listing.read_text().splitlines() if ln.strip()]
    try:
        k = int(lines[0])
    except (IndexError, ValueError):
        raise DatasetError(f"{listing}: first line must be the number of images") from None
    entries = lines[1:]
    if len(entries) < k:
        raise DatasetError(f"{listing}: says {k} images but lists {len(entries)} paths")

    def resolve(p: str) -> Path:
        parts = Path(p).parts
        rel = Path(*parts[1:]) if parts and parts[0] == "psmImages" else Path(p)
        return _inside(root, str(rel), listing)

    paths = [resolve(p) for p in entries[:k]]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise DatasetError(f"{listing}: {len(missing)} listed images are missing, e.g. {missing[0]}")
    lights = _lights(_read_matrix(root / "lights.txt", 3, "light directions", count_line=True), k, root)
    mask_path = resolve(entries[k]) if len(entries) > k else folder / f"{folder.name}.mask.tga"
    mask = _mask_from(mask_path) if mask_path.exists() else None
    return _probe(
        folder.name,
        "uw-psm",
        k,
        lambda i: read_image(paths[i]),
        lights=lights,
        intensities=None,
        mask=mask,
        files=(*paths, *([mask_path] if mask_path.exists() else []), root / "lights.txt", listing),
        image_labels=labels(paths),
    )


def write_npy_folder(folder: Path, images: NDArray, lights: NDArray, mask: NDArray | None = None) -> Path:
    """Write a dataset in the NPY-stack layout (used by ``maxfs demo`` and tests)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "images.npy", images)
    np.savetxt(folder / "lights.txt", np.asarray(lights, dtype=np.float64))
    if mask is not None:
        np.save(folder / "mask.npy", np.asarray(mask, dtype=bool))
    return folder
