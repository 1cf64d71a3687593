"""Raw values on a coarser grid than their type: 12-bit data shifted into 16-bit files, 8-bit data
shifted or scaled to 16 bits. The step is measured when a job starts, on the eps sample, whatever
eps was asked for; a stack then gives the same normals in any container its values fit."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

import maxfs
from maxfs.service.cli.main import main
from maxfs.service.cli.verbs import format_status
from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.observations import QUANTUM_EVIDENCE, ObservationModel, raw_quantum
from maxfs.storage.params import JobParams
from maxfs.worker import synthetic

RNG = np.random.default_rng(7)
NOISY16 = RNG.integers(0, 65536, (6, 20, 20)).astype(np.uint16)
LEVELS = RNG.integers(0, 4096, (6, 20, 20)).astype(np.uint16)  # 12-bit values
BYTES = RNG.integers(0, 256, (6, 20, 20)).astype(np.uint16)  # 8-bit values

#: (raw values, the step they have)
QUANTA = {
    "16-bit, every value": (NOISY16, 1),
    "12-bit, unshifted": (LEVELS, 1),
    "12-bit shifted left 4": (LEVELS << 4, 16),
    "10-bit shifted left 6": ((LEVELS >> 2) << 6, 64),
    "8-bit shifted left 8": (BYTES << 8, 256),
    "8-bit scaled by 257": (BYTES * 257, 257),
    "8-bit as uint8": (BYTES.astype(np.uint8), 1),
    "8-bit, every other value": (BYTES.astype(np.uint8) & 0xFE, 2),
    "signed, shifted": ((LEVELS.astype(np.int16) - 2048) << 2, 4),
    "float": (LEVELS.astype(np.float32) * 16, 1),
    "12-bit shifted, a hot pixel at 65535": (
        np.where(np.arange(2400).reshape(6, 20, 20) == 77, 65535, LEVELS << 4),
        16,
    ),
    "12-bit shifted, highlights written as 65535": (np.where(LEVELS > 4000, 65535, LEVELS << 4), 16),
    "12-bit shifted, one stray value": (
        np.where(np.arange(2400).reshape(6, 20, 20) == 5, 1001, LEVELS << 4),
        16,
    ),
    "12-bit shifted, one image unshifted": (np.concatenate([LEVELS[:1], LEVELS[1:] << 4]), 1),
    "12-bit shifted, a black level added": ((LEVELS << 4) + 3, 1),
    "all zero": (np.zeros((6, 4, 4), np.uint16), 1),
    "too few levels to tell": (np.arange(QUANTUM_EVIDENCE - 1, dtype=np.uint16) * 16, 1),
    "just enough levels": (np.arange(QUANTUM_EVIDENCE + 1, dtype=np.uint16) * 16, 16),
}


@pytest.mark.parametrize("name", QUANTA)
def test_the_raw_step_is_the_values_common_divisor(name: str) -> None:
    raw, step = QUANTA[name]
    assert raw_quantum(raw) == step


@pytest.mark.parametrize(
    ("dtype", "step", "top"),
    [("uint16", 16, 65520), ("uint16", 256, 65280), ("uint16", 257, 65535), ("uint8", 1, 255)],
)
def test_the_saturation_level_is_the_top_of_the_grid(dtype: str, step: int, top: int) -> None:
    obs = ObservationModel.for_input(np.dtype(dtype), 2, None, dequantize=True, quantum=step)
    assert obs.sensor_max == top
    raw = np.array([[[top, top - step, 0]], [[step, top, top - step]]], dtype=dtype)
    grey, _, sat = obs.prepare(raw)
    assert sat.tolist() == [[True, False], [False, True], [False, False]]
    # dequantised to the middle of [v, v + step); zero stays zero (a shadow)
    assert grey[0, 1] == step + step / 2 and grey[2, 0] == 0.0
    assert obs.step == step


def _stack(k: int, spec: float) -> tuple[np.ndarray, synthetic.Scene]:
    sc = synthetic.sphere(k, 32, specular=spec, noise=0.8, bits=None, seed=k)
    return np.clip(np.floor(sc.images), 0, 255).astype(np.uint8), sc


@pytest.mark.parametrize("k", [8, 12])
@pytest.mark.parametrize(
    ("container", "convert"),
    [
        ("shifted", lambda a: a.astype(np.uint16) << 8),
        ("scaled", lambda a: a.astype(np.uint16) * 257),
    ],
)
def test_8_bit_data_in_16_bit_files_give_the_normals_of_8_bit_files(k: int, container: str, convert) -> None:
    images, sc = _stack(k, 40.0)
    a = maxfs.solve(images, sc.lights, sc.mask)
    b = maxfs.solve(convert(images), sc.lights, sc.mask)
    # the same problem up to the unit: the same inliers, and normals equal to rounding
    scale = 256 if container == "shifted" else 257
    assert b.eps == pytest.approx(scale * a.eps, rel=1e-6)
    np.testing.assert_array_equal(a.inliers, b.inliers)
    assert np.nanmax(synthetic.angular_error_deg(a.normal, b.normal)[sc.mask]) < 1e-3


def test_given_eps_and_response_still_measure_the_step() -> None:
    images, sc = _stack(12, 40.0)
    a = maxfs.solve(images, sc.lights, sc.mask, eps=2.0, response=1.0)
    b = maxfs.solve(images.astype(np.uint16) << 8, sc.lights, sc.mask, eps=512.0, response=1.0)
    np.testing.assert_array_equal(a.inliers, b.inliers)
    assert np.nanmax(synthetic.angular_error_deg(a.normal, b.normal)[sc.mask]) < 1e-3


def test_maxfs_run_records_and_prints_the_step(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    images, sc = _stack(12, 40.0)
    f = write_npy_folder(tmp_path / "in", images.astype(np.uint16) << 8, sc.lights, sc.mask)
    assert main(["run", str(f), "-o", str(tmp_path / "out"), "--eps", "300"]) == 0
    assert "(raw values in steps of 256)" in capsys.readouterr().out
    r = maxfs.open_result(tmp_path / "out")
    assert r.params["quantum"] == 256 and r.params["eps"] == 300.0
    ref = maxfs.solve(images, sc.lights, sc.mask, eps=300.0 / 256)
    np.testing.assert_array_equal(r.inliers, ref.inliers)


def test_records_made_before_the_step_keep_their_digest() -> None:
    """A store's finished tiles count only under its parameters' digest: records written before
    the step existed have no ``quantum`` and used 1; their digest is what it was."""
    old = {k: v for k, v in JobParams.build(eps=2.0).with_eps(2.0).to_json().items() if k != "quantum"}
    left_out = {"eps_request", "response_request", "depth", "depth_k", "fx", "fy", "cx", "cy", "distance"}
    fields = {k: v for k, v in old.items() if k not in left_out}
    then = hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]
    p = JobParams.from_json(old)
    assert p.quantum == 1 and p.resolved and p.digest() == then
    assert JobParams.from_json(old | {"quantum": 16}).digest() != then
    assert not JobParams.build(eps=2.0).resolved  # a new job measures the step when it starts


@pytest.mark.parametrize(("step", "shown"), [(None, False), (1, False), (16, True)])
def test_maxfs_status_names_a_raw_step_above_one(step: int | None, shown: bool) -> None:
    st = {"id": "j", "state": "done", "progress": {}, "eps": 300.0, "raw_step": step}
    assert ("eps 300 (raw values in steps of 16)" in format_status(st)) is shown
