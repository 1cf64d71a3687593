"""The compiled LTS of the response estimate (worker/lts_kernel.py) against numpy's
(:func:`worker.noise.lts_fit` and the residual medians of :func:`worker.noise._residuals`):
the same fit to rounding, the same undetermined pixels, on ties, sparse and degenerate rows."""

from __future__ import annotations

import numpy as np
import pytest

from maxfs.worker import noise, synthetic
from maxfs.worker.lts_kernel import _kth_smallest, lts_normals, response_medians


def _cases():
    rng = np.random.default_rng(5)
    L = synthetic.lights_uniform(24)
    n = rng.normal(size=(400, 3)) * [0.3, 0.3, 1.0]
    clean = np.maximum(n @ L.T, 0.0) * 200
    noisy = clean + rng.normal(scale=2.0, size=clean.shape)
    noisy[rng.random(clean.shape) < 0.2] += 150  # outliers
    usable = noisy > 0
    yield "noisy", np.maximum(noisy, 0.0), usable, L
    yield "ties", np.round(noisy / 40), usable, L  # many equal intensities and residuals
    # rows of 0-10 observations
    yield "sparse", np.maximum(noisy, 0.0), usable & (rng.random(usable.shape) < 0.2), L
    coplanar = L.copy()
    coplanar[:, 2] = 0.5  # every light in one plane's direction: some fits undetermined
    yield "exact", clean, usable, L
    yield "coplanar", clean, usable, coplanar


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: c[0])
def test_lts_normals_is_lts_fit(case):
    _, I, sel, L = case
    a, b = noise.lts_fit(I, sel, L), lts_normals(I, sel, L, 3)
    assert np.array_equal(np.isnan(a), np.isnan(b))
    fin = np.isfinite(a)
    np.testing.assert_allclose(b[fin], a[fin], rtol=0, atol=1e-9 * max(1.0, np.abs(a[fin]).max()))


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: c[0])
@pytest.mark.parametrize("g", [1.0, 0.6, 1.7])
def test_response_medians_match_numpy(case, g):
    _, I, sel, L = case
    ref = noise._row_medians(np.abs(noise._residuals(I, sel, L, g, noise.lts_fit)))
    got = response_medians(I, sel, L, g, 3)
    got = got[~np.isnan(got)]
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9 * max(1.0, float(I.max())))


def test_kth_smallest_is_sorted_value():
    rng = np.random.default_rng(0)
    for t in range(2000):
        m = int(rng.integers(1, 100))
        v = rng.integers(0, 6, m).astype(float) if t % 2 else rng.random(m)
        k = int(rng.integers(0, m))
        assert _kth_smallest(v.copy(), np.empty(m), m, k) == np.sort(v)[k]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # NaN and inf observations
@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: c[0])
def test_lts_fit_compiled_round_is_bit_identical(case, monkeypatch):
    """lts_fit's compiled selection (numba loaded) and numpy's sort give the same n, bit for bit."""
    _, I, sel, L = case
    I = I.copy()
    I[::37, 5] = np.nan  # NaN and inf observations, selected or not
    I[::41, 7] = np.inf
    got = noise.lts_fit(I, sel, L)
    monkeypatch.setattr(noise, "_compiled_keep", lambda: None)
    ref = noise.lts_fit(I, sel, L)
    assert np.array_equal(got, ref, equal_nan=True)


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: c[0])
@pytest.mark.parametrize("g", [1.0, 0.6, 1.7])
def test_response_medians_read_only_selected_values(case, g):
    """The kernel raises only the selected observations to 1/g: what the others hold (here
    NaN, inf or huge) changes no bit of any pixel's median."""
    _, I, sel, L = case
    junk = I.copy()
    junk[~sel] = np.resize([np.nan, np.inf, 1e300, -5.0], int((~sel).sum()))
    a, b = response_medians(I, sel, L, g, 3), response_medians(junk, sel, L, g, 3)
    assert a.tobytes() == b.tobytes()


def test_bin_order_parts_are_the_stable_sorts():
    """noise.bin_order's parts hold the same observations as a stable argsort's, ties at the
    boundaries included, so the estimate's per-bin medians are unchanged."""
    rng = np.random.default_rng(3)
    for t in range(400):
        n, bins = int(rng.integers(1, 2000)), int(rng.integers(1, 14))
        top = int(rng.integers(1, 40)) if t % 3 else 10**9  # many ties, or almost none
        x = rng.integers(0, top, n) / rng.uniform(0.5, 2.0)
        ref = np.array_split(np.argsort(x, kind="stable"), bins)
        got = np.array_split(noise.bin_order(x, bins), bins)
        for a, b in zip(ref, got, strict=True):
            np.testing.assert_array_equal(np.sort(a), np.sort(b))
