"""Progress inside a running tile: a job of a few long tiles does not sit at 0 % until one ends."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import maxfs.worker.task as task
from maxfs.service.http.models import status_body
from maxfs.service.runs.inprocess import run_in_process
from maxfs.service.runs.local import ingest
from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.inputs import load_folder
from maxfs.storage.params import JobParams
from maxfs.storage.records import JobRecord, JobState
from maxfs.worker import cancel, synthetic
from maxfs.worker.exact import exact_pixels
from maxfs.worker.problem import slabs


def test_the_exact_kernel_reports_how_far_it_is_between_batches() -> None:
    sc = synthetic.bump_scene(12, 24, noise=1.0)
    I = sc.images.reshape(12, -1).T[sc.mask.ravel()].astype(np.float64)
    V = I > 1.0
    lo, hi = slabs(I, 2.0)
    heard: list[tuple[int, int]] = []
    with cancel.cancel_points(lambda: None, report=lambda d, n: heard.append((d, n)), report_interval=0.0):
        exact_pixels(I, lo, hi, V, sc.lights, 10.0, 10**6)
    P = len(I)
    assert len(heard) >= 2, heard
    assert all(n == P and 0 < d < P for d, n in heard)
    assert [d for d, _ in heard] == sorted(d for d, _ in heard)
    # without a report the kernel runs as before; the answer never depends on the batches
    plain = exact_pixels(I, lo, hi, V, sc.lights, 10.0, 10**6)
    with cancel.cancel_points(lambda: None, report=lambda d, n: None, report_interval=0.0):
        np.testing.assert_array_equal(exact_pixels(I, lo, hi, V, sc.lights, 10.0, 10**6)[2], plain[2])


def test_progress_notes_count_only_unfinished_tiles(tmp_path: Path) -> None:
    sc = synthetic.bump_scene(6, 32)
    folder = write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask)
    store, _ = ingest(load_folder(folder), tmp_path / "out", JobParams.build(eps=1.0, tile=16))
    assert store.running_pixels() == 0
    store.note_tile_progress(1, 40)
    store.note_tile_progress(2, 7)
    store.note_tile_progress(2, 9)  # replaced, not added
    assert store.running_pixels() == 49
    done = np.zeros(len(store.tiles()), bool)
    done[1] = True
    assert store.running_pixels(done) == 9
    store.clear_tile_progress(2)
    assert store.running_pixels(done) == 0
    store.clear_tile_progress()
    assert store.running_pixels() == 0
    assert not any("maxfs-progress" in name for _, name in store.download_files())


def test_the_status_fraction_counts_pixels_solved_in_running_tiles() -> None:
    rec = JobRecord(id="j", state=JobState.RUNNING, tiles_total=1, pixels_total=1000, pixels_running=250)
    p = status_body(rec, "http://x")["progress"]
    assert p["fraction"] == pytest.approx(0.25) and p["pixels_running"] == 250
    rec.state = JobState.FAILED  # what stopped is not progress
    assert status_body(rec, "http://x")["progress"]["fraction"] == 0.0


def test_a_one_tile_run_reports_progress_before_its_tile_ends(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(task, "PROGRESS_SECONDS", 0.0)
    sc = synthetic.bump_scene(24, 48, noise=1.5)
    folder = write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask)
    ingest(load_folder(folder), tmp_path / "out", JobParams.build(eps=2.0, tile=64))
    seen: list[tuple[int, int, int]] = []
    rec = run_in_process(
        tmp_path / "out",
        threads=1,
        progress_interval=0.0,
        on_progress=lambda r: seen.append((r.tiles_done, r.pixels_running, r.pixels_total)),
    )
    assert rec.state is JobState.DONE and rec.tiles_total == 1
    inside = [run for done, run, _ in seen if done == 0 and run > 0]
    assert inside, seen
    assert max(inside) < rec.pixels_total
    assert rec.pixels_running == 0
