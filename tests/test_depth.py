"""Depth from normals (issue 26): the iterative ls solve against the direct one, bini on steps, the
perspective model, options and their validation, the mesh across jumps; the CLI, HTTP and the Python API."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg
import zarr

from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.errors import InvalidInputError
from maxfs.storage.params import JobParams
from maxfs.worker import depth_scenes as S
from maxfs.worker import synthetic
from maxfs.worker.depth import Camera, discontinuities, integrate, slopes
from maxfs.worker.depth_solver import fine_apply, grid_links, solve
from tests.procs import Server, poll_until

MAXFS = str(Path(sys.executable).parent / "maxfs")


def _direct_ls(normal: np.ndarray, mask: np.ndarray, lam: float = 1e-9) -> np.ndarray:
    """The least squares of the trapezoidal 4-neighbour differences by a sparse direct solve of
    ``(A^T A + lam I) z = A^T b``, each piece shifted to mean 0 (the depth before issue 26)."""
    dom = mask & np.isfinite(normal).all(axis=2)
    p, q = slopes(np.where(dom[..., None], normal, 0.0))
    idx = np.full(dom.shape, -1)
    idx[dom] = np.arange(int(dom.sum()))
    rows, cols, vals, rhs = [], [], [], []
    m = 0
    for pair, a, b, s in (
        (dom[:, :-1] & dom[:, 1:], idx[:, :-1], idx[:, 1:], 0.5 * (p[:, :-1] + p[:, 1:])),
        (dom[:-1] & dom[1:], idx[:-1], idx[1:], 0.5 * (q[:-1] + q[1:])),
    ):
        e = np.arange(m, m + int(pair.sum()))
        rows += [e, e]
        cols += [b[pair], a[pair]]
        vals += [np.ones(e.size), -np.ones(e.size)]
        rhs.append(s[pair])
        m += e.size
    A = scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))))
    N = (A.T @ A + lam * scipy.sparse.identity(A.shape[1])).tocsc()
    z = scipy.sparse.linalg.spsolve(N, A.T @ np.concatenate(rhs))
    _, lab = scipy.sparse.csgraph.connected_components(N, directed=False)
    z -= (np.bincount(lab, weights=z) / np.bincount(lab))[lab]
    out = np.full(dom.shape, np.nan)
    out[dom] = z
    return out


def _two_pieces(size: int = 72) -> tuple[np.ndarray, np.ndarray]:
    """Bumps on a disc cut in two by a slot, with a notch, a hole, a one-pixel bridge and one isolated
    pixel."""
    r, c = np.mgrid[0:size, 0:size].astype(np.float64)
    g = 9 * np.exp(-((c - 0.3 * size) ** 2 + (r - 0.35 * size) ** 2) / (2 * (0.12 * size) ** 2))
    dzdc = -g * (c - 0.3 * size) / (0.12 * size) ** 2
    dzdr = -g * (r - 0.35 * size) / (0.12 * size) ** 2
    n = np.stack([-dzdc, dzdr, np.ones_like(g)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    mask = np.hypot(c - size / 2, r - size / 2) < 0.45 * size
    mask &= ~((r > 0.5 * size) & (r < 0.55 * size))
    mask &= ~((c > 0.65 * size) & (r < 0.3 * size))
    mask &= np.hypot(c - 0.5 * size, r - 0.75 * size) > 0.08 * size  # a hole
    mask[int(0.62 * size) : int(0.64 * size), : int(0.5 * size)] = False  # a slot ...
    mask[int(0.62 * size) : int(0.64 * size), int(0.25 * size)] = True  # ... crossed by one pixel
    mask[0, 0] = True  # isolated
    return n, mask


# -- the math -------------------------------------------------------------------------------------------
def _graph(dom: np.ndarray, wh: np.ndarray, wv: np.ndarray) -> scipy.sparse.csr_matrix:
    """``A^T W A`` of the stencil's edges, assembled independently: pixel pairs from the grid."""
    idx = np.full(dom.shape, -1)
    idx[dom] = np.arange(int(dom.sum()))
    hw, vw = np.zeros(dom.shape), np.zeros(dom.shape)
    hw[dom], vw[dom] = wh, wv
    a, b, w = [], [], []
    for pair, i, j, ww in (
        (dom[:, :-1] & dom[:, 1:], idx[:, :-1], idx[:, 1:], hw[:, :-1]),
        (dom[:-1] & dom[1:], idx[:-1], idx[1:], vw[:-1]),
    ):
        a.append(i[pair])
        b.append(j[pair])
        w.append(ww[pair])
    a, b, w = np.concatenate(a), np.concatenate(b), np.concatenate(w)
    n = idx.max() + 1
    off = scipy.sparse.csr_matrix((np.r_[w, w], (np.r_[a, b], np.r_[b, a])), shape=(n, n))
    return scipy.sparse.diags(np.asarray(off.sum(1)).ravel()) - off


def _weighted(seed: int, shape=(40, 52)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mask of :func:`_two_pieces`, cut to ``shape``, with two pieces touching only at a corner,
    and random edge weights of which a tenth are all but cut (bini's floor at a depth jump)."""
    rng = np.random.default_rng(seed)
    dom = _two_pieces(max(shape))[1][: shape[0], : shape[1]].copy()
    dom[-6:, -6:] = False
    dom[-6:-3, -6:-3] = True
    dom[-3:, -3:] = True  # meets the square above only at a corner
    down = grid_links(dom)[1]
    right = np.zeros(dom.shape, dtype=bool)
    right[:, :-1] = dom[:, :-1] & dom[:, 1:]
    wh = np.where(right[dom], rng.uniform(0.05, 2.0, int(dom.sum())), 0.0).astype(np.float32)
    wv = np.where(down >= 0, rng.uniform(0.05, 2.0, down.size), 0.0).astype(np.float32)
    for w in (wh, wv):
        w[(w > 0) & (rng.random(w.size) < 0.1)] = 1e-5
    return dom, wh, wv


def test_stencil_applies_a_transpose_w_a() -> None:
    dom, wh, wv = _weighted(3)
    up, down = grid_links(dom)
    x = np.random.default_rng(4).standard_normal(wh.size)
    got = np.empty_like(x)
    xax = fine_apply(wh, wv, up, down, x, got)
    want = _graph(dom, wh, wv) @ x
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert abs(xax - x @ want) < 1e-9 * abs(x @ want)


def test_multigrid_cg_equals_a_direct_sparse_solve() -> None:
    # two pieces (and one touching only at a corner), a hole, a one-pixel bridge, an isolated pixel,
    # and weights spanning five orders of magnitude: the coarse levels see blocks that fall apart
    for seed in range(3):
        dom, wh, wv = _weighted(seed)
        up, down = grid_links(dom)
        L = _graph(dom, wh.astype(np.float64), wv.astype(np.float64))
        npiece, lab = scipy.sparse.csgraph.connected_components(L, directed=False)
        assert npiece >= 4
        b = np.random.default_rng(10 + seed).standard_normal(wh.size)
        b -= (np.bincount(lab, weights=b) / np.bincount(lab))[lab]  # consistent: 0 per piece
        # the reference: each piece's first pixel held at 0, then every piece shifted to mean 0
        first = np.unique(lab, return_index=True)[1]
        keep = np.setdiff1d(np.arange(b.size), first)
        want = np.zeros(b.size)
        want[keep] = scipy.sparse.linalg.spsolve(L[keep][:, keep].tocsc(), b[keep])
        want -= (np.bincount(lab, weights=want) / np.bincount(lab))[lab]
        x = np.zeros(b.size)
        its = solve(dom, wh, wv, up, down, b.copy(), x, 1e-10)
        x -= (np.bincount(lab, weights=x) / np.bincount(lab))[lab]
        assert np.linalg.norm(L @ x - (L @ want)) <= 1e-10 * np.linalg.norm(L @ want) * 10
        np.testing.assert_allclose(x, want, atol=1e-7 * np.abs(want).max())
        assert 0 < its < 60, its


def test_dense_coarsest_factor_equals_the_sparse_one() -> None:
    # the coarsest level is factored by numpy when small (no scipy import on a run), by scipy's sparse
    # LU when large: the same pieces held, the same solves, on levels with several pieces
    from maxfs.worker.depth_solver import Multigrid, _factor, _sparse_factor

    for seed in range(3):
        dom, wh, wv = _weighted(seed, (80, 96))
        up, down = grid_links(dom)
        for lev in Multigrid(dom, wh, wv, up, down).levels:
            n = lev.diag.size
            rows = np.repeat(np.arange(n), np.diff(lev.indptr))
            A = scipy.sparse.csr_matrix((lev.val, lev.idx, lev.indptr), shape=(n, n))
            _, lab = scipy.sparse.csgraph.connected_components(A, directed=False)
            b = np.random.default_rng(seed).standard_normal(n)
            b -= (np.bincount(lab, weights=b) / np.bincount(lab))[lab]
            dense, sparse = _factor(lev)(b), _sparse_factor(lev, rows)(b)
            np.testing.assert_allclose(dense, sparse, rtol=1e-9, atol=1e-9 * np.abs(sparse).max())


def test_ls_equals_the_direct_solve_within_the_solver_tolerance() -> None:
    n, mask = _two_pieces()
    want = _direct_ls(n, mask)
    got = integrate(n, mask)
    # CG stops at a relative residual of 1e-7; the depths then agree to 1e-5 px (1.2e-6 here)
    assert np.nanmax(np.abs(got.depth - want)) < 1e-5
    assert got.pieces == 3 and got.method == "ls" and got.units == "pixels" and got.cg_iterations > 0
    assert (np.isnan(got.depth) == np.isnan(want)).all()


def test_the_same_normals_give_the_same_depth_bit_for_bit() -> None:
    # the multigrid setup and the float32 preconditioner start from nothing random
    n, mask = _two_pieces()
    for method in ("ls", "bini"):
        a, b = (integrate(n, mask, method=method) for _ in range(2))
        assert a.depth.tobytes() == b.depth.tobytes() and a.cg_iterations == b.cg_iterations


def test_bini_keeps_steps_that_ls_smooths_over() -> None:
    sc = S.step_ortho(64)
    far = sc.mask & ~sc.step_band
    err = {}
    for m in ("ls", "bini"):
        e = np.abs(S.aligned_error(integrate(sc.normal, sc.mask, method=m).depth, sc))
        err[m] = (np.sqrt(np.mean(e[far] ** 2)), np.median(e[sc.step_band]))
    assert err["bini"][0] < 0.25 * err["ls"][0], err  # away from the steps
    assert err["bini"][1] < 0.25 * err["ls"][1], err  # at them (median: the rim pixel is ambiguous)


def test_bini_on_a_smooth_surface_is_as_good_as_ls() -> None:
    sc = S.sphere_ortho(48)
    e_ls = S.aligned_error(integrate(sc.normal, sc.mask).depth, sc)
    r = integrate(sc.normal, sc.mask, method="bini")
    e_bini = S.aligned_error(r.depth, sc)
    assert np.sqrt(np.nanmean(e_bini**2)) < 1.5 * np.sqrt(np.nanmean(e_ls**2)) + 0.05
    assert r.params["k"] == 2.0 and 1 <= r.params["iterations"] <= 100


def test_perspective_model_fits_a_perspective_scene_and_the_orthographic_does_not() -> None:
    sc = S.sphere_perspective(64)
    ortho = S.aligned_error(integrate(sc.normal, sc.mask).depth, sc, scale=True)
    persp = S.aligned_error(integrate(sc.normal, sc.mask, camera=sc.camera).depth, sc, scale=True)
    assert np.sqrt(np.nanmean(persp**2)) < 0.25 * np.sqrt(np.nanmean(ortho**2))


def test_perspective_depth_is_in_camera_units_given_the_distance() -> None:
    sc = S.sphere_perspective(64)
    true_mean = float(np.exp(np.mean(np.log(-sc.z[sc.mask]))))
    r = integrate(sc.normal, sc.mask, camera=sc.camera, distance=true_mean)
    assert r.units == "camera units" and r.camera == "perspective" and r.params["fx"] == sc.camera.fx
    # no fit: the depth itself, against the sphere's z (radius 1 at distance 3)
    e = r.depth - sc.z
    assert np.sqrt(np.nanmean(e**2)) < 0.01 * true_mean and np.nanmax(np.abs(e)) < 0.05 * true_mean
    rel = integrate(sc.normal, sc.mask, camera=sc.camera)
    assert rel.units == "relative" and abs(np.exp(np.mean(np.log(-rel.depth[sc.mask]))) - 1) < 1e-5


def test_discontinuities_and_the_mesh_leave_steps_open() -> None:
    from maxfs.service.results.export import grid_mesh

    sc = S.step_ortho(64)
    depth = integrate(sc.normal, sc.mask, method="bini").depth
    cuts = discontinuities(depth, sc.normal)
    mesh = grid_mesh(depth, sc.normal, cuts=cuts)
    assert len(mesh.faces) > 0.9 * 2 * 63 * 63

    # no triangle has an edge across a detected jump
    W = depth.shape[1]
    flat = np.flatnonzero(sc.mask.ravel())
    r, c = np.divmod(flat[mesh.faces], W)  # (faces, 3) rows and columns of the vertices
    for i, j in ((0, 1), (1, 2), (0, 2)):
        dr, dc = r[:, j] - r[:, i], c[:, j] - c[:, i]
        horiz = (dr == 0) & (np.abs(dc) == 1)
        vert = (dc == 0) & (np.abs(dr) == 1)
        assert not cuts[0][r[horiz, i], np.minimum(c[horiz, i], c[horiz, j])].any()
        assert not cuts[1][np.minimum(r[vert, i], r[vert, j]), c[vert, i]].any()

    # and the faces that straddle the true step are a few (the rim pixel's side is ambiguous)
    def across(m) -> int:
        reg = sc.region[sc.mask][m.faces]
        return int((reg.min(1) != reg.max(1)).sum())

    assert across(mesh) < 0.5 * across(grid_mesh(depth, sc.normal))
    sphere = S.sphere_ortho(48)
    smooth = integrate(sphere.normal, sphere.mask).depth
    inner = np.hypot(*np.mgrid[-23.5:24.5, -23.5:24.5]) < 15
    ch, cv = discontinuities(smooth, sphere.normal)
    assert not (ch & inner[:, 1:]).any() and not (cv & inner[1:]).any()


def test_perspective_mesh_is_in_the_camera_frame() -> None:
    from maxfs.service.results.export import grid_mesh

    sc = S.sphere_perspective(40)
    r = integrate(sc.normal, sc.mask, camera=sc.camera, distance=2.0)
    mesh = grid_mesh(r.depth, sc.normal, camera=sc.camera)
    # the sphere's points, scaled: |P - C| is the same for all of them (C by linear least squares)
    P = mesh.vertices
    A = np.c_[2 * P, np.ones(len(P))]
    sol = np.linalg.lstsq(A, (P**2).sum(1), rcond=None)[0]
    C = sol[:3]
    radius = np.linalg.norm(P - C, axis=1)
    assert radius.std() < 0.01 * radius.mean() and C[2] < 0


def test_depth_options_are_validated_and_kept_out_of_the_tile_digest() -> None:
    base = JobParams.build(eps=1.0).with_eps(1.0)
    p = JobParams.build(
        eps=1.0, depth="bini", depth_k=4.0, fx=500.0, fy=500.0, cx=31.5, cy=31.5, distance=2.0
    ).with_eps(1.0)
    assert p.digest() == base.digest() and p.depth == "bini" and p.fx == 500.0
    assert JobParams.from_json(p.to_json()) == p
    old = {k: v for k, v in base.to_json().items() if k not in ("depth", "depth_k", "fx", "fy", "cx", "cy")}
    assert JobParams.from_json(old).depth == "ls"  # a store made before the depth options
    for bad, words in (
        ({"depth": "poisson"}, "unknown depth method"),
        ({"depth_k": 0}, "depth_k"),
        ({"fx": 500.0}, "fy, cx, cy missing"),
        ({"fx": -1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}, "fx"),
        ({"distance": 3.0}, "give the camera"),
    ):
        with pytest.raises(InvalidInputError, match=words):
            JobParams.build(eps=1.0, **bad)


def test_camera_from_a_k_file(tmp_path: Path) -> None:
    (tmp_path / "K.txt").write_text("600 0 320.5\n0 610 240\n0 0 1\n")
    assert Camera.from_file(tmp_path / "K.txt") == Camera(600.0, 610.0, 320.5, 240.0)
    (tmp_path / "bad.txt").write_text("600 0\n0 610\n")
    with pytest.raises(InvalidInputError, match="3 x 3"):
        Camera.from_file(tmp_path / "bad.txt")


# -- the Python API, the CLI and HTTP ------------------------------------------------------------------
def _scene(size: int = 40):
    sc = synthetic.bump_scene(8, size, seed=2)
    return sc.images.astype(np.uint8), sc.lights, sc.mask


@pytest.mark.slow
def test_python_api_takes_the_depth_options_and_k_txt(tmp_path: Path) -> None:
    import maxfs
    from maxfs.storage.layout import JobStore

    images, lights, mask = _scene()
    r = maxfs.solve(images, lights, mask, eps=2.0, tile=32, depth="bini", depth_k=3.0, output=tmp_path / "a")
    a = JobStore.open(r.path, mode="r").array_meta("depth").attrs
    assert r.depth is not None and a["method"] == "bini" and a["k"] == 3.0 and a["camera"] == "orthographic"
    np.testing.assert_allclose(r.depth, integrate(r.normal, mask, method="bini", k=3.0).depth, atol=1e-5)
    assert maxfs.solve(images, lights, mask, eps=2.0, tile=32, depth="none").depth is None
    with pytest.raises(InvalidInputError, match="unknown depth method"):
        maxfs.solve(images, lights, mask, eps=2.0, depth="nope")
    folder = write_npy_folder(tmp_path / "in", images, lights, mask)
    (folder / "K.txt").write_text("60 0 19.5\n0 60 19.5\n0 0 1\n")
    r = maxfs.solve_folder(folder, tmp_path / "b", eps=2.0, tile=32, distance=5.0)
    a = JobStore.open(r.path, mode="r").array_meta("depth").attrs
    assert a["method"] == "ls" and a["camera"] == "perspective" and a["fx"] == 60.0 and a["distance"] == 5.0
    assert a["units"] == "camera units" and np.nanmax(r.depth) < 0  # camera-frame z: in front of it


def _maxfs(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([MAXFS, *args], capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_cli_depth_method_k_file_and_export_without_faces_across_jumps(tmp_path: Path) -> None:
    images, lights, mask = _scene()
    folder = write_npy_folder(tmp_path / "in", images, lights, mask)
    (folder / "K.txt").write_text("60 0 19.5\n0 60 19.5\n0 0 1\n")
    out = tmp_path / "out.zarr"
    r = _maxfs("run", str(folder), "-o", str(out), "--eps", "2", "--tile", "32", "--depth", "bini")
    assert r.returncode == 0, r.stderr
    a = zarr.open_group(out / "results.zarr", mode="r")["depth"].attrs
    assert a["method"] == "bini" and a["camera"] == "perspective" and a["fx"] == 60.0  # from K.txt
    r = _maxfs("export", str(out), "-o", str(tmp_path / "ex"), "--depth", "ls", "--mesh-format", "ply")
    assert r.returncode == 0, r.stderr
    manifest = json.loads((tmp_path / "ex" / "export.json").read_text())
    assert manifest["depth"]["method"] == "ls" and "camera frame" in manifest["files"]["mesh.ply"]["frame"]
    assert "not_joined" in manifest["files"]["mesh.ply"]
    r = _maxfs("run", str(folder), "-o", str(tmp_path / "bad.zarr"), "--eps", "2", "--fx", "50")
    assert r.returncode != 0 and "fy, cx, cy missing" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
def test_http_job_takes_the_depth_method_and_refuses_bad_ones(
    tmp_path: Path, server_factory: Callable[..., Server]
) -> None:
    images, lights, _mask = _scene()
    k, H, W = images.shape
    server = server_factory(workers=1)
    shape = {"k": k, "height": H, "width": W, "lights": lights.tolist(), "eps": 2.0, "tile": 32}
    with httpx.Client(base_url=server.url, timeout=120) as http:
        r = http.post("/jobs", json=shape | {"depth": "poisson"})
        assert r.status_code == 422 and "depth" in r.text
        r = http.post("/jobs", json=shape | {"fx": 50.0})
        assert 400 <= r.status_code < 500 and "fy, cx, cy missing" in r.text
        r = http.post("/jobs", json=shape | {"depth": "bini", "depth_k": 3.0})
        assert r.status_code == 201, r.text
        jid = r.json()["id"]
        for i in range(k):
            assert http.put(f"/jobs/{jid}/images/{i}", content=images[i].tobytes()).status_code == 200
        assert http.post(f"/jobs/{jid}/start").status_code == 202
        store = tmp_path / "data" / "jobs" / jid
        poll_until(lambda: (store / "previews" / "depth.png").exists(), 120, "depth written")
        a = zarr.open_group(store / "results.zarr", mode="r")["depth"].attrs
        assert a["method"] == "bini" and a["k"] == 3.0 and a["camera"] == "orthographic"
        assert http.get(f"/jobs/{jid}/results/depth.npy").status_code == 200
