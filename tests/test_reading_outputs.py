"""Outputs open the way a researcher expects (issue 25): store and export names agree, PNGs read
as readers expect, previews say what their greys mean."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.params import JobParams


def _colour_store(path: Path) -> JobStore:
    lights = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, 0.5, 0.866]])
    spec = JobSpec(3, 16, 16, 3, "uint8", lights, np.ones((3, 3)))
    store = JobStore.create(path, spec, JobParams.build(eps=1.0, tile=16))
    g = store.group
    g["normal"][...] = np.broadcast_to(np.array([0.0, 0.6, 0.8], np.float32), (16, 16, 3))
    g["albedo"][...] = np.full((16, 16), 50.0, np.float32)
    g["albedo_rgb"][...] = np.broadcast_to(np.array([40.0, 50.0, 60.0], np.float32), (16, 16, 3))
    return store


def test_export_names_albedo_as_the_store_does(tmp_path: Path) -> None:
    from maxfs.service.results.export import export

    store = _colour_store(tmp_path / "res")
    m = export(store.path, tmp_path / "x", items=("normal", "albedo"))
    grey, rgb = np.load(tmp_path / "x" / "albedo.npy"), np.load(tmp_path / "x" / "albedo_rgb.npy")
    np.testing.assert_array_equal(grey, store.read_output("albedo"))  # grey, like the store's albedo
    np.testing.assert_array_equal(rgb, store.read_output("albedo_rgb"))
    assert grey.shape == (16, 16) and rgb.shape == (16, 16, 3)
    assert {"albedo.npy", "albedo.png", "albedo_rgb.npy", "albedo_rgb.png"} <= set(m["files"])
    assert {"normal.png", "normal16.png"} <= set(m["files"])


def test_docs_say_how_to_read_every_exported_file(tmp_path: Path) -> None:
    """docs/outputs.md has a line for each file an export writes (the mesh and depth included)."""
    from maxfs.service.results.export import export

    store = _colour_store(tmp_path / "res")
    m = export(store.path, tmp_path / "x")
    doc = (Path(__file__).parents[1] / "docs" / "outputs.md").read_text()
    missing = [name for name in [*m["files"], "export.json"] if f"`{name}`" not in doc]
    assert not missing, f"docs/outputs.md does not describe {missing}"


def test_the_inlier_count_preview_has_a_legend(tmp_path: Path) -> None:
    from maxfs.service.runs.local import write_previews
    from maxfs.storage.imageio import read_image

    store = _colour_store(tmp_path / "res")
    store.group["inlier_count"][...] = np.full((16, 16), 3, np.uint16)
    write_previews(JobStore.open(store.path, mode="r"))
    png = read_image(store.path / "previews" / "inlier_count.png")
    assert png.shape[1] == 16 and png.shape[0] > 16  # the image, then the legend under it
    assert (png[:16] == 255).all()  # 3 of 3 images: white
    ramp = png[18]  # the legend's ramp: black (0 images) to white (all)
    assert ramp[0] == 0 and ramp[-1] == 255 and (np.diff(ramp.astype(int)) >= 0).all()
    assert (png[24:] > 0).any()  # its labels
    normal = read_image(store.path / "previews" / "normal.png")
    assert normal.shape == (16, 16, 3)  # a colour map: no legend
