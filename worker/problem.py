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


#: Largest per-pixel node budget of the exact solver (about an hour of one core per pixel).
MAX_NODES_LIMIT = 10**9
#: Largest per-pixel MILP time limit, seconds.
MAX_MILP_TIME_LIMIT = 3600.0
#: Light sets whose condition number (largest / smallest singular value of the k x 3
#: direction matrix) is above this are refused: a normal's error is amplified by about
#: this factor, and coplanar or repeated lights (rank < 3) determine no normal at all.
#: Real rigs sit far below (UW psm 6.4, DiLiGenT 3.2; lights in a 10-degree cone: ~8).
MAX_LIGHT_CONDITION = 50.0
#: Above this, loaders and the CLI warn that the light set is badly conditioned.
WARN_LIGHT_CONDITION = 20.0


def _finite_number(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not np.isfinite(v):
        raise InvalidInputError(f"{name} must be finite, got {value!r}")
    return v


def check_options(
    *,
    eps: float | None,
    shadow: float | None = None,
    saturation: float | None = None,
    box_factor: float = DEFAULT_BOX_FACTOR,
    max_nodes: int | None = None,
    milp_time_limit: float | None = None,
) -> None:
    """The one validator of solver options, used by the library, the CLI and HTTP.

    ``eps=None`` means "not known yet" (``eps="auto"`` before estimation): checks that
    need it run again when it is known (:func:`make_thresholds`). Raises
    :class:`InvalidInputError` with what is wrong and the allowed range.
    """
    if eps is not None and not _finite_number("eps", eps) > 0:
        raise InvalidInputError(f"eps must be a positive finite number or 'auto', got {eps!r}")
    if shadow is not None and not _finite_number("shadow", shadow) >= 0:
        raise InvalidInputError(f"shadow threshold must be finite and >= 0, got {shadow!r}")
    if saturation is not None:
        if not _finite_number("saturation", saturation) > 0:
            raise InvalidInputError(f"saturation must be a positive finite number, got {saturation!r}")
        low = shadow if shadow is not None else eps
        if low is not None and not saturation > low:
            which = "shadow" if shadow is not None else "eps (the default shadow threshold)"
            raise InvalidInputError(
                f"saturation ({saturation}) must be above {which} ({low}); otherwise every "
                "observation is a shadow or saturated and nothing can be solved"
            )
    if not _finite_number("box_factor", box_factor) >= 1:
        raise InvalidInputError(f"box_factor must be a finite number >= 1, got {box_factor!r}")
    if max_nodes is not None:
        if isinstance(max_nodes, bool) or not isinstance(max_nodes, (int, np.integer)):
            raise InvalidInputError(f"max_nodes must be a whole number, got {max_nodes!r}")
        if not 1 <= max_nodes <= MAX_NODES_LIMIT:
            raise InvalidInputError(f"max_nodes must be between 1 and {MAX_NODES_LIMIT}, got {max_nodes}")
    if milp_time_limit is not None:
        t = _finite_number("milp_time_limit", milp_time_limit)
        if not 0 < t <= MAX_MILP_TIME_LIMIT:
            raise InvalidInputError(
                f"milp_time_limit must be above 0 and at most {MAX_MILP_TIME_LIMIT:g} s, "
                f"got {milp_time_limit}"
            )


def make_thresholds(
    k: int,
    eps: float,
    *,
    shadow: float | None = None,
    saturation: float | ArrayLike | None = None,
    box_factor: float = DEFAULT_BOX_FACTOR,
) -> Thresholds:
    """Validate (:func:`check_options`) and build :class:`Thresholds` (``shadow`` defaults to ``eps``)."""
    scalar_sat = saturation if saturation is None or np.ndim(saturation) == 0 else None
    check_options(eps=eps, shadow=shadow, saturation=scalar_sat, box_factor=box_factor)
    shadow_v = float(eps if shadow is None else shadow)
    sat = saturation_vector(k, saturation)
    if np.any(sat <= shadow_v):
        raise InvalidInputError("saturation thresholds must be above the shadow threshold")
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


def light_singular_values(lights: ArrayLike) -> NDArray[np.float64]:
    """Singular values of the ``(k, 3)`` light matrix, largest first."""
    return np.linalg.svd(np.asarray(lights, dtype=np.float64), compute_uv=False)


def light_condition(lights: ArrayLike) -> float:
    """Condition number of the light matrix (inf when rank < 3)."""
    s = light_singular_values(lights)
    return float(s[0] / s[2]) if s.size == 3 and s[2] > 1e-12 * s[0] else float("inf")


def check_lights(lights: ArrayLike, k: int | None = None) -> NDArray[np.float64]:
    """Validate light directions: shape ``(k, 3)``, finite, unit length (1e-3), and able
    to determine a normal (rank 3, condition number at most :data:`MAX_LIGHT_CONDITION`)."""
    try:
        arr = np.asarray(lights, dtype=np.float64)
    except (ValueError, TypeError):
        raise InvalidInputError("lights must be k rows of 3 numbers each (x, y, z)") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"lights must be k rows of 3 numbers (x, y, z), got shape {arr.shape}")
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
    unit = arr / norms[:, None]
    cond = light_condition(unit) if unit.shape[0] >= 3 else float("inf")
    if not cond <= MAX_LIGHT_CONDITION:
        sv = ", ".join(f"{v:.3g}" for v in light_singular_values(unit))
        why = (
            "they are coplanar or repeated (rank < 3)"
            if not np.isfinite(cond)
            else f"their condition number is {cond:.3g} (the limit is {MAX_LIGHT_CONDITION:g})"
        )
        raise InvalidInputError(
            f"the {unit.shape[0]} light directions cannot determine a surface normal: {why}; "
            f"singular values {sv}. Lights must span 3-D: use lights from at least 3 directions "
            "that are not in one plane through the object, spread around the camera axis"
        )
    return unit
