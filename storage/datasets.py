"""Reading the input folders labs already have, one loader for all layouts.

Layouts (detected in this order):

* **DiLiGenT**: ``filenames.txt``, ``light_directions.txt`` (k x 3),
  optional ``light_intensities.txt`` (k x 3 RGB, or k x 1), optional ``mask.png``;
  8/16-bit PNG or TIFF, grey or RGB.
* **NPY stack**: ``images.npy`` (k, H, W[, C]) plus ``lights.txt`` or
  ``lights.npy`` (k x 3); optional ``mask.npy``/``mask.png`` and
  ``intensities.txt``/``intensities.npy``.
* **UW psm** (CSE 455 ``psmImages``): the object folder ``OBJ/`` whose parent
  holds ``lights.txt`` (a count line, then k directions) and ``OBJ.txt`` (a count
  line, then the image paths, then the mask path; paths may start with
  ``psmImages/``); ``OBJ.mask.tga`` is a soft mask.

Images are read one at a time (:meth:`Dataset.read`), never as a whole stack.

Text files may start with a UTF-8 byte-order mark (Windows Notepad); in light direction and
intensity tables, blank lines and lines starting with ``#`` (a ``# x y z`` header) are skipped.
Light intensities are k x 1 (one per image) or k x 3 (R G B), for grey and RGB images alike.
A mask pixel is the object where it is above half the mask's own maximum (0/1, 0/255, 0/65535
and soft-edged masks alike); a mask whose colour is all zero is read from its alpha channel.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.errors import DatasetError, InvalidInputError
from maxfs.storage.imageio import load_npy, read_mask_plane
from maxfs.storage.imageio import read_image as _decode_file
from maxfs.storage.observations import INTENSITY_RANGE
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


def read_image(path: Path, reader: Callable[[Path], NDArray] = _decode_file) -> NDArray:
    """An image file of a dataset; unreadable files are :class:`DatasetError`."""
    try:
        return reader(path)
    except DatasetError:
        raise
    except InvalidInputError as e:
        raise DatasetError(str(e)) from None


def read_text(path: Path, what: str) -> str:
    """A listing or calibration file's text; a UTF-8 byte-order mark (Windows Notepad writes one)
    is not part of it, or the first file name or number would carry it."""
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(f"missing {what}: {path}") from None
    except UnicodeDecodeError as e:
        raise DatasetError(
            f"{path}: not UTF-8 text (byte {e.start} cannot be decoded); save it as UTF-8 or plain ASCII"
        ) from None


def _inside(root: Path, name: str, listing: Path) -> Path:
    """``root / name``, refusing names that are absolute or climb out with ``..``."""
    p = Path(name)
    if p.is_absolute() or ".." in p.parts:
        raise DatasetError(
            f"{listing}: entry {name!r} points outside the dataset folder; list images by paths "
            "relative to it, without '..'"
        )
    return root / p


@dataclass(frozen=True)
class Table:
    """Rows of numbers from a calibration file, with where each came from (for messages)."""

    values: NDArray[np.float64]  # (rows, columns)
    path: Path
    rows: tuple[str, ...]  # "line 4" (text) or "row 4" (NPY) per row, numbered from 1


def _table_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """``(line number, text)`` of the lines that hold data: not blank, not a ``#`` comment
    (a ``# x y z`` header, or what ``np.savetxt(header=...)`` writes)."""
    lines = enumerate(read_text(path, what).splitlines(), start=1)
    return [(n, ln) for n, ln in lines if ln.strip() and not ln.lstrip().startswith("#")]


def _read_matrix(path: Path, cols: tuple[int, ...], what: str, count_line: bool = False) -> Table:
    """A table of ``what`` with one of ``cols`` numbers per line (the same on every line)."""
    lines = _table_lines(path, what)
    want = " or ".join(str(c) for c in cols)
    if count_line:
        try:
            n = int(lines[0][1].split()[0])
        except (IndexError, ValueError):
            raise DatasetError(f"{path}: first line must be the number of rows") from None
        lines = lines[1:]
        if len(lines) != n:
            raise DatasetError(f"{path}: says {n} rows but has {len(lines)}")
    if not lines:
        raise DatasetError(f"{path} holds no {what}; give one line of {want} numbers per image")
    rows = []
    for n, ln in lines:
        try:
            rows.append([float(v) for v in ln.replace(",", " ").split()])
        except ValueError:
            raise DatasetError(
                f"{path} line {n}: not a table of numbers ({ln.strip()[:60]!r}); give {want} numbers per "
                "line, and start a header or comment line with '#'"
            ) from None
        got = len(rows[-1])
        if got not in cols:
            raise DatasetError(f"{path} line {n}: {got} numbers; {what} take {want} per line")
        if got != len(rows[0]):
            raise DatasetError(
                f"{path} line {n}: {got} numbers but line {lines[0][0]} has {len(rows[0])}; give as many "
                "on every line"
            )
    return Table(np.array(rows, dtype=np.float64), path, tuple(f"line {n}" for n, _ in lines))


def _npy_table(path: Path, what: str) -> Table:
    """A table of ``what`` from an NPY file: (k, columns), or (k,) as one column."""
    try:
        arr = np.atleast_1d(load_npy(path).astype(np.float64))
    except InvalidInputError as e:  # not an NPY file, or pickled objects
        raise DatasetError(str(e)) from None
    except (ValueError, TypeError) as e:  # strings or records
        raise DatasetError(f"{path}: {what} must be numbers ({e})") from None
    if arr.ndim == 1:
        arr = arr[:, None]
    return Table(arr, path, tuple(f"row {i + 1}" for i in range(len(arr))))


def _lights(table: Table, k: int) -> NDArray[np.float64]:
    where = table.path
    if table.values.shape[0] != k:
        raise DatasetError(
            f"{where}: {table.values.shape[0]} light directions for {k} images; give one per image"
        )
    try:
        return check_lights(table.values, k, rows=table.rows)
    except InvalidInputError as e:
        raise DatasetError(f"{where}: {e}") from None


def _intensities(table: Table | None, k: int, channels: int | None) -> NDArray[np.float64] | None:
    """The light intensities as (k, C) for images of ``channels`` (C = 1 for grey), from a table
    of one value per image or three (R G B), whatever the images are."""
    if table is None:
        return None
    v, where = table.values, table.path
    if v.shape[0] != k:
        raise DatasetError(f"{where}: {v.shape[0]} light intensities for {k} images; give one line per image")
    if v.ndim != 2 or v.shape[1] not in (1, 3):
        raise DatasetError(
            f"{where}: light intensities have shape {v.shape}; give one per image (k x 1) or one per "
            "image and channel (k x 3, R G B)"
        )
    lo, hi = INTENSITY_RANGE
    bad = ~(np.isfinite(v) & (v > 0)).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise DatasetError(
            f"{where} {table.rows[i]}: light intensities must be finite and positive, got {_numbers(v[i])}"
        )
    off = ((v < lo) | (v > hi)).any(axis=1)
    if off.any():
        i = int(np.argmax(off))
        raise DatasetError(
            f"{where} {table.rows[i]}: light intensities must be between {lo:g} and {hi:g} (relative "
            f"brightness), got {_numbers(v[i])}; scale them, e.g. divide them all by the largest"
        )
    if channels is None and v.shape[1] == 3:
        # grey images with R G B intensities (DiLiGenT's files): grey is the mean of the channels,
        # so the light's grey intensity is the mean of its three
        return v.mean(axis=1, keepdims=True)
    # one value per image: the same intensity in every channel
    return np.broadcast_to(v, (k, channels or 1)).copy()


def _numbers(row: NDArray[np.float64]) -> str:
    return " ".join(f"{x:g}" for x in row)


def _mask_from(path: Path) -> NDArray[np.bool_]:
    m = read_image(path, read_mask_plane)
    vals = m[np.isfinite(m)] if m.dtype.kind == "f" else m
    top = float(vals.max()) if vals.size else 0.0
    # half the mask's own maximum, not the dtype's: 0/1 masks (numpy, OpenCV), 0/255, 0/65535
    # and soft edges alike; an all-zero mask stays empty (and is refused as selecting no pixel)
    return m > top / 2 if top > 0 else np.zeros(m.shape, dtype=bool)


def _existing(paths: list[Path], folder: Path, *names: str) -> tuple[Path, ...]:
    """``paths`` plus those of ``names`` in ``folder`` that exist."""
    return (*paths, *(folder / n for n in names if (folder / n).exists()))


#: Text files no layout reads but a dataset folder may well hold.
_HARMLESS_TEXT = ("readme", "license", "licence", "notes", "citation")


def folder_notes(
    folder: Path, known: tuple[str, ...], expected: tuple[str, ...] = (), listed: tuple[str, ...] = ()
) -> tuple[str, ...]:
    """Calibration files that look wrong in ``folder``: ``*.txt`` files the layout does not read
    (``known`` are those it reads; a README or LICENSE is fine; ``listed``: names the listing
    gives as images, read as such) and ``expected`` files missing."""
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
        if p.name not in known and p.name not in listed and not p.name.lower().startswith(_HARMLESS_TEXT)
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


def _probe(
    name: str, layout: str, k: int, reader: Callable[[int], NDArray], intensities: Table | None = None, **kw
) -> Dataset:
    first = reader(0)
    h, w = first.shape[:2]
    ch = None if first.ndim == 2 else first.shape[2]
    mask = kw.pop("mask", None)
    if mask is not None and mask.shape != (h, w):
        raise DatasetError(f"{name}: mask is {mask.shape[0]} x {mask.shape[1]} but images are {h} x {w}")
    inten = _intensities(intensities, k, ch)  # their shape follows the images' channels
    return Dataset(
        name, layout, k, h, w, ch, str(first.dtype), _reader=reader, mask=mask, intensities=inten, **kw
    )


#: The text files of the DiLiGenT layout.
DILIGENT_TEXT = ("filenames.txt", "light_directions.txt", "light_intensities.txt")


def diligent(folder: Path) -> Dataset:
    text = read_text(folder / "filenames.txt", "image list")
    names = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if len(names) < 3:
        raise DatasetError(f"{folder}/filenames.txt lists {len(names)} images; at least 3 are needed")
    paths = [_inside(folder, n, folder / "filenames.txt") for n in names]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise DatasetError(f"{folder}: {len(missing)} listed images are missing, e.g. {missing[0]}")
    lights = _lights(_read_matrix(folder / "light_directions.txt", (3,), "light directions"), len(paths))
    inten = None
    if (folder / "light_intensities.txt").exists():
        inten = _read_matrix(folder / "light_intensities.txt", (1, 3), "light intensities")
    mask = _mask_from(folder / "mask.png") if (folder / "mask.png").exists() else None
    return _probe(
        folder.name,
        "diligent",
        len(paths),
        lambda i: read_image(paths[i]),
        lights=lights,
        intensities=inten,
        mask=mask,
        files=_existing(paths, folder, "mask.png", "light_directions.txt", "light_intensities.txt"),
        notes=folder_notes(
            folder,
            DILIGENT_TEXT,
            expected=("light_intensities.txt",),
            listed=tuple(Path(n).as_posix() for n in names),
        ),
        image_labels=labels(paths),
    )


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
        raw = _npy_table(folder / "lights.npy", "light directions")
    else:
        raw = _read_matrix(folder / "lights.txt", (3,), "light directions")
    lights = _lights(raw, k)
    inten = None
    if (folder / "intensities.txt").exists():  # before the NPY file, as it always was
        inten = _read_matrix(folder / "intensities.txt", (1, 3), "light intensities")
    elif (folder / "intensities.npy").exists():
        inten = _npy_table(folder / "intensities.npy", "light intensities")
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
    lines = [ln.strip() for ln in read_text(listing, "image list").splitlines() if ln.strip()]
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
    lights = _lights(_read_matrix(root / "lights.txt", (3,), "light directions", count_line=True), k)
    mask_path = resolve(entries[k]) if len(entries) > k else folder / f"{folder.name}.mask.tga"
    mask = _mask_from(mask_path) if mask_path.exists() else None
    return _probe(
        folder.name,
        "uw-psm",
        k,
        lambda i: read_image(paths[i]),
        lights=lights,
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
