"""More input layouts (a multi-page TIFF stack; a plain folder of images and a lights file), and choosing
a subset of a dataset's images (``--images 1-20,25``).

* **TIFF stack**: a folder holding ``images.tif``/``images.tiff`` (or exactly one ``.tif``/``.tiff``) with one
  page per image (grey or RGB, 8/16-bit or float32), plus a lights file. Pages are read one at a time.
* **Plain folder**: image files (``.png .tif .tiff .tga .bmp .jpg .jpeg``) and a lights file, no
  ``filenames.txt``. Images are taken in name order with numbers compared as numbers (``img2`` before
  ``img10``); ``mask.*``, ``*.mask.*`` and ``Normal_gt.*`` are not images. Line i of the lights file is
  the light of the i-th image in that order.

Lights file: ``light_directions.txt`` or ``lights.txt`` (k lines of x y z; x right, y up, z toward the
camera), or ``lights.npy``. Optional: ``light_intensities.txt``/``intensities.txt`` (k x 3 or k x 1,
for grey and RGB images alike), ``mask.png`` (above half its maximum = object). Text and mask rules as
in :mod:`maxfs.storage.datasets`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.datasets import (
    Dataset,
    Table,
    _existing,
    _lights,
    _mask_from,
    _npy_table,
    _probe,
    _read_matrix,
    folder_notes,
    labels,
    read_image,
)
from maxfs.storage.errors import DatasetError, InvalidInputError
from maxfs.storage.options import (
    DTYPES,
    WARN_LIGHT_CONDITION,
    check_lights,
    light_condition,
    light_singular_values,
)

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".tga", ".bmp", ".jpg", ".jpeg")
LIGHT_FILES = ("light_directions.txt", "lights.txt", "lights.npy")
INTENSITY_FILES = ("light_intensities.txt", "intensities.txt")
TEXT_FILES = tuple(n for n in (*LIGHT_FILES, *INTENSITY_FILES) if n.endswith(".txt"))


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _not_an_image(name: str) -> bool:
    low = name.lower()
    stem = low.split(".")[0]
    return stem in ("mask", "normal_gt") or ".mask." in low


def lights_file(folder: Path) -> Path | None:
    for n in LIGHT_FILES:
        if (folder / n).is_file():
            return folder / n
    return None


def _read_lights(folder: Path, k: int) -> tuple[NDArray[np.float64], Table | None, list[Path]]:
    """The light directions, the intensities' table (fitted to the images by ``_probe``) and the
    files they came from."""
    lf = lights_file(folder)
    if lf is None:
        raise DatasetError(f"{folder}: no lights file; add light_directions.txt (k lines of x y z)")
    what = "light directions"
    lights = _lights(_npy_table(lf, what) if lf.suffix == ".npy" else _read_matrix(lf, (3,), what), k)
    inten, used = None, [lf]
    for n in INTENSITY_FILES:
        p = folder / n
        if p.is_file():
            inten = _read_matrix(p, (1, 3), "light intensities")
            used.append(p)
            break
    return lights, inten, used


def stack_file(folder: Path) -> Path | None:
    """The multi-page TIFF of a TIFF-stack folder, if the folder is one."""
    for n in ("images.tif", "images.tiff"):
        if (folder / n).is_file():
            return folder / n
    tifs = [
        p for p in folder.iterdir() if p.suffix.lower() in (".tif", ".tiff") and not _not_an_image(p.name)
    ]
    if len(tifs) == 1 and lights_file(folder) is not None:
        import tifffile  # only for TIFF input (90 ms to import)

        with tifffile.TiffFile(tifs[0]) as t:
            if len(t.pages) >= 3:
                return tifs[0]
    return None


def tiff_stack(folder: Path, path: Path) -> Dataset:
    try:
        import tifffile  # only for TIFF input (90 ms to import)

        with tifffile.TiffFile(path) as t:
            k = len(t.pages)
    except Exception as e:  # tifffile raises several types for bad files
        raise DatasetError(f"{path}: not a readable TIFF ({e})") from None
    if k < 3:
        raise DatasetError(f"{path} has {k} pages; a stack needs one page per image, at least 3")
    lights, inten, used = _read_lights(folder, k)

    def page(i: int) -> NDArray:
        import tifffile  # only for TIFF input (90 ms to import)

        with tifffile.TiffFile(path) as t:
            arr = t.pages[i].asarray()
        if arr.ndim == 3 and arr.shape[2] == 4:
            arr = arr[..., :3]
        if str(arr.dtype) not in DTYPES:
            if np.issubdtype(arr.dtype, np.floating):
                return arr.astype(np.float32)
            raise DatasetError(f"{path} page {i + 1}: pixel type {arr.dtype}; use 8/16-bit or float32")
        return arr

    mask = _mask_from(folder / "mask.png") if (folder / "mask.png").exists() else None
    return _probe(
        folder.name,
        "tiff-stack",
        k,
        page,
        lights=lights,
        intensities=inten,
        mask=mask,
        files=_existing([path, *used], folder, "mask.png"),
        notes=folder_notes(folder, TEXT_FILES),
    )


def plain_images(folder: Path) -> list[Path]:
    return sorted(
        (
            p
            for p in folder.iterdir()
            if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not _not_an_image(p.name)
        ),
        key=lambda p: _natural_key(p.name),
    )


def plain_folder(folder: Path) -> Dataset:
    paths = plain_images(folder)
    if len(paths) < 3:
        raise DatasetError(f"{folder}: {len(paths)} images beside the lights file; at least 3 are needed")
    lights, inten, used = _read_lights(folder, len(paths))
    mask = _mask_from(folder / "mask.png") if (folder / "mask.png").exists() else None
    return _probe(
        folder.name,
        "plain",
        len(paths),
        lambda i: read_image(paths[i]),
        lights=lights,
        intensities=inten,
        mask=mask,
        files=_existing([*paths, *used], folder, "mask.png"),
        notes=folder_notes(folder, TEXT_FILES),
        image_labels=labels(paths),
    )


# -- choosing images -----------------------------------------------------------------------------------
def parse_selection(text: str, k: int) -> list[int]:
    """``"1-20,25"`` to 0-based indices ``[0..19, 24]``: 1-based, inclusive ranges, in the order given."""
    if not text.strip(" ,"):  # ``--images=`` (an empty shell variable): not "every image" by accident
        raise InvalidInputError(
            f"--images is empty; give image numbers such as 1-{k} or 1-3,5, or leave it out"
        )
    out: list[int] = []
    for part in text.replace(" ", "").split(","):
        if not part:
            continue
        m = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if not m:
            raise InvalidInputError(f"--images: {part!r} is not N or N-M (images are numbered 1..{k})")
        a = int(m.group(1))
        b = int(m.group(2) or a)
        if not (1 <= a <= b <= k):
            raise InvalidInputError(f"--images: {part} is outside 1..{k} (or the range runs backwards)")
        out.extend(range(a - 1, b))
    twice = sorted({i + 1 for i in out if out.count(i) > 1})
    if twice:
        which = f"image {twice[0]} is" if len(twice) == 1 else f"images {', '.join(map(str, twice))} are"
        raise InvalidInputError(f"--images: {which} chosen twice; choose each once")
    if len(out) < 3:
        raise InvalidInputError(f"--images chooses {len(out)} images; at least 3 are needed")
    return out


def select_images(ds: Dataset, indices: list[int]) -> Dataset:
    """The dataset restricted to ``indices`` (0-based), in that order."""
    idx = list(indices)
    try:
        lights = check_lights(ds.lights[idx], len(idx))
    except InvalidInputError as e:
        raise InvalidInputError(f"the chosen images' lights: {e}") from None
    inten = ds.intensities[idx] if ds.intensities is not None and len(ds.intensities) == ds.k else None
    reader = ds._reader
    return Dataset(
        name=ds.name,
        layout=f"{ds.layout}, images {len(idx)} of {ds.k}",
        k=len(idx),
        height=ds.height,
        width=ds.width,
        channels=ds.channels,
        dtype=ds.dtype,
        lights=lights,
        intensities=inten if inten is not None else ds.intensities,
        mask=ds.mask,
        _reader=lambda i: reader(idx[i]),
        files=(),  # no file fingerprint: the same files with another choice are other inputs
        notes=ds.notes,
        image_labels=tuple(ds.label(j) for j in idx),  # as numbered in the folder
    )


def conditioning_warning(lights: NDArray[np.floating]) -> str | None:
    """A warning when the lights' condition number is above ``WARN_LIGHT_CONDITION`` (yet accepted)."""

    cond = light_condition(lights)
    if cond <= WARN_LIGHT_CONDITION:
        return None
    sv = ", ".join(f"{v:.3g}" for v in light_singular_values(lights))
    return (
        f"the light directions are badly conditioned (condition number {cond:.3g} > "
        f"{WARN_LIGHT_CONDITION:g}; singular values {sv}): normals will be noisy along the weakest "
        "direction; add lights from more varied directions"
    )
