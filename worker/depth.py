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

Solver: the normal equations are a weighted graph Laplacian on the domain's pixels, applied matrix-free
from one float32 weight per edge and solved by conjugate gradients preconditioned with a geometric
aggregation multigrid of its own (:mod:`worker.depth_solver`) to a relative residual ``tol``; the slopes
are computed from the normals where they are needed, not stored. Memory (about 85 bytes per pixel) and time
are linear in pixels. Each connected piece's free constant is fixed afterwards (mean 0, or the distance in
perspective).

Slopes are clipped where the normal is nearly perpendicular to the view (``nz`` or ``den`` below
``min_nz``, about 85 deg): there the surface is a silhouette and the slope is unbounded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.options import DEFAULT_DEPTH_K, DepthMethod
from maxfs.worker.camera import Camera
from maxfs.worker.depth_solver import grid_links, join_pieces, solve

#: What each method is, as recorded with the depth.
DESCRIPTIONS = {
    DepthMethod.LS: "least squares on 4-neighbour differences, trapezoidal slopes; "
    "CG with a geometric aggregation multigrid",
    DepthMethod.BINI: "bilateral normal integration (Cao et al., ECCV 2022): IRLS of one-sided differences "
    "with sigmoid weights; CG with a geometric aggregation multigrid",
}
DEFAULT_TOL = 1e-7  # relative residual of the normal equations
DEFAULT_K = DEFAULT_DEPTH_K
DEFAULT_BINI_TOL = 1e-4  # bini stops when its energy changes by less than this, relatively
DEFAULT_BINI_ITERATIONS = 100
MIN_NZ = 0.087
#: Smallest edge weight kept: bini's sigmoid can underflow to 0, which would leave pieces with no
#: equation tying their pixels; a tiny floor keeps each piece one system without moving the result.
_MIN_WEIGHT = 1e-5
#: bini's solves stop here at the latest: its weights change more than this between iterations anyway.
_BINI_CG_TOL = 1e-6


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


@njit(cache=True, nogil=True, inline="always")
def _pixel(n, r, c, cam):  # pragma: no cover - numba
    """``(pc, pr, sc, sr)`` of pixel ``(r, c)``: the unknown's slopes along columns and rows, and the
    scales that turn a difference of the unknown into pixel-like units. ``cam`` is ``(perspective, fx,
    fy, cx, cy, min_nz)``."""
    nx, ny, nz = float(n[r, c, 0]), float(n[r, c, 1]), float(n[r, c, 2])
    if cam[0] == 0.0:
        s = max(nz, cam[5])
        return -nx / s, ny / s, s, s
    fx, fy = cam[1], cam[2]
    u = (c - cam[3]) / fx
    v = (cam[4] - r) / fy
    den = max(nz - nx * u - ny * v, cam[5])
    return nx / (fx * den), -ny / (fy * den), fx * den, fy * den


@njit(cache=True, nogil=True, inline="always")
def _wplus(z, i, prev, nxt, s, k):  # pragma: no cover - numba
    """bini's forward weight of pixel ``i`` along one axis (``prev``/``nxt`` its neighbours, -1 for
    none): ``sigmoid(k * (back^2 - fwd^2))`` of its one-sided differences scaled by ``s``."""
    fwd = s * (z[nxt] - z[i]) if nxt >= 0 else 0.0
    back = s * (z[i] - z[prev]) if prev >= 0 else 0.0
    return 0.5 * (1.0 + np.tanh(0.5 * k * (back * back - fwd * fwd)))


@njit(cache=True, nogil=True)
def _equations(n, dom, up, down, cam, mode, z, k, min_weight, wh, wv, b):  # pragma: no cover - numba
    """The normal equations' edge weights ``wh``, ``wv`` (float32) and right-hand side ``b`` (zeros on
    entry). ``mode`` 0: ls (weight 1, the trapezoidal target); 1: bini's first step (one-sided weights
    1/2); 2: bini's weights from the depth ``z``. Returns bini's energy at ``z`` under those weights
    (mode 2). An edge's two one-sided equations ``w+ q_a (dz - p_a)^2 + w- q_b (dz - p_b)^2`` add up
    to one of weight ``w+ q_a + w- q_b`` and target their weighted mean; ``q`` is the squared cosine
    of the view (a grazing pixel's slope is unreliable and weighs little)."""
    H, W = dom.shape
    fs, gs = (1.0, 1.0) if cam[0] == 0.0 else (cam[1], cam[2])
    energy = 0.0
    i = 0
    for r in range(H):
        for c in range(W):
            if not dom[r, c]:
                continue
            pc, pr, sc, sr = _pixel(n, r, c, cam)
            for axis in range(2):
                if axis == 0:
                    if c + 1 >= W or not dom[r, c + 1]:
                        continue
                    j = i + 1
                    pa, qa = pc, (sc / fs) ** 2
                    pb, _, sb, _ = _pixel(n, r, c + 1, cam)
                    qb = (sb / fs) ** 2
                else:
                    j = down[i]
                    if j < 0:
                        continue
                    pa, qa = pr, (sr / gs) ** 2
                    _, pb, _, sb = _pixel(n, r + 1, c, cam)
                    qb = (sb / gs) ** 2
                if mode == 0:
                    w, g = 1.0, 0.5 * (pa + pb)
                else:
                    if mode == 1:
                        hp = hm = 0.5
                    elif axis == 0:
                        left = i - 1 if c > 0 and dom[r, c - 1] else -1
                        right = j + 1 if c + 2 < W and dom[r, c + 2] else -1
                        hp = _wplus(z, i, left, j, sc, k)
                        hm = 1.0 - _wplus(z, j, i, right, sb, k)
                    else:
                        hp = _wplus(z, i, up[i], j, sr, k)
                        hm = 1.0 - _wplus(z, j, i, down[j], sb, k)
                    a_, b_ = hp * qa, hm * qb
                    if mode == 2:
                        dz = z[j] - z[i]
                        energy += a_ * (dz - pa) ** 2 + b_ * (dz - pb) ** 2
                    w, g = max(a_ + b_, min_weight), a_ * pa + b_ * pb
                if axis == 0:
                    wh[i] = w
                else:
                    wv[i] = w
                b[i] -= g
                b[j] += g
            i += 1
    return energy


@njit(cache=True, nogil=True)
def _ls_residual(n, dom, down, cam, z):  # pragma: no cover - numba
    """``(sum of squares, largest, count)`` of the ls equations' residuals ``dz - (p_a + p_b) / 2``, in
    pixels (perspective: times the mean focal length)."""
    H, W = dom.shape
    scale = 1.0 if cam[0] == 0.0 else 0.5 * (cam[1] + cam[2])
    sq, top, m = 0.0, 0.0, 0
    i = 0
    for r in range(H):
        for c in range(W):
            if not dom[r, c]:
                continue
            pc, pr, _, _ = _pixel(n, r, c, cam)
            if c + 1 < W and dom[r, c + 1]:
                pb = _pixel(n, r, c + 1, cam)[0]
                e = abs((z[i + 1] - z[i]) - 0.5 * (pc + pb)) * scale
                sq += e * e
                top = max(top, e)
                m += 1
            j = down[i]
            if j >= 0:
                pb = _pixel(n, r + 1, c, cam)[1]
                e = abs((z[j] - z[i]) - 0.5 * (pr + pb)) * scale
                sq += e * e
                top = max(top, e)
                m += 1
            i += 1
    return sq, top, m


@njit(cache=True, nogil=True)
def _pieces(wh, down, lab):  # pragma: no cover - numba
    """Connected pieces of the domain (its 4-neighbour edges: ``wh[i] != 0`` to ``i + 1``, ``down``):
    each pixel's piece into ``lab`` (numbered in raster order of their first pixel); returns how many."""
    n = lab.size
    for i in range(n):
        lab[i] = i
    for i in range(n):
        for e in range(2):
            j = (i + 1 if wh[i] != 0.0 else -1) if e == 0 else down[i]
            if j >= 0:
                join_pieces(lab, i, j)
    count = 0
    for i in range(n):  # a parent comes before its children, so it is numbered already
        if lab[i] == i:
            lab[i] = count
            count += 1
        else:
            lab[i] = lab[lab[i]]
    return count


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
    dom = np.isfinite(n[..., 0])  # a channel at a time: no (H, W, 3) temporary
    dom &= np.isfinite(n[..., 1])
    dom &= np.isfinite(n[..., 2])
    if mask is not None:
        dom &= np.asarray(mask, dtype=bool)
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
            np.full((H, W), np.nan, dtype=np.float32),
            method.value,
            DESCRIPTIONS[method],
            units,
            0.0,
            0.0,
            0,
            0,
            0,
            min_nz,
            cam,
            tol,
        )
    # the stencil of the normal equations (edge weights, float32) and its right-hand side; the slopes
    # are made again from the normals wherever needed rather than kept: memory is what the solve holds
    par = np.array(
        [0.0, 1.0, 1.0, 0.0, 0.0, min_nz]
        if camera is None
        else [1.0, camera.fx, camera.fy, camera.cx, camera.cy, min_nz]
    )
    up, down = grid_links(dom)
    wh = np.zeros(npx, dtype=np.float32)
    wv = np.zeros(npx, dtype=np.float32)
    b = np.zeros(npx)
    z = np.zeros(npx)
    _equations(n, dom, up, down, par, 0, z, k, _MIN_WEIGHT, wh, wv, b)
    cg = solve(dom, wh, wv, up, down, b, z, tol)
    iterations = 0
    if method == DepthMethod.BINI:
        b[:] = 0.0
        _equations(n, dom, up, down, par, 1, z, k, _MIN_WEIGHT, wh, wv, b)  # one-sided weights 1/2
        energy = None
        while iterations < max_iterations:
            iterations += 1
            cg += solve(dom, wh, wv, up, down, b, z, max(tol, _BINI_CG_TOL))
            # the next step's equations, and the energy at z under their weights
            b[:] = 0.0
            new = _equations(n, dom, up, down, par, 2, z, k, _MIN_WEIGHT, wh, wv, b)
            done = energy is not None and abs(energy - new) <= bini_tol * max(energy, 1e-300)
            energy = new
            if done:
                break
        params["iterations"] = iterations
    del wv, b, up
    sq, top, m = _ls_residual(n, dom, down, par, z)
    lab = np.empty(npx, dtype=np.int32)
    pieces = _pieces(wh, down, lab)
    del wh, down
    counts = np.maximum(np.bincount(lab, minlength=pieces), 1)
    z -= (np.bincount(lab, weights=z, minlength=pieces) / counts)[lab]
    if camera is not None:
        z = -np.exp(z) * (1.0 if distance is None else distance)
    depth = np.full((H, W), np.nan, dtype=np.float32)
    depth[dom] = z
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
    full = np.asarray(depth, dtype=np.float64)
    img = np.zeros(full.shape, dtype=np.uint8)
    dom = np.isfinite(full)
    rows, cols = np.flatnonzero(dom.any(axis=1)), np.flatnonzero(dom.any(axis=0))
    if not rows.size:
        return img
    # computed inside the domain's bounding box only: every difference that leaves the domain is
    # NaN (one-sided), as the box's NaN padding makes it, so the pixels are those of the whole image
    box = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
    z, dom = full[box], dom[box]
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
    part = np.round(255 * v).astype(np.uint8)
    part[~dom] = 0
    img[box] = part
    return img
