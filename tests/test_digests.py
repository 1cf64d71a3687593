"""Input digests name their hash: new stores (format 5) record SHA-256, stores of format 4 record
none and keep BLAKE2b, and such a store still resumes (and still refuses other inputs)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from maxfs.service.runs.local import read_stack
from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.digests import DIGEST, LEGACY_DIGEST, ArrayHasher, array_digest
from maxfs.storage.errors import StoreError
from maxfs.storage.inputs import load_folder
from maxfs.storage.layout import FORMAT_VERSION, GROUP_DIR, JobSpec, JobStore
from maxfs.storage.params import JobParams
from maxfs.storage.stack import StackReader
from maxfs.worker import synthetic

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _maxfs(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=300)


def _folder(tmp: Path) -> Path:
    sc = synthetic.bump_scene(8, 48, seed=3)
    return write_npy_folder(tmp / "scene", sc.images.astype(np.uint8), sc.lights, sc.mask)


def _as_format_4(out: Path) -> None:
    """Make ``out``'s store what a format 4 maxfs left: the same arrays, no hash named, and every
    input digest (images and mask) BLAKE2b."""
    meta = out / GROUP_DIR / "zarr.json"
    doc = json.loads(meta.read_text())
    del doc["attributes"]["input_digest"]
    doc["attributes"]["maxfs_format"] = 4
    meta.write_text(json.dumps(doc))


@pytest.mark.parametrize(("algorithm", "make"), [("sha256", hashlib.sha256), ("blake2b", None)])
def test_a_digest_is_the_named_hash_of_shape_dtype_and_little_endian_bytes(algorithm: str, make) -> None:
    a = np.arange(24, dtype=">u2").reshape(2, 4, 3)  # big-endian in memory: digested little-endian
    h = make() if make else hashlib.blake2b(digest_size=32)
    h.update(b"(2, 4, 3)|<u2|" + a.astype("<u2").tobytes())
    assert array_digest(a, algorithm) == h.digest()
    banded = ArrayHasher(a.shape, a.dtype, algorithm)
    for band in (a[:1], a[1:]):
        banded.update(band)
    assert banded.digest() == h.digest()
    with pytest.raises(ValueError, match="unknown input digest"):
        array_digest(a, "md5")


def test_new_stores_record_sha256_and_digest_what_they_store(tmp_path: Path) -> None:
    sc = synthetic.sphere(k=4, size=12)
    images = np.clip(sc.images, 0, 255).astype(np.uint8)
    store = JobStore.create(
        tmp_path / "s", JobSpec(4, 12, 12, None, "uint8", sc.lights), JobParams.build(eps=1)
    )
    assert DIGEST == "sha256" and store.spec.digest == DIGEST
    assert dict(store.group.attrs)["input_digest"] == "sha256"
    assert dict(store.group.attrs)["maxfs_format"] == FORMAT_VERSION == 5
    store.write_image(2, images[2])
    store.write_mask(sc.mask)
    again = JobStore.open(tmp_path / "s", mode="r")
    assert again.spec.digest == "sha256"
    assert again.digests()[2] == array_digest(images[2], "sha256") != array_digest(images[2], "blake2b")
    assert again.digests()[4] == array_digest(sc.mask, "sha256")


def test_a_format_4_store_keeps_blake2b_for_what_it_stores_and_reads(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    ds = load_folder(folder)
    spec = JobSpec.of(ds)
    JobStore.create(tmp_path / "s", spec, JobParams.build(eps=1, tile=16))
    _as_format_4(tmp_path / "s")
    old = JobStore.open(tmp_path / "s")
    assert old.spec.digest == LEGACY_DIGEST
    old.write_image(0, ds.read(0))  # an upload to a job made before: its digest in BLAKE2b
    old.write_mask(ds.mask)
    # a reader started with a new store's hash before the store was open is not used for this one
    read_stack(ds, old, 1, StackReader(ds, 1))
    assert old.digests() == [array_digest(ds.read(i), "blake2b") for i in range(ds.k)] + [
        array_digest(ds.mask, "blake2b")
    ]
    meta = tmp_path / "s" / GROUP_DIR / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"].update(maxfs_format=5, input_digest="md5")
    meta.write_text(json.dumps(doc))
    with pytest.raises(StoreError, match="'md5'"):
        JobStore.open(tmp_path / "s")
    doc["attributes"].update(maxfs_format=3)
    meta.write_text(json.dumps(doc))
    with pytest.raises(StoreError, match="reads 4, 5"):
        JobStore.open(tmp_path / "s")


@pytest.mark.slow
def test_a_format_4_store_resumes_and_still_refuses_other_images(tmp_path: Path) -> None:
    """``maxfs run`` into a format 4 store (BLAKE2b digests, no hash named) that has tiles left:
    its digests are compared in BLAKE2b (the files' fingerprint is forgotten, so every image is
    decoded and compared), it finishes with the results of an uninterrupted run, and a changed
    image is still refused."""
    folder, out, ref = _folder(tmp_path), tmp_path / "out", tmp_path / "ref"
    assert _maxfs("run", str(folder), "-o", str(ref), "--eps", "1", "--tile", "16").returncode == 0
    assert _maxfs("run", str(folder), "-o", str(out), "--eps", "1", "--tile", "16").returncode == 0
    ds = load_folder(folder)
    store = JobStore.open(out)
    rows = [array_digest(ds.read(i), "blake2b") for i in range(ds.k)] + [array_digest(ds.mask, "blake2b")]
    store.record_digests(dict(enumerate(rows[: ds.k])))
    store.group["inputs/input_digests"][ds.k] = np.frombuffer(rows[ds.k], np.uint8)
    store.source_fingerprint = None
    counts = store.masked_per_tile().ravel()
    redo = [t for t in store.tiles() if counts[t.index]][:2]
    for t in redo:
        store.group["tiles/done"][t.ty, t.tx] = 0
    _as_format_4(out)
    r = _maxfs("run", str(folder), "-o", str(out), "--eps", "1", "--tile", "16")
    assert r.returncode == 0, r.stderr
    assert "other inputs" not in r.stderr
    old, want = JobStore.open(out, mode="r"), JobStore.open(ref, mode="r")
    assert dict(old.group.attrs)["maxfs_format"] == 4 and old.spec.digest == "blake2b"
    assert old.digests() == rows
    assert old.done_grid().all()
    runs = old.run_counts()
    assert sorted(t for t, n in runs.items() if n == 2) == sorted(t.index for t in redo)
    for name in ("normal", "inliers", "inlier_count", "albedo"):
        np.testing.assert_array_equal(old.read_output(name), want.read_output(name), err_msg=name)
    images = np.load(folder / "images.npy")
    images[3, 20, 20] ^= 1
    np.save(folder / "images.npy", images)
    r = _maxfs("run", str(folder), "-o", str(out), "--eps", "1", "--tile", "16")
    assert r.returncode == 2 and "image 4 first" in r.stderr, r.stderr
