"""The public solve() facade: accuracy, degenerate pixels, thresholds, options."""

from __future__ import annotations

import numpy as np
import pytest

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.options import Solver
from maxfs.worker import synthetic
from maxfs.worker.milp import MilpSolver
from maxfs.worker.problem import make_thresholds, usable
from maxfs.worker.solve import solve, solve_pixels


@pytest.mark.parametrize(("k", "paper_deg"), [(12, 0.138), (24, 0.085)])
def test_sphere_accuracy_beats_paper(k: int, paper_deg: float) -> None:
    sc = synthetic.sphere(k, 64)
    sol = solve(sc.images, sc.lights, sc.mask, eps=1.0, saturation=sc.saturation)
    err = synthetic.angular_error_deg(sol.normal, sc.normals)[sc.mask]
    assert np.isfinite(err).all()
    assert err.mean() <= paper_deg
    # the baseline is far worse on the same data: the robustness is real
    l2 = solve(sc.images, sc.lights, sc.mask, solver="l2")
    assert synthetic.angular_error_deg(l2.normal, sc.normals)[sc.mask].mean() > 10 * err.mean()


def test_l2_is_least_squares_on_every_image() -> None:
    L = synthetic.lights_uniform(8)
    n = np.array([0.3, -0.2, 0.9]) * 150
    images = np.tile((L @ n)[:, None, None], (1, 2, 3))
    sol = solve(images, L, solver=Solver.L2)
    np.testing.assert_allclose(sol.normal[1, 2], n / np.linalg.norm(n), atol=1e-6)
    np.testing.assert_allclose(sol.albedo[1, 2], np.linalg.norm(n), rtol=1e-6)
    assert sol.inliers.all()


def test_degenerate_pixels_give_nan_normal_and_zero_albedo() -> None:
    sc = synthetic.sphere(12, 8)
    images = sc.images.copy()
    images[:, 0, 0] = 0.0  # all dark
    images[2:, 0, 1] = 0.0  # only 2 usable images
    images[:, 0, 2] = 255.0  # all saturated
    mask = np.ones((8, 8), bool)
    mask[0, 3] = False  # masked out
    for solver in ("exact", "milp"):
        sol = solve(images, sc.lights, mask, eps=1.0, saturation=255, solver=solver)
        for x in range(4):
            assert np.isnan(sol.normal[0, x]).all()
            assert sol.albedo[0, x] == 0
            assert sol.inlier_count[0, x] == 0
            assert not sol.inliers[:, 0, x].any()
        centre = sol.normal[4, 4]
        assert np.isfinite(centre).all()


def test_shadowed_and_saturated_images_are_never_inliers() -> None:
    sc = synthetic.bump_scene(24, 32)
    sol = solve(sc.images, sc.lights, sc.mask, eps=1.0, saturation=255, model="paper")
    assert not (sol.inliers & (sc.images <= 1.0)).any()
    assert not (sol.inliers & (sc.images >= 255)).any()
    # the cast-shadow scene really has both kinds of observation
    assert (sc.images[:, sc.mask] == 0).any() and (sc.images[:, sc.mask] >= 255).any()


def test_robust_model_counts_attached_shadows_only_where_the_light_is_behind() -> None:
    sc = synthetic.bump_scene(24, 32)
    sol = solve(sc.images, sc.lights, sc.mask, eps=1.0, saturation=255, model="robust", response=1.0)
    assert not (sol.inliers & (sc.images >= 255)).any()
    rim = synthetic.sphere(24, 32)  # attached shadows near the silhouette
    sol = solve(rim.images, rim.lights, rim.mask, eps=1.0, saturation=255, model="robust", response=1.0)
    dark = sol.inliers & (rim.images <= sol.eps / 3)  # shadow inliers
    true_ln = np.einsum("kd,hwd->khw", rim.lights, np.nan_to_num(rim.normals))
    assert dark.sum() > 50 and (true_ln[dark] < 0.01).all()  # the light is really behind
    cast = (sc.images == 0) & (np.einsum("kd,hwd->khw", sc.lights, np.nan_to_num(sc.normals)) > 0.2)
    assert cast[:, sc.mask].sum() > 50  # cast shadows (the light is in front) ...
    sol = solve(sc.images, sc.lights, sc.mask, eps=1.0, saturation=255, model="robust", response=1.0)
    assert not (sol.inliers & cast).any()  # ... are never inliers


def test_shadow_threshold_is_configurable() -> None:
    sc = synthetic.sphere(12, 24)
    sol = solve(sc.images, sc.lights, sc.mask, eps=1.0, shadow=20.0, saturation=255, model="paper")
    assert not (sol.inliers & (sc.images <= 20.0)).any()
    assert (sol.inliers & (sc.images > 20.0) & (sc.images < 30)).any()


def test_auto_eps_tracks_the_noise_level() -> None:
    quiet = synthetic.sphere(24, 48)
    noisy = synthetic.sphere(24, 48, noise=3.0, seed=1)
    e_quiet = solve(quiet.images, quiet.lights, quiet.mask, eps="auto", saturation=255).eps
    e_noisy = solve(noisy.images, noisy.lights, noisy.mask, eps="auto", saturation=255).eps
    assert 0.5 <= e_quiet <= 1.5  # 8-bit rounding: uniform +-0.5
    assert 6.0 <= e_noisy <= 12.0  # 3 sigma of sigma = 3
    sol = solve(noisy.images, noisy.lights, noisy.mask, eps="auto", saturation=255)
    err = synthetic.angular_error_deg(sol.normal, noisy.normals)[noisy.mask]
    assert err.mean() < 2.0


def test_rgb_albedo_per_channel_on_grey_inliers() -> None:
    sc = synthetic.sphere(12, 24)
    rgb = np.stack([sc.images, 0.5 * sc.images, 0.25 * sc.images], axis=-1)
    col = solve(rgb, sc.lights, sc.mask, eps=1.0, saturation=255)
    grey = solve(rgb.mean(axis=-1), sc.lights, sc.mask, eps=1.0, saturation=255)
    np.testing.assert_array_equal(col.inliers, grey.inliers)
    np.testing.assert_array_equal(col.normal, grey.normal)
    ratio = col.albedo_rgb[sc.mask] / col.albedo_rgb[sc.mask][:, :1]
    np.testing.assert_allclose(ratio, np.broadcast_to([1.0, 0.5, 0.25], ratio.shape), rtol=1e-6)


def test_exhausted_budget_falls_back_to_milp() -> None:
    # 24 images: at 12 the kernel's box LPs decide nearly every pixel at the root node
    sc = synthetic.bump_scene(24, 24)
    th = make_thresholds(24, 1.0, saturation=255)
    I = sc.images[:, sc.mask].T[::4]
    V = usable(I.T, th).T
    forced = solve_pixels(I, sc.lights, th, "exact", max_nodes=1)
    ref = MilpSolver(sc.lights).solve_rows(I, V, 1.0, th.box_factor)
    rows = V.sum(axis=1) >= 3
    assert (forced.nodes[rows] > 1).sum() > 10  # the budget really was exhausted
    assert forced.optimal.all()
    point_counts = forced.inliers.sum(axis=1)
    assert ((point_counts == ref[2]) | ~rows).all()


def test_milp_time_limit_marks_pixels_not_optimal() -> None:
    sc = synthetic.bump_scene(48, 16)
    th = make_thresholds(48, 1.0, saturation=255)
    I = sc.images[:, sc.mask].T[::8]
    res = solve_pixels(I, sc.lights, th, "exact", max_nodes=1, milp_time_limit=1e-4)
    ref = solve_pixels(I, sc.lights, th, "exact")
    assert ref.optimal.all()
    assert not res.optimal.all()
    # where nothing was proved, the answer is still a valid (maybe smaller) count
    assert (res.count <= ref.count).all()
    np.testing.assert_array_equal(res.count[res.optimal], ref.count[res.optimal])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"eps": -1.0}, "eps must be a positive"),
        ({"eps": "loose"}, "eps must be a positive number or 'auto'"),
        ({"shadow": -3.0}, "shadow threshold"),
        ({"saturation": [255.0, 255.0]}, "saturation must be a number or one number per image"),
        ({"box_factor": 0.5}, "box_factor"),
        ({"eps": 10**400}, "eps must be finite"),  # a Python int beyond float's range
        ({"box_factor": np.float32("inf")}, "box_factor must be finite"),
        ({"tile": 10**400}, "tile must be a whole number between 8 and 4096"),
        ({"tile": "32"}, "tile must be a whole number between 8 and 4096"),
        ({"intensities": [10**400, 1, 1, 1, 1, 1]}, "light intensities must be numbers"),
        ({"intensities": "bright"}, "light intensities must be numbers"),
        ({"intensities": [[1, 2], [1]]}, "light intensities must be numbers"),
        ({"solver": "simplex"}, "simplex"),
    ],
)
def test_bad_options_are_rejected_clearly(kwargs: dict, message: str) -> None:
    sc = synthetic.sphere(6, 4)
    with pytest.raises(ValueError, match=message):
        solve(sc.images, sc.lights, **kwargs)


@pytest.mark.parametrize(
    ("images", "lights", "mask", "message"),
    [
        (np.zeros((4, 5)), synthetic.lights_uniform(4), None, r"images must be \(k, H, W\)"),
        (np.zeros((4, 5, 5)), synthetic.lights_uniform(3), None, "3 light directions for 4 images"),
        (np.zeros((4, 5, 5)), synthetic.lights_uniform(4) * 2, None, "unit vectors"),
        (np.zeros((4, 5, 5)), np.full((4, 3), np.nan), None, "NaN"),
        (np.zeros((4, 5, 5)), synthetic.lights_uniform(4), np.ones((5, 4)), "mask has shape"),
        (np.zeros((2, 5, 5)), synthetic.lights_uniform(2), None, "at least 3 images"),
    ],
)
def test_bad_inputs_raise_invalid_input(images, lights, mask, message) -> None:
    with pytest.raises(InvalidInputError, match=message):
        solve(images, lights, mask)
