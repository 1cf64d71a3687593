"""More input layouts: a multi-page TIFF stack, a plain folder of images; choosing images; light warnings."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from maxfs.storage.errors import DatasetError, InvalidInputError
from maxfs.storage.folders import conditioning_warning, parse_selection, select_images
from maxfs.storage.imageio import encode_png
from maxfs.storage.inputs import load_folder
from maxfs.storage.layout import JobStore
from maxfs.worker import synthetic

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _scene(k: int = 8, size: int = 24):
    s = synthetic.sphere(k, size, specular=0.0)
    return s.images.astype(np.uint8), s.lights, s.mask


def test_multipage_tiff_stack_reads_page_by_page(tmp_path: Path) -> None:
    images, lights, mask = _scene()
    tifffile.imwrite(tmp_path / "stack.tif", images)  # one page per image
    np.savetxt(tmp_path / "light_directions.txt", lights)
    (tmp_path / "mask.png").write_bytes(encode_png(mask.astype(np.uint8) * 255))
    ds = load_folder(tmp_path)
    assert ds.layout == "tiff-stack" and ds.k == 8 and (ds.height, ds.width) == (24, 24)
    for i in range(ds.k):
        np.testing.assert_array_equal(ds.read(i), images[i])
    np.testing.assert_array_equal(ds.mask, mask)
    np.testing.assert_allclose(ds.lights, lights / np.linalg.norm(lights, axis=1, keepdims=True))

    rgb = np.repeat(images[..., None], 3, axis=3).astype(np.uint16) * 257
    d2 = tmp_path / "rgb"
    d2.mkdir()
    tifffile.imwrite(d2 / "images.tiff", rgb, photometric="rgb")
    np.savetxt(d2 / "lights.txt", lights)
    ds = load_folder(d2)
    assert ds.channels == 3 and ds.dtype == "uint16"
    np.testing.assert_array_equal(ds.read(5), rgb[5])


def test_plain_folder_takes_images_in_natural_name_order(tmp_path: Path) -> None:
    images, lights, _ = _scene(k=11)
    for i, img in enumerate(images):
        (tmp_path / f"img{i + 1}.png").write_bytes(encode_png(img))  # img1 .. img11: img2 before img10
    (tmp_path / "mask.png").write_bytes(encode_png(np.full((24, 24), 255, np.uint8)))
    (tmp_path / "Normal_gt.png").write_bytes(encode_png(np.zeros((24, 24, 3), np.uint8)))
    np.savetxt(tmp_path / "lights.txt", lights)
    ds = load_folder(tmp_path)
    assert ds.layout == "plain" and ds.k == 11 and ds.mask.all()
    for i in (0, 1, 9, 10):
        np.testing.assert_array_equal(ds.read(i), images[i])
    np.savetxt(tmp_path / "lights.txt", lights[:10])
    with pytest.raises(DatasetError, match="10 light directions for 11 images"):
        load_folder(tmp_path)


def test_selection_parses_and_restricts_images_and_lights(tmp_path: Path) -> None:
    assert parse_selection("1-3,5", 8) == [0, 1, 2, 4]
    bad_cases = (
        ("0-3", "outside"),
        ("1-9", "outside"),
        ("2,2,3", "image 2 is chosen twice"),
        ("1-4,3-5", "images 3, 4 are chosen twice"),
        ("1,x", "not N"),
        ("1,2", "3"),
        ("", "empty"),
        (" , ", "empty"),
    )
    for bad, msg in bad_cases:
        with pytest.raises(InvalidInputError, match=msg):
            parse_selection(bad, 8)
    images, lights, _ = _scene()
    tifffile.imwrite(tmp_path / "images.tif", images)
    np.savetxt(tmp_path / "lights.txt", lights)
    ds = select_images(load_folder(tmp_path), [7, 0, 3, 4])
    assert ds.k == 4 and ds.fingerprint() is None
    np.testing.assert_array_equal(ds.read(0), images[7])
    np.testing.assert_allclose(ds.lights[2], lights[3] / np.linalg.norm(lights[3]))


def test_badly_conditioned_lights_warn() -> None:
    good = synthetic.lights_uniform(12)
    assert conditioning_warning(good) is None
    narrow = synthetic.lights_uniform(12, max_zenith_deg=5.0)  # nearly the same direction
    w = conditioning_warning(narrow)
    assert w is not None and "badly conditioned" in w


@pytest.mark.slow
def test_cli_run_with_images_on_a_tiff_stack(tmp_path: Path) -> None:
    images, lights, _ = _scene(k=10, size=20)
    data = tmp_path / "data"
    data.mkdir()
    tifffile.imwrite(data / "images.tif", images)
    np.savetxt(data / "light_directions.txt", lights)
    out = tmp_path / "out.zarr"
    opts = ["--shadow", "2", "--max-nodes", "5000", "--milp-time-limit", "5"]
    r = subprocess.run(
        [MAXFS, "run", str(data), "-o", str(out), "--images", "1-6,9", "--workers", "1", "--eps", "1", *opts],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert r.returncode == 0, r.stderr
    assert "7 images of 20 x 20 (tiff-stack, images 7 of 10" in r.stderr
    store = JobStore.open(out, mode="r")
    assert store.spec.k == 7
    p = store.params
    assert (p.shadow, p.max_nodes, p.milp_time_limit) == (2.0, 5000, 5.0)
    # an in-process run keeps the stack in memory and records each image's digest
    from maxfs.storage.layout import array_digest

    assert store.digests()[6] == array_digest(images[8], store.spec.digest)
