"""Batched least squares on chosen images: the refit and the Woodham baseline."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: Smallest acceptable ratio of the normal matrix's determinant to trace^3; below
#: it the chosen lights are (nearly) coplanar and n is not determined.
_COND = 1e-9


def refit(
    I: NDArray[np.floating],
    sel: NDArray[np.bool_],
    L: NDArray[np.float64],
    max_cond: float | None = None,
) -> NDArray[np.float64]:
    """Least-squares ``n`` per pixel over the selected images.

    Parameters
    ----------
    I : (P, k) intensities; sel : (P, k) bool; L : (k, 3) lights; max_cond : largest
    condition number of the selected lights (``sqrt`` of the normal matrix's) for which
    ``n`` counts as determined.

    Returns
    -------
    (P, 3) float64; NaN where fewer than 3 images are selected or the selected
    lights do not determine ``n`` (nearly coplanar, or above ``max_cond``).
    """
    k = L.shape[0]
    w = sel.astype(np.float64)
    Iw = np.where(sel, I, 0.0)
    # G = sum_i w_i L_i L_i^T and r = sum_i w_i I_i L_i as two matrix products (BLAS): a
    # three-operand einsum loops in C without them, 10-25x slower at k = 96
    g = w @ (L[:, :, None] * L[:, None, :]).reshape(k, 9)
    r = Iw @ L
    g00, g01, g02, g11, g12, g22 = g[:, 0], g[:, 1], g[:, 2], g[:, 4], g[:, 5], g[:, 8]
    # the symmetric 3 x 3 systems solved by their cofactors (vectorised; LAPACK's batched
    # solve costs more than the products above for 3 x 3)
    c00, c11, c22 = g11 * g22 - g12 * g12, g00 * g22 - g02 * g02, g00 * g11 - g01 * g01
    c01, c02, c12 = g02 * g12 - g01 * g22, g01 * g12 - g02 * g11, g01 * g02 - g00 * g12
    det = g00 * c00 + g01 * c01 + g02 * c02
    tr = g00 + g11 + g22
    ok = (sel.sum(axis=1) >= 3) & (det > _COND * tr**3)
    if max_cond is not None and ok.any():
        # lambda_max <= tr and lambda_min >= det / (tr / 2)^2 (the other two sum to <= tr), so
        # tr^3 <= 4 det max_cond^2 proves the bound; eigenvalues only for the rest
        unsure = ok & (tr**3 > 0.99 * 4.0 * max_cond**2 * det)
        if unsure.any():
            ev = np.linalg.eigvalsh(g[unsure].reshape(-1, 3, 3))
            ok[unsure] = ev[:, 2] <= max_cond**2 * ev[:, 0]
    n = np.full(r.shape, np.nan)
    if ok.all():  # the usual batch: the same arithmetic without a dozen masked copies
        r0, r1, r2 = r.T
        n[:, 0] = (c00 * r0 + c01 * r1 + c02 * r2) / det
        n[:, 1] = (c01 * r0 + c11 * r1 + c12 * r2) / det
        n[:, 2] = (c02 * r0 + c12 * r1 + c22 * r2) / det
    elif ok.any():
        d, (r0, r1, r2) = det[ok], r[ok].T
        n[ok, 0] = (c00[ok] * r0 + c01[ok] * r1 + c02[ok] * r2) / d
        n[ok, 1] = (c01[ok] * r0 + c11[ok] * r1 + c12[ok] * r2) / d
        n[ok, 2] = (c02[ok] * r0 + c12[ok] * r1 + c22[ok] * r2) / d
    return n


def normal_albedo(n: NDArray[np.float64]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Split ``n = rho N`` into unit normal (NaN where undefined) and albedo (0 there)."""
    rho = np.linalg.norm(n, axis=-1)
    good = np.isfinite(rho) & (rho > 0)
    normal = np.full(n.shape, np.nan, dtype=np.float32)
    normal[good] = (n[good] / rho[good, None]).astype(np.float32)
    albedo = np.where(good, rho, 0.0).astype(np.float32)
    return normal, albedo


def channel_albedo(
    I_rgb: NDArray[np.floating], sel: NDArray[np.bool_], L: NDArray[np.float64], normal: NDArray[np.floating]
) -> NDArray[np.float32]:
    """Per-channel albedo for a fixed normal: ``argmin_rho sum_i (I_ci - rho L_i.N)^2``.

    I_rgb : (P, k, C); sel : (P, k); normal : (P, 3). Returns (P, C), 0 where undefined.
    """
    s = np.einsum("ki,pi->pk", L, np.nan_to_num(normal.astype(np.float64)))
    s = np.where(sel, s, 0.0)
    # the mask spread over the channels first: a where with a broadcast last axis of 3 costs
    # 1.5x one on contiguous operands (same values, same contiguous operand for the einsum)
    sel_c = np.repeat(sel, I_rgb.shape[2], axis=1).reshape(I_rgb.shape)
    num = np.einsum("pkc,pk->pc", np.where(sel_c, I_rgb, 0.0), s)
    den = np.einsum("pk,pk->p", s, s)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(den[:, None] > 0, num / den[:, None], 0.0)
    return np.nan_to_num(rho).astype(np.float32)
