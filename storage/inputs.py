"""The input formats, in one table: which folder layouts ``maxfs run`` and ``maxfs submit`` read.

Each row names a layout, says how it is recognised from the folder (files only, nothing decoded) and
which function opens it as a :class:`~maxfs.storage.datasets.Dataset`. Rows are tried in order and
the first that matches opens the folder. A new input format is a reader function (returning a
``Dataset`` whose images are read one at a time) and a row here; the error message for an
unrecognised folder is made from the rows, so it names the new layout too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from maxfs.storage import datasets, folders
from maxfs.storage.datasets import Dataset
from maxfs.storage.errors import DatasetError


@dataclass(frozen=True)
class InputFormat:
    """One folder layout: recognised by ``matches(folder)``, opened by ``open(folder)``."""

    name: str
    expects: str  #: what the folder must hold, for the "not a recognised dataset" message
    matches: Callable[[Path], bool]
    open: Callable[[Path], Dataset]


def _is_uw(folder: Path) -> bool:
    return (folder.parent / "lights.txt").exists() and (folder.parent / f"{folder.name}.txt").exists()


def _is_tiff_stack(folder: Path) -> bool:
    return folders.lights_file(folder) is not None and folders.stack_file(folder) is not None


def _is_plain(folder: Path) -> bool:
    return folders.lights_file(folder) is not None and bool(folders.plain_images(folder))


#: Every input layout, in the order they are tried.
FORMATS: tuple[InputFormat, ...] = (
    InputFormat(
        "diligent",
        "filenames.txt + light_directions.txt (DiLiGenT)",
        lambda f: (f / "filenames.txt").exists(),
        datasets.diligent,
    ),
    InputFormat(
        "npy",
        "images.npy + lights.txt (NPY stack)",
        lambda f: (f / "images.npy").exists(),
        datasets.npy_stack,
    ),
    InputFormat(
        "uw-psm", "a UW psm object folder with ../lights.txt and ../OBJECT.txt", _is_uw, datasets.uw_psm
    ),
    InputFormat(
        "tiff-stack",
        "a multi-page TIFF with light_directions.txt or lights.txt",
        _is_tiff_stack,
        lambda f: folders.tiff_stack(f, folders.stack_file(f)),  # type: ignore[arg-type]
    ),
    InputFormat(
        "plain", "image files with light_directions.txt or lights.txt", _is_plain, folders.plain_folder
    ),
)


def load_folder(folder: Path | str) -> Dataset:
    """Open a dataset folder of any layout in :data:`FORMATS` (the first that matches)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder} is not a folder; give the folder that holds the images")
    for fmt in FORMATS:
        if fmt.matches(folder):
            return fmt.open(folder)
    expected = "; ".join(f.expects for f in FORMATS)
    raise DatasetError(f"{folder} is not a recognised dataset: expected one of: {expected}")
