"""The public face: ``import maxfs``; ``solve_folder``/``solve`` equal ``maxfs run``, results open as numpy
and xarray, and the wheel installs one top-level name."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import maxfs
from maxfs.service.cli.main import main
from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.errors import InvalidInputError
from maxfs.worker import synthetic

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, synthetic.Scene]:
    sc = synthetic.bump_scene(12, 40, noise=1.0)
    f = write_npy_folder(
        tmp_path_factory.mktemp("api") / "in", sc.images.astype(np.uint8), sc.lights, sc.mask
    )
    return f, sc


def test_solve_folder_is_bit_identical_to_maxfs_run(folder, tmp_path: Path) -> None:
    f, sc = folder
    assert main(["run", str(f), "-o", str(tmp_path / "out")]) == 0
    cli = maxfs.open_result(tmp_path / "out")
    r = maxfs.solve_folder(f)
    for name in ("normal", "albedo", "inliers", "source", "inlier_count", "depth"):
        np.testing.assert_array_equal(getattr(r, name), getattr(cli, name), err_msg=name)
    assert r.path is None and cli.path is not None
    assert r.eps == cli.eps and r.params == cli.params
    assert cli.response == cli.params["response"] is not None and r.response == cli.response
    err = synthetic.angular_error_deg(r.normal, sc.normals)[sc.mask]
    assert np.nanmean(err) < 5
    assert r.N is r.normal and r.normal.shape == (40, 40, 3) and r.inliers.shape == (12, 40, 40)


def test_solve_on_arrays_equals_the_folder(folder) -> None:
    f, sc = folder
    a = maxfs.solve(sc.images.astype(np.uint8), sc.lights, sc.mask)
    b = maxfs.solve_folder(f)
    np.testing.assert_array_equal(a.normal, b.normal)
    np.testing.assert_array_equal(a.inliers, b.inliers)


def test_options_and_image_selection(folder, tmp_path: Path) -> None:
    f, sc = folder
    r = maxfs.solve_folder(f, tmp_path / "o", images="1-8", solver="l2")
    assert r.inliers.shape[0] == 8 and r.params["solver"] == "l2"
    assert (tmp_path / "o").is_dir() and r.path is not None
    with pytest.raises(InvalidInputError, match="did you mean 'eps'"):
        maxfs.solve_folder(f, esp=2.0)
    with pytest.raises(InvalidInputError, match=r"lights must be \(12, 3\)"):
        maxfs.solve(sc.images, sc.lights[:5])


def test_to_xarray_has_coordinates(folder) -> None:
    pytest.importorskip("xarray")
    r = maxfs.solve_folder(folder[0], solver="l2")
    ds = r.to_xarray()
    assert list(ds.normal.sel(xyz="z").dims) == ["y", "x"]
    np.testing.assert_array_equal(ds.normal.sel(xyz="z").values, r.normal[..., 2])
    assert list(ds.image.values) == list(range(1, 13))
    assert ds.inliers.sel(image=1).shape == (40, 40)


@pytest.mark.slow
def test_wheel_installs_only_maxfs(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path), str(ROOT)],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    (wheel,) = tmp_path.glob("*.whl")
    tops = {
        n.split("/")[0]
        for n in zipfile.ZipFile(wheel).namelist()
        if not n.split("/")[0].endswith(".dist-info")
    }
    assert tops == {"maxfs"}
    names = zipfile.ZipFile(wheel).namelist()
    assert "maxfs/service/static/page/index.html" in names and "maxfs/worker/exact.py" in names


def test_a_result_has_every_output_of_the_table(folder) -> None:
    from maxfs.storage.outputs import OUTPUT_TABLE

    r = maxfs.solve_folder(folder[0], solver="l2")
    for o in OUTPUT_TABLE:
        a = getattr(r, o.name)
        assert a is None if not o.exists(None) else a.shape == o.shape(12, 40, 40, None), o.name
    with pytest.raises(AttributeError, match="its arrays"):
        r.normals  # noqa: B018
