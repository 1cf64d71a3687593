"""The per-pixel Max-FS problem shared by every solver.

For image i at a pixel, the Lambertian law holds within ``eps`` when ``n = rho N``
lies in the slab ``a_i <= L_i . n <= b_i`` with ``a_i = max(I_i - eps, eps)`` and
``b_i = I_i + eps`` (Yu, Seo, Lee, ECCV 2010, eq. 3). ``n`` is confined to the box
``|n_j| <= U`` with ``U = box_factor * max_i b_i`` so the MILP has finite, valid
big-M values; every solver uses the same box, so their optima are comparable.

Two kinds of image are *outliers by definition*, never candidates:

* shadowed: ``I_i <= shadow``. With ``I_i = 0`` the slab degenerates to the plane
  ``L_i . n = eps``; the exact optimum often sits on such a plane at a vertex and so
  counts a shadowed image as an inlier, which biases the normal. The default
  ``shadow = eps`` removes every slab whose lower side is clamped to ``eps``
  entirely by the clamp.
* saturated: ``I_i >= saturation`` (the sensor's maximum); the true value is unknown.

**Models.** ``paper`` is the formulation above, exactly. ``robust`` (the default of the
CLI, HTTP, :func:`worker.solve.solve` and ``maxfs demo``) generalises it for real captures,
and every part stays a set of k slabs ``lo_i <= L_i . n <= hi_i``, so the optimum is still
exact and checkable against the MILP:

* tolerance growing with intensity: ``|I_i - s_i| <= t_i``, ``t_i = eps + eps_rel I_i``;
* a camera/BRDF response ``I = s^g`` (``response`` g, estimated per job, 1 = Lambertian):
  the condition ``|I_i - (L_i . n)^g| <= t_i`` is the slab
  ``max(I_i - t_i, m)^(1/g) <= L_i . n <= (I_i + t_i)^(1/g)`` (the power is monotone), and
  the refit is least squares on ``I^(1/g)``;
* shadows follow the noise: ``shadow = eps / 3`` (one noise sigma when eps is 3 sigma) and
  the clamp ``m`` is the shadow threshold (the paper's is ``eps``);
* a shadow is evidence (``shadow_slabs``): the sensor sees ``max(L.n, 0)``, so an
  observation ``I <= shadow`` says ``L.n <= I + t``, the one-sided slab ``lo = -inf``. It
  counts as an inlier where it holds (the optimum stays exact and MILP-checked), only where
  a first-pass normal agrees the light is behind (else it is a cast shadow, an outlier), and
  it never enters the least-squares refit (it bounds ``n``, it does not measure it);
* near-mirror highlights (``mirror_deg``, :mod:`worker.outliers`): lit candidates whose
  half-vector is within 20 degrees of a first-pass normal and that are brighter than it
  predicts are outliers; each pixel keeps at least 6 lit candidates;
* ``fallback``: a pixel with fewer than 3 candidates (or rank-deficient inliers) gets the
  least-squares fit on its non-zero, unsaturated observations instead of no normal.

Dequantisation of integer input is part of the observation model
(:mod:`storage.observations`), the estimates of eps and g of :mod:`worker.noise`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.options import DEFAULT_BOX_FACTOR, MODEL_DEFAULTS, Model, check_options

#: Relative tolerance for "point lies in slab"; scaled by the pixel's largest ``b_i``.
REL_TOL = 1e-9


@dataclass(frozen=True)
class Thresholds:
    """Which observations may be inliers, and the slab half-width.

    Attributes
    ----------
    eps
        Tolerance of the Lambertian law, in intensity units (after division by
        the light intensity).
    shadow
        Observations ``<= shadow`` are shadows (outliers by definition).
    saturation
        Per-image threshold, shape ``(k,)``: observations ``>= saturation[i]`` are
        saturated (outliers by definition). ``inf`` disables the check.
    box_factor
        Box half-width on ``n`` as a multiple of the pixel's largest ``b_i``.
    eps_rel
        Tolerance growth with intensity: ``t_i = eps + eps_rel * I_i``.
    response
        Exponent g of the response ``I = (L.n)^g`` (1 = Lambertian, the paper).
    min_shading
        Smallest ``L.n`` an inlier may have (before the response); None means ``eps``
        (the paper's clamp ``a = max(I - eps, eps)``).
    drop_bright
        Share of each pixel's candidates, brightest first, that are outliers by definition.
    fallback
        Least squares on the non-zero unsaturated observations where Max-FS gives no normal.
    shadow_slabs
        A shadow (finite, unsaturated, ``<= shadow``) is the one-sided slab
        ``L.n <= (max(I, 0) + t)^(1/g)``: an inlier when the light is (nearly) behind the
        surface, never a least-squares row.
    mirror_deg
        Lit candidates whose half-vector lies within this angle of a first-pass normal
        and that are brighter than it predicts are outliers (:mod:`worker.outliers`); 0: none.
    """

    eps: float
    shadow: float
    saturation: NDArray[np.float64]
    box_factor: float = DEFAULT_BOX_FACTOR
    eps_rel: float = 0.0
    response: float = 1.0
    min_shading: float | None = None
    drop_bright: float = 0.0
    fallback: bool = False
    shadow_slabs: bool = False
    mirror_deg: float = 0.0


def make_thresholds(
    k: int,
    eps: float,
    *,
    shadow: float | None = None,
    saturation: float | ArrayLike | None = None,
    box_factor: float = DEFAULT_BOX_FACTOR,
    model: Model | str = Model.PAPER,
    eps_rel: float | None = None,
    response: float | None = None,
    drop_bright: float | None = None,
    fallback: bool | None = None,
) -> Thresholds:
    """Validate (:func:`check_options`) and build :class:`Thresholds`.

    Options left None take the ``model``'s defaults (:data:`MODEL_DEFAULTS`): ``shadow``
    is ``eps`` (paper) or ``eps / 3`` (robust). ``response`` must be a number here
    (estimate ``"auto"`` first, :func:`worker.noise.estimate_model`); None is 1.
    """
    d = MODEL_DEFAULTS[Model(model)] if model in tuple(Model) else None
    scalar_sat = saturation if saturation is None or np.ndim(saturation) == 0 else None
    check_options(
        eps=eps,
        shadow=shadow,
        saturation=scalar_sat,
        box_factor=box_factor,
        model=model,
        eps_rel=eps_rel,
        response=response,
        drop_bright=drop_bright,
    )
    assert d is not None
    if response == "auto":
        raise InvalidInputError("estimate the response first (worker.noise.estimate_model)")
    robust = Model(model) is Model.ROBUST
    shadow_v = float(d.shadow_per_eps * eps if shadow is None else shadow)
    sat = saturation_vector(k, saturation)
    if np.any(sat <= shadow_v):
        raise InvalidInputError("saturation thresholds must be above the shadow threshold")
    return Thresholds(
        float(eps),
        shadow_v,
        sat,
        float(box_factor),
        eps_rel=float(d.eps_rel if eps_rel is None else eps_rel),
        response=float(1.0 if response is None else response),
        min_shading=shadow_v if robust else None,
        drop_bright=float(d.drop_bright if drop_bright is None else drop_bright),
        fallback=bool(d.fallback if fallback is None else fallback),
        shadow_slabs=d.shadow_slabs,
        mirror_deg=d.mirror_deg,
    )


def saturation_vector(k: int, saturation: float | ArrayLike | None) -> NDArray[np.float64]:
    """Per-image saturation thresholds, shape ``(k,)``; ``None`` means none (inf)."""
    if saturation is None:
        return np.full(k, np.inf)
    try:
        sat = np.broadcast_to(np.asarray(saturation, dtype=np.float64), (k,)).copy()
    except (ValueError, TypeError) as e:
        raise InvalidInputError(f"saturation must be a number or one number per image ({k}): {e}") from None
    if np.any(np.isnan(sat)):
        raise InvalidInputError("saturation thresholds must not be NaN")
    return sat


#: Largest intensity used as an observation: above it a value is treated like a saturated one
#: (a float32 pixel near its maximum, 3e38, solved to an albedo of +inf once scaled).
MAX_INTENSITY = 1e30


def usable(images: NDArray[np.floating], th: Thresholds) -> NDArray[np.bool_]:
    """Observations that may be inliers: finite, above shadow, below saturation and
    :data:`MAX_INTENSITY`.

    ``images`` has the image axis first: ``(k, ...)``.
    """
    sat = np.minimum(th.saturation, MAX_INTENSITY).reshape((-1,) + (1,) * (images.ndim - 1))
    # no isfinite pass: NaN fails both comparisons, -inf the first, +inf the second (``sat``
    # is at most MAX_INTENSITY, or NaN, which no value is below)
    with np.errstate(invalid="ignore"):
        return (images > th.shadow) & (images < sat)


def slabs(
    intensities: NDArray[np.floating], eps: float | Thresholds
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Slab bounds ``lo <= L.n <= hi`` of each observation, in the solver's units.

    With a number: the paper's ``a = max(I - eps, eps)``, ``b = I + eps`` (eq. 3). With
    :class:`Thresholds`: ``t = eps + eps_rel I``, ``a = max(I - t, min_shading)``,
    ``b = I + t``, both raised to ``1 / response`` (see the module docstring); for the
    paper's thresholds this is the same arithmetic, bit for bit.
    """
    i = np.asarray(intensities, dtype=np.float64)
    if not isinstance(eps, Thresholds):
        return np.maximum(i - eps, eps), i + eps
    th = eps
    t = th.eps + th.eps_rel * i if th.eps_rel else th.eps
    floor = th.eps if th.min_shading is None else th.min_shading
    if th.shadow_slabs and th.response == 1.0 and th.shadow >= 0:
        return _linear_shadow_slabs(i, th, t, floor)
    a, b = np.maximum(i - t, floor), i + t
    if th.shadow_slabs:
        with np.errstate(invalid="ignore"):
            dark = i <= th.shadow
        a = np.where(dark, -np.inf, a)
        b = np.where(dark, np.maximum(i, 0.0) + t, b)
    if th.response != 1.0:
        with np.errstate(invalid="ignore"):
            a, b = np.where(a > -np.inf, a, 0.0) ** (1.0 / th.response), b ** (1.0 / th.response)
        if th.shadow_slabs:
            a = np.where(dark, -np.inf, a)
    return a, b


def _linear_shadow_slabs(
    i: NDArray[np.float64], th: Thresholds, t: float | NDArray[np.float64], floor: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`slabs` for shadow slabs under the linear response, bit for bit, in place on two
    arrays instead of a dozen temporaries (the robust model's every tile). With ``shadow >= 0``
    a shadow's ``max(I, 0) + t`` is ``I + t`` except where ``I < 0`` (then ``t``: ``0 + t``),
    and every ``I < 0`` is a shadow."""
    with np.errstate(invalid="ignore"):
        a = np.subtract(i, t)
        np.maximum(a, floor, out=a)
        np.copyto(a, -np.inf, where=i <= th.shadow)
        b = np.add(i, t)
        neg = i < 0
    if neg.any():
        np.copyto(b, t, where=neg)
    return a, b


def shading(intensities: NDArray[np.floating], th: Thresholds) -> NDArray[np.float64]:
    """The value ``L.n`` should match: ``I^(1/response)`` (``I`` itself for response 1)."""
    i = np.asarray(intensities, dtype=np.float64)
    if th.response == 1.0:
        return i
    with np.errstate(invalid="ignore"):
        return np.maximum(i, 0.0) ** (1.0 / th.response)


def candidates(
    intensities: NDArray[np.floating],
    th: Thresholds,
    outlier: NDArray[np.bool_] | None = None,
    active: NDArray[np.bool_] | None = None,
    *,
    use: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """``(P, k)`` observations that may be inliers: :func:`usable`, not ``outlier``, of an
    ``active`` pixel, and not among the brightest ``drop_bright`` share of the pixel's
    candidates (``floor(drop_bright * m)`` of ``m``, never leaving fewer than 3; ties go
    to the lower image index). With ``shadow_slabs`` the :func:`shadows` are candidates too.
    ``use``: :func:`usable` of these intensities, when the caller has it already.
    """
    i = np.asarray(intensities, dtype=np.float64)
    valid = usable(i.T, th).T if use is None else use.copy()
    if th.shadow_slabs:
        valid |= shadows(i, th)
    if outlier is not None:
        valid &= ~np.asarray(outlier, dtype=bool)
    if active is not None:
        act = np.asarray(active, dtype=bool)
        if not act.all():  # (every pixel active: the solver's usual batch)
            valid &= act[:, None]
    return drop_brightest(i, valid, th.drop_bright)


def shadows(intensities: NDArray[np.floating], th: Thresholds) -> NDArray[np.bool_]:
    """``(P, k)`` finite observations at or below the shadow threshold (the one-sided slabs
    of ``shadow_slabs``); saturation thresholds above the shadow one keep them unsaturated."""
    i = np.asarray(intensities, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.isfinite(i) & (i <= th.shadow)


def drop_brightest(
    intensities: NDArray[np.floating], valid: NDArray[np.bool_], share: float
) -> NDArray[np.bool_]:
    """``valid`` without the brightest ``floor(share * m)`` of each row's ``m`` valid
    observations, never leaving fewer than 3 (ties: the lower image index is dropped first)."""
    valid = np.asarray(valid, dtype=bool)
    if share <= 0 or not valid.size:
        return valid
    i = np.asarray(intensities, dtype=np.float64)
    m = valid.sum(axis=1)
    drop = np.minimum(np.floor(share * m), np.maximum(m - 3, 0)).astype(np.int64)
    if not drop.any():
        return valid
    order = np.argsort(np.where(valid, -i, np.inf), axis=1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.broadcast_to(np.arange(i.shape[1]), i.shape), axis=1)
    return valid & (rank >= drop[:, None])


def box_halfwidth(b: NDArray[np.float64], valid: NDArray[np.bool_], box_factor: float) -> float:
    """Half-width ``U`` of the box on ``n`` for one pixel."""
    return float(box_factor * (b[valid].max() if valid.any() else 1.0))
