"""Calibration checks (worker/calibration.py): each common calibration mistake is warned about with
its reason, through the CLI and HTTP, and good data gets no warning.

Fast tests exercise the pure checks on analytic scenes; the slow ones run ``maxfs run`` on broken
copies of the DiLiGenT cat crop (the mistakes of issue 21), ``maxfs submit`` to a real server with
broken synthetic scenes, and every shared dataset and synthetic scene for false alarms.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest

from maxfs.service.cli import main as cli
from maxfs.storage.datasets import folder_notes, write_npy_folder
from maxfs.storage.inputs import load_folder
from maxfs.storage.observations import ObservationModel
from maxfs.storage.records import JobRecord, JobState
from maxfs.worker import calibration as cal
from maxfs.worker import synthetic
from maxfs.worker.calibration import MISTAKES, miscalibrated_copy
from tests import data
from tests.procs import Server

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _observations(sc: synthetic.Scene, lights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P, k) grey values and usable flags of a scene's masked pixels, as the checks get them."""
    raw = np.clip(sc.images, 0, 255).astype(np.uint8)[:, sc.mask]
    grey, _, sat = ObservationModel.for_input(np.uint8, raw.shape[0], None).prepare(raw)
    return grey, ~sat


# -- the pure checks ---------------------------------------------------------------------------
def test_lights_facing_away() -> None:
    L = synthetic.lights_uniform(12)
    assert not cal.lights_facing(L).tripped and cal.lights_facing(L).value == 0.0
    f = cal.lights_facing(L * [1, 1, -1])
    assert f.tripped and f.value == 1.0 and "negate the lights' z" in f.message


def test_normals_facing_away() -> None:
    n = synthetic.sphere(8, 32).normals
    assert not cal.normals_facing(n).tripped
    f = cal.normals_facing(n * [1, 1, -1])
    assert f.tripped and f.value == 1.0 and "face away" in f.message
    assert cal.normals_facing(np.full((4, 4, 3), np.nan)).value is None


def test_light_order_and_intensities_against_the_data() -> None:
    sc = synthetic.sphere(24, 48, noise=1.0, specular=30.0)
    grey, ok = _observations(sc)
    assert not any(f.tripped for f in cal.light_checks(grey, ok, sc.lights))
    shuffled = sc.lights[np.random.default_rng(2).permutation(24)]
    order = {f.check: f for f in cal.light_checks(grey, ok, shuffled)}[cal.ORDER_CHECK]
    assert order.tripped and order.value > 0.9 and "another order" in order.message
    # lights of unequal brightness, read as equal (intensities missing): each image scaled
    gains = np.random.default_rng(3).uniform(0.4, 1.6, 24)
    dim = dataclasses.replace(sc, images=sc.images * gains[:, None, None])
    found = {f.check: f for f in cal.light_checks(*_observations(dim), sc.lights)}
    assert found[cal.GAIN_CHECK].tripped and "intensities" in found[cal.GAIN_CHECK].message
    assert not found[cal.ORDER_CHECK].tripped  # tested on gain-corrected lights: one reason, not two


def test_light_checks_abstain_where_the_data_cannot_tell() -> None:
    """A mirror (lit in one image or two per pixel) or too few images: no value, no warning."""
    k = 12
    grey = np.zeros((500, k))
    grey[np.arange(500), np.arange(500) % k] = 200.0
    found = cal.light_checks(grey, np.ones_like(grey, bool), synthetic.lights_uniform(k))
    assert all(f.value is None and not f.tripped for f in found)
    sc = synthetic.sphere(5, 32)
    assert all(f.value is None for f in cal.light_checks(*_observations(sc), sc.lights))


def test_y_flip_shows_in_the_integrability_of_the_normals() -> None:
    for sc in (synthetic.sphere(8, 64), synthetic.realistic_scene(8, 64)):
        good = cal.flip_integrability(sc.normals)
        flipped = cal.flip_integrability(sc.normals * [1, -1, 1])
        assert good.value < 0 and not good.tripped
        assert flipped.tripped and flipped.value > 2 * cal.FLIP_Z and "flipped" in flipped.message
    # where the shape cannot tell (a plane under noise) the test stays near chance either way
    plane = np.zeros((64, 64, 3))
    plane[..., 2] = 1.0
    plane += np.random.default_rng(0).normal(0.0, 0.05, plane.shape)
    for n in (plane, plane * [1, -1, 1]):
        f = cal.flip_integrability(n)
        assert abs(f.value) < 4 and not f.tripped


def test_no_mask_background_share() -> None:
    bright = np.full((40, 40), 150.0)
    assert not cal.no_mask(bright, 3.0).tripped
    bright[:, :20] = 1.0
    f = cal.no_mask(bright, 3.0)
    assert f.tripped and f.value == 0.5 and "no mask was given" in f.message


def test_folder_notes_name_missing_and_unknown_text_files(tmp_path: Path) -> None:
    (tmp_path / "light_intensity.txt").write_text("1 1 1\n")
    (tmp_path / "README.txt").write_text("a dataset\n")
    notes = folder_notes(
        tmp_path,
        ("filenames.txt", "light_directions.txt", "light_intensities.txt"),
        expected=("light_intensities.txt",),
    )
    assert len(notes) == 2
    assert "no light_intensities.txt" in notes[0] and "light_intensity.txt" in notes[1]
    assert "README" not in notes[1]


def test_record_and_cli_summary_say_calibration_suspect() -> None:
    rec = JobRecord(
        id="x", state=JobState.DONE, pixels_total=10, pixels_done=10, solved_pixels=10, certified_pixels=10
    )
    assert not any("calibration" in w for w in rec.warnings()) and "suspect" not in cli.shares(rec)
    rec.calibration = ["light order: the lights explain the images hardly better than ..."]
    assert rec.warnings()[-1].startswith("calibration suspect: light order:")
    assert cli.shares(rec).endswith("certified optimal 100.0% but calibration suspect: light order")
    assert JobRecord.from_json(json.loads(json.dumps(rec.to_json()))).calibration == rec.calibration


# -- through the CLI: the mistakes of issue 21 on the DiLiGenT cat crop ------------------------
EXPECTED = {
    "no intensities": ("image brightness vs light intensities", "no light_intensities.txt"),
    "misnamed intensities": ("image brightness vs light intensities", "light_intensity.txt"),
    "lights permuted": ("light order", "another order"),
    "y down": ("normals integrate (y flip)", "flipped"),
    "z negated": ("lights facing away", "normals facing away"),
    "no mask": ("no mask", "background included"),
}


@pytest.mark.slow
@pytest.mark.parametrize("mistake", [None, *MISTAKES])
def test_cli_run_warns_about_each_calibration_mistake(
    tmp_path: Path, diligent: Path, mistake: str | None, capsys: pytest.CaptureFixture
) -> None:
    folder = diligent / "catPNG"
    if mistake is not None:
        folder = miscalibrated_copy(folder, tmp_path / "cat", mistake)
    assert (
        cli.main(
            [
                "run",
                str(folder),
                "-o",
                str(tmp_path / "out"),
                "--gt",
                str(diligent / "catPNG" / "Normal_gt.mat"),
            ]
        )
        == 0
    )
    out, err = capsys.readouterr()
    certified = next(ln for ln in out.splitlines() if "certified optimal" in ln)
    rec = json.loads((tmp_path / "out" / "maxfs-job.json").read_text())
    if mistake is None:
        assert "suspect" not in out + err and rec["calibration"] == []
        return
    assert "but calibration suspect" in certified
    for needle in EXPECTED[mistake]:
        assert needle in out + err
    assert rec["calibration"] and all("calibration suspect" in out for _ in rec["calibration"])


# -- through HTTP: broken synthetic scenes sent to a real server -------------------------------
def _maxfs(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=300)


def _variants(root: Path) -> dict[str, tuple[Path, str | None]]:
    """Synthetic sphere folders: right, and one calibration mistake each (the check expected)."""
    sc = synthetic.sphere(24, 48, noise=1.0, specular=30.0)
    img = np.clip(sc.images, 0, 255).astype(np.uint8)
    gains = np.random.default_rng(3).uniform(0.4, 1.0, 24)
    out = {
        "good": (write_npy_folder(root / "good", img, sc.lights, sc.mask), None),
        "permuted": (
            write_npy_folder(
                root / "perm", img, sc.lights[np.random.default_rng(1).permutation(24)], sc.mask
            ),
            "light order",
        ),
        "y down": (
            write_npy_folder(root / "ydown", img, sc.lights * [1, -1, 1], sc.mask),
            "normals integrate",
        ),
        "z negated": (
            write_npy_folder(root / "zneg", img, sc.lights * [1, 1, -1], sc.mask),
            "lights facing away",
        ),
        "no intensities": (
            write_npy_folder(
                root / "dim", np.round(img * gains[:, None, None]).astype(np.uint8), sc.lights, sc.mask
            ),
            "image brightness",
        ),
        "no mask": (write_npy_folder(root / "nomask", img, sc.lights), "no mask"),
    }
    # the same dimmed images with their intensities given: right again
    good = write_npy_folder(
        root / "dim-right", np.round(img * gains[:, None, None]).astype(np.uint8), sc.lights, sc.mask
    )
    np.savetxt(good / "intensities.txt", gains)
    out["intensities given"] = (good, None)
    return out


@pytest.mark.slow
def test_http_status_warns_about_calibration_mistakes(
    tmp_path: Path, server_factory: Callable[..., Server]
) -> None:
    server = server_factory(workers=2, graceful=True)
    url = ["--server", server.url]
    ids = {}
    for name, (folder, _) in _variants(tmp_path).items():
        r = _maxfs("submit", str(folder), *url)
        assert r.returncode == 0, r.stderr
        ids[name] = r.stdout.split()[0]
    for name, (_, expected) in _variants(tmp_path / "again").items():
        r = _maxfs("wait", ids[name], *url, "--json")
        assert r.returncode == 0, r.stderr
        st = httpx.get(f"{server.url}/jobs/{ids[name]}").json()
        assert st["state"] == "done"
        status_line = _maxfs("status", ids[name], *url).stdout
        if expected is None:
            assert st["calibration"] == [] and st["warnings"] == [], (name, st["warnings"])
            assert "suspect" not in status_line
            continue
        assert any(c.startswith(expected) for c in st["calibration"]), (name, st["calibration"])
        assert any(w.startswith(f"calibration suspect: {expected}") for w in st["warnings"])
        assert (
            "but calibration suspect" in status_line
            and f"warning: calibration suspect: {expected}" in status_line
        )


# -- no false alarms ---------------------------------------------------------------------------
SCENES: dict[str, Callable[[], synthetic.Scene]] = {
    "sphere12": lambda: synthetic.sphere(12, 64, noise=1.0),
    "sphere8": lambda: synthetic.sphere(8, 64),
    "bumps24": lambda: synthetic.bump_scene(24, 64, noise=1.0),
    "bumps8": lambda: synthetic.bump_scene(8, 64, noise=2.0),
    "bumps96": lambda: synthetic.bump_scene(96, 64),
    "realistic48": lambda: synthetic.realistic_scene(48, 64),
    "realistic12-8bit": lambda: synthetic.realistic_scene(12, 64, bits=8),
}
GOOD = [
    *(f"diligent/{o}PNG" for o in ("cat", "cow", "pot1")),
    *(f"uw-psm/{o}" for o in data.UW_OBJECTS),
    *(f"synthetic/{n}" for n in SCENES),
]


@pytest.mark.slow
@pytest.mark.parametrize("name", GOOD)
def test_no_calibration_warning_on_good_data(tmp_path: Path, name: str) -> None:
    """Every shared dataset and the synthetic scenes: no calibration warning from ``maxfs run``."""
    kind, obj = name.split("/")
    if kind == "synthetic":
        sc = SCENES[obj]()
        dtype = np.uint16 if sc.saturation > 255 else np.uint8
        folder = write_npy_folder(tmp_path / obj, sc.images.astype(dtype), sc.lights, sc.mask)
    else:
        folder = data.require((data.DILIGENT if kind == "diligent" else data.UW) / obj)
    assert not load_folder(folder).notes
    out = tmp_path / "out"
    r = subprocess.run(
        [MAXFS, "run", str(folder), "-o", str(out)], capture_output=True, text=True, timeout=280
    )
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "maxfs-job.json").read_text())["calibration"] == [], r.stdout
    assert "suspect" not in r.stdout + r.stderr
