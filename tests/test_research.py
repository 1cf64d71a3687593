"""What researchers do with a result: eval against ground truth, depth, export, xarray."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from maxfs.storage.imageio import encode_png
from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.params import JobParams
from maxfs.worker.depth import integrate
from maxfs.worker.evaluate import evaluate, load_ground_truth

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _maxfs(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=timeout)


def _sphere(size: int, R: float, frac: float = 1.0):
    """Unit normals, true height and mask of a sphere of radius R pixels (x right, y up, row 0 on top)."""
    c = np.arange(size) + 0.5 - size / 2
    x, yy = np.meshgrid(c, c)
    y = -yy
    r2 = x**2 + y**2
    mask = r2 < (frac * R) ** 2
    z = np.sqrt(np.clip(R**2 - r2, 0, None))
    n = np.stack([x, y, z], -1) / R
    n[~mask] = np.nan
    return n, np.where(mask, z, np.nan), mask


def _bumps(size: int):
    """Gaussian bumps and a dip on a non-rectangular (ring-and-notch) domain with two pieces."""
    r, c = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = c, -r
    z = np.zeros_like(x)
    dzdx = np.zeros_like(x)
    dzdy = np.zeros_like(x)
    for cx, cy, a, s in ((0.3, -0.3, 12.0, 0.12), (0.7, -0.6, -8.0, 0.1), (0.45, -0.75, 6.0, 0.08)):
        cx, cy, s = cx * size, cy * size, s * size
        g = a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s**2))
        z += g
        dzdx += -g * (x - cx) / s**2
        dzdy += -g * (y - cy) / s**2
    n = np.stack([-dzdx, -dzdy, np.ones_like(z)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    d = np.hypot(c - size / 2, r - size / 2)
    mask = (d < 0.45 * size) & ~((r > 0.4 * size) & (r < 0.45 * size))  # a slot cuts it in two pieces
    mask &= ~((c > 0.6 * size) & (r < 0.3 * size))  # and a notch
    n[~mask] = np.nan
    return n, np.where(mask, z, np.nan), mask


def _store_with_normals(path: Path, normal: np.ndarray, mask: np.ndarray) -> JobStore:
    """A job store whose outputs are given (no run): enough for eval, depth and export."""
    H, W = mask.shape
    lights = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, 0.5, 0.866], [-0.5, -0.5, 0.707]])
    spec = JobSpec(4, H, W, None, "uint8", lights)
    store = JobStore.create(path, spec, JobParams.build(eps=1.0, tile=32))
    store.write_mask(mask)
    g = store.group
    g["normal"][...] = np.where(mask[..., None], normal, np.nan).astype(np.float32)
    g["albedo"][...] = np.where(mask, 100.0, 0.0).astype(np.float32)
    g["inlier_count"][...] = np.where(mask, 3, 0).astype(np.uint16)
    return store


def _independent_angles(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Textbook arccos of the normalised dot product (float64)."""
    a = est / np.linalg.norm(est, axis=-1, keepdims=True)
    b = gt / np.linalg.norm(gt, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


# -- eval ------------------------------------------------------------------------------------------------
def test_eval_cli_matches_an_independent_computation(tmp_path: Path) -> None:
    import scipy.io

    rng = np.random.default_rng(1)
    gt_n, _, gt_mask = _sphere(48, 22)
    est = gt_n + rng.normal(0, 0.08, gt_n.shape)  # errors of a few to ~20 degrees
    est /= np.linalg.norm(est, axis=-1, keepdims=True)
    mask = gt_mask.copy()
    est[20:23, 20:23] = np.nan  # some unsolved pixels inside the ground truth's mask
    store = _store_with_normals(tmp_path / "out.zarr", est, mask)
    est32 = store.read_output("normal").astype(np.float64)
    mat = np.where(gt_mask[..., None], gt_n, 0.0)  # DiLiGenT: zeros outside the object
    scipy.io.savemat(tmp_path / "Normal_gt.mat", {"Normal_gt": mat})

    r = _maxfs("eval", str(store.path), "--gt", str(tmp_path / "Normal_gt.mat"), "--json")
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)

    sel = gt_mask & np.isfinite(est32[..., 0])
    ang = _independent_angles(est32[sel], gt_n[sel])
    assert got["pixels"] == gt_mask.sum() and got["missing"] == 9 and got["evaluated"] == ang.size
    assert abs(got["mean_deg"] - ang.mean()) < 1e-4
    assert abs(got["median_deg"] - np.median(ang)) < 1e-4
    for t in (5, 10, 15, 20):
        assert got["under"][str(t)] == pytest.approx((ang < t).mean(), abs=1e-12)
    assert 2 < got["mean_deg"] < 15
    name = f"{tmp_path.name}-Normal_gt"  # files named after the ground truth's folder and file
    png = store.path / "previews" / f"angular_error-{name}.png"
    first = store.path / f"maxfs-eval-{name}.json"
    assert png.stat().st_size > 1000 and json.loads(first.read_text()) == got

    # the human form, with the unsolved share beside the mean (left out of it), and the same
    # numbers from an NPY and a 16-bit (n+1)/2 PNG ground truth
    r = _maxfs("eval", str(store.path), "--gt", str(tmp_path / "Normal_gt.mat"))
    unsolved = (
        f"{9 / gt_mask.sum():.1%} without a normal (unsolved, or outside the job's mask), not in the mean"
    )
    assert r.returncode == 0 and f"mean {ang.mean():.3f} deg ({unsolved})" in r.stdout, r.stdout
    np.save(tmp_path / "gt.npy", gt_n)
    r = _maxfs("eval", str(store.path), "--gt", str(tmp_path / "gt.npy"))  # a second ground truth
    assert r.returncode == 0 and (store.path / f"maxfs-eval-{tmp_path.name}-gt.json").exists()
    assert json.loads(first.read_text()) == got  # the first one's numbers are still there
    ev, _ = evaluate(est32, load_ground_truth(tmp_path / "gt.npy"))
    assert abs(ev.mean_deg - ang.mean()) < 1e-4
    q = np.where(gt_mask[..., None], np.round((gt_n + 1) / 2 * 65535), 0).astype(np.uint16)
    (tmp_path / "gt.png").write_bytes(encode_png(q))
    ev, _ = evaluate(est32, load_ground_truth(tmp_path / "gt.png"))
    deq = q / 65535.0 * 2 - 1
    ang_png = _independent_angles(est32[sel], deq[sel])
    assert abs(ev.mean_deg - ang_png.mean()) < 1e-4 and ev.pixels == gt_mask.sum()


def test_eval_refuses_a_ground_truth_of_another_size(tmp_path: Path) -> None:
    n, _, m = _sphere(32, 14)
    store = _store_with_normals(tmp_path / "out.zarr", n, m)
    np.save(tmp_path / "gt.npy", _sphere(40, 14)[0])
    r = _maxfs("eval", str(store.path), "--gt", str(tmp_path / "gt.npy"))
    assert r.returncode == 2 and "same image size" in r.stderr and "Traceback" not in r.stderr


# -- depth -----------------------------------------------------------------------------------------------
def test_depth_of_a_sphere_is_within_one_percent_of_its_radius() -> None:
    R = 60.0
    n, z, m = _sphere(128, R)  # the whole disc, silhouette included
    d = integrate(n, m)
    e = d.depth[m] - z[m]
    e -= e.mean()  # depth is known up to a constant
    rel = np.sqrt(np.mean(e**2)) / R
    assert rel < 0.01, rel
    assert d.pieces == 1 and np.isnan(d.depth[~m]).all() and d.residual_rms < 0.05
    print(f"sphere R={R:g}: RMS depth error {rel:.3%} of the radius, max {np.abs(e).max() / R:.2%}")


def test_depth_of_bumps_on_a_two_piece_non_rectangular_mask() -> None:
    n, z, m = _bumps(96)
    d = integrate(n, m)
    assert d.pieces == 2
    import scipy.ndimage

    labels, k = scipy.ndimage.label(m)
    amplitude = np.nanmax(z) - np.nanmin(z)
    for i in range(1, k + 1):
        sel = labels == i
        e = d.depth[sel] - z[sel]
        e -= e.mean()  # each piece has its own constant
        rel = np.sqrt(np.mean(e**2)) / amplitude
        assert rel < 0.005, rel
        assert abs(float(np.mean(d.depth[sel]))) < 1e-3  # each piece has mean 0
    assert np.isnan(d.depth[~m]).all()


def test_depth_is_written_into_the_store_with_its_method(tmp_path: Path) -> None:
    import zarr

    from maxfs.service.results.research import write_depth

    n, _, m = _sphere(40, 18)
    store = _store_with_normals(tmp_path / "out.zarr", n, m)
    res = write_depth(store.path)
    arr = zarr.open_group(store.path / "results.zarr", mode="r")["depth"]
    assert arr.shape == (40, 40) and arr.dtype == np.float32
    assert arr.attrs["method"] == res.method and arr.attrs["residual_rms"] == res.residual_rms
    np.testing.assert_array_equal(JobStore.open(store.path, mode="r").read_output("depth"), res.depth)
    assert (store.path / "previews" / "depth.png").stat().st_size > 500


# -- export ----------------------------------------------------------------------------------------------
def test_export_cli_writes_images_arrays_and_a_mesh_that_trimesh_reads_back(tmp_path: Path) -> None:
    import tifffile
    import trimesh

    from maxfs.storage.imageio import read_image

    n, _, m = _sphere(40, 18)
    m[5:8, 18:21] = False  # a hole: the mesh must go around it
    store = _store_with_normals(tmp_path / "out.zarr", n, m)
    r = _maxfs("export", str(store.path))
    assert r.returncode == 0, r.stderr
    out = tmp_path / "out-export"
    normal = np.load(out / "normal.npy")
    np.testing.assert_array_equal(normal, store.read_output("normal"))
    png = read_image(out / "normal16.png")
    assert png.dtype == np.uint16 and png.shape == (40, 40, 3)
    ok = np.isfinite(normal[..., 0])
    # (n + 1) / 2 in all three channels, nz included
    np.testing.assert_allclose(png[ok] / 65535.0 * 2 - 1, normal[ok], atol=2e-5)
    assert not png[~ok].any()
    # normal.png is what readers expect: 8-bit RGB, as Pillow opens it
    from PIL import Image

    with Image.open(out / "normal.png") as im:
        assert im.mode == "RGB" and im.size == (40, 40)
        eight = np.asarray(im)
    np.testing.assert_allclose(eight[ok] / 255.0 * 2 - 1, normal[ok], atol=1 / 255 + 1e-6)  # half a step
    # albedo.npy is the store's grey albedo (a grey store has no albedo_rgb)
    np.testing.assert_array_equal(np.load(out / "albedo.npy"), store.read_output("albedo"))
    assert not (out / "albedo_rgb.npy").exists()
    np.testing.assert_array_equal(tifffile.imread(out / "normal.tiff"), normal)
    depth = np.load(out / "depth.npy")
    assert depth.dtype == np.float32 and (np.isfinite(depth) == ok).all()
    assert np.load(out / "inlier_count.npy").max() == 3

    manifest = json.loads((out / "export.json").read_text())
    for fmt in ("ply", "obj"):
        mesh = trimesh.load(out / f"mesh.{fmt}", process=False)
        assert len(mesh.vertices) == ok.sum() == manifest["files"][f"mesh.{fmt}"]["vertices"]
        assert len(mesh.faces) == manifest["files"][f"mesh.{fmt}"]["faces"] > ok.sum()
        np.testing.assert_allclose(mesh.vertices[:, 2], depth[ok], atol=1e-4)
        np.testing.assert_allclose(mesh.vertex_normals, normal[ok], atol=1e-4)
        # triangles face the camera like the surface they approximate
        assert (np.sum(mesh.face_normals * mesh.vertex_normals[mesh.faces].mean(1), axis=1) > 0).all()
    ply = trimesh.load(out / "mesh.ply", process=False)
    assert (ply.visual.vertex_colors[:, :3] > 0).all()  # albedo colour on every vertex

    r = _maxfs("export", str(store.path), "-o", str(tmp_path / "only"), "--only", "depth", "--no-mesh")
    assert r.returncode == 0 and sorted(p.name for p in (tmp_path / "only").iterdir()) == [
        "depth.npy",
        "depth.png",
        "depth.tiff",
        "export.json",
    ]
    r = _maxfs("export", str(store.path), "--only", "volume")
    assert r.returncode == 2 and "cannot export" in r.stderr


def test_normal_preview_is_n_plus_one_over_two_in_all_channels() -> None:
    from maxfs.service.results.previews import normal_rgb

    n = np.array([[[0.0, 0.0, 1.0], [0.6, -0.8, 0.0], [np.nan, np.nan, np.nan]]])
    np.testing.assert_array_equal(normal_rgb(n), [[[128, 128, 255], [204, 25, 128], [0, 0, 0]]])


# -- stores other tools read -----------------------------------------------------------------------------
@pytest.mark.parametrize("channels", [None, 3])
def test_xarray_opens_a_job_store_with_named_dimensions(tmp_path: Path, channels: int | None) -> None:
    import xarray as xr

    from maxfs.service.results.research import write_depth

    n, _, m = _sphere(24, 10)
    if channels is None:
        store = _store_with_normals(tmp_path / "out.zarr", n, m)
        write_depth(store.path)
    else:
        lights = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, 0.5, 0.866]])
        spec = JobSpec(3, 24, 24, 3, "uint16", lights, np.ones((3, 3)))
        store = JobStore.create(tmp_path / "out.zarr", spec, JobParams.build(eps=1.0, tile=16))
    (store.path / "previews").mkdir(exist_ok=True)  # beside the group, never inside it
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. zarr's "Object at previews is not recognized"
        ds = xr.open_zarr(store.path / "results.zarr", consolidated=False)
    k = store.spec.k
    assert ds["normal"].dims == ("y", "x", "xyz") and ds.sizes["xyz"] == 3
    assert ds["inliers"].dims == ("image", "y", "x") and ds.sizes["image"] == k
    assert ds["lights"].dims == ("image", "xyz")
    # coordinates: the normal's components and channels by name, images numbered from 1
    assert list(ds["xyz"].values) == ["x", "y", "z"] and list(ds["image"].values) == list(range(1, k + 1))
    assert ds["normal"].sel(xyz="z").dims == ("y", "x")
    assert list(ds["channel"].values) == (["grey"] if channels is None else ["r", "g", "b"])
    # only results: the input stack and the tile bookkeeping are in subgroups, still one call away
    assert not {"images", "uploaded", "input_digests", "done", "tile_stats"} & set(ds.variables)
    inputs = xr.open_zarr(store.path / "results.zarr", group="inputs", consolidated=False)
    tiles = xr.open_zarr(store.path / "results.zarr", group="tiles", consolidated=False)
    assert "done" in tiles and "tile_stats" in tiles and "uploaded" in inputs
    if channels is None:
        assert inputs["images"].dims == ("image", "y", "x") and "albedo_rgb" not in ds
        assert ds["depth"].dims == ("y", "x") and ds["depth"].attrs["units"] == "pixels"
        assert "residual_rms" in ds["depth"].attrs
        np.testing.assert_array_equal(ds["normal"].values, store.read_output("normal"))
        np.testing.assert_array_equal(ds["albedo"].values, store.read_output("albedo"))  # 0 stays 0
        assert ds["inlier_count"].dtype == np.uint16
    else:
        assert inputs["images"].dims == ("image", "y", "x", "channel") and ds.sizes["channel"] == 3
        assert ds["albedo_rgb"].dims == ("y", "x", "channel")
    assert "long_name" in ds["normal"].attrs
    assert ds.attrs["k"] == k and ds.attrs["params"]["tile"] == store.params.tile


@pytest.mark.slow
def test_run_reports_the_folders_own_ground_truth_and_gt_overrides_it(tmp_path: Path, diligent: Path) -> None:
    """A DiLiGenT folder's Normal_gt.mat is evaluated at the end of ``maxfs run``; ``--gt`` names
    another map, and the printed numbers are those of ``maxfs eval``."""
    folder = diligent / "catPNG"
    out = tmp_path / "cat.zarr"
    r = _maxfs("run", str(folder), "-o", str(out), "--images", "1-24", "--eps", "2", timeout=300)
    assert r.returncode == 0, r.stderr
    assert f"vs {folder / 'Normal_gt.mat'}: angular error" in r.stdout, r.stdout
    ev = json.loads(_maxfs("eval", str(out), "--gt", str(folder / "Normal_gt.mat"), "--json").stdout)
    assert f"mean {ev['mean_deg']:.3f} deg" in r.stdout, (r.stdout, ev)
    assert ev["mean_deg"] < 30
    # --gt: another map, here the ground truth as an NPY of the same normals, gives the same numbers
    np.save(tmp_path / "gt.npy", np.nan_to_num(load_ground_truth(folder / "Normal_gt.mat").normal))
    r = _maxfs(
        "run", str(folder), "-o", str(out), "--images", "1-24", "--eps", "2", "--gt", str(tmp_path / "gt.npy")
    )
    assert r.returncode == 0 and f"vs {tmp_path / 'gt.npy'}: " in r.stdout
    assert f"mean {ev['mean_deg']:.3f} deg" in r.stdout, r.stdout


@pytest.mark.parametrize(
    ("missing", "pixels", "text"),
    [(9138, 9142, ">99.9%"), (9142, 9142, "100.0%"), (1, 9142, "<0.1%"), (9, 900, "1.0%")],
)
def test_the_unsolved_share_reads_100_or_0_percent_only_when_it_is(
    missing: int, pixels: int, text: str
) -> None:
    from maxfs.worker.evaluate import Evaluation

    ev = Evaluation(1.0, 1.0, {"5": 1.0}, pixels, pixels - missing, missing)
    assert f"({text} without a normal" in ev.summary()
