"""The robust model at few images (issue #21): eps estimated consistently whatever k, the
refit of the sensor model ``s = max(L.n, 0)`` over lit and shadow inliers, and a normal for
every pixel the least-squares baseline gets one for."""

from __future__ import annotations

import numpy as np
import pytest

from maxfs.storage.outputs import Source
from maxfs.worker import synthetic
from maxfs.worker.lstsq import refit
from maxfs.worker.noise import estimate_noise
from maxfs.worker.problem import make_thresholds
from maxfs.worker.solve import censored_refit, solve_pixels


@pytest.mark.parametrize("k", [4, 5, 6, 7, 8, 12, 48])
def test_noise_sigma_is_consistent_at_every_k(k: int) -> None:
    # Lambertian, Gaussian noise of known sigma, only clearly lit observations usable: the
    # least-trimmed-squares residuals of 4 of 8 images understate sigma about 2.8-fold; below 8
    # images (no pixel where the trimmed fit keeps more than the 3 unknowns) least squares
    sc = synthetic.sphere(k, 40, specular=0.0, bits=None, noise=0.0)
    shade = sc.images[:, sc.mask].T
    rng = np.random.default_rng(k)
    I = shade + rng.normal(0.0, 2.0, shade.shape)
    usable = shade > 20.0
    for by_intensity in (False, True):
        eps, sigma = estimate_noise(I, usable, sc.lights, step=None, by_intensity=by_intensity)
        assert 0.8 * 2.0 < sigma < 1.25 * 2.0, (k, by_intensity, sigma)
        assert eps == pytest.approx(3.0 * sigma)


def test_censored_refit_pulls_only_where_the_fit_lights_a_shadow() -> None:
    L = synthetic.lights_uniform(8)
    n_true = np.array([0.95, 0.0, 0.31]) * 100.0
    s = np.maximum(L @ n_true, 0.0)
    dark = s <= 0.0
    assert 1 <= dark.sum() <= 5
    S = np.tile(s, (2, 1))
    near = np.flatnonzero(~dark)[np.argmax(L[~dark] @ L[dark].mean(axis=0))]
    S[1, near] += 60.0  # an unrejected error next to the shadows tilts pixel 1's lit fit to them
    lit = np.tile(~dark, (2, 1))
    sh = np.tile(dark, (2, 1))
    n_lit = refit(S, lit, L)
    n = censored_refit(S, lit, sh, L, n_lit)
    np.testing.assert_array_equal(n[0], n_lit[0])  # the exact fit already keeps its shadows dark
    breaks = (n_lit[1] @ L.T > S[1]) & dark
    assert breaks.any(), "the case must make the lit fit light a shadow"
    # the answer is the fixed point: least squares over the lit rows and the shadow rows it lights
    active = dark & (n[1] @ L.T > S[1])
    want = refit(S[1:], (lit[1] | active)[None], L)[0]
    np.testing.assert_allclose(n[1], want, rtol=1e-12)
    err = lambda v: np.degrees(np.arccos(v @ n_true / np.linalg.norm(v) / np.linalg.norm(n_true)))  # noqa: E731
    assert err(n[1]) < err(n_lit[1])


def test_a_nearly_black_pixel_gets_the_normal_least_squares_gives() -> None:
    # two non-zero values of eight: too few to determine a normal from the non-zero ones, but
    # the zeros measure max(L.n, 0) as well; the l2 baseline fits them all, and so must the
    # fallback (a pixel without a normal counts as 180 degrees)
    L = synthetic.lights_uniform(8)
    I = np.zeros((1, 8))
    I[0, [1, 5]] = [2.0, 1.0]
    th = make_thresholds(8, 1.5, model="robust", response=1.0)
    r = solve_pixels(I, L, th, "exact")
    l2 = solve_pixels(I, L, th, "l2")
    assert r.source[0] == Source.FIT and not r.optimal[0]
    np.testing.assert_allclose(r.normal[0], l2.normal[0], rtol=1e-6)
    assert r.inliers[0].all()
