"""One loader for DiLiGenT, NPY and UW psm folders; clear errors for broken ones."""

from __future__ import annotations

from pathlib import Path

import imagecodecs
import numpy as np
import pytest
import tifffile

from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.errors import DatasetError
from maxfs.storage.inputs import load_folder
from maxfs.worker import synthetic
from tests.data import UW_OBJECTS


@pytest.mark.parametrize("obj", UW_OBJECTS)
def test_uw_psm_objects_load(obj: str, uw_psm: Path) -> None:
    ds = load_folder(uw_psm / obj)
    assert (ds.layout, ds.k, ds.height, ds.width, ds.channels, ds.dtype) == (
        "uw-psm",
        12,
        340,
        512,
        3,
        "uint8",
    )
    assert ds.mask is not None and 0.05 < ds.mask.mean() < 0.9
    np.testing.assert_allclose(np.linalg.norm(ds.lights, axis=1), 1.0, atol=1e-6)
    img = ds.read(11)
    assert img.shape == (340, 512, 3) and img.max() > 100


def _diligent(folder: Path, images: list[np.ndarray], lights: np.ndarray, ext: str = "png") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, im in enumerate(images):
        name = f"{i + 1:03d}.{ext}"
        if ext == "png":
            (folder / name).write_bytes(imagecodecs.png_encode(im))
        else:
            tifffile.imwrite(folder / name, im)
        names.append(name)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", lights)
    return folder


def test_diligent_16bit_rgb_png_is_read_faithfully(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 65535, size=(6, 5, 3), dtype=np.uint16) for _ in range(4)]
    folder = _diligent(tmp_path / "obj", imgs, synthetic.lights_uniform(4))
    np.savetxt(folder / "light_intensities.txt", np.full((4, 3), 0.5))
    (folder / "mask.png").write_bytes(imagecodecs.png_encode(np.full((6, 5), 255, np.uint8)))
    ds = load_folder(folder)
    assert (ds.layout, ds.dtype, ds.channels) == ("diligent", "uint16", 3)
    for i in range(4):
        np.testing.assert_array_equal(ds.read(i), imgs[i])
    assert ds.intensities.shape == (4, 3) and ds.mask.all()


def test_diligent_16bit_grey_tiff(tmp_path: Path) -> None:
    imgs = [np.full((4, 4), 1000 * (i + 1), np.uint16) for i in range(3)]
    ds = load_folder(_diligent(tmp_path / "t", imgs, synthetic.lights_uniform(3), ext="tiff"))
    assert (ds.dtype, ds.channels) == ("uint16", None)
    np.testing.assert_array_equal(ds.read(2), imgs[2])


def test_npy_stack(tmp_path: Path) -> None:
    sc = synthetic.sphere(5, 8)
    ds = load_folder(write_npy_folder(tmp_path / "n", sc.images.astype(np.uint8), sc.lights, sc.mask))
    assert (ds.layout, ds.k, ds.dtype) == ("npy", 5, "uint8")
    np.testing.assert_array_equal(ds.mask, sc.mask)


def _break(kind: str, root: Path) -> Path:
    imgs = [np.full((4, 4), 50 * (i + 1), np.uint8) for i in range(4)]
    folder = _diligent(root / kind, imgs, synthetic.lights_uniform(4))
    if kind == "missing-image":
        (folder / "002.png").unlink()
    elif kind == "count-mismatch":
        np.savetxt(folder / "light_directions.txt", synthetic.lights_uniform(3))
    elif kind == "corrupt-png":
        (folder / "003.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    elif kind == "different-size":
        (folder / "004.png").write_bytes(imagecodecs.png_encode(np.zeros((5, 4), np.uint8)))
    elif kind == "not-unit-lights":
        np.savetxt(folder / "light_directions.txt", 3 * synthetic.lights_uniform(4))
    elif kind == "not-numbers":
        (folder / "light_directions.txt").write_text("a b c\n" * 4)
    elif kind == "no-dataset":  # images but no listing and no lights file (with one it is a plain folder)
        (folder / "filenames.txt").unlink()
        (folder / "light_directions.txt").unlink()
    elif kind == "name-with-dotdot":
        (folder / "filenames.txt").write_text("001.png\n002.png\n../003.png\n004.png\n")
    elif kind == "absolute-name":
        (folder / "filenames.txt").write_text(f"001.png\n002.png\n{folder / '003.png'}\n004.png\n")
    elif kind == "npy-truncated":
        np.save(folder / "images.npy", np.zeros((4, 4, 4), np.uint8))
        (folder / "filenames.txt").unlink()
        np.savetxt(folder / "lights.txt", synthetic.lights_uniform(4))
        data = (folder / "images.npy").read_bytes()
        (folder / "images.npy").write_bytes(data[:-8])
    return folder


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("missing-image", "listed images are missing"),
        ("count-mismatch", "3 light directions for 4 images"),
        ("corrupt-png", "cannot decode image"),
        ("different-size", "all images must have the same size"),
        ("not-unit-lights", "unit vectors"),
        ("not-numbers", "not a table of numbers"),
        ("no-dataset", "is not a recognised dataset"),
        ("name-with-dotdot", "outside the dataset folder"),
        ("absolute-name", "outside the dataset folder"),
        ("npy-truncated", "truncated"),
    ],
)
def test_broken_folders_give_clear_errors(tmp_path: Path, kind: str, message: str) -> None:
    folder = _break(kind, tmp_path)
    with pytest.raises(DatasetError, match=message):
        ds = load_folder(folder)
        for i in range(ds.k):
            ds.read(i)
