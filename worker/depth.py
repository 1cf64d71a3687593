"""Depth from a normal map: least squares (``ls``) or bilateral (``bini``) integration over any mask,
orthographic or perspective, with a memory-bounded iterative solver.

Frame: x right, y up, z toward the camera; image row 0 is the top. A unit normal ``n`` facing the camera
has ``nz > 0``.

Orthographic (default): the unknown is the height ``z`` toward the camera in pixel units; along image
columns ``dz/dc = -nx/nz`` and along rows ``dz/dr = +ny/nz``.

Perspective (a :class:`Camera` with focal lengths ``fx, fy`` and principal point ``cx, cy`` in pixels):
the point seen at pixel ``(c, r)`` is ``d * (u, v, -1)`` with ``u = (c - cx) / fx``, ``v = (cy - r) / fy``
and ``d > 0`` its distance along the optical axis. The unknown is ``l = log d`` (the log-depth formulation
of the survey by Queau, Durou and Aujol, 2018), whose gradient is linear in the normal:
``dl/dc = nx / (fx * den)``, ``dl/dr = -ny / (fy * den)`` with ``den = nz - nx * u - ny * v`` (the cosine
between the normal and the viewing ray, up to the ray's length). ``d`` follows up to one scale factor per
connected piece: the geometric mean distance of each piece is ``distance`` (camera units) when given, else 1.
The stored depth is then the camera-frame ``z = -d``, so "larger is closer" in both models.

Equations: for each pair of 4-neighbours that are both in the domain (mask pixels with a finite normal)
the unknown's difference equals a mean of the two pixels' slopes. ``ls`` takes the plain mean (the
trapezoidal rule) with weight 1. ``bini`` (bilateral normal integration, Cao et al., ECCV 2022) writes each
pixel's one-sided equations, forward and backward, with weights ``w+ = sigmoid(k * (e-^2 - e+^2))`` and
``w- = 1 - w+`` where ``e+-`` are the one-sided differences (scaled to pixel-like units, see
:func:`_bini_weights`), and iterates (IRLS): a pixel next to a depth jump trusts the side without it, so the
surface is not pulled across the jump. An edge's two one-sided equations add up to one weighted equation,
so both methods solve the same weighted graph Laplacian, and ``bini`` starts from ``ls`` (all weights 1/2).

Solver: the normal equations are a weighted graph Laplacian on the domain's pixels (5 non-zeros a row),
built straight in CSR form (float32 values, int32 indices) and solved by conjugate gradients in float64
preconditioned with smoothed-aggregation algebraic multigrid (pyamg, float32) to a relative residual ``tol``;
memory and time are linear in pixels. Each
connected piece's free constant is fixed afterwards (mean 0, or the distance in perspective).

Slopes are clipped where the normal is nearly perpendicular to the view (``nz`` or ``den`` below
``min_nz``, about 85 deg): there the surface is a silhouette and the slope is unbounded.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.options import DEFAULT_DEPTH_K, DepthMethod

#: What each method is, as recorded with the depth.
DESCRIPTIONS = {
    DepthMethod.LS: "least squares on 4-neighbour differences, trapezoidal slopes; "
    "CG with smoothed-aggregation AMG (pyamg)",
    DepthMethod.BINI: "bilateral normal integration (Cao et al., ECCV 2022): IRLS of one-sided differences "
    "with sigmoid weights; CG with smoothed-aggregation AMG (pyamg)",
}
DEFAULT_TOL = 1e-7  # relative residual of the normal equations (float64 CG stalls near 1e-8 at megapixels)
DEFAULT_K = DEFAULT_DEPTH_K
DEFAULT_BINI_TOL = 1e-4  # bini stops when its energy changes by less than this, relatively
DEFAULT_BINI_ITERATIONS = 100
MIN_NZ = 0.087
#: Smallest edge weight kept: bini's sigmoid can underflow to 0, which would leave pieces with no
#: equation tying their pixels; a tiny floor keeps each piece one system without moving the result.
_MIN_WEIGHT = 1e-5
#: bini's solves stop here at the latest: its weights change more than this between iterations anyway.
_BINI_CG_TOL = 1e-6
#: Strength threshold of the AMG's aggregation: edges bini has all but cut are not "strong", so
#: aggregates stay on one side of a jump.
_THETA = 0.1


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels (``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if not np.isfinite(v):
                raise InvalidInputError(f"camera {name} must be a finite number, got {v!r}")
        if not (self.fx > 0 and self.fy > 0):
            raise InvalidInputError(f"focal lengths must be > 0 pixels, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_matrix(cls, K: NDArray[np.floating]) -> Camera:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise InvalidInputError(
                f"an intrinsic matrix K must be 3 x 3 finite numbers, got shape {K.shape}"
            )
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]):
            raise InvalidInputError("K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    @classmethod
    def from_file(cls, path: Path | str) -> Camera:
        """A ``K.txt`` (3 rows of 3 numbers, as most photometric-stereo datasets with intrinsics ship it)."""
        try:
            K = np.loadtxt(path, dtype=np.float64, ndmin=2)
        except ValueError as e:
            raise InvalidInputError(
                f"{path}: cannot read an intrinsic matrix ({e}); write 3 rows of 3 numbers"
            ) from None
        return cls.from_matrix(K)

    def rays(self, H: int, W: int) -> tuple[NDArray, NDArray]:
        """``(u, v)`` of every pixel, (1, W) and (H, 1): the ray through it is ``(u, v, -1)``."""
        u = (np.arange(W, dtype=np.float64) - self.cx) / self.fx
        v = (self.cy - np.arange(H, dtype=np.float64)) / self.fy
        return u[None, :], v[:, None]


@dataclass(frozen=True)
class DepthResult:
    depth: NDArray[np.float32]  # (H, W) z toward the camera, NaN outside the domain
    method: str  # ls or bini
    description: str
    units: str  # pixels (orthographic), the distance's units, or "relative" (perspective, no distance)
    residual_rms: float  # RMS of the ls equations' residuals, in pixels (perspective: f * log-depth)
    residual_max: float
    equations: int
    pixels: int
    pieces: int  # connected pieces of the domain (each has its own free constant)
    min_nz: float
    camera: str = "orthographic"
    solver_tol: float = DEFAULT_TOL
    cg_iterations: int = 0  # of all solves
    params: dict = field(default_factory=dict)  # the method's and camera's parameters

    def attrs(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k not in ("depth", "params")}
        return d | self.params


def slopes(normal: NDArray[np.floating], min_nz: float = MIN_NZ) -> tuple[NDArray, NDArray]:
    """``(dz/dc, dz/dr)`` per pixel from unit normals (H, W, 3), with ``nz`` clipped below at ``min_nz``."""
    n = np.asarray(normal, dtype=np.float64)
    nz = np.maximum(n[..., 2], min_nz)
    return -n[..., 0] / nz, n[..., 1] / nz


def _structure(dom: NDArray[np.bool_]) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """The 4-neighbour edges of the domain (pixels numbered in raster order): the first pixel of each
    horizontal edge (the second is the next index) and the two ends of each vertical edge."""
    H, W = dom.shape
    npx = int(dom.sum())
    idx = np.full((H, W), -1, dtype=np.int32)
    idx[dom] = np.arange(npx, dtype=np.int32)
    ha = idx[:, :-1][dom[:, :-1] & dom[:, 1:]]
    pair = dom[:-1, :] & dom[1:, :]
    va = idx[:-1, :][pair]
    vb = idx[1:, :][pair]
    del idx
    return ha, np.stack([va, vb])


def _laplacian(npx: int, ha: NDArray, vab: NDArray, wh: NDArray, wv: NDArray, dtype=np.float64):
    """The weighted graph Laplacian ``A^T W A`` in CSR, built straight from the edges: row ``i`` holds
    its up, left, self, right and down neighbours, already in column order (raster indices)."""
    import scipy.sparse

    va, vb = vab
    up = np.zeros(npx, dtype=np.int8)
    left = np.zeros(npx, dtype=np.int8)
    right = np.zeros(npx, dtype=np.int8)
    down = np.zeros(npx, dtype=np.int8)
    up[vb] = 1
    left[ha + 1] = 1
    right[ha] = 1
    down[va] = 1
    count = 1 + up + left + right + down
    indptr = np.zeros(npx + 1, dtype=np.int64)
    np.cumsum(count, out=indptr[1:])
    del count
    itype = np.int32 if indptr[-1] < 2**31 else np.int64
    indptr = indptr.astype(itype)
    self_slot = indptr[:-1] + up + left
    del up, left
    nnz = int(indptr[-1])
    indices = np.empty(nnz, dtype=itype)
    data = np.empty(nnz, dtype=dtype)
    indices[self_slot] = np.arange(npx, dtype=itype)
    diag = np.bincount(ha, weights=wh, minlength=npx)
    diag += np.bincount(ha + 1, weights=wh, minlength=npx)
    diag += np.bincount(va, weights=wv, minlength=npx)
    diag += np.bincount(vb, weights=wv, minlength=npx)
    # a pixel with no neighbour keeps its own row (depth 0 of its one-pixel piece)
    diag[diag == 0] = 1.0
    data[self_slot] = diag
    del diag
    s = self_slot[ha]  # horizontal edge (a, a + 1): right of a, left of a + 1
    indices[s + 1] = ha + 1
    data[s + 1] = -wh
    indices[self_slot[ha + 1] - 1] = ha
    data[self_slot[ha + 1] - 1] = -wh
    del s
    s = self_slot[va] + 1 + right[va]  # vertical (a, b): down of a, up of b (first in b's row)
    indices[s] = vb
    data[s] = -wv
    s = indptr[:-1][vb]
    indices[s] = va
    data[s] = -wv
    return scipy.sparse.csr_matrix((data, indices, indptr), shape=(npx, npx))


def _rhs(npx: int, ha: NDArray, vab: NDArray, gh: NDArray, gv: NDArray) -> NDArray[np.float64]:
    """``A^T W g`` for weighted edge targets ``gh``, ``gv`` (weights folded in)."""
    va, vb = vab
    b = np.bincount(ha + 1, weights=gh, minlength=npx)
    b -= np.bincount(ha, weights=gh, minlength=npx)
    b += np.bincount(vb, weights=gv, minlength=npx)
    b -= np.bincount(va, weights=gv, minlength=npx)
    return b


def _solve(N, b: NDArray, x0: NDArray | None, tol: float) -> tuple[NDArray[np.float64], int]:
    """CG in float64 preconditioned by smoothed-aggregation AMG (pyamg) in the matrix's precision
    (float32: half the memory of the hierarchy, and a preconditioner needs no more) on the (singular,
    consistent) Laplacian."""
    import pyamg

    # weighting "local": the prolongation smoother's scaling from row sums, not from a spectral radius
    # estimated from a random start, so that the same normals give the same depth bit for bit
    # symmetry "symmetric": the restriction is the prolongator's transpose view, not a copy
    strength = ("symmetric", {"theta": _THETA})
    if _all_strong(N, _THETA):
        # every edge is strong (ls: unit weights), so the fine level's strength graph is the matrix
        # itself: no copy of it (the same aggregates as pyamg's own strength)
        strength = [(None, {}), strength]
    ml = pyamg.smoothed_aggregation_solver(
        N,
        symmetry="symmetric",
        strength=strength,
        smooth=("jacobi", {"omega": 4.0 / 3.0, "weighting": "local"}),
        improve_candidates=None,
    )
    cycle = ml.aspreconditioner()

    def precondition(r: NDArray) -> NDArray:
        return cycle.matvec(r.astype(N.dtype)).astype(np.float64)

    return _cg(N, b, x0, tol, precondition)


def _cg(N, b: NDArray, x0: NDArray | None, tol: float, precondition, maxiter: int = 500):
    """Preconditioned conjugate gradients in float64 on a float32 matrix, stopping at a relative
    residual ``tol``; ``b`` is overwritten (it becomes the residual). Written out rather than scipy's
    ``cg`` for memory: the matrix-vector product goes a block of rows at a time, so float64 copies of
    the matrix's values are a block's, not the whole matrix's; and it holds four vectors and no more."""
    from scipy.linalg.blas import daxpy

    n = N.shape[0]
    bounds = np.linspace(0, n, 9).astype(np.int64)  # 8 blocks of rows
    blocks = []
    for lo, hi in itertools.pairwise(bounds):
        s, e = int(N.indptr[lo]), int(N.indptr[hi])
        ptr = N.indptr[lo : hi + 1] - N.indptr[lo]
        blocks.append((lo, hi, type(N)((N.data[s:e], N.indices[s:e], ptr), shape=(hi - lo, n))))

    def matvec(v: NDArray) -> NDArray:
        out = np.empty(n)
        for lo, hi, blk in blocks:
            out[lo:hi] = blk @ v
        return out

    bnorm = float(np.linalg.norm(b))
    if x0 is None:
        x = np.zeros(n)
    else:
        x = np.array(x0, dtype=np.float64)
        daxpy(matvec(x), b, a=-1.0)
    r = b
    if bnorm == 0.0 or float(np.linalg.norm(r)) <= tol * bnorm:
        return x, 0
    p = precondition(r)
    rz = float(np.dot(r, p))
    its = 0
    while its < maxiter:
        its += 1
        q = matvec(p)
        pq = float(np.dot(p, q))
        # p can be all but a null vector of this singular matrix (a constant per piece): pq is then
        # rounding noise of either sign, and the step along p harmless, as in scipy's cg
        if pq == 0.0:
            break
        alpha = rz / pq
        daxpy(p, x, a=alpha)
        daxpy(q, r, a=-alpha)
        del q
        if float(np.linalg.norm(r)) <= tol * bnorm:
            break
        z = precondition(r)
        rz, rz_old = float(np.dot(r, z)), rz
        if rz_old == 0.0:
            break
        daxpy(p, z, a=rz / rz_old)
        p = z
        del z
    return x, its


def _all_strong(N, theta: float) -> bool:
    """Whether each off-diagonal entry passes pyamg's symmetric strength test
    ``|a_ij| >= theta * sqrt(a_ii * a_jj)``, checked against the largest diagonal."""
    off = N.data[N.data < 0]
    return off.size == 0 or float(-off.max()) >= theta * float(N.diagonal().max())


def _pieces(dom: NDArray[np.bool_]) -> tuple[int, NDArray[np.int32]]:
    """Connected pieces of the domain under 4-neighbour edges (every edge has a weight > 0), and each
    domain pixel's piece in raster order."""
    import scipy.ndimage

    lab, n = scipy.ndimage.label(dom, structure=[[0, 1, 0], [1, 1, 1], [0, 1, 0]])
    return int(n), (lab[dom] - 1).astype(np.int32, copy=False)


def _targets(
    n: NDArray, dom: NDArray[np.bool_], camera: Camera | None, min_nz: float
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per domain pixel (raster order): the unknown's slopes along columns and rows, and the scales
    that turn a difference of the unknown into pixel-like units (bini's one-sided differences)."""
    nd = n[dom].astype(np.float64)  # (npx, 3)
    if camera is None:
        sc = np.maximum(nd[:, 2], min_nz)
        return -nd[:, 0] / sc, nd[:, 1] / sc, sc, sc
    H, W = dom.shape
    u, v = camera.rays(H, W)
    rows, cols = np.nonzero(dom)
    den = nd[:, 2] - nd[:, 0] * u[0, cols] - nd[:, 1] * v[rows, 0]
    del rows, cols
    den = np.maximum(den, min_nz)
    pc, pr = nd[:, 0] / (camera.fx * den), -nd[:, 1] / (camera.fy * den)
    return pc, pr, camera.fx * den, camera.fy * den


def _trapezoid(ha: NDArray, vab: NDArray, pc: NDArray, pr: NDArray) -> tuple[NDArray, NDArray]:
    """The ls targets: the mean of an edge's two slopes."""
    return 0.5 * (pc[ha] + pc[ha + 1]), 0.5 * (pr[vab[0]] + pr[vab[1]])


def _bini_weights(
    z: NDArray, npx: int, ha: NDArray, vab: NDArray, sc: NDArray, sr: NDArray, k: float
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Bini's one-sided weights per edge end: ``(w+ of the first pixel, w- of the second)`` for the
    horizontal and the vertical edges. A one-sided difference is ``scale * (difference of the unknown)``
    (pixels, times the cosine of the view as in the paper's equations); a missing neighbour counts as 0."""
    va, vb = vab
    dh = z[ha + 1] - z[ha]
    dv = z[vb] - z[va]
    fwd_c = np.zeros(npx)
    back_c = np.zeros(npx)
    fwd_c[ha] = dh
    back_c[ha + 1] = dh
    fwd_c *= sc
    back_c *= sc
    wc = _sigmoid(k * (back_c**2 - fwd_c**2))  # w+ along columns, per pixel
    del fwd_c, back_c
    fwd_r = np.zeros(npx)
    back_r = np.zeros(npx)
    fwd_r[va] = dv
    back_r[vb] = dv
    fwd_r *= sr
    back_r *= sr
    wr = _sigmoid(k * (back_r**2 - fwd_r**2))
    return wc[ha], 1.0 - wc[ha + 1], wr[va], 1.0 - wr[vb]


def _sigmoid(x: NDArray) -> NDArray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # = 1 / (1 + exp(-x)) without overflow


def integrate(
    normal: NDArray[np.floating],
    mask: NDArray[np.bool_] | None = None,
    *,
    method: DepthMethod | str = DepthMethod.LS,
    camera: Camera | None = None,
    distance: float | None = None,
    min_nz: float = MIN_NZ,
    tol: float = DEFAULT_TOL,
    k: float = DEFAULT_K,
    bini_tol: float = DEFAULT_BINI_TOL,
    max_iterations: int = DEFAULT_BINI_ITERATIONS,
) -> DepthResult:
    """Depth (H, W) float32 from unit normals (H, W, 3); NaN outside the domain.

    Parameters
    ----------
    normal
        (H, W, 3) unit normals, NaN where there is none.
    mask
        Optional (H, W) bool: the domain is the mask's pixels with a finite normal.
    method
        ``"ls"`` (least squares) or ``"bini"`` (keeps depth discontinuities); see the module docstring.
    camera
        None for orthographic (depth in pixels), or the intrinsics of a perspective camera.
    distance
        Perspective: each piece's geometric mean distance from the camera, in the units the depth is
        wanted in (None: 1, relative depth). Ignored for orthographic.
    min_nz
        Slopes are clipped where the cosine of the view is below this.
    tol
        Relative residual at which each CG solve stops.
    k, bini_tol, max_iterations
        ``bini`` only: the sigmoid's sharpness (larger keeps more jumps), the relative energy change
        at which the iteration stops, and its most iterations.
    """
    method = _method(method)
    if distance is not None and not (np.isfinite(distance) and distance > 0):
        raise InvalidInputError(f"distance must be a positive number (camera units), got {distance!r}")
    if not (np.isfinite(k) and k > 0):
        raise InvalidInputError(f"bini's k must be a positive number, got {k!r}")
    n = np.asarray(normal)
    H, W = n.shape[:2]
    dom = np.isfinite(n).all(axis=2)
    if mask is not None:
        dom &= np.asarray(mask, dtype=bool)
    depth = np.full((H, W), np.nan, dtype=np.float32)
    npx = int(dom.sum())
    params: dict = (
        {"k": k, "bini_tol": bini_tol, "max_iterations": max_iterations} if method == "bini" else {}
    )
    if camera is not None:
        params |= {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}
        params |= {"distance": distance} if distance is not None else {}
    units = "pixels" if camera is None else ("camera units" if distance is not None else "relative")
    cam = "orthographic" if camera is None else "perspective"
    if npx == 0:
        return DepthResult(
            depth, method.value, DESCRIPTIONS[method], units, 0.0, 0.0, 0, 0, 0, min_nz, cam, tol
        )
    # one code path for both methods: the ls solve (bini's start) holds only the matrix, its right-hand
    # side and the solver; the slopes and edges are made again afterwards, which is cheaper than keeping them
    ha, vab = _structure(dom)
    pc, pr, _, _ = _targets(n, dom, camera, min_nz)
    rhs = _rhs(npx, ha, vab, *_trapezoid(ha, vab, pc, pr))
    del pc, pr
    N = _laplacian(npx, ha, vab, np.ones(ha.size), np.ones(vab.shape[1]), np.float32)
    del ha, vab
    z, cg = _solve(N, rhs, None, tol)
    del N, rhs
    ha, vab = _structure(dom)
    va, vb = vab
    pc, pr, sc, sr = _targets(n, dom, camera, min_nz)
    iterations = 0
    if method == DepthMethod.BINI:
        # the paper's equations are scaled by the cosine of the view (nz, or den in perspective):
        # a grazing pixel's slope is unreliable and weighs little
        qc = (sc / (1.0 if camera is None else camera.fx)) ** 2
        qr = (sr / (1.0 if camera is None else camera.fy)) ** 2
        hp, hm, vp, vm = (np.full(e.size, 0.5) for e in (ha, ha, va, va))
        energy = None
        while iterations < max_iterations:
            iterations += 1
            a_h, b_h, a_v, b_v = hp * qc[ha], hm * qc[ha + 1], vp * qr[va], vm * qr[vb]
            wh = np.maximum(a_h + b_h, _MIN_WEIGHT)
            wv = np.maximum(a_v + b_v, _MIN_WEIGHT)
            gh = a_h * pc[ha] + b_h * pc[ha + 1]
            gv = a_v * pr[va] + b_v * pr[vb]
            del a_h, b_h, a_v, b_v
            N = _laplacian(npx, ha, vab, wh, wv, np.float32)
            del wh, wv
            z, its = _solve(N, _rhs(npx, ha, vab, gh, gv), z, max(tol, _BINI_CG_TOL))
            del N, gh, gv
            cg += its
            hp, hm, vp, vm = _bini_weights(z, npx, ha, vab, sc, sr, k)
            new = _bini_energy(z, ha, vab, pc, pr, hp * qc[ha], hm * qc[ha + 1], vp * qr[va], vm * qr[vb])
            done = energy is not None and abs(energy - new) <= bini_tol * max(energy, 1e-300)
            energy = new
            if done:
                break
        params["iterations"] = iterations
    del sc, sr
    # residuals of the ls equations, one direction at a time
    sq, top, m = 0.0, 0.0, 0
    for a, b, t in ((ha, ha + 1, 0.5 * (pc[ha] + pc[ha + 1])), (va, vb, 0.5 * (pr[va] + pr[vb]))):
        res = (z[b] - z[a]) - t
        del t
        if camera is not None:
            res *= 0.5 * (camera.fx + camera.fy)
        if res.size:
            sq += float(np.dot(res, res))
            top = max(top, float(np.abs(res).max()))
        m += res.size
        del res
    del pc, pr, ha, vab, va, vb
    pieces, lab = _pieces(dom)
    counts = np.maximum(np.bincount(lab, minlength=pieces), 1)
    z -= (np.bincount(lab, weights=z, minlength=pieces) / counts)[lab]
    if camera is not None:
        z = -np.exp(z) * (1.0 if distance is None else distance)
    depth[dom] = z.astype(np.float32)
    return DepthResult(
        depth=depth,
        method=method.value,
        description=DESCRIPTIONS[method],
        units=units,
        residual_rms=float(np.sqrt(sq / m)) if m else 0.0,
        residual_max=top,
        equations=int(m),
        pixels=npx,
        pieces=pieces,
        min_nz=min_nz,
        camera=cam,
        solver_tol=tol,
        cg_iterations=int(cg),
        params=params,
    )


def _bini_energy(z, ha, vab, pc, pr, hp, hm, vp, vm) -> float:
    va, vb = vab
    dh = z[ha + 1] - z[ha]
    dv = z[vb] - z[va]
    e = np.sum(hp * (dh - pc[ha]) ** 2) + np.sum(hm * (dh - pc[ha + 1]) ** 2)
    return float(e + np.sum(vp * (dv - pr[va]) ** 2) + np.sum(vm * (dv - pr[vb]) ** 2))


def _method(method: DepthMethod | str) -> DepthMethod:
    try:
        m = DepthMethod(method)
    except ValueError:
        raise InvalidInputError(
            f"unknown depth method {method!r}; choose one of {', '.join(DepthMethod)}"
        ) from None
    if m is DepthMethod.NONE:
        raise InvalidInputError("depth method 'none' integrates nothing; do not call integrate() for it")
    return m


def discontinuities(
    depth: NDArray[np.floating],
    normal: NDArray[np.floating],
    camera: Camera | None = None,
    *,
    jump: float = 1.0,
    min_nz: float = MIN_NZ,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Edges the depth jumps across: ``(cut_h (H, W-1), cut_v (H-1, W))``, True where two neighbours'
    depth difference is off the difference their normals predict (the ls target) by more than ``jump``
    pixels (perspective: ``f`` times the log-depth difference, the same pixel-like units). A smooth
    surface, however steep, stays joined; a step that ``bini`` kept (or that ``ls`` spread over a few
    pixels into a steep curtain) is cut."""
    z = np.asarray(depth, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    H, W = z.shape
    if camera is None:
        pc, pr = slopes(n, min_nz)
        q, fc, fr = z, 1.0, 1.0
    else:
        u, v = camera.rays(H, W)
        den = np.maximum(n[..., 2] - n[..., 0] * u - n[..., 1] * v, min_nz)
        pc, pr = n[..., 0] / (camera.fx * den), -n[..., 1] / (camera.fy * den)
        with np.errstate(invalid="ignore", divide="ignore"):
            q = np.log(-z)
        fc, fr = camera.fx, camera.fy
    with np.errstate(invalid="ignore"):
        cut_h = np.abs(np.diff(q, axis=1) - 0.5 * (pc[:, :-1] + pc[:, 1:])) * fc > jump
        cut_v = np.abs(np.diff(q, axis=0) - 0.5 * (pr[:-1] + pr[1:])) * fr > jump
    return cut_h, cut_v


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
