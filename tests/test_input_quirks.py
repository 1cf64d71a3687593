"""Input files as users really save them: 0/1 and alpha masks, a UTF-8 byte-order mark, ``#`` header
lines, k x 1 or k x 3 intensities for grey and RGB images; and errors that name the file, the 1-based
line and only what is really wrong."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import imagecodecs
import numpy as np
import pytest
import tifffile

from maxfs.storage.datasets import Dataset, write_npy_folder
from maxfs.storage.errors import DatasetError, InvalidInputError
from maxfs.storage.imageio import decode_bytes, encode_png
from maxfs.storage.inputs import load_folder
from maxfs.storage.observations import ObservationModel
from maxfs.worker import synthetic

K, SIZE = 8, 32
BOM = b"\xef\xbb\xbf"

#: Per layout: the file of light directions and the file of light intensities it reads.
LIGHTS = {
    "diligent": "light_directions.txt",
    "plain": "lights.txt",
    "tiff-stack": "light_directions.txt",
    "npy": "lights.txt",
    "uw-psm": "../lights.txt",
}
INTENSITIES = {
    "diligent": "light_intensities.txt",
    "plain": "intensities.txt",
    "tiff-stack": "light_intensities.txt",
    "npy": "intensities.txt",
}


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s = synthetic.sphere(K, SIZE, specular=0.0)
    return s.images.astype(np.uint8), s.lights, s.mask


def _lights_text(lights: np.ndarray, count: bool = False) -> str:
    rows = "".join(f"{x:.9f} {y:.9f} {z:.9f}\n" for x, y, z in lights)
    return f"{len(lights)}\n{rows}" if count else rows


def _folder(root: Path, layout: str, rgb: bool = False) -> Path:
    """A small dataset of ``layout``: K images of SIZE x SIZE, grey or RGB, 8-bit, no mask."""
    images, lights, _ = _scene()
    if rgb:
        images = np.repeat(images[..., None], 3, axis=3)
    folder = root / "obj"
    folder.mkdir(parents=True)
    if layout in ("diligent", "plain"):
        names = [f"{i + 1:03d}.png" for i in range(K)]
        for name, img in zip(names, images, strict=True):
            (folder / name).write_bytes(encode_png(img))
        if layout == "diligent":
            (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    elif layout == "tiff-stack":
        tifffile.imwrite(folder / "images.tif", images, photometric="rgb" if rgb else "minisblack")
    elif layout == "npy":
        write_npy_folder(folder, images, lights)
    elif layout == "uw-psm":
        names = [f"psmImages/obj/obj.{i}.png" for i in range(K)]
        for i, img in enumerate(images):
            (folder / f"obj.{i}.png").write_bytes(encode_png(img))
        (root / "obj.txt").write_text(f"{K}\n" + "\n".join(names) + "\n")
    (folder / LIGHTS[layout]).write_text(_lights_text(lights, count=layout == "uw-psm"))
    return folder


def _edit(path: Path, fn: Callable[[str], str]) -> None:
    path.write_text(fn(path.read_text()))


def _prepend_bom(path: Path) -> None:
    path.write_bytes(BOM + path.read_bytes())


# -- 1. masks ------------------------------------------------------------------------------------------
def _ring(mask: np.ndarray) -> np.ndarray:
    """The object's pixels next to the background (a soft mask's edge)."""
    inner = mask.copy()
    inner[1:-1, 1:-1] &= mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
    return mask & ~inner


def _soft(mask: np.ndarray) -> np.ndarray:
    """0 outside, 200 inside, 120 on the edge (above half the mask's maximum of 200)."""
    m = np.where(mask, 200, 0).astype(np.uint8)
    m[_ring(mask)] = 120
    return m


def _alpha(mask: np.ndarray, channels: int) -> np.ndarray:
    """Black colour, the object in the alpha channel (RGBA or grey + alpha)."""
    m = np.zeros((*mask.shape, channels), np.uint8)
    m[..., -1] = mask * 255
    return m


#: (name, the mask file's array from the object's mask): masks the dtype's half maximum read as empty
MASKS = [
    ("0/1 uint8", lambda m: m.astype(np.uint8)),
    ("0/1 RGB", lambda m: np.repeat(m[..., None], 3, axis=2).astype(np.uint8)),
    ("0/1 uint16", lambda m: m.astype(np.uint16)),
    ("soft edge, maximum 200", _soft),
    ("black RGBA, object in alpha", lambda m: _alpha(m, 4)),
    ("black grey+alpha, object in alpha", lambda m: _alpha(m, 2)),
]
#: Masks read as before (a guard for the rule, not a fix): the object, or nothing.
KEPT_MASKS = [
    ("0/255 uint8", lambda m: m.astype(np.uint8) * 255, True),
    ("0/65535 uint16", lambda m: m.astype(np.uint16) * 65535, True),
    ("all zero", lambda m: np.zeros(m.shape, np.uint8), False),
    ("opaque black RGBA", lambda m: _alpha(np.ones_like(m), 4), False),
]


def _masks_read(root: Path, make: Callable[[np.ndarray], np.ndarray]) -> list[np.ndarray]:
    """The mask ``make`` writes as mask.png, as a DiLiGenT and a plain folder read it."""
    _, _, mask = _scene()
    out = []
    for layout in ("diligent", "plain"):
        folder = _folder(root / layout, layout)
        (folder / "mask.png").write_bytes(imagecodecs.png_encode(np.ascontiguousarray(make(mask))))
        ds = load_folder(folder)
        assert ds.mask is not None
        out.append(ds.mask)
    return out


@pytest.mark.parametrize(("name", "make"), MASKS, ids=[m[0] for m in MASKS])
def test_masks_are_read_at_half_their_own_maximum(
    tmp_path: Path, name: str, make: Callable[[np.ndarray], np.ndarray]
) -> None:
    _, _, mask = _scene()
    for read in _masks_read(tmp_path, make):
        np.testing.assert_array_equal(read, mask)


@pytest.mark.parametrize(("name", "make", "found"), KEPT_MASKS, ids=[m[0] for m in KEPT_MASKS])
def test_masks_that_were_read_right_still_are(
    tmp_path: Path, name: str, make: Callable[[np.ndarray], np.ndarray], found: bool
) -> None:
    _, _, mask = _scene()
    for read in _masks_read(tmp_path, make):
        np.testing.assert_array_equal(read, mask if found else np.zeros_like(mask))


# -- 2. a UTF-8 byte-order mark --------------------------------------------------------------------
#: (layout, the file that starts with a BOM, relative to the object folder)
BOM_FILES = [
    ("diligent", "filenames.txt"),
    ("diligent", "light_directions.txt"),
    ("diligent", "light_intensities.txt"),
    ("plain", "lights.txt"),
    ("plain", "intensities.txt"),
    ("tiff-stack", "light_directions.txt"),
    ("tiff-stack", "light_intensities.txt"),
    ("npy", "lights.txt"),
    ("npy", "intensities.txt"),
    ("uw-psm", "../lights.txt"),
    ("uw-psm", "../obj.txt"),
]


def _same_inputs(a: Dataset, b: Dataset) -> None:
    assert (a.layout, a.k, a.height, a.width, a.channels) == (b.layout, b.k, b.height, b.width, b.channels)
    np.testing.assert_array_equal(a.lights, b.lights)
    if b.intensities is None:
        assert a.intensities is None
    else:
        np.testing.assert_array_equal(a.intensities, b.intensities)
    np.testing.assert_array_equal(a.read(K - 1), b.read(K - 1))


@pytest.mark.parametrize(("layout", "name"), BOM_FILES)
def test_a_byte_order_mark_is_ignored(tmp_path: Path, layout: str, name: str) -> None:
    plain, bom = _folder(tmp_path / "plain", layout), _folder(tmp_path / "bom", layout)
    if layout in INTENSITIES:
        for f in (plain, bom):
            np.savetxt(f / INTENSITIES[layout], np.linspace(0.5, 2.0, 3 * K).reshape(K, 3))
    _prepend_bom(bom / name)
    _same_inputs(load_folder(bom), load_folder(plain))


# -- 3. light errors count from 1 and name the file and line -----------------------------------------
def _set_row(i: int, row: str) -> Callable[[str], str]:
    def edit(text: str) -> str:
        lines = text.splitlines()
        lines[i] = row
        return "\n".join(lines) + "\n"

    return edit


def _npy_lights(folder: Path, row: int, value: list[float]) -> None:
    lights = np.loadtxt(folder / "lights.txt")
    lights[row] = value
    (folder / "lights.txt").unlink()
    np.save(folder / "lights.npy", lights)


#: (layout, how the folder is broken, what the error says)
LIGHT_ERRORS = [
    (
        "diligent",
        lambda f: _edit(f / "light_directions.txt", _set_row(2, "0 0 0")),
        "light_directions.txt: light 3 (line 3) has length 0.0000",
    ),
    (
        "diligent",
        lambda f: _edit(f / "light_directions.txt", lambda t: "# x y z\n" + _set_row(2, "0 0 0")(t)),
        "light_directions.txt: light 3 (line 4) has length 0.0000",
    ),
    (
        "plain",
        lambda f: _edit(f / "lights.txt", _set_row(4, "0 nan 1")),
        "lights.txt: light 5 (line 5) contains NaN",
    ),
    (
        "tiff-stack",
        lambda f: _edit(f / "light_directions.txt", lambda t: "\n" + _set_row(7, "0 0 2")(t)),
        "light_directions.txt: light 8 (line 9) has length 2.0000",
    ),
    ("npy", lambda f: _npy_lights(f, 1, [0.0, 0.0, 0.0]), "lights.npy: light 2 (row 2) has length 0.0000"),
    (
        "uw-psm",
        lambda f: _edit(f / "../lights.txt", _set_row(1, "0 0 3")),
        "lights.txt: light 1 (line 2) has length 3.0000",
    ),
]


@pytest.mark.parametrize(("layout", "breaks", "message"), LIGHT_ERRORS, ids=[e[2] for e in LIGHT_ERRORS])
def test_light_errors_count_from_one_and_name_the_line(
    tmp_path: Path, layout: str, breaks: Callable[[Path], None], message: str
) -> None:
    folder = _folder(tmp_path, layout)
    breaks(folder)
    with pytest.raises(DatasetError, match=re.escape(message)):
        load_folder(folder)


# -- 4. '#' lines are comments in light tables -------------------------------------------------------
#: (layout, file, the lines put before its rows)
COMMENTS = [
    ("diligent", "light_directions.txt", "# x y z\n"),
    ("diligent", "light_intensities.txt", "# R G B\n"),
    ("plain", "lights.txt", "#x y z (x right, y up)\n\n"),
    ("tiff-stack", "light_directions.txt", "  # one per image\n"),
    ("npy", "lights.txt", "# written by np.savetxt(header=...)\n"),
    ("uw-psm", "../lights.txt", "# directions of the UW rig\n"),
]


@pytest.mark.parametrize(("layout", "name", "header"), COMMENTS)
def test_hash_lines_in_light_tables_are_comments(tmp_path: Path, layout: str, name: str, header: str) -> None:
    plain, commented = _folder(tmp_path / "plain", layout), _folder(tmp_path / "commented", layout)
    if layout in INTENSITIES:
        for f in (plain, commented):
            np.savetxt(f / INTENSITIES[layout], np.linspace(0.5, 2.0, K)[:, None])
    _edit(commented / name, lambda t: header + t)
    # a comment after the rows too (between the count line and the rows would be as fine)
    _edit(commented / name, lambda t: t + "# end\n")
    _same_inputs(load_folder(commented), load_folder(plain))


#: (layout, file, its first line, what the error says)
NOT_NUMBERS = [
    (
        "diligent",
        "light_directions.txt",
        "x y z",
        "light_directions.txt line 1: not a table of numbers ('x y z')",
    ),
    ("plain", "intensities.txt", "R G B", "intensities.txt line 1: not a table of numbers ('R G B')"),
    ("npy", "intensities.txt", "1 2 3 // first", "intensities.txt line 1: not a table of numbers"),
]


@pytest.mark.parametrize(("layout", "name", "first", "message"), NOT_NUMBERS)
def test_other_words_in_light_tables_are_refused_by_line(
    tmp_path: Path, layout: str, name: str, first: str, message: str
) -> None:
    folder = _folder(tmp_path, layout)
    np.savetxt(folder / INTENSITIES[layout], np.ones((K, 3)))
    _edit(folder / name, lambda t: first + "\n" + t)
    with pytest.raises(DatasetError, match=re.escape(message)) as err:
        load_folder(folder)
    assert "start a header or comment line with '#'" in str(err.value)


# -- 5. intensities: k x 1 or k x 3, grey or RGB, in every layout ---------------------------------------
def _was_read(layout: str, rgb: bool, cols: int, suffix: str) -> bool:
    """Whether the loaders read these intensities right before k x 1 and k x 3 were accepted for
    grey and RGB alike: a DiLiGenT folder's k x 3, another layout's k x C (not an NPY's (k,))."""
    if layout == "diligent":
        return cols == 3
    return cols == (3 if rgb else 1) and not (suffix == ".npy" and cols == 1)


#: (layout, RGB images, columns of the intensities file, the intensities file: text or NPY)
ALL_SHAPES = [
    (layout, rgb, cols, suffix)
    for layout in ("diligent", "plain", "tiff-stack", "npy")
    for rgb in (False, True)
    for cols in (1, 3)
    for suffix in ((".txt", ".npy") if layout == "npy" else (".txt",))
]
SHAPES = [row for row in ALL_SHAPES if not _was_read(*row)]
KEPT_SHAPES = [row for row in ALL_SHAPES if _was_read(*row)]


@pytest.mark.parametrize(("layout", "rgb", "cols", "suffix"), SHAPES)
def test_intensities_of_one_or_three_columns_fit_grey_and_rgb(
    tmp_path: Path, layout: str, rgb: bool, cols: int, suffix: str
) -> None:
    folder = _folder(tmp_path, layout, rgb=rgb)
    given = np.linspace(0.5, 2.0, K * cols).reshape(K, cols)
    name = INTENSITIES[layout].replace(".txt", suffix)
    if suffix == ".npy":
        np.save(folder / name, given[:, 0] if cols == 1 else given)  # (k,) is one column too
    else:
        np.savetxt(folder / name, given)
    ds = load_folder(folder)
    C = 3 if rgb else 1
    expect = np.broadcast_to(given, (K, C)) if cols == 1 or rgb else given.mean(axis=1, keepdims=True)
    assert ds.intensities is not None and ds.intensities.shape == (K, C)
    np.testing.assert_allclose(ds.intensities, expect, rtol=1e-12)
    obs = ObservationModel.for_input(np.dtype(ds.dtype), ds.k, ds.channels, ds.intensities)
    np.testing.assert_allclose(obs.intensities, expect, rtol=1e-12)


@pytest.mark.parametrize(("layout", "rgb", "cols", "suffix"), KEPT_SHAPES)
def test_intensities_that_were_read_right_still_are(
    tmp_path: Path, layout: str, rgb: bool, cols: int, suffix: str
) -> None:
    # a guard for the new rule, not a fix: the same test on the shapes that always worked
    test_intensities_of_one_or_three_columns_fit_grey_and_rgb(tmp_path, layout, rgb, cols, suffix)


def _npy_intensities(folder: Path, values: np.ndarray) -> None:
    np.save(folder / "intensities.npy", values)


#: (layout, RGB images, intensities file name, what it holds, what the error says)
INTENSITY_ERRORS = [
    (
        "diligent",
        True,
        "light_intensities.txt",
        "1 1 1\n" * (K - 1),
        "light_intensities.txt: 7 light intensities for 8 images",
    ),
    (
        "plain",
        False,
        "intensities.txt",
        "1 1\n" * K,
        "intensities.txt line 1: 2 numbers; light intensities take 1 or 3 per line",
    ),
    (
        "tiff-stack",
        True,
        "light_intensities.txt",
        "1\n" * 3 + "1 1 1\n" * (K - 3),
        "light_intensities.txt line 4: 3 numbers but line 1 has 1",
    ),
    (
        "diligent",
        False,
        "light_intensities.txt",
        "1 1 1\n" * 4 + "1 -1 1\n" * (K - 4),
        "light_intensities.txt line 5: light intensities must be finite and positive, got 1 -1 1",
    ),
    (
        "plain",
        True,
        "light_intensities.txt",
        "# R G B\n" + "2\n" * 2 + "0\n" * (K - 2),
        "light_intensities.txt line 4: light intensities must be finite and positive, got 0",
    ),
    (
        "npy",
        False,
        "intensities.txt",
        "1\n" * (K - 1) + "nan\n",
        "intensities.txt line 8: light intensities must be finite and positive, got nan",
    ),
    (
        "npy",
        True,
        "intensities.npy",
        np.r_[np.ones(2), np.inf, np.ones(K - 3)],
        "intensities.npy row 3: light intensities must be finite and positive, got inf",
    ),
    (
        "npy",
        False,
        "intensities.npy",
        np.ones((K, 2)),
        "intensities.npy: light intensities have shape (8, 2)",
    ),
    (
        "tiff-stack",
        False,
        "intensities.txt",
        "1e9\n" * K,
        "intensities.txt line 1: light intensities must be between",
    ),
]


@pytest.mark.parametrize(
    ("layout", "rgb", "name", "content", "message"), INTENSITY_ERRORS, ids=[e[4] for e in INTENSITY_ERRORS]
)
def test_intensity_errors_name_the_file_and_line(
    tmp_path: Path, layout: str, rgb: bool, name: str, content: str | np.ndarray, message: str
) -> None:
    folder = _folder(tmp_path, layout, rgb=rgb)
    if isinstance(content, str):
        (folder / name).write_text(content)
    else:
        _npy_intensities(folder, content)
    with pytest.raises(DatasetError, match=re.escape(message)):
        load_folder(folder)


# -- 6 and 7. a listed file that is no image ---------------------------------------------------------
#: (what the listed file holds: text, or bytes no decoder knows)
NOT_IMAGES = [
    ("005.txt", b"not an image\n"),
    ("005.dat", b"\x00\x01\x02" * 40),
    ("005.png", b"hello, world"),
]


@pytest.mark.parametrize(("name", "data"), NOT_IMAGES)
def test_a_listed_file_that_is_no_image_fails_to_decode_without_a_false_note(
    tmp_path: Path, name: str, data: bytes
) -> None:
    folder = _folder(tmp_path, "diligent")
    (folder / "005.png").unlink()
    (folder / name).write_bytes(data)
    _edit(folder / "filenames.txt", lambda t: t.replace("005.png", name))
    (folder / "stray.txt").write_text("1 1 1\n")  # not listed: still noted
    ds = load_folder(folder)
    assert not any(name in n for n in ds.notes), ds.notes
    assert any("stray.txt" in n for n in ds.notes), ds.notes
    with pytest.raises(DatasetError, match=re.escape(f"{name}: cannot decode image")) as err:
        ds.read(4)
    assert "that maxfs reads" in str(err.value) and "server" not in str(err.value)


@pytest.mark.parametrize("data", [b"", b"plain text\n", b"\x00\x01\x02" * 40])
def test_undecodable_bytes_are_described_without_a_server(data: bytes) -> None:
    with pytest.raises(InvalidInputError) as err:
        decode_bytes(data, "upload 3")
    assert str(err.value) == (
        "upload 3: cannot decode image (not a PNG, TIFF, BMP, JPEG or other image file that maxfs reads)"
    )
