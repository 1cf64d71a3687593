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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from worker.errors import InvalidInputError

#: Default half-width of the box on ``n`` in units of the pixel's largest ``b_i``.
#: 10 admits albedos up to ten times the brightest observation (``L.N >= 0.1``).
DEFAULT_BOX_FACTOR = 10.0
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
    """

    eps: float
    shadow: float
    saturation: NDArray[np.float64]
    box_factor: float = DEFAULT_BOX_FACTOR


def make_thresholds(
    k: int,
    eps: float,
    *,
    shadow: float | None = None,
    saturation: float | ArrayLike | None = None,
    box_factor: float = DEFAULT_BOX_FACTOR,
) -> Thresholds:
    """Validate and build :class:`Thresholds` (``shadow`` defaults to ``eps``)."""
    if not np.isfinite(eps) or eps <= 0:
        raise InvalidInputError(f"eps must be a positive finite number, got {eps!r}")
    shadow_v = float(eps if shadow is None else shadow)
    if not np.isfinite(shadow_v) or shadow_v < 0:
        raise InvalidInputError(f"shadow threshold must be finite and >= 0, got {shadow!r}")
    sat = saturation_vector(k, saturation)
    if np.any(sat <= shadow_v):
        raise InvalidInputError("saturation thresholds must be above the shadow threshold")
    if not np.isfinite(box_factor) or box_factor < 1:
        raise InvalidInputError(f"box_factor must be >= 1, got {box_factor!r}")
    return Thresholds(float(eps), shadow_v, sat, float(box_factor))


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


def usable(images: NDArray[np.floating], th: Thresholds) -> NDArray[np.bool_]:
    """Observations that may be inliers: finite, above shadow, below saturation.

    ``images`` has the image axis first: ``(k, ...)``.
    """
    sat = th.saturation.reshape((-1,) + (1,) * (images.ndim - 1))
    with np.errstate(invalid="ignore"):
        return np.isfinite(images) & (images > th.shadow) & (images < sat)


def slabs(intensities: NDArray[np.floating], eps: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Slab bounds ``a = max(I - eps, eps)``, ``b = I + eps`` (paper eq. 3)."""
    i = np.asarray(intensities, dtype=np.float64)
    return np.maximum(i - eps, eps), i + eps


def box_halfwidth(b: NDArray[np.float64], valid: NDArray[np.bool_], box_factor: float) -> float:
    """Half-width ``U`` of the box on ``n`` for one pixel."""
    return float(box_factor * (b[valid].max() if valid.any() else 1.0))


def check_lights(lights: ArrayLike, k: int | None = None) -> NDArray[np.float64]:
    """Validate light directions: shape ``(k, 3)``, finite, unit length (1e-3)."""
    arr = np.asarray(lights, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"lights must have shape (k, 3), got {arr.shape}")
    if k is not None and arr.shape[0] != k:
        raise InvalidInputError(f"{arr.shape[0]} light directions for {k} images; give one per image")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError("lights contain NaN or infinite values")
    norms = np.linalg.norm(arr, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        bad = int(np.argmax(np.abs(norms - 1.0)))
        raise InvalidInputError(
            f"light {bad} has length {norms[bad]:.4f}; light directions must be unit vectors "
            "(normalise them, and put the light's strength in the intensities instead)"
        )
    return arr / norms[:, None]
