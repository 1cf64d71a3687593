"""An output folder's results are never lost to a mistake in a later run, and a folder that holds
nothing worth keeping never stands in the way (``maxfs run`` into an existing ``-o``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from maxfs.service.runs.local import ASIDE, ingest, run_folder
from maxfs.storage.datasets import Dataset, write_npy_folder
from maxfs.storage.errors import ConflictError, InvalidInputError
from maxfs.storage.imageio import encode_png
from maxfs.storage.inputs import load_folder
from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.params import ESTIMATE_MIN_IMAGES, JobParams
from maxfs.storage.requests import job_params
from maxfs.worker import synthetic
from tests.stores import finish_a_tile

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _npy_folder(path: Path, k: int = 8, size: int = 32, sink: float = 0.4) -> Dataset:
    sc = synthetic.bump_scene(k, size, sink=sink)
    return load_folder(write_npy_folder(path, sc.images.astype(np.uint8), sc.lights, sc.mask))


def _png_folder(path: Path, k: int = 8, size: int = 32) -> Path:
    """A DiLiGenT-layout folder of 8-bit PNGs (decoded image by image, so one can be broken)."""
    sc = synthetic.bump_scene(k, size, seed=3)
    path.mkdir(parents=True)
    names = [f"{i + 1:03d}.png" for i in range(k)]
    for name, img in zip(names, sc.images, strict=True):
        (path / name).write_bytes(encode_png(np.clip(img, 0, 255).astype(np.uint8)))
    (path / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(path / "light_directions.txt", sc.lights)
    (path / "mask.png").write_bytes(encode_png((sc.mask * 255).astype(np.uint8)))
    return path


# --- a store with no finished tile is replaced; one with a finished tile is refused ---------------
CHANGES = [
    ("other parameters", lambda ds, tmp: ds, JobParams.build(eps=2.0, tile=16), "eps 1.0 -> 2.0"),
    (
        "other images",
        lambda ds, tmp: _npy_folder(tmp / "other", sink=0.2),
        JobParams.build(eps=1.0, tile=16),
        "images",
    ),
]


@pytest.mark.parametrize(("what", "second", "params", "refusal"), CHANGES, ids=[c[0] for c in CHANGES])
def test_a_store_with_no_finished_tile_is_replaced_with_a_note(
    tmp_path: Path, what, second, params, refusal
) -> None:
    ds = _npy_folder(tmp_path / "in")
    out = tmp_path / "out"
    ingest(ds, out, JobParams.build(eps=1.0, tile=16))  # a run that stopped before its first tile
    other = second(ds, tmp_path)
    store, note = ingest(other, out, params)
    assert note.startswith(f"replacing {out}") and "no finished tile" in note
    assert store.params.eps == params.eps and store.progress().tiles_done == 0


@pytest.mark.parametrize(("what", "second", "params", "refusal"), CHANGES, ids=[c[0] for c in CHANGES])
def test_a_store_with_a_finished_tile_is_refused_and_kept(
    tmp_path: Path, what, second, params, refusal
) -> None:
    ds = _npy_folder(tmp_path / "in")
    out = tmp_path / "out"
    store, _ = ingest(ds, out, JobParams.build(eps=1.0, tile=16))
    finish_a_tile(store, ds)
    with pytest.raises(ConflictError, match=refusal):
        ingest(second(ds, tmp_path), out, params)
    kept = JobStore.open(out, mode="r")
    assert kept.params.eps == 1.0 and kept.progress().tiles_done == 1


def test_an_empty_mask_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    sc = synthetic.bump_scene(8, 16, seed=2)
    ds = load_folder(write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask * 0))
    with pytest.raises(InvalidInputError, match="selects no pixel"):
        ingest(ds, tmp_path / "out", JobParams.build(eps=1.0, tile=16))
    assert not (tmp_path / "out").exists()


# --- --overwrite removes the old results only once the new run has finished a tile --------------
def _normals(out: Path) -> np.ndarray:
    return JobStore.open(out, mode="r").read_output("normal")


def test_overwrite_with_a_broken_image_keeps_the_old_results(tmp_path: Path) -> None:
    good = _png_folder(tmp_path / "good")
    out = tmp_path / "out"
    params = JobParams.build(eps=3.0, tile=16, solver="l2")
    _, rec = run_folder(load_folder(good), out, params, workers=1)
    assert rec.state.value == "done"
    before = _normals(out)
    bad = tmp_path / "bad"
    shutil.copytree(good, bad)
    (bad / "005.png").write_bytes((good / "005.png").read_bytes()[:200])  # cut short
    notes: list[str] = []
    with pytest.raises(InvalidInputError, match=r"005\.png"):
        run_folder(load_folder(bad), out, params, workers=1, overwrite=True, on_note=notes.append)
    np.testing.assert_array_equal(_normals(out), before)
    assert notes and notes[-1].startswith(f"kept the earlier results in {out}")
    assert not (tmp_path / ASIDE.format(name="out")).exists()


def test_overwrite_that_finishes_replaces_the_old_results(tmp_path: Path) -> None:
    good = _png_folder(tmp_path / "good")
    out = tmp_path / "out"
    run_folder(load_folder(good), out, JobParams.build(eps=3.0, tile=16, solver="l2"), workers=1)
    _, rec = run_folder(
        load_folder(good), out, JobParams.build(eps=6.0, tile=16, solver="l2"), workers=1, overwrite=True
    )
    assert rec.state.value == "done" and JobStore.open(out, mode="r").params.eps == 6.0
    assert not (tmp_path / ASIDE.format(name="out")).exists()


# --- other inputs refused before anything is stored or run --------------------------------------
@pytest.mark.parametrize("options", [{}, {"response": 1.0}, {"response": "auto"}])
def test_too_few_images_to_estimate_eps_are_refused_naming_what_to_give(options: dict) -> None:
    k = ESTIMATE_MIN_IMAGES - 1
    spec = JobSpec(k, 16, 16, None, "uint8", synthetic.lights_uniform(k)).validate()
    with pytest.raises(InvalidInputError) as e:
        job_params(spec, {"eps": "auto"} | options, 1 << 30)
    assert f"{k} images are too few to estimate eps " in str(e.value) and "--eps" in str(e.value)
    # eps given: the response, if "auto", falls back to the linear sensor's when the job runs
    assert job_params(spec, {"eps": 3.0} | options, 1 << 30).eps_request == 3.0


@pytest.mark.parametrize("argv", [["--workers", "0"], ["--workers", "-1"], ["--workers", "two"]])
def test_workers_below_one_are_refused_by_the_command_line(tmp_path: Path, argv: list[str]) -> None:
    r = subprocess.run(
        [MAXFS, "run", str(tmp_path), "-o", str(tmp_path / "o"), *argv], capture_output=True, text=True
    )
    assert r.returncode == 2 and "--workers must be" in r.stderr and "Traceback" not in r.stderr


def test_maxfs_workers_below_one_is_refused_by_the_settings(monkeypatch) -> None:
    from maxfs.service.settings import Settings

    monkeypatch.setenv("MAXFS_WORKERS", "0")
    with pytest.raises(InvalidInputError, match="MAXFS_WORKERS must be at least 1, got 0"):
        Settings()
    monkeypatch.delenv("MAXFS_WORKERS")
    with pytest.raises(InvalidInputError, match="workers must be at least 1, got -1"):
        Settings(workers=-1)


def test_export_of_a_job_with_nothing_solved_says_so(tmp_path: Path) -> None:
    ds = _npy_folder(tmp_path / "in")
    ingest(ds, tmp_path / "out", JobParams.build(eps=1.0, tile=16))
    r = subprocess.run([MAXFS, "export", str(tmp_path / "out")], capture_output=True, text=True)
    assert r.returncode == 2 and "no estimated normal yet" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out-export").exists()
