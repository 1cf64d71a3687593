"""The exact solver against the HiGHS MILP reference, on real optima."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from maxfs.worker import synthetic
from maxfs.worker.exact import exact_pixels
from maxfs.worker.milp import MilpSolver
from maxfs.worker.problem import REL_TOL, make_thresholds, slabs, usable


@dataclass(frozen=True)
class Case:
    scene: str
    k: int
    eps: float = 1.0
    noise: float = 0.0
    pixels: int = 160


CASES = [Case(scene, k) for scene in ("sphere", "bump") for k in (4, 12, 24)] + [
    Case("sphere", 12, eps=4.0, noise=2.0),
    Case("bump", 24, eps=3.0, noise=1.5),
]


def _pixels(case: Case) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    make = synthetic.sphere if case.scene == "sphere" else synthetic.bump_scene
    sc = make(case.k, 40, noise=case.noise, seed=case.k)
    th = make_thresholds(case.k, case.eps, saturation=sc.saturation)
    I = sc.images[:, sc.mask].T
    V = usable(sc.images, th)[:, sc.mask].T
    rows = np.flatnonzero(V.sum(axis=1) >= 3)
    pick = rows[np.linspace(0, rows.size - 1, case.pixels).astype(int)]
    return I[pick], V[pick], sc.lights


def _assert_feasible(I, V, L, eps, point, inl, tol_rel):
    """Every claimed inlier lies in its slab at the returned point; none is unusable."""
    a, b = slabs(I, eps)
    v = point @ L.T
    tol = tol_rel * np.where(V, b, 0).max(axis=1, keepdims=True)
    inside = (v >= a - tol) & (v <= b + tol)
    assert not (inl & ~V).any(), "an unusable image was counted as an inlier"
    assert (inside | ~inl).all(), "a claimed inlier violates its slab at the solver's point"
    np.testing.assert_array_equal(inl, inside & V)


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c.scene}-k{c.k}-eps{c.eps}-noise{c.noise}")
def test_exact_matches_milp_optimum(case: Case) -> None:
    I, V, L = _pixels(case)
    pt, inl, cnt, _, cert = exact_pixels(I, *slabs(I, case.eps), V, L, 10.0, 10**7)
    mpt, minl, mcnt, mcert, stats = MilpSolver(L, time_limit=60).solve_rows(I, V, case.eps, 10.0)
    assert cert.all() and mcert.all(), "both solvers must prove optimality here"
    np.testing.assert_array_equal(stats.claimed, mcnt)  # HiGHS's claimed inliers re-check
    np.testing.assert_array_equal(cnt, mcnt)
    _assert_feasible(I, V, L, case.eps, pt, inl, REL_TOL)
    _assert_feasible(I, V, L, case.eps, mpt, minl, 1e-6)
    # the sample is not trivial: some pixels have outliers among usable images
    assert (cnt < V.sum(axis=1)).sum() >= 5


@pytest.mark.slow
def test_random_arrangements_match_milp() -> None:
    """Random lights over the whole upper hemisphere and random outliers."""
    rng = np.random.default_rng(7)
    for trial in range(12):
        k = int(rng.integers(4, 30))
        L = rng.normal(size=(k, 3))
        L[:, 2] = np.abs(L[:, 2]) + 0.1
        L /= np.linalg.norm(L, axis=1, keepdims=True)
        n_true = rng.normal(size=(25, 3)) * 40 + np.array([0, 0, 120])
        I = n_true @ L.T + rng.normal(0, 0.7, size=(25, k))
        out = rng.random((25, k)) < 0.3
        I[out] += rng.uniform(-80, 120, size=out.sum())
        I = np.clip(I, 0, None)
        eps = float(rng.uniform(0.5, 3))
        th = make_thresholds(k, eps)
        V = usable(I.T, th).T
        keep = V.sum(axis=1) >= 3
        I, V = I[keep], V[keep]
        pt, inl, cnt, _, cert = exact_pixels(I, *slabs(I, eps), V, L, 10.0, 10**7)
        _, _, mcnt, mcert, _ = MilpSolver(L, time_limit=60).solve_rows(I, V, eps, 10.0)
        assert cert.all() and mcert.all()
        np.testing.assert_array_equal(cnt, mcnt, err_msg=f"trial {trial}")
        _assert_feasible(I, V, L, eps, pt, inl, REL_TOL)


def test_one_sided_shadow_slabs_match_milp() -> None:
    """Shadows as one-sided slabs ``L.n <= hi`` (``lo = -inf``): random lights over the
    hemisphere (many behind the surface), random outliers and dark cast shadows."""
    rng = np.random.default_rng(11)
    for trial in range(10):
        k = int(rng.integers(6, 30))
        L = rng.normal(size=(k, 3))
        L[:, 2] = np.abs(L[:, 2]) + 0.1
        L /= np.linalg.norm(L, axis=1, keepdims=True)
        n_true = rng.normal(size=(25, 3)) * 60 + np.array([0, 0, 80])
        I = np.maximum(n_true @ L.T, 0.0) + rng.normal(0, 0.7, size=(25, k))
        out = rng.random((25, k)) < 0.25
        I[out] = np.where(rng.random(out.sum()) < 0.5, 0.0, I[out] + rng.uniform(-60, 100, out.sum()))
        I = np.clip(I, 0, None)
        th = make_thresholds(k, float(rng.uniform(0.5, 3)), model="robust", response=1.0)
        lo, hi = slabs(I, th)
        V = np.isfinite(I)
        assert np.isinf(lo).any() and np.isfinite(lo).any()
        keep = (V & np.isfinite(lo)).sum(axis=1) >= 3
        I, V, lo, hi = I[keep], V[keep], lo[keep], hi[keep]
        pt, inl, cnt, _, cert = exact_pixels(I, lo, hi, V, L, 10.0, 10**7)
        mpt, minl, mcnt, mcert, stats = MilpSolver(L, time_limit=60).solve_rows(I, V, (lo, hi), 10.0)
        assert cert.all() and mcert.all()
        np.testing.assert_array_equal(stats.claimed, mcnt)
        np.testing.assert_array_equal(cnt, mcnt, err_msg=f"trial {trial}")
        for p, il in ((pt, inl), (mpt, minl)):
            v = p @ L.T
            tol = 1e-6 * np.where(V, hi, 0).max(axis=1, keepdims=True)
            assert ((v >= lo - tol) & (v <= hi + tol) | ~il).all()
        assert (inl & np.isinf(lo)).sum() >= 5  # shadows really count


def test_the_milp_reference_prints_nothing_to_stdout() -> None:
    """HiGHS 1.16 writes a copyright banner to stdout on the first ``Highs()`` of a process,
    whatever ``output_flag`` says; ``maxfs run``'s MILP fallback would print it between its
    progress lines. A fresh process, so the banner has not been shown yet."""
    import subprocess
    import sys

    code = (
        "from maxfs.worker.milp import MilpSolver\n"
        "from maxfs.worker import synthetic\n"
        "import numpy as np\n"
        "L = synthetic.lights_uniform(8)\n"
        "I = np.clip(L @ np.array([0.1, 0.2, 0.9]) * 100, 0, None)[None]\n"
        "MilpSolver(L, 5.0).solve_rows(I, I > 0, 1.0, 10.0)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout == ""
