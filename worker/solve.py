"""Public entry points: solve a pixel batch (tile tasks) or a whole image stack.

Example
-------
>>> from worker import synthetic
>>> from worker.solve import solve
>>> scene = synthetic.sphere(k=12, size=32)
>>> sol = solve(scene.images, scene.lights, scene.mask, eps=1.0, saturation=255)
>>> sol.normal.shape, sol.inliers.shape
((32, 32, 3), (12, 32, 32))
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from worker.errors import InvalidInputError
from worker.exact import exact_pixels
from worker.lstsq import channel_albedo, normal_albedo, refit
from worker.milp import MilpSolver
from worker.noise import estimate_eps
from worker.observations import ObservationModel
from worker.problem import (
    DEFAULT_BOX_FACTOR,
    Thresholds,
    check_lights,
    make_thresholds,
    slabs,
    usable,
)
from worker.tiles import DEFAULT_TILE, Tile, tiles

#: Per-pixel search budget of the exact solver before it falls back to the MILP.
DEFAULT_MAX_NODES = 200_000
#: Seconds the MILP may spend on one pixel (as reference, or as fallback).
DEFAULT_MILP_TIME_LIMIT = 30.0


class Solver(StrEnum):
    """Available solvers."""

    EXACT = "exact"  #: branch and bound, exact and fast (default)
    MILP = "milp"  #: the paper's big-M MILP with HiGHS (reference)
    L2 = "l2"  #: Woodham least squares on every image (baseline, not robust)


@dataclass(frozen=True)
class PixelResult:
    """Results for a flat batch of P pixels with k images."""

    normal: NDArray[np.float32]  # (P, 3), NaN where unsolved
    albedo: NDArray[np.float32]  # (P,), 0 where unsolved
    albedo_rgb: NDArray[np.float32] | None  # (P, C) for colour input
    inliers: NDArray[np.bool_]  # (P, k)
    count: NDArray[np.uint16]  # (P,) optimal inlier count, 0 where unsolved
    optimal: NDArray[np.bool_]  # (P,) True where the optimum is proved
    point: NDArray[np.float64]  # (P, 3) the Max-FS point before the refit
    nodes: NDArray[np.int64]  # (P,) search nodes used by the exact solver


@dataclass(frozen=True)
class Solution:
    """Results for an image stack of k images of H x W pixels."""

    normal: NDArray[np.float32]  # (H, W, 3)
    albedo: NDArray[np.float32]  # (H, W)
    albedo_rgb: NDArray[np.float32] | None  # (H, W, C)
    inliers: NDArray[np.bool_]  # (k, H, W)
    inlier_count: NDArray[np.uint16]  # (H, W)
    optimal: NDArray[np.bool_]  # (H, W)
    eps: float  # the eps used (estimated when eps="auto")


def solve_pixels(
    I: NDArray[np.floating],
    L: NDArray[np.float64],
    th: Thresholds,
    solver: Solver | str = Solver.EXACT,
    *,
    rgb: NDArray[np.floating] | None = None,
    active: NDArray[np.bool_] | None = None,
    outlier: NDArray[np.bool_] | None = None,
    max_nodes: int = DEFAULT_MAX_NODES,
    milp_time_limit: float = DEFAULT_MILP_TIME_LIMIT,
) -> PixelResult:
    """Solve a batch of pixels.

    Parameters
    ----------
    I
        (P, k) grey intensities, already divided by the light intensities.
    L
        (k, 3) unit light directions.
    th
        Tolerance and outlier thresholds (see :mod:`worker.problem`).
    solver
        ``exact``, ``milp`` or ``l2``.
    rgb
        Optional (P, k, C) colour intensities for per-channel albedo.
    active
        Optional (P,) bool; inactive (masked) pixels are skipped and cost nothing.
    outlier
        Optional (P, k) bool: observations known to be unusable (e.g. saturated in
        any colour channel), on top of the thresholds.
    max_nodes
        Exact solver's per-pixel budget; a pixel that exhausts it is solved by the
        MILP with ``milp_time_limit``; if that stops early too, ``optimal`` is False.
    """
    solver = Solver(solver)
    I = np.asarray(I, dtype=np.float64)
    P, k = I.shape
    act = np.ones(P, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    valid = usable(I.T, th).T & act[:, None]
    if outlier is not None:
        valid &= ~outlier
    nodes = np.zeros(P, dtype=np.int64)
    if solver is Solver.L2:
        inl = np.isfinite(I) & act[:, None]
        point = refit(I, inl, L)
        optimal = np.zeros(P, dtype=bool)  # least squares proves no optimum
    else:
        point = np.full((P, 3), np.nan)
        inl = np.zeros((P, k), dtype=bool)
        optimal = np.ones(P, dtype=bool)
        rows = np.flatnonzero(valid.sum(axis=1) >= 3)
        if rows.size:
            if solver is Solver.EXACT:
                lo, hi = slabs(I[rows], th.eps)
                pt, il, _, nd, cert = exact_pixels(I[rows], lo, hi, valid[rows], L, th.box_factor, max_nodes)
                nodes[rows] = nd
                redo = np.flatnonzero(~cert)
                if redo.size:  # budget exhausted: the MILP decides
                    ms = MilpSolver(L, milp_time_limit)
                    mpt, mil, _, mcert, _ = ms.solve_pixels(
                        I[rows[redo]], valid[rows[redo]], th.eps, th.box_factor
                    )
                    better = mil.sum(axis=1) >= il[redo].sum(axis=1)
                    pt[redo[better]] = mpt[better]
                    il[redo[better]] = mil[better]
                    cert[redo] = mcert
            else:
                ms = MilpSolver(L, milp_time_limit)
                pt, il, _, cert, _ = ms.solve_pixels(I[rows], valid[rows], th.eps, th.box_factor)
            point[rows], inl[rows], optimal[rows] = pt, il, cert
    n = refit(I, inl, L)
    normal, albedo = normal_albedo(n)
    solved = np.isfinite(normal[:, 0])
    inl &= solved[:, None]
    count = inl.sum(axis=1).astype(np.uint16)
    albedo_rgb = None
    if rgb is not None:
        albedo_rgb = channel_albedo(np.asarray(rgb, dtype=np.float64), inl, L, normal)
    return PixelResult(normal, albedo, albedo_rgb, inl, count, optimal, point, nodes)


def estimate_job_eps(
    read_block: Callable[[Tile], NDArray],
    L: NDArray[np.float64],
    obs: ObservationModel,
    mask: NDArray[np.bool_] | None,
    shape: tuple[int, int],
    tile: int,
    request: str = "auto",
) -> float:
    """Estimate eps from a fixed sample of pixels in a few tiles (:func:`eps_sample`).

    ``read_block(tile)`` returns the raw block ``(k, h, w[, C])`` of one tile, so
    the in-process and the service paths see the same sample, and the service
    reads k chunks per sampled tile instead of the whole stack.
    """
    if request != "auto":
        raise InvalidInputError(f"eps must be a positive number or 'auto', got {request!r}")
    picks = eps_sample(shape, mask, tile)
    if not picks:
        raise InvalidInputError("cannot estimate eps: the mask selects no pixel; give eps explicitly")
    raw = np.concatenate([read_block(t)[:, ys, xs] for t, ys, xs in picks], axis=1)
    grey, _, saturated = obs.prepare(raw)
    ok = np.isfinite(grey) & (grey > 0) & ~saturated
    return estimate_eps(grey, ok, L, integer_valued=obs.integer_valued)


def eps_sample(
    shape: tuple[int, int], mask: NDArray[np.bool_] | None, tile: int, n: int = 4096, max_tiles: int = 4
) -> list[tuple[Tile, NDArray[np.intp], NDArray[np.intp]]]:
    """Pixels used to estimate eps: up to ``max_tiles`` tiles spread over the object
    (evenly spaced in raster order among those at least half as covered by the mask
    as the best one), and in each every s-th masked pixel, ``n`` pixels in all."""
    grid = list(tiles(shape[0], shape[1], tile))
    cover = np.array(
        [t.shape[0] * t.shape[1] if mask is None else int(mask[t.y0 : t.y1, t.x0 : t.x1].sum()) for t in grid]
    )
    if cover.max(initial=0) == 0:
        return []
    good = [t for t, c in zip(grid, cover, strict=True) if c > 0 and 2 * c >= cover.max()]
    chosen = sorted({int(j) for j in np.linspace(0, len(good) - 1, min(max_tiles, len(good)))})
    per = -(-n // len(chosen))
    out = []
    for j in chosen:
        t = good[j]
        local = np.ones(t.shape, bool) if mask is None else np.asarray(mask[t.y0 : t.y1, t.x0 : t.x1], bool)
        flat = np.flatnonzero(local)
        ys, xs = np.unravel_index(flat[:: max(1, -(-flat.size // per))], t.shape)
        out.append((t, ys.astype(np.intp), xs.astype(np.intp)))
    return out


@dataclass(frozen=True)
class TileResult:
    """Results for one tile of h x w pixels (see :class:`Solution`)."""

    normal: NDArray[np.float32]  # (h, w, 3)
    albedo: NDArray[np.float32]  # (h, w)
    albedo_rgb: NDArray[np.float32] | None  # (h, w, C)
    inliers: NDArray[np.bool_]  # (k, h, w)
    inlier_count: NDArray[np.uint16]  # (h, w)
    optimal: NDArray[np.bool_]  # (h, w)
    nodes: int  # exact-solver search nodes spent on the tile


def solve_tile(
    raw: NDArray,
    L: NDArray[np.float64],
    obs: ObservationModel,
    th: Thresholds,
    solver: Solver | str,
    mask: NDArray[np.bool_] | None = None,
    *,
    max_nodes: int = DEFAULT_MAX_NODES,
    milp_time_limit: float = DEFAULT_MILP_TIME_LIMIT,
) -> TileResult:
    """Solve one tile of raw images ``(k, h, w[, C])``: the path every caller takes."""
    k, h, w = raw.shape[:3]
    grey, rgb, saturated = obs.prepare(raw)
    r = solve_pixels(
        grey,
        L,
        th,
        solver,
        rgb=rgb,
        active=None if mask is None else mask.reshape(h * w),
        outlier=saturated,
        max_nodes=max_nodes,
        milp_time_limit=milp_time_limit,
    )
    return TileResult(
        normal=r.normal.reshape(h, w, 3),
        albedo=r.albedo.reshape(h, w),
        albedo_rgb=None if r.albedo_rgb is None else r.albedo_rgb.reshape(h, w, -1),
        inliers=np.ascontiguousarray(r.inliers.T.reshape(k, h, w)),
        inlier_count=r.count.reshape(h, w),
        optimal=r.optimal.reshape(h, w),
        nodes=int(r.nodes.sum()),
    )


def solve(
    images: ArrayLike,
    lights: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    eps: float | str = 1.0,
    solver: Solver | str = Solver.EXACT,
    intensities: ArrayLike | None = None,
    shadow: float | None = None,
    saturation: float | ArrayLike | None = None,
    box_factor: float = DEFAULT_BOX_FACTOR,
    max_nodes: int = DEFAULT_MAX_NODES,
    milp_time_limit: float = DEFAULT_MILP_TIME_LIMIT,
    tile: int = DEFAULT_TILE,
) -> Solution:
    """Normals, albedo and inlier masks of a whole stack, in this process.

    Parameters
    ----------
    images
        (k, H, W) grey or (k, H, W, C) colour. Integer arrays are raw sensor values:
        a value at the dtype's maximum in any channel is saturated. Float arrays
        are used as they are (see ``saturation``).
    lights
        (k, 3) unit light directions (x right, y up, z toward the camera).
    mask
        Optional (H, W) bool; False pixels are not solved.
    eps
        Tolerance of the Lambertian law, or ``"auto"`` to estimate it.
    intensities
        Optional light intensities, (k,) or (k, C); images are divided by them.
    shadow, saturation, box_factor
        See :func:`worker.problem.make_thresholds`; ``shadow`` defaults to eps;
        ``saturation`` (in units after division) applies to the grey value.
    tile
        Tile edge; pixels are solved tile by tile exactly as the service does, so
        results equal the service's for the same tile size (see :mod:`worker.tiles`).
    """
    arr = np.asarray(images)
    if arr.ndim not in (3, 4):
        raise InvalidInputError(f"images must be (k, H, W) or (k, H, W, C), got shape {arr.shape}")
    k, H, W = arr.shape[:3]
    if k < 3:
        raise InvalidInputError(f"photometric stereo needs at least 3 images, got {k}")
    L = check_lights(lights, k)
    obs = ObservationModel.for_input(arr.dtype, k, arr.shape[3] if arr.ndim == 4 else None, intensities)
    m = None
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (H, W):
            raise InvalidInputError(f"mask has shape {m.shape}, images are {H} x {W}")
    if isinstance(eps, str):
        eps_v = estimate_job_eps(lambda t: arr[:, t.y0 : t.y1, t.x0 : t.x1], L, obs, m, (H, W), tile, eps)
    else:
        eps_v = float(eps)
    th = make_thresholds(k, eps_v, shadow=shadow, saturation=saturation, box_factor=box_factor)
    C = arr.shape[3] if arr.ndim == 4 else None
    normal = np.empty((H, W, 3), np.float32)
    albedo = np.empty((H, W), np.float32)
    albedo_rgb = None if C is None else np.empty((H, W, C), np.float32)
    inliers = np.empty((k, H, W), bool)
    count = np.empty((H, W), np.uint16)
    optimal = np.empty((H, W), bool)
    for t in tiles(H, W, tile):
        ys, xs = slice(t.y0, t.y1), slice(t.x0, t.x1)
        r = solve_tile(
            arr[:, ys, xs],
            L,
            obs,
            th,
            solver,
            None if m is None else m[ys, xs],
            max_nodes=max_nodes,
            milp_time_limit=milp_time_limit,
        )
        normal[ys, xs] = r.normal
        albedo[ys, xs] = r.albedo
        if albedo_rgb is not None and r.albedo_rgb is not None:
            albedo_rgb[ys, xs] = r.albedo_rgb
        inliers[:, ys, xs] = r.inliers
        count[ys, xs] = r.inlier_count
        optimal[ys, xs] = r.optimal
    return Solution(normal, albedo, albedo_rgb, inliers, count, optimal, eps_v)
