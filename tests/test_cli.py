"""The maxfs command line, run as a real process."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from storage.layout import JobStore
from tests.test_datasets import UW, UW_OBJECTS

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _maxfs(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=timeout)


#: Share of object pixels expected to get a normal. The chrome sphere is a mirror
#: (it is there to calibrate the lights): few of its pixels have 3 Lambertian views.
SOLVED_SHARE = {obj: (0.95, 1.0) for obj in UW_OBJECTS} | {"chrome": (0.0, 0.3)}


@pytest.mark.parametrize("obj", UW_OBJECTS)
def test_run_uw_object_writes_sane_outputs(tmp_path: Path, obj: str) -> None:
    out = tmp_path / f"{obj}.zarr"
    r = _maxfs("run", str(UW / obj), "-o", str(out), "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "certified optimal: 100.00%" in r.stdout
    g = zarr.open_group(out, mode="r")
    mask = g["mask"][...]
    normal = g["normal"][...][mask]
    solved = np.isfinite(normal[:, 0])
    lo, hi = SOLVED_SHARE[obj]
    assert lo <= solved.mean() <= hi
    np.testing.assert_allclose(np.linalg.norm(normal[solved], axis=1), 1.0, atol=1e-5)
    if obj != "chrome":  # a diffuse visible surface faces the camera
        assert (normal[solved, 2] > 0).mean() > 0.97
    assert (g["inlier_count"][...][mask][solved] >= 3).all()
    assert not g["inliers"][...][:, mask][:, ~solved].any()
    assert (g["albedo_rgb"][...][mask][solved] >= 0).all()
    assert g["optimal"][...][mask].all()
    assert not np.isfinite(g["normal"][...][~mask]).any()
    for p in ("normal", "albedo", "inlier_count"):
        assert (out / "previews" / f"{p}.png").stat().st_size > 1000
    if obj == "cat":  # running again resumes: nothing is recomputed
        store = JobStore.open(out, mode="r")
        before, n = store.run_counts(), len(store.tiles())
        r = _maxfs("run", str(UW / obj), "-o", str(out), "--workers", "1")
        assert r.returncode == 0 and f"{n} of {n} tiles already done" in r.stderr
        assert JobStore.open(out, mode="r").run_counts() == before


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "/nonexistent/folder", "-o", "x.zarr"], "is not a folder"),
        (["run", str(UW), "-o", "x.zarr"], "is not a recognised dataset"),
        (["run", str(UW / "cat"), "-o", "x.zarr", "--eps", "-2"], "eps must be positive"),
        (["status", "0" * 32, "--server", "http://127.0.0.1:9"], "cannot talk to the server"),
    ],
)
def test_cli_errors_are_messages_not_tracebacks(tmp_path: Path, args: list[str], message: str) -> None:
    r = subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2
    assert message in r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "x.zarr").exists()
