"""Automatic choice of eps from the data's own noise level."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from worker.errors import InvalidInputError
from worker.lstsq import refit

#: eps = this many robust standard deviations of the inlier residuals.
EPS_SIGMAS = 3.0


def estimate_eps(
    I: NDArray[np.floating],
    usable: NDArray[np.bool_],
    L: NDArray[np.float64],
    *,
    integer_valued: bool,
    sample: int = 4000,
    seed: int = 0,
) -> float:
    """Estimate eps as ``3 sigma`` of the residuals of a robust per-pixel fit.

    For up to ``sample`` pixels with at least 6 usable observations, a least
    trimmed squares fit (refit on the half of the observations closest to the
    current fit, three times) gives residuals; sigma is 1.4826 times their pooled
    median absolute value, which ignores specular and shadow outliers as long as
    they are under half. Integer-valued data are never given eps below 0.5, the
    largest rounding error.

    Parameters
    ----------
    I : (P, k) intensities; usable : (P, k) bool; L : (k, 3).
    """
    rows = np.flatnonzero(usable.sum(axis=1) >= 6)
    if rows.size == 0:
        raise InvalidInputError(
            "cannot estimate eps: no pixel has 6 or more usable observations; give eps explicitly"
        )
    rng = np.random.default_rng(seed)
    if rows.size > sample:
        rows = np.sort(rng.choice(rows, sample, replace=False))
    Is, sel = I[rows].astype(np.float64), usable[rows]
    keep = sel.copy()
    for _ in range(3):
        n = refit(Is, keep, L)
        r = np.abs(Is - n @ L.T)
        r[~sel] = np.inf
        half = np.maximum(3, sel.sum(axis=1) // 2)
        kth = np.take_along_axis(np.sort(r, axis=1), (half - 1)[:, None], axis=1)
        keep = sel & (r <= kth)
    n = refit(Is, keep, L)
    res = np.abs(Is - n @ L.T)[sel & np.isfinite(n[:, :1])]
    sigma = 1.4826 * float(np.median(res)) if res.size else 0.0
    floor = 0.5 if integer_valued else 1e-6 * float(np.nanmax(Is))
    return max(EPS_SIGMAS * sigma, floor)
