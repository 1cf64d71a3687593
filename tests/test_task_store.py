"""A Dask worker reuses a job's open store for its next tile tasks (:func:`worker.task.open_store`)
exactly while the store is the same: new parameters or a store made again get a fresh one."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.params import JobParams
from maxfs.worker import synthetic
from maxfs.worker.task import TileStatus, open_store, run_tile


def _store(path: Path, eps: float = 2.0) -> JobStore:
    sc = synthetic.bump_scene(6, 16)
    spec = JobSpec(6, 16, 16, None, "uint8", sc.lights)
    store = JobStore.create(path, spec, JobParams.build(eps=eps, tile=8).with_eps(eps))
    for i, img in enumerate(sc.images.astype(np.uint8)):
        store.write_image(i, img)
    return store


def test_the_next_task_reuses_the_store_while_it_is_unchanged(tmp_path: Path) -> None:
    _store(tmp_path / "job")
    a = open_store(str(tmp_path / "job"))
    assert open_store(str(tmp_path / "job")) is a
    digest = a.params.digest()
    assert run_tile(str(tmp_path / "job"), 0, digest).status is TileStatus.DONE
    assert run_tile(str(tmp_path / "job"), 1, digest).status is TileStatus.DONE
    assert open_store(str(tmp_path / "job")) is a  # its own writes leave the group's metadata alone


def test_new_parameters_open_the_store_again(tmp_path: Path) -> None:
    _store(tmp_path / "job")
    a = open_store(str(tmp_path / "job"))
    JobStore.open(tmp_path / "job").set_params(replace(a.params, eps=3.0))
    b = open_store(str(tmp_path / "job"))
    assert b is not a
    assert b.params.eps == 3.0
    assert run_tile(str(tmp_path / "job"), 0, b.params.digest()).status is TileStatus.DONE


def test_a_store_made_again_is_opened_again(tmp_path: Path) -> None:
    _store(tmp_path / "job")
    a = open_store(str(tmp_path / "job"))
    digest = a.params.digest()
    assert run_tile(str(tmp_path / "job"), 0, digest).status is TileStatus.DONE
    shutil.rmtree(tmp_path / "job")
    _store(tmp_path / "job")  # the very same metadata, new folders
    b = open_store(str(tmp_path / "job"))
    assert b is not a
    assert run_tile(str(tmp_path / "job"), 0, digest).status is TileStatus.DONE
    assert b.tile_done(b.tiles()[0])
