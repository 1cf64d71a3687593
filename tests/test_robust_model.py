"""The robust model (issue #16): every tolerance model is still exact against the MILP,
the job-level estimates do not depend on the tile grid, and each pixel says how its
normal was obtained."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.observations import ObservationModel
from maxfs.storage.options import Estimate
from maxfs.storage.outputs import Source
from maxfs.storage.params import JobParams
from maxfs.worker import synthetic
from maxfs.worker.exact import exact_pixels
from maxfs.worker.milp import MilpSolver
from maxfs.worker.noise import estimate_eps, select_response
from maxfs.worker.problem import REL_TOL, candidates, make_thresholds, shading, slabs
from maxfs.worker.solve import eps_sample, solve, solve_pixels
from maxfs.worker.task import estimate_eps_of


def _robust_pixels(k: int, seed: int, response: float, eps_rel: float, drop: float):
    """Pixels of a glossy scene rendered through the response ``I = s^g``, with noise."""
    sc = synthetic.bump_scene(k, 32, noise=1.0, seed=seed, bits=None)
    lin = np.clip(sc.images, 0, None)
    I = (lin / 255.0) ** response * 255.0  # a response applied to the linear radiance
    P = I[:, sc.mask].T
    rng = np.random.default_rng(seed)
    out = rng.random(P.shape) < 0.2  # outliers of both signs, so the optima are not trivial
    P[out] = np.clip(P[out] + rng.uniform(-40, 80, out.sum()), 0, 250)
    th = make_thresholds(
        k, 2.0, model="robust", response=response, eps_rel=eps_rel, drop_bright=drop, saturation=255
    )
    V = candidates(P, th)
    rows = np.flatnonzero(V.sum(axis=1) >= 3)
    pick = rows[np.linspace(0, rows.size - 1, 40).astype(int)]
    return P[pick], V[pick], sc.lights, th


@pytest.mark.parametrize(
    ("k", "response", "eps_rel", "drop"),
    [(12, 1.0, 0.05, 0.0), (24, 1.6, 0.0, 0.3), (24, 0.7, 0.03, 0.3), (40, 2.2, 0.02, 0.2)],
)
def test_exact_matches_milp_for_every_tolerance_model(k, response, eps_rel, drop) -> None:
    I, V, L, th = _robust_pixels(k, k, response, eps_rel, drop)
    lo, hi = slabs(I, th)
    S = shading(I, th)
    pt, inl, cnt, _, cert = exact_pixels(S, lo, hi, V, L, th.box_factor, 10**7)
    _, _, mcnt, mcert, stats = MilpSolver(L, time_limit=60).solve_rows(S, V, (lo, hi), th.box_factor)
    assert cert.all() and mcert.all()
    np.testing.assert_array_equal(stats.claimed, mcnt)
    np.testing.assert_array_equal(cnt, mcnt)
    # the exact point really lies in every claimed slab, and the slabs are not all one width
    v = pt @ L.T
    tol = REL_TOL * np.where(V, hi, 0).max(axis=1, keepdims=True)
    np.testing.assert_array_equal(inl, V & (v >= lo - tol) & (v <= hi + tol))
    assert (cnt < V.sum(axis=1)).sum() >= 3
    one_sided = V & np.isinf(lo)  # shadows: L.n <= hi, counted where they hold
    assert (one_sided & inl).sum() >= 5 and (one_sided & ~inl).any()
    width = np.where(V & ~one_sided, hi - lo, np.nan)
    assert np.nanmax(width) > 1.5 * np.nanmin(width)


def test_slabs_of_the_robust_model() -> None:
    th = make_thresholds(3, 3.0, model="robust", response=2.0, eps_rel=0.1)
    I = np.array([[4.0, 100.0, 1.5]])
    lo, hi = slabs(I, th)
    t = 3.0 + 0.1 * I
    np.testing.assert_allclose(lo, np.sqrt(np.maximum(I - t, th.shadow)))
    np.testing.assert_allclose(hi, np.sqrt(I + t))
    assert th.shadow == pytest.approx(1.0)  # eps / 3: one sigma
    paper = make_thresholds(3, 3.0)
    np.testing.assert_array_equal(slabs(I, paper)[0], slabs(I, 3.0)[0])  # bit for bit


def test_brightest_candidates_are_dropped_but_three_stay() -> None:
    # the paper's model: its shadows (<= eps) are no candidates, so the second row has 4
    th = make_thresholds(10, 1.0, model="paper", drop_bright=0.3)
    I = np.array([[10, 20, 30, 40, 50, 60, 70, 80, 90, 100.0], [0, 0, 0, 0, 0, 0, 5, 6, 7, 8.0]])
    V = candidates(I, th)
    np.testing.assert_array_equal(V[0], I[0] <= 70)  # 3 of 10 dropped
    np.testing.assert_array_equal(V[1], np.r_[[False] * 6, True, True, True, False])  # 4 -> 3


def test_dequantize_reads_floors_as_bin_centres() -> None:
    raw = np.array([[[0, 10, 255]]], dtype=np.uint8).reshape(1, 3)
    obs = ObservationModel.for_input(np.dtype(np.uint8), 1, None, None, dequantize=True)
    grey, _, sat = obs.prepare(raw)
    np.testing.assert_array_equal(grey[:, 0], [0.0, 10.5, 255.5])
    np.testing.assert_array_equal(sat[:, 0], [False, False, True])
    assert not ObservationModel.for_input(np.dtype(np.float32), 1, None, None, dequantize=True).dequantize


def test_response_is_recovered_from_the_data() -> None:
    sc = synthetic.sphere(48, 40, specular=0.0, bits=None, noise=0.0)
    lin = sc.images[:, sc.mask].T
    for g in (1.0, 1.8, 0.6):
        I = np.round((lin / 200.0) ** g * 200.0 * 50) / 50  # I = (L.n)^g, finely quantised
        ok = I > 1.0
        assert select_response(I, ok, sc.lights) == pytest.approx(g, rel=0.05)


def test_eps_floor_scales_with_the_data_range() -> None:
    sc = synthetic.sphere(12, 24, specular=0.0, bits=None)
    I = sc.images[:, sc.mask].T * 250.0  # 16-bit scale, noise-free: the fit is exact
    eps = estimate_eps(I, I > 0, sc.lights, step=1.0)
    assert eps >= 1e-3 * np.percentile(I[I > 0], 99) > 10


def _scene_and_store(tmp_path: Path, tile: int) -> tuple[np.ndarray, np.ndarray, JobStore]:
    sc = synthetic.bump_scene(12, 200, seed=4)
    images = sc.images.astype(np.uint8)
    spec = JobSpec(12, 200, 200, None, "uint8", sc.lights)
    params = JobParams.build(eps="auto", tile=tile, model="robust")
    store = JobStore.create(tmp_path / f"t{tile}", spec, params)
    for i in range(12):
        store.write_image(i, images[i])
    store.write_mask(sc.mask)
    return images, sc.lights, store


def test_estimates_do_not_depend_on_the_tile_size(tmp_path: Path) -> None:
    ests = []
    for tile in (96, 128):
        images, lights, store = _scene_and_store(tmp_path, tile)
        ests.append(estimate_eps_of(store))  # the Dask task's path: windows read from the store
    assert isinstance(ests[0], Estimate) and ests[0] == ests[1]
    # the in-process path reads the same windows from memory
    mask = store.read_mask()
    for tile in (96, 128):
        sol = solve(images, lights, mask, eps="auto", model="robust", tile=tile, max_nodes=1, solver="l2")
        assert (sol.eps, sol.response) == (ests[0].eps, ests[0].response)
    windows = eps_sample((200, 200), mask)
    assert 3000 <= sum(len(ys) for _, ys, _ in windows) <= 4096


def test_source_codes_and_rank_deficient_pixels() -> None:
    # seven lights: four in the plane y = 0, two well out of it, one barely (y = 0.01)
    L = np.array([[0.5, 0, 0.866], [-0.5, 0, 0.866], [0.3, 0, 0.954], [-0.3, 0, 0.954]] + [[0.0] * 3] * 3)
    L[4:] = [[0, 0.5, 0.866], [0.2, -0.5, 0.843], [0.0, 0.01, 1.0]]
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    n = np.array([0.1, 0.2, 0.97]) * 100
    good = L @ n
    I = np.tile(good, (5, 1))
    I[1, 4:] = 0.0  # only the coplanar lights are lit: no Max-FS normal, never certified
    I[4, 4:6] = 0.0  # coplanar lights and one barely out of the plane: badly conditioned
    I[2, 2:] = 0.0  # two candidates: too few for Max-FS; the robust model's fallback
    I[2, 4] = 0.2  # uses this third non-zero value (a shadow for both models' thresholds)
    active = np.array([True, True, True, False, True])
    for model in ("paper", "robust"):
        th = make_thresholds(7, 1.0, model=model, response=1.0)
        r = solve_pixels(I, L, th, "exact", active=active)
        assert r.source[0] == Source.CERTIFIED and r.optimal[0]
        for p in (1, 4):
            assert not r.optimal[p]
            if model == "paper":
                assert r.source[p] == Source.UNDETERMINED and np.isnan(r.normal[p]).all()
            else:  # the fallback's last resort: every observation, zeros included (as l2)
                assert r.source[p] == Source.FIT and np.isfinite(r.normal[p]).all()
        assert r.source[3] == Source.MASKED and not r.optimal[3]
        assert r.source[2] == (Source.FIT if model == "robust" else Source.UNDETERMINED)
        assert np.isfinite(r.normal[2]).all() == (model == "robust") and not r.optimal[2]
    l2 = solve_pixels(I, L, make_thresholds(7, 1.0), "l2")
    assert (l2.source[:3] == Source.FIT).all() and not l2.optimal.any()
    capped = solve_pixels(I[:1], L, make_thresholds(7, 1.0), "milp", milp_time_limit=1e-6)
    assert capped.source[0] in (Source.CERTIFIED, Source.BEST_FOUND)
    assert (capped.source[0] == Source.CERTIFIED) == capped.optimal[0]


def test_params_resolve_both_estimates_and_keep_old_records() -> None:
    p = JobParams.build(eps=2.0, model="robust")
    assert p.eps is None and p.response is None and p.response_request == "auto"
    assert p.drop_bright == 0.0 and p.dequantize and p.fallback
    r = p.with_eps(Estimate(2.0, 1.3, 0.0))
    assert (r.eps, r.response) == (2.0, 1.3) and r.unresolved() == p
    fixed = JobParams.build(eps=2.0, model="robust", response=1.3)
    assert fixed.eps == 2.0 and fixed.with_eps(2.0).response == 1.3
    old = JobParams.from_json({"solver": "exact", "eps": 1.0, "eps_request": 1.0})
    assert old.model == "paper" and old.response == 1.0 and old.digest()
    with pytest.raises(ValueError, match="drop_bright"):
        JobParams.build(model="robust", drop_bright=1.5)
    with pytest.raises(ValueError, match="unknown model"):
        JobParams.build(model="fancy")


def test_shadow_inliers_count_for_the_optimum_but_not_the_refit() -> None:
    # lights behind the surface give zeros: one-sided slabs that hold at the true normal
    L = synthetic.lights_uniform(12)
    n = np.array([0.95, 0.0, 0.31]) * 100.0
    I = np.maximum(L @ n, 0.0)[None].repeat(2, axis=0)
    I[1, np.argmax(I[1])] += 60.0  # a highlight-like outlier on the second pixel
    assert (I[0] == 0).sum() >= 2
    th = make_thresholds(12, 1.0, model="robust", response=1.0)
    r = solve_pixels(I, L, th, "exact")
    dark = I <= th.shadow
    assert r.optimal.all() and (r.inliers & dark).sum() == dark.sum()  # every shadow holds
    np.testing.assert_array_equal(r.count, r.inliers.sum(axis=1))
    # the normal is the least-squares fit of the lit inliers alone: shadows do not pull it to 0
    lit = r.inliers & ~dark
    for p in range(2):
        want, *_ = np.linalg.lstsq(L[lit[p]], I[p, lit[p]], rcond=None)
        np.testing.assert_allclose(r.normal[p] * r.albedo[p], want, rtol=1e-5, atol=1e-4)
    paper = solve_pixels(I, L, make_thresholds(12, 1.0), "exact")
    assert (paper.count < r.count).all()  # the paper's model never counts a shadow


def test_near_mirror_rule_keeps_lambertian_and_few_image_pixels() -> None:
    from maxfs.worker.outliers import MIN_KEPT, half_vectors, near_mirror

    L = synthetic.lights_uniform(24)
    N = np.array([0.0, 0.0, 1.0])
    S = np.tile(L @ N * 100.0, (3, 1))
    close = half_vectors(L) @ N > np.cos(np.radians(12.0))
    assert 3 <= close.sum() <= 8
    S[1, close] += 30.0  # a lobe around the mirror direction, inside the rule's 20 degrees
    lit = np.ones_like(S, dtype=bool)
    lit[2, 8:] = False  # 8 lit images: at most 2 may go
    S[2, :8][close[:8]] += 30.0
    out = near_mirror(S, lit, L, 20.0, 1.0)
    assert not out[0].any()  # Lambertian: the near-mirror images fit, none is rejected
    np.testing.assert_array_equal(out[1], close)
    assert out[2].sum() <= 8 - MIN_KEPT and (out[2] <= close).all()
    assert not near_mirror(S[:, :MIN_KEPT], lit[:, :MIN_KEPT], L[:MIN_KEPT], 20.0, 1.0).any()


def test_response_is_kept_only_if_it_predicts_held_out_images_better() -> None:
    from maxfs.worker.noise import validated_response

    sc = synthetic.sphere(24, 32, specular=0.0, bits=None, noise=0.5, seed=2)
    lin = np.maximum(sc.images[:, sc.mask].T, 0.0)
    ok = lin > 1.0
    assert validated_response(lin, ok, sc.lights, 1.6) == 1.0  # linear data: g = 1.6 predicts worse
    curved = (lin / 200.0) ** 1.6 * 200.0
    assert validated_response(curved, curved > 1.0, sc.lights, 1.6) == 1.6


def test_solve_defaults_are_the_cli_and_http_defaults() -> None:
    import inspect

    from maxfs.storage.options import SOLVE_OPTIONS

    sig = inspect.signature(solve).parameters
    for opt in SOLVE_OPTIONS:
        if opt.name in sig and opt.default is not None and opt.name != "tile":
            assert str(sig[opt.name].default) == str(opt.default), opt.name
    sc = synthetic.sphere(12, 16, noise=1.0)
    a = solve(sc.images.astype(np.uint8), sc.lights, sc.mask)
    b = solve(sc.images.astype(np.uint8), sc.lights, sc.mask, model="robust", eps="auto")
    np.testing.assert_array_equal(a.normal, b.normal)
    assert a.eps == b.eps
