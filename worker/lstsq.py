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
    w = sel.astype(np.float64)
    Iw = np.where(sel, I, 0.0)
    G = np.einsum("pk,ki,kj->pij", w, L, L)
    r = np.einsum("pk,ki->pi", Iw, L)
    tr = np.trace(G, axis1=1, axis2=2)
    ok = (sel.sum(axis=1) >= 3) & (np.linalg.det(G) > _COND * tr**3)
    if max_cond is not None and ok.any():
        ev = np.linalg.eigvalsh(G[ok])
        ok[ok] = ev[:, 2] <= max_cond**2 * ev[:, 0]
    n = np.full(r.shape, np.nan)
    if ok.any():
        n[ok] = np.linalg.solve(G[ok], r[ok][..., None])[..., 0]
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
    num = np.einsum("pkc,pk->pc", np.where(sel[..., None], I_rgb, 0.0), s)
    den = np.einsum("pk,pk->p", s, s)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(den[:, None] > 0, num / den[:, None], 0.0)
    return np.nan_to_num(rho).astype(np.float32)
