"""Never a silent wrong or empty result (issue #9), with real processes: a reused output
folder, lights that cannot determine a normal, honest solved/certified counts, partial
results, and a mask write cut short by a killed server."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
import zarr

from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.layout import MASK_WRITING, JobStore
from maxfs.worker import synthetic
from tests.faults import fault_env
from tests.procs import Server, poll_until

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _maxfs(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=300, cwd=cwd)


def _scene_folder(tmp: Path, name: str, seed: int = 0, lights: np.ndarray | None = None) -> Path:
    sc = synthetic.bump_scene(8, 48, seed=seed)
    return write_npy_folder(
        tmp / name, sc.images.astype(np.uint8), sc.lights if lights is None else lights, sc.mask
    )


def _normals(out: Path) -> np.ndarray:
    return np.asarray(zarr.open_group(out / "results.zarr", mode="r")["normal"][...])


@pytest.mark.slow
def test_reused_output_of_another_object_is_refused_then_overwritten(tmp_path: Path, uw_psm: Path) -> None:
    out = tmp_path / "cat.zarr"
    assert _maxfs("run", str(uw_psm / "cat"), "-o", str(out), "--workers", "1").returncode == 0
    cat = _normals(out)
    r = _maxfs("run", str(uw_psm / "owl"), "-o", str(out), "--workers", "1")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "holds results for other inputs" in r.stderr and "--overwrite" in r.stderr
    np.testing.assert_array_equal(_normals(out), cat)  # nothing stored was touched
    r = _maxfs("run", str(uw_psm / "owl"), "-o", str(out), "--workers", "1", "--overwrite")
    assert r.returncode == 0, r.stderr
    owl = _normals(out)
    both = np.isfinite(owl[..., 0]) & np.isfinite(cat[..., 0])
    assert both.sum() > 1000 and not np.allclose(owl[both], cat[both])
    r = _maxfs("run", str(uw_psm / "owl"), "-o", str(out), "--workers", "1")
    assert r.returncode == 0 and "tiles already done" in r.stderr


@pytest.mark.slow
def test_changed_image_content_is_refused_and_unchanged_inputs_resume(tmp_path: Path) -> None:
    folder = _scene_folder(tmp_path, "scene")
    out = tmp_path / "out.zarr"
    assert _maxfs("run", str(folder), "-o", str(out), "--eps", "1").returncode == 0
    # touching the files without changing them is still the same input (content digests agree)
    images = np.load(folder / "images.npy")
    np.save(folder / "images.npy", images)
    r = _maxfs("run", str(folder), "-o", str(out), "--eps", "1")
    assert r.returncode == 0 and "tiles already done" in r.stderr, r.stderr
    images[5, 10, 10] ^= 1  # one value of one image: same shape, lights and mask
    np.save(folder / "images.npy", images)
    r = _maxfs("run", str(folder), "-o", str(out), "--eps", "1")
    assert r.returncode == 2 and "image 6 first" in r.stderr and "--overwrite" in r.stderr
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    r = _maxfs("run", str(folder), "-o", str(tmp_path / "other"), "--eps", "1")
    assert r.returncode == 2 and "holds no maxfs results" in r.stderr
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(
    ("lights", "message"),
    [
        (np.array([[0, 0, 1], [0, 0.6, 0.8], [0, -0.6, 0.8], [0, 0.8, 0.6]] * 2), "coplanar"),
        (np.array([[0.0, 0.0, 1.0]] * 8), "rank < 3"),
    ],
    ids=["coplanar", "repeated"],
)
def test_lights_that_cannot_determine_a_normal_are_refused(tmp_path: Path, lights, message) -> None:
    folder = _scene_folder(tmp_path, "bad", lights=lights / np.linalg.norm(lights, axis=1, keepdims=True))
    r = _maxfs("run", str(folder), "-o", str(tmp_path / "out.zarr"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert message in r.stderr and "singular values" in r.stderr
    assert not (tmp_path / "out.zarr").exists()


def _shares(stdout: str) -> tuple[float, float]:
    m = re.search(r"solved ([\d.]+)%, certified optimal ([\d.]+)%", stdout)
    assert m, stdout
    return float(m.group(1)), float(m.group(2))


def test_summary_counts_are_honest(tmp_path: Path) -> None:
    folder = _scene_folder(tmp_path, "scene")
    r = _maxfs("run", str(folder), "-o", str(tmp_path / "l2.zarr"), "--solver", "l2", "--eps", "1")
    assert r.returncode == 0, r.stderr
    assert _shares(r.stdout) == (100.0, 0.0)  # least squares proves nothing
    rec = JobStore.open(tmp_path / "l2.zarr", mode="r").progress()
    assert rec.solved == rec.pixels_done == rec.pixels_total > 0 and rec.certified == 0
    # every value in shadow: nothing can be solved, and the user is told loudly
    dark = tmp_path / "dark"
    sc = synthetic.bump_scene(8, 48)
    write_npy_folder(dark, np.zeros_like(sc.images, dtype=np.uint8), sc.lights, sc.mask)
    r = _maxfs("run", str(dark), "-o", str(tmp_path / "dark.zarr"), "--eps", "1", "--response", "1")
    assert r.returncode == 0, r.stderr
    assert _shares(r.stdout) == (0.0, 0.0)
    assert "WARNING: only 0.0% of the" in r.stderr


def _job(http: httpx.Client, images: np.ndarray, lights: np.ndarray, **params) -> str:
    k, H, W = images.shape
    r = http.post(
        "/jobs", json={"k": k, "height": H, "width": W, "lights": lights.tolist(), "eps": 2.0, **params}
    )
    assert r.status_code == 201, r.text
    jid = r.json()["id"]
    for i in range(k):
        r = http.put(f"/jobs/{jid}/images/{i}", content=images[i].tobytes())
        assert r.status_code == 200, r.text
    return jid


def _mask_put(http: httpx.Client, jid: str, mask: np.ndarray) -> httpx.Response:
    return http.put(
        f"/jobs/{jid}/mask",
        content=mask.astype(np.uint8).tobytes(),
        headers={"Content-Type": "application/octet-stream"},
    )


def _mask_put_until_killed(http: httpx.Client, jid: str, mask: np.ndarray) -> None:
    try:
        _mask_put(http, jid, mask)
    except httpx.HTTPError:  # the server is killed mid-request, on purpose
        pass


def test_mask_cut_short_by_a_killed_server_is_never_used(
    tmp_path: Path, server_factory: Callable[..., Server]
) -> None:
    sc = synthetic.bump_scene(6, 160, seed=1)
    images = sc.images.astype(np.uint8)
    server = server_factory(workers=1, env=fault_env(pause_mask_write=True))
    with httpx.Client(base_url=server.url, timeout=120) as http:
        jid = _job(http, images, sc.lights, tile=32)
        threading.Thread(target=_mask_put_until_killed, args=(http, jid, sc.mask), daemon=True).start()
        store = tmp_path / "data" / "jobs" / jid

        def writing() -> bool:
            row = np.asarray(
                zarr.open_group(store / "results.zarr", mode="r")["inputs/input_digests"][images.shape[0]]
            )
            return bytes(row) == MASK_WRITING

        poll_until(writing, 60, "the server to be part-way through the mask")
        server.kill()
    assert JobStore.open(store, mode="r").mask_state() == "incomplete"
    server = server_factory(workers=1)
    with httpx.Client(base_url=server.url, timeout=120) as http:
        r = http.post(f"/jobs/{jid}/start")
        assert r.status_code == 409 and "upload the mask again" in r.json()["detail"]
        assert _mask_put(http, jid, sc.mask).status_code == 200
        assert http.post(f"/jobs/{jid}/start").status_code == 202
        poll_until(lambda: http.get(f"/jobs/{jid}").json()["state"] == "done", 120, "job done")
        st = http.get(f"/jobs/{jid}").json()
        assert st["progress"]["pixels_total"] == int(sc.mask.sum())
        assert st["progress"]["solved_share"] > 0.9 and st["progress"]["certified_share"] > 0.9
        r = http.get(f"/jobs/{jid}/results/mask.npy")
        assert r.headers["x-maxfs-partial"] == "false"
        # server jobs get the previews and the depth that `maxfs run` makes (issue #13)
        poll_until(lambda: (store / "previews" / "depth.png").exists(), 60, "previews written")
        depth = http.get(f"/jobs/{jid}/results/depth.npy")
        assert depth.status_code == 200, depth.text
    np.testing.assert_array_equal(JobStore.open(store, mode="r").read_mask(), sc.mask)


def test_results_of_an_unfinished_job_say_so_and_fetch_refuses_them(
    tmp_path: Path, server_factory: Callable[..., Server]
) -> None:
    sc = synthetic.bump_scene(12, 64, seed=3)
    server = server_factory(workers=1)
    with httpx.Client(base_url=server.url, timeout=120) as http:
        jid = _job(http, sc.images.astype(np.uint8), sc.lights, solver="milp", tile=16)
        assert http.post(f"/jobs/{jid}/start").status_code == 202
        poll_until(lambda: http.get(f"/jobs/{jid}").json()["state"] == "running", 60, "job running")
        r = http.delete(f"/jobs/{jid}")
        assert r.status_code == 200, r.text
        st = http.get(f"/jobs/{jid}").json()
        assert st["state"] == "cancelled" and st["results"]["available"] and st["results"]["partial"]
        assert st["results"]["resumable"] and st["results"]["note"].startswith(("Partial", "No results"))
        assert http.get(f"/jobs/{jid}/results/normal.npy").headers["x-maxfs-partial"] == "true"
    env = ["--server", server.url]
    r = _maxfs("fetch", jid, "-o", str(tmp_path / "got.zarr"), *env)
    assert r.returncode == 2 and "--partial" in r.stderr and "cancelled" in r.stderr
    assert not (tmp_path / "got.zarr").exists()
    r = _maxfs("fetch", jid, "-o", str(tmp_path / "got.zarr"), "--partial", *env)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "got.zarr" / "results.zarr" / "zarr.json").exists()
    assert not (tmp_path / "got.zarr" / "results.zarr" / "inputs" / "images").exists()  # results only
    assert (tmp_path / "got.zarr" / "maxfs-job.json").exists()
    r = _maxfs("fetch", jid, "-o", str(tmp_path / "all"), "--partial", "--inputs", *env)
    assert (
        r.returncode == 0 and (tmp_path / "all" / "results.zarr" / "inputs" / "images" / "zarr.json").exists()
    )
    server.kill()
    shutil.rmtree(tmp_path / "data", ignore_errors=True)


def test_validating_lights_again_changes_no_bit() -> None:
    """The input identity digests validated lights: validating twice (loader, CLI, store)
    must not move them by an ulp, or a re-run would see "other inputs"."""
    from maxfs.storage.layout import JobSpec, lights_digest
    from maxfs.storage.options import check_lights

    rng = np.random.default_rng(0)
    raw = synthetic.lights_uniform(96) * (1 + 1e-7 * rng.standard_normal((96, 1)))
    once = check_lights(raw)
    np.testing.assert_array_equal(check_lights(once), once)
    spec = JobSpec(96, 4, 4, None, "uint16", raw, None).validate()
    assert lights_digest(spec.validate().validate()) == lights_digest(spec)
