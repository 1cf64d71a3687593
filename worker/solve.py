"""Public entry points: solve a pixel batch (tile tasks) or a whole image stack.

Example
-------
>>> from maxfs.worker import synthetic
>>> from maxfs.worker.solve import solve
>>> scene = synthetic.sphere(k=12, size=32)
>>> sol = solve(scene.images, scene.lights, scene.mask)  # the CLI's defaults: robust model, eps auto
>>> sol.normal.shape, sol.inliers.shape
((32, 32, 3), (12, 32, 32))
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.observations import ObservationModel, raw_quantum
from maxfs.storage.options import (
    DEFAULT_BOX_FACTOR,
    DEFAULT_EPS,
    DEFAULT_MAX_NODES,
    DEFAULT_MILP_TIME_LIMIT,
    DEFAULT_MODEL,
    MAX_LIGHT_CONDITION,
    MODEL_DEFAULTS,
    Estimate,
    Model,
    Solver,
    check_lights,
    check_options,
)
from maxfs.storage.outputs import TILE_OUTPUTS, Source
from maxfs.storage.params import check_tile_edge
from maxfs.storage.tiles import DEFAULT_TILE, Tile, tiles
from maxfs.worker.lstsq import channel_albedo, normal_albedo, refit
from maxfs.worker.noise import estimate_model
from maxfs.worker.problem import MAX_INTENSITY, Thresholds, make_thresholds, shading, usable
from maxfs.worker.solvers import SOLVERS, Batch


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
    source: NDArray[np.uint8]  # (P,) how the normal was obtained (:class:`Source`)


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
    source: NDArray[np.uint8]  # (H, W) how each normal was obtained (:class:`Source`)
    response: float = 1.0  # the response g used (estimated when response="auto")


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
    impl = SOLVERS[Solver(solver)]
    I = np.asarray(I, dtype=np.float64)
    P = I.shape[0]
    act = np.ones(P, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    S = shading(I, th)  # what L.n should match: I, or I^(1/g) under a response
    use = usable(I.T, th).T if impl.max_fs else None  # once, for the search and the refit
    found = impl.search(Batch(I, S, L, th, act, outlier, max_nodes, milp_time_limit, use))
    point, inl, optimal, nodes, source = found.point, found.inliers, found.optimal, found.nodes, found.source
    # the refit is least squares on the lit inliers: a shadow inlier says L.n <= s, not L.n = I
    # (it would pull n toward the shadow's value), so it is a row only where the fit breaks it
    lit = inl & use if use is not None else inl
    n = refit(S, lit, L, MAX_LIGHT_CONDITION)  # a badly conditioned inlier set determines no normal
    if impl.max_fs and th.shadow_slabs:
        n = censored_refit(S, lit, inl & ~lit, L, n)
    if th.fallback and impl.max_fs:
        # least squares on the non-zero unsaturated observations; where those do not
        # determine a normal (a nearly black pixel), on every finite unsaturated one: a zero
        # measures max(L.n, 0) too, and these are the rows the l2 baseline fits
        for nonzero in (True, False):
            need = np.flatnonzero(act & ~np.isfinite(n[:, 0]))
            if not need.size:
                break
            if nonzero:
                fb = usable(I[need].T, _no_shadow(th)).T
            else:
                with np.errstate(invalid="ignore"):
                    fb = np.isfinite(I[need]) & (I[need] < np.minimum(th.saturation, MAX_INTENSITY))
            if outlier is not None:
                fb &= ~outlier[need]
            nf = refit(S[need], fb, L, MAX_LIGHT_CONDITION)
            got = np.isfinite(nf[:, 0]) & np.any(nf != 0.0, axis=1)  # all zeros: no direction
            n[need[got]] = nf[got]
            inl[need] = fb & got[:, None]
            lit[need] = inl[need]
            optimal[need] = False
            source[need[got]] = Source.FIT
    normal, albedo = normal_albedo(n)
    solved = np.isfinite(normal[:, 0])
    inl &= solved[:, None]
    optimal &= solved  # a normal the inliers do not determine is not an answer
    source[~solved] = Source.UNDETERMINED
    source[~act] = Source.MASKED
    count = inl.sum(axis=1).astype(np.uint16)
    albedo_rgb = None
    if rgb is not None:
        rgb_s = shading(np.asarray(rgb, dtype=np.float64), th)
        albedo_rgb = channel_albedo(rgb_s, lit & solved[:, None], L, normal)
    return PixelResult(normal, albedo, albedo_rgb, inl, count, optimal, point, nodes, source)


#: Active-set rounds of :func:`censored_refit` (it settles in two or three).
CENSORED_ROUNDS = 8


def censored_refit(
    S: NDArray[np.float64],
    lit: NDArray[np.bool_],
    dark: NDArray[np.bool_],
    L: NDArray[np.float64],
    n: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Least squares of the sensor model ``s = max(L.n, 0)`` over the inliers: a lit inlier
    costs ``(L.n - s)^2``, a shadow inlier (``dark``) ``max(L.n - s, 0)^2``, so it pulls only
    where the fit would light it. Solved from ``n`` (the lit fit) by active sets: the shadow
    rows ``L.n > s`` join the lit rows, refit, until the active set stops changing. Where the
    lit fit satisfies every shadow inlier (the Max-FS point always does) it is returned as is;
    few lit images (small k) are where it breaks them."""
    rows = np.flatnonzero(dark.any(axis=1) & np.isfinite(n[:, 0]))
    if not rows.size:
        return n
    n = n.copy()
    Sr, lr, dr = S[rows], lit[rows], dark[rows]
    nr = n[rows]
    active = np.zeros_like(dr)
    for _ in range(CENSORED_ROUNDS):
        new = dr & (nr @ L.T > Sr)
        if np.array_equal(new, active):
            break
        active = new
        fit = refit(Sr, lr | active, L, MAX_LIGHT_CONDITION)
        nr = np.where(np.isfinite(fit[:, :1]), fit, nr)
    n[rows] = nr
    return n


def _no_shadow(th: Thresholds) -> Thresholds:
    """``th`` with only zero (and below) counted as shadow: the fallback's observations."""
    return Thresholds(0.0 if th.eps <= 0 else th.eps, 0.0, th.saturation, th.box_factor)


def estimate_job(
    read_block: Callable[[Tile], NDArray],
    L: NDArray[np.float64],
    obs: ObservationModel,
    mask: NDArray[np.bool_] | None,
    shape: tuple[int, int],
    *,
    eps: float | str = "auto",
    response: float | str = 1.0,
    drop_bright: float = 0.0,
    model: Model | str = Model.PAPER,
) -> Estimate:
    """Resolve ``"auto"`` eps and response (:func:`worker.noise.estimate_model`) on the
    fixed sample of :func:`eps_sample`, and the raw values' step there
    (:func:`storage.observations.raw_quantum`; ``obs`` is the model before it is known,
    its step 1): the estimate is made with the step, and records it.

    ``read_block(window)`` returns the raw block ``(k, h, w[, C])`` of a window (a
    :class:`Tile` that need not be on the tile grid), so the in-process and the service
    paths see the same pixels whatever their tile size, and the service reads a few
    chunks per window instead of the whole stack.
    """
    for name, v in (("eps", eps), ("response", response)):
        if isinstance(v, str) and v != "auto":
            raise InvalidInputError(f"{name} must be a positive number or 'auto', got {v!r}")
    picks = eps_sample(shape, mask)
    if not picks:
        if eps == "auto" or response == "auto":
            raise InvalidInputError("cannot estimate eps: the mask selects no pixel; give eps explicitly")
        return Estimate(float(eps), float(response), 0.0)  # nothing to solve, nor to measure
    raw = np.concatenate([read_block(t)[:, ys, xs] for t, ys, xs in picks], axis=1)
    obs = obs.with_quantum(raw_quantum(raw))
    grey, _, saturated = obs.prepare(raw)
    ok = np.isfinite(grey) & (grey > 0) & ~saturated
    est = estimate_model(
        grey,
        ok,
        L,
        step=obs.step,
        eps=eps,
        response=response,
        drop_bright=drop_bright,
        by_intensity=MODEL_DEFAULTS[Model(model)].noise_by_intensity,
    )
    return replace(est, quantum=obs.quantum)


def estimate_job_eps(
    read_block: Callable[[Tile], NDArray],
    L: NDArray[np.float64],
    obs: ObservationModel,
    mask: NDArray[np.bool_] | None,
    shape: tuple[int, int],
    tile: int | None = None,
    request: str = "auto",
) -> float:
    """eps alone, for the Lambertian response (``tile`` is ignored: the sample does not
    depend on the tile grid). See :func:`estimate_job`."""
    return estimate_job(read_block, L, obs, mask, shape, eps=request).eps


#: The sample for the job-level estimates: this many windows of ``SAMPLE_EDGE`` pixels.
SAMPLE_WINDOWS = 16
SAMPLE_EDGE = 16


def eps_sample(
    shape: tuple[int, int],
    mask: NDArray[np.bool_] | None,
    windows: int = SAMPLE_WINDOWS,
    edge: int = SAMPLE_EDGE,
) -> list[tuple[Tile, NDArray[np.intp], NDArray[np.intp]]]:
    """Pixels for the eps and response estimates, a function of the image size and mask
    only (never of the tile grid): ``windows`` square windows of ``edge`` pixels centred
    on masked pixels evenly spaced in raster order (so spread over the object's rows),
    and every masked pixel inside them not taken by an earlier window (up to
    ``windows * edge**2`` = 4096 pixels). Each item is ``(window, ys, xs)`` with
    coordinates local to the window; a window costs a few chunk reads per image."""
    H, W = shape
    m = np.ones((H, W), bool) if mask is None else np.asarray(mask, dtype=bool)
    flat = np.flatnonzero(m)
    if flat.size == 0:
        return []
    centres = flat[np.unique(np.linspace(0, flat.size - 1, min(windows, flat.size)).astype(np.int64))]
    taken = np.zeros((H, W), bool)
    out = []
    for j, c in enumerate(centres):
        cy, cx = divmod(int(c), W)
        y0 = min(max(cy - edge // 2, 0), max(H - edge, 0))
        x0 = min(max(cx - edge // 2, 0), max(W - edge, 0))
        y1, x1 = min(y0 + edge, H), min(x0 + edge, W)
        local = m[y0:y1, x0:x1] & ~taken[y0:y1, x0:x1]
        if not local.any():
            continue
        taken[y0:y1, x0:x1] |= local
        ys, xs = np.nonzero(local)
        out.append((Tile(-1 - j, -1, -1, y0, y1, x0, x1), ys.astype(np.intp), xs.astype(np.intp)))
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
    source: NDArray[np.uint8] | None = None  # (h, w) how each normal was obtained

    @classmethod
    def of_pixels(cls, r: PixelResult, h: int, w: int) -> TileResult:
        """The tile's arrays from the results of its ``h * w`` pixels in raster order."""
        k = r.inliers.shape[1]
        return cls(
            normal=r.normal.reshape(h, w, 3),
            albedo=r.albedo.reshape(h, w),
            albedo_rgb=None if r.albedo_rgb is None else r.albedo_rgb.reshape(h, w, -1),
            inliers=np.ascontiguousarray(r.inliers.T.reshape(k, h, w)),
            inlier_count=r.count.reshape(h, w),
            optimal=r.optimal.reshape(h, w),
            nodes=int(r.nodes.sum()),
            source=r.source.reshape(h, w),
        )

    def outputs(self) -> dict[str, NDArray]:
        """The arrays of :data:`storage.outputs.TILE_OUTPUTS` by name (``albedo_rgb`` only for
        colour input): what :meth:`storage.layout.JobStore.write_tile` stores."""
        out = {o.name: getattr(self, o.name) for o in TILE_OUTPUTS}
        return {name: a for name, a in out.items() if a is not None}


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
    """Solve one tile of raw images ``(k, h, w[, C])``: the path every caller takes.

    Only the masked pixels are prepared and solved (the exact solver visits them in the
    same raster order either way, so results do not depend on it); the others get the
    values :func:`solve_pixels` gives an inactive pixel.
    """
    k, h, w = raw.shape[:3]
    idx = None if mask is None else np.flatnonzero(mask.reshape(h * w))
    if idx is not None and idx.size == 0:
        # nothing to solve (a tile outside the mask): every pixel is the inactive fill
        r = _scatter(None, idx, h * w, obs, L, th, solver, k, raw.shape[3] if raw.ndim == 4 else None)
    else:
        part = idx is not None and idx.size < h * w
        grey, rgb, saturated = obs.prepare(raw, idx if part else None)  # gathered as it is transposed
        r = solve_pixels(
            grey,
            L,
            th,
            solver,
            rgb=rgb,
            outlier=saturated,
            max_nodes=max_nodes,
            milp_time_limit=milp_time_limit,
        )
        if part:
            r = _scatter(r, idx, h * w, obs, L, th, solver)
    return TileResult.of_pixels(r, h, w)


def _scatter(
    r: PixelResult | None,
    idx: NDArray[np.intp],
    P: int,
    obs: ObservationModel,
    L,
    th: Thresholds,
    solver,
    k: int | None = None,
    C: int | None = None,
) -> PixelResult:
    """``r`` (results of pixels ``idx``) spread over ``P`` pixels; the rest hold exactly what
    :func:`solve_pixels` returns for an inactive pixel (computed, not restated: once per
    process and inputs, :func:`_inactive_fill`). ``r`` None: no pixel solved (``idx`` empty),
    then ``k`` and ``C`` give the shapes."""
    if r is not None:
        k = r.inliers.shape[1]
        C = None if r.albedo_rgb is None else r.albedo_rgb.shape[1]
    assert k is not None
    fill = _inactive_fill(obs, L, th, solver, k, C)
    out = {}
    for name in (f.name for f in dataclasses.fields(PixelResult)):
        f = getattr(fill, name)
        part = f if r is None else getattr(r, name)
        if part is None:
            out[name] = None
            continue
        full = np.repeat(f, P, axis=0)
        if r is not None:
            full[idx] = part
        out[name] = full
    return PixelResult(**out)


#: The last :func:`_inactive_fill` (its key, its result): a job's tiles share their inputs,
#: so a tile with masked-out pixels no longer solves a blank pixel each (about 0.2 ms a tile).
_FILL: tuple[tuple, PixelResult] | None = None


def _inactive_fill(obs: ObservationModel, L, th: Thresholds, solver, k: int, C: int | None) -> PixelResult:
    """What :func:`solve_pixels` returns for one inactive pixel of these inputs (read only:
    callers copy it, :func:`_scatter` by ``np.repeat``)."""
    global _FILL
    Lf = np.asarray(L, dtype=np.float64)
    key = (
        obs.intensities.tobytes(),
        obs.intensities.shape,
        obs.sensor_max,
        obs.channels,
        obs.dequantize,
        obs.quantum,
        Lf.tobytes(),
        Lf.shape,
        tuple(
            (f.name, v.tobytes() if isinstance(v, np.ndarray) else v)
            for f in dataclasses.fields(th)
            for v in (getattr(th, f.name),)
        ),
        str(solver),
        k,
        C,
    )
    cached = _FILL
    if cached is not None and cached[0] == key:
        return cached[1]
    blank = np.zeros((k, 1) if C is None else (k, 1, C))
    g, rgb, sat = obs.prepare(blank)
    fill = solve_pixels(g, L, th, solver, rgb=rgb, active=np.zeros(1, bool), outlier=sat)
    _FILL = (key, fill)
    return fill


def solve(
    images: ArrayLike,
    lights: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    eps: float | str = DEFAULT_EPS,
    solver: Solver | str = Solver.EXACT,
    intensities: ArrayLike | None = None,
    shadow: float | None = None,
    saturation: float | ArrayLike | None = None,
    box_factor: float = DEFAULT_BOX_FACTOR,
    max_nodes: int = DEFAULT_MAX_NODES,
    milp_time_limit: float = DEFAULT_MILP_TIME_LIMIT,
    tile: int = DEFAULT_TILE,
    model: Model | str = DEFAULT_MODEL,
    response: float | str | None = None,
    eps_rel: float | None = None,
    drop_bright: float | None = None,
    dequantize: bool | None = None,
    fallback: bool | None = None,
) -> Solution:
    """Normals, albedo and inlier masks of a whole stack, in this process.

    Parameters
    ----------
    images
        (k, H, W) grey or (k, H, W, C) colour. Integer arrays are raw sensor values:
        a value at the top of the data's grid (the dtype's maximum, or its largest multiple of
        the raw step, :func:`storage.observations.raw_quantum`) in any channel is saturated. Float arrays
        are used as they are (see ``saturation``).
    lights
        (k, 3) unit light directions (x right, y up, z toward the camera).
    mask
        Optional (H, W) bool; False pixels are not solved.
    eps
        Tolerance of the Lambertian law, or ``"auto"`` (default, as the CLI and HTTP) to estimate it.
    intensities
        Optional light intensities, (k,) or (k, C); images are divided by them.
    shadow, saturation, box_factor
        See :func:`worker.problem.make_thresholds`; ``shadow`` defaults to eps;
        ``saturation`` (in units after division) applies to the grey value.
    tile
        Tile edge; pixels are solved tile by tile exactly as the service does, so
        results equal the service's for the same tile size (see :mod:`storage.tiles`).
    model
        ``"robust"`` (the default everywhere: :data:`storage.options.DEFAULT_MODEL`) or
        ``"paper"`` (Yu, Seo, Lee 2010 as published); see :mod:`worker.problem`. The options below left None
        take the model's values (:data:`worker.problem.MODEL_DEFAULTS`).
    response
        Exponent g of ``I = (L.n)^g``, or ``"auto"`` (:func:`worker.noise.select_response`).
    eps_rel, drop_bright, fallback
        See :class:`worker.problem.Thresholds`.
    dequantize
        Integer input: read a raw value ``v > 0`` as ``v + q/2``, ``q`` the raw step (see
        :class:`storage.observations.ObservationModel`).
    """
    arr = np.asarray(images)
    if arr.ndim not in (3, 4):
        raise InvalidInputError(f"images must be (k, H, W) or (k, H, W, C), got shape {arr.shape}")
    k, H, W = arr.shape[:3]
    if k < 3:
        raise InvalidInputError(f"photometric stereo needs at least 3 images, got {k}")
    L = check_lights(lights, k)
    # a given eps is checked now, before the response estimate uses it ("auto" and other words later)
    given = None if isinstance(eps, str) else eps
    check_options(eps=given, model=model, eps_rel=eps_rel, response=response, drop_bright=drop_bright)
    check_tile_edge(tile)
    defaults = MODEL_DEFAULTS[Model(model)]
    deq = defaults.dequantize if dequantize is None else bool(dequantize)
    resp = defaults.response if response is None else response
    obs = ObservationModel.for_input(
        arr.dtype, k, arr.shape[3] if arr.ndim == 4 else None, intensities, dequantize=deq
    )
    m = None
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (H, W):
            raise InvalidInputError(f"mask has shape {m.shape}, images are {H} x {W}")
    # always, as the service does when a job starts: the raw step is measured on the sample
    # even when eps and the response are given
    est = estimate_job(
        lambda t: arr[:, t.y0 : t.y1, t.x0 : t.x1],
        L,
        obs,
        m,
        (H, W),
        eps=eps,
        response=resp,
        drop_bright=defaults.drop_bright if drop_bright is None else drop_bright,
        model=model,
    )
    eps_v, resp_v, obs = est.eps, est.response, obs.with_quantum(est.quantum)
    th = make_thresholds(
        k,
        eps_v,
        shadow=shadow,
        saturation=saturation,
        box_factor=box_factor,
        model=model,
        eps_rel=eps_rel,
        response=resp_v,
        drop_bright=drop_bright,
        fallback=fallback,
    )
    C = arr.shape[3] if arr.ndim == 4 else None
    full = {o.name: np.empty(o.shape(k, H, W, C), o.dtype) for o in TILE_OUTPUTS if o.exists(C)}
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
        for o in TILE_OUTPUTS:
            if o.name in full:
                if o.per == "image":
                    full[o.name][:, ys, xs] = getattr(r, o.name)
                else:
                    full[o.name][ys, xs] = getattr(r, o.name)
    return Solution(
        full["normal"],
        full["albedo"],
        full.get("albedo_rgb"),
        full["inliers"],
        full["inlier_count"],
        full["optimal"],
        eps_v,
        full["source"],
        resp_v,
    )
