"""Depth (height) from a normal map: sparse least-squares integration over any mask.

Orthographic camera, x right, y up, z toward the camera; image row 0 is the top (largest y). A unit normal
``n`` gives the slopes ``dz/dx = -nx/nz`` and ``dz/dy = -ny/nz``, so along image columns ``dz/dc = -nx/nz``
and along rows ``dz/dr = +ny/nz``, in pixel units.

For each pair of 4-neighbours that are both in the domain (mask pixels with a finite normal) there is one
equation: the depth difference equals the mean of the two pixels' slopes (the trapezoidal rule, second-order
accurate). The domain may have any shape and any number of pieces; nothing is assumed about rectangles or
boundaries (no Poisson boundary condition, no DCT). The over-determined system ``A z = b`` is solved in the
least-squares sense through its normal equations ``(A^T A + lam I) z = A^T b`` (sparse direct solve,
scipy's SuperLU), where the tiny ``lam`` fixes each piece's free constant; then each connected piece is
shifted to mean depth 0. The result is the height toward the camera, up to that constant per piece.

Slopes are clipped where the normal is nearly perpendicular to the view (``nz < min_nz``, about 85 deg):
there the surface is a silhouette and the slope is unbounded. Such pixels and isolated pixels (no neighbour
in the domain) get a depth but carry little information.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

METHOD = "sparse least squares on 4-neighbour differences, trapezoidal slopes, SuperLU (scipy)"


@dataclass(frozen=True)
class DepthResult:
    depth: NDArray[np.float32]  # (H, W), NaN outside the domain
    method: str
    residual_rms: float  # RMS of A z - b over the difference equations (pixels)
    residual_max: float
    equations: int
    pixels: int
    pieces: int  # connected pieces of the domain (each has its own free constant)
    min_nz: float

    def attrs(self) -> dict:
        d = asdict(self)
        d.pop("depth")
        return d


def slopes(normal: NDArray[np.floating], min_nz: float = 0.087) -> tuple[NDArray, NDArray]:
    """``(dz/dc, dz/dr)`` per pixel from unit normals (H, W, 3), with ``nz`` clipped below at ``min_nz``."""
    n = np.asarray(normal, dtype=np.float64)
    nz = np.maximum(n[..., 2], min_nz)
    return -n[..., 0] / nz, n[..., 1] / nz


def integrate(
    normal: NDArray[np.floating],
    mask: NDArray[np.bool_] | None = None,
    *,
    min_nz: float = 0.087,
    lam: float = 1e-9,
) -> DepthResult:
    """Depth (H, W) float32 in pixel units from unit normals (H, W, 3); NaN outside the domain."""
    import scipy.sparse
    import scipy.sparse.csgraph
    import scipy.sparse.linalg

    n = np.asarray(normal, dtype=np.float64)
    H, W = n.shape[:2]
    dom = np.isfinite(n).all(axis=2)
    if mask is not None:
        dom &= np.asarray(mask, dtype=bool)
    depth = np.full((H, W), np.nan, dtype=np.float32)
    npx = int(dom.sum())
    if npx == 0:
        return DepthResult(depth, METHOD, 0.0, 0.0, 0, 0, 0, min_nz)
    p, q = slopes(np.where(dom[..., None], n, 0.0), min_nz)
    idx = np.full((H, W), -1, dtype=np.int64)
    idx[dom] = np.arange(npx)
    rows, cols, vals, rhs = [], [], [], []
    m = 0
    # horizontal pairs (r, c) -> (r, c + 1): z[c+1] - z[c] = (p[c] + p[c+1]) / 2
    pair = dom[:, :-1] & dom[:, 1:]
    a, b = idx[:, :-1][pair], idx[:, 1:][pair]
    e = np.arange(m, m + a.size)
    rows += [e, e]
    cols += [b, a]
    vals += [np.ones(a.size), -np.ones(a.size)]
    rhs.append(0.5 * (p[:, :-1][pair] + p[:, 1:][pair]))
    m += a.size
    # vertical pairs (r, c) -> (r + 1, c): z[r+1] - z[r] = (q[r] + q[r+1]) / 2
    pair = dom[:-1, :] & dom[1:, :]
    a, b = idx[:-1, :][pair], idx[1:, :][pair]
    e = np.arange(m, m + a.size)
    rows += [e, e]
    cols += [b, a]
    vals += [np.ones(a.size), -np.ones(a.size)]
    rhs.append(0.5 * (q[:-1, :][pair] + q[1:, :][pair]))
    m += a.size
    A = scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(m, npx)
    )
    bvec = np.concatenate(rhs)
    N = (A.T @ A + lam * scipy.sparse.identity(npx, format="csr")).tocsc()
    z = scipy.sparse.linalg.spsolve(N, A.T @ bvec, permc_spec="MMD_AT_PLUS_A")
    res = A @ z - bvec
    # the 4-connected pieces of the domain are the components of N's graph (csgraph comes with
    # scipy.sparse.linalg; scipy.ndimage.label would cost another 0.2 s of imports)
    pieces, lab = scipy.sparse.csgraph.connected_components(N, directed=False)
    means = np.bincount(lab, weights=z, minlength=pieces) / np.maximum(np.bincount(lab), 1)
    z = z - means[lab]
    depth[dom] = z.astype(np.float32)
    return DepthResult(
        depth=depth,
        method=METHOD,
        residual_rms=float(np.sqrt(np.mean(res**2))) if m else 0.0,
        residual_max=float(np.abs(res).max()) if m else 0.0,
        equations=int(m),
        pixels=npx,
        pieces=int(pieces),
        min_nz=min_nz,
    )


def relief_rgb(depth: NDArray[np.floating], light: tuple[float, float, float] = (-1.0, 1.0, 1.0)) -> NDArray:
    """A shaded relief of a depth map (uint8 grey, black outside): Lambertian shading of the depth's own
    normals under a light from the upper left, which shows shape better than a colour scale of depth."""
    z = np.asarray(depth, dtype=np.float64)
    dom = np.isfinite(z)
    zf = np.where(dom, z, 0.0)
    # central differences inside, one-sided at the domain's edge
    dzdc = np.zeros_like(zf)
    dzdr = np.zeros_like(zf)
    for axis, out in ((1, dzdc), (0, dzdr)):
        fwd = np.diff(zf, axis=axis)
        ok = np.diff(dom.astype(np.int8), axis=axis) == 0
        ok &= np.take(dom, range(dom.shape[axis] - 1), axis=axis)
        fwd = np.where(ok, fwd, np.nan)
        pad_lo = [(0, 0), (0, 0)]
        pad_hi = [(0, 0), (0, 0)]
        pad_lo[axis], pad_hi[axis] = (1, 0), (0, 1)
        back = np.pad(fwd, pad_lo, constant_values=np.nan)
        ahead = np.pad(fwd, pad_hi, constant_values=np.nan)
        count = np.isfinite(back).astype(np.int8) + np.isfinite(ahead)
        out[...] = (np.nan_to_num(back) + np.nan_to_num(ahead)) / np.maximum(count, 1)
    # surface normal (x right, y up): (-dz/dx, -dz/dy, 1) with dz/dx = dz/dc, dz/dy = -dz/dr
    nx, ny = -dzdc, dzdr
    L = np.asarray(light, dtype=np.float64)
    L = L / np.linalg.norm(L)
    shade = (nx * L[0] + ny * L[1] + L[2]) / np.sqrt(nx**2 + ny**2 + 1.0)
    v = np.clip(0.15 + 0.85 * shade, 0.0, 1.0)
    img = np.round(255 * v).astype(np.uint8)
    img[~dom] = 0
    return img
