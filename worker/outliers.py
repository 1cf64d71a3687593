"""Data-dependent outlier rules of the robust model (what each pixel's own data says).

**Near-mirror highlights.** A specular lobe or sheen adds light only where the half-vector
``h_i = (L_i + v) / |L_i + v|`` (view ``v = +z``) is close to the normal. A first-pass
normal ``n0`` per pixel (least trimmed squares over its lit candidates,
:func:`worker.noise.lts_fit`) tells which images those are; a lit candidate is an outlier
by definition when ``angle(n0, h_i) < mirror_deg`` *and* it is brighter than ``n0``
predicts by more than the noise (``eps / 3``, one sigma) *and* the pixel has a lobe: the mean
excess of its near-mirror images is more than :data:`LOBE_Z` standard errors above zero (a
one-sided test). A Lambertian pixel keeps its near-mirror images (noise scatters them around
the fit, and one sigma alone would reject about one in six), a glossy one loses the lobe even
where it fits within the tolerance. The rule never starves a pixel: it removes at most ``m - MIN_KEPT`` of its
``m`` lit candidates (the largest excesses first), so a pixel with few images keeps them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from maxfs.worker.noise import lts_fit

#: A pixel keeps at least this many lit candidates (twice the 3 unknowns of ``n``).
MIN_KEPT = 6
#: A pixel has a lobe when its near-mirror images' mean excess is this many standard errors above 0.
LOBE_Z = 2.0
VIEW = np.array([0.0, 0.0, 1.0])


def half_vectors(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(k, 3)`` unit half-vectors of the lights and the view ``+z``."""
    h = L + VIEW
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def first_pass(S: NDArray[np.float64], lit: NDArray[np.bool_], L: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(P, 3)`` least-trimmed-squares ``n`` over the lit candidates; NaN where undetermined."""
    n0 = np.full((S.shape[0], 3), np.nan)
    rows = np.flatnonzero(lit.sum(axis=1) >= 3)
    if rows.size == S.shape[0]:  # every pixel: the same fit without copying the batch
        return lts_fit(S, lit, L)
    if rows.size:
        n0[rows] = lts_fit(S[rows], lit[rows], L)
    return n0


def near_mirror(
    S: NDArray[np.float64],
    lit: NDArray[np.bool_],
    L: NDArray[np.float64],
    mirror_deg: float,
    excess: float,
    n_first: NDArray[np.float64] | None = None,
) -> NDArray[np.bool_]:
    """``(P, k)`` lit candidates to reject as highlights (module docstring).

    Parameters
    ----------
    S : (P, k) what ``L.n`` should match; lit : (P, k) lit candidates; L : (k, 3) lights;
    mirror_deg : the cone around the mirror direction; excess : how much brighter than the
    first-pass fit (in ``S`` units) an observation must be to count as a highlight.
    """
    P, k = S.shape
    out = np.zeros((P, k), dtype=bool)
    m = lit.sum(axis=1)
    rows = np.flatnonzero(m > MIN_KEPT)
    if mirror_deg <= 0 or rows.size == 0:
        return out
    n0 = lts_fit(S[rows], lit[rows], L) if n_first is None else n_first[rows]
    rho = np.linalg.norm(n0, axis=1)
    ok = np.isfinite(rho) & (rho > 0)
    rows, n0, rho = rows[ok], n0[ok], rho[ok]
    if rows.size == 0:
        return out
    whole = rows.size == P  # every pixel: no row copies of S and lit
    res = (S if whole else S[rows]) - n0 @ L.T
    close = (n0 / rho[:, None]) @ half_vectors(L).T > np.cos(np.radians(mirror_deg))
    cone = (lit if whole else lit[rows]) & close
    # a lobe first: the pixel's near-mirror images must be brighter than the first pass on
    # average, beyond what noise gives (one-sided z-test of their mean excess at 2 sigma of the
    # mean); a Lambertian pixel's images scatter around it and keep every image
    n_c = cone.sum(axis=1)
    mean_res = np.where(n_c > 0, (np.where(cone, res, 0.0)).sum(axis=1) / np.maximum(n_c, 1), 0.0)
    glossy = mean_res > LOBE_Z * excess / np.sqrt(np.maximum(n_c, 1))
    cand = cone & (res > excess) & glossy[:, None]
    # never leave fewer than MIN_KEPT: keep the smallest excesses of the ones over the cap
    cap = m[rows] - MIN_KEPT
    over = cand.sum(axis=1) > cap
    if over.any():
        r = np.where(cand[over], res[over], -np.inf)
        rank = np.argsort(np.argsort(-r, axis=1, kind="stable"), axis=1, kind="stable")
        cand[over] &= rank < cap[over, None]
    if whole:
        return cand
    out[rows] = cand
    return out
