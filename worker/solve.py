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

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from worker.errors import InvalidInputError
from worker.exact import exact_pixels
from worker.lstsq import channel_albedo, normal_albedo, refit
from worker.milp import MilpSolver
from worker.noise import estimate_eps
from worker.problem import (
    DEFAULT_BOX_FACTOR,
    Thresholds,
    check_lights,
    make_thresholds,
    saturation_vector,
    usable,
)
from worker.tiles import DEFAULT_TILE, tiles

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
    point: NDArray[np.float64]  # (H, W, 3)
    eps: float  # the eps used (estimated when eps="auto")


def solve_pixels(
    I: NDArray[np.floating],
    L: NDArray[np.float64],
    th: Thresholds,
    solver: Solver | str = Solver.EXACT,
    *,
    rgb: NDArray[np.floating] | None = None,
    active: NDArray[np.bool_] | None = None,
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
    max_nodes
        Exact solver's per-pixel budget; a pixel that exhausts it is solved by the
        MILP with ``milp_time_limit``; if that stops early too, ``optimal`` is False.
    """
    solver = Solver(solver)
    I = np.asarray(I, dtype=np.float64)
    P, k = I.shape
    act = np.ones(P, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    valid = usable(I.T, th).T & act[:, None]
    nodes = np.zeros(P, dtype=np.int64)
    if solver is Solver.L2:
        inl = np.isfinite(I) & act[:, None]
        point = refit(I, inl, L)
        optimal = np.ones(P, dtype=bool)
    else:
        point = np.full((P, 3), np.nan)
        inl = np.zeros((P, k), dtype=bool)
        optimal = np.ones(P, dtype=bool)
        rows = np.flatnonzero(valid.sum(axis=1) >= 3)
        if rows.size:
            if solver is Solver.EXACT:
                pt, il, _, nd, cert = exact_pixels(I[rows], valid[rows], L, th.eps, th.box_factor, max_nodes)
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


def to_grey(images: NDArray[np.floating]) -> NDArray[np.float64]:
    """(k, H, W, C) colour to (k, H, W) grey as (R + G + B) / 3; grey passes through."""
    arr = np.asarray(images, dtype=np.float64)
    return arr.mean(axis=-1) if arr.ndim == 4 else arr


def resolve_eps(
    eps: float | str,
    grey: NDArray[np.float64],
    L: NDArray[np.float64],
    saturation: NDArray[np.float64],
    mask: NDArray[np.bool_] | None,
    integer_valued: bool,
) -> float:
    """A number for ``eps``; ``"auto"`` estimates it (:func:`worker.noise.estimate_eps`)."""
    if isinstance(eps, str):
        if eps != "auto":
            raise InvalidInputError(f"eps must be a positive number or 'auto', got {eps!r}")
        k = grey.shape[0]
        I = grey.reshape(k, -1).T
        ok = np.isfinite(I) & (I > 0) & (I < saturation[None, :])
        if mask is not None:
            ok &= mask.reshape(-1)[:, None]
        return estimate_eps(I, ok, L, integer_valued=integer_valued)
    return float(eps)


def solve(
    images: ArrayLike,
    lights: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    eps: float | str = 1.0,
    solver: Solver | str = Solver.EXACT,
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
        (k, H, W) grey or (k, H, W, C) colour, already divided by light intensity.
        Integer arrays are accepted; their dtype's maximum is then the default
        saturation.
    lights
        (k, 3) unit light directions (x right, y up, z toward the camera).
    mask
        Optional (H, W) bool; False pixels are not solved.
    eps
        Tolerance of the Lambertian law, or ``"auto"`` to estimate it.
    shadow, saturation, box_factor
        See :func:`worker.problem.make_thresholds`; ``shadow`` defaults to eps.
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
    if saturation is None and np.issubdtype(arr.dtype, np.integer):
        saturation = float(np.iinfo(arr.dtype).max)
    integer_valued = bool(np.issubdtype(arr.dtype, np.integer))
    grey = to_grey(arr)
    m = None
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (H, W):
            raise InvalidInputError(f"mask has shape {m.shape}, images are {H} x {W}")
    eps_v = resolve_eps(eps, grey, L, saturation_vector(k, saturation), m, integer_valued)
    th = make_thresholds(k, eps_v, shadow=shadow, saturation=saturation, box_factor=box_factor)
    C = arr.shape[3] if arr.ndim == 4 else None
    normal = np.empty((H, W, 3), np.float32)
    albedo = np.empty((H, W), np.float32)
    albedo_rgb = None if C is None else np.empty((H, W, C), np.float32)
    inliers = np.empty((k, H, W), bool)
    count = np.empty((H, W), np.uint16)
    optimal = np.empty((H, W), bool)
    point = np.empty((H, W, 3))
    for t in tiles(H, W, tile):
        win = (slice(t.y0, t.y1), slice(t.x0, t.x1))
        P = (t.y1 - t.y0) * (t.x1 - t.x0)
        rgb = (
            None
            if C is None
            else np.moveaxis(arr[:, win[0], win[1]].astype(np.float64).reshape(k, P, C), 0, 1)
        )
        r = solve_pixels(
            grey[:, win[0], win[1]].reshape(k, P).T,
            L,
            th,
            solver,
            rgb=rgb,
            active=None if m is None else m[win].reshape(P),
            max_nodes=max_nodes,
            milp_time_limit=milp_time_limit,
        )
        shape = t.shape
        normal[win] = r.normal.reshape(*shape, 3)
        albedo[win] = r.albedo.reshape(shape)
        if albedo_rgb is not None and r.albedo_rgb is not None:
            albedo_rgb[win] = r.albedo_rgb.reshape(*shape, C)
        inliers[:, win[0], win[1]] = r.inliers.T.reshape(k, *shape)
        count[win] = r.count.reshape(shape)
        optimal[win] = r.optimal.reshape(shape)
        point[win] = r.point.reshape(*shape, 3)
    return Solution(normal, albedo, albedo_rgb, inliers, count, optimal, point, eps_v)
