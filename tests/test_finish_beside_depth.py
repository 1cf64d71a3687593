"""The Dask path's finishing steps, depth on a thread beside the previews and the calibration
checks (:func:`service.runs.local.finish_beside_depth`), write what :func:`finish` writes."""

from __future__ import annotations

import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import zarr

from maxfs.service.runs.local import finish, finish_beside_depth, load_depth_kernels, run_folder
from maxfs.service.runs.timings import Timings
from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.inputs import load_folder
from maxfs.storage.params import JobParams
from maxfs.worker import synthetic


def test_depth_beside_the_previews_and_checks_writes_the_same(tmp_path: Path) -> None:
    sc = synthetic.bump_scene(10, 64, seed=3)
    folder = write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask)
    params = JobParams.build(eps=2.0, tile=32)
    run_folder(load_folder(folder), tmp_path / "a", params)
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    shutil.rmtree(tmp_path / "b" / "previews")
    found = finish(tmp_path / "a")
    pool = ThreadPoolExecutor(1)
    pool.submit(load_depth_kernels, params)
    tm = Timings()
    assert finish_beside_depth(tmp_path / "b", tm, None, pool) == found
    pool.shutdown()
    assert list(tm.phases) == ["previews", "depth and derived results", "calibration checks"]
    a, b = (zarr.open_group(tmp_path / n / "results.zarr", mode="r") for n in "ab")
    np.testing.assert_array_equal(a["depth"][...], b["depth"][...])
    assert dict(a["depth"].attrs) == dict(b["depth"].attrs)
    pngs = sorted(p.name for p in (tmp_path / "a" / "previews").iterdir())
    assert pngs == sorted(p.name for p in (tmp_path / "b" / "previews").iterdir())
    for name in pngs:
        assert (tmp_path / "a" / "previews" / name).read_bytes() == (
            tmp_path / "b" / "previews" / name
        ).read_bytes()


def test_loading_the_depth_kernels_takes_any_depth_options() -> None:
    for depth in ("ls", "bini", "none"):
        load_depth_kernels(JobParams.build(eps=2.0, depth=depth))
    load_depth_kernels(JobParams.build(eps=2.0, fx=500.0, fy=500.0, cx=10.0, cy=12.0, distance=3.0))
