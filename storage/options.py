"""The shared vocabulary of solve options: solver and model names, defaults, limits and
the one validator (:func:`check_options`), used by the library, the CLI, HTTP and the store.

It sits at the bottom of the layers so that ``storage`` (which records the options) and
``worker`` (which computes with them) both import it; see ``tests/test_layers.py``. numpy is
imported only by the functions that check arrays: every ``maxfs`` command imports this module
(through the settings), and the client commands (``status``, ``wait``, ``fetch``, ``jobs``)
never need numpy, whose import costs ~0.15 s of each (``tests/test_layers.py`` keeps them free of it).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from maxfs.storage.errors import InvalidInputError

if TYPE_CHECKING:
    from collections.abc import Sequence

    import numpy as np
    from numpy.typing import ArrayLike, NDArray

#: Default half-width of the box on ``n`` in units of the pixel's largest ``b_i``.
#: 10 admits albedos up to ten times the brightest observation (``L.N >= 0.1``).
DEFAULT_BOX_FACTOR = 10.0
#: Pixel types of stored images (and of every loader and upload).
#: Most pixels per image (H x W) anywhere: the server's default ``MAXFS_MAX_PIXELS`` and the
#: local readers' limit (:mod:`storage.imageio`): a file declaring more is refused from its
#: header, before decoding.
MAX_PIXELS = 64_000_000
DTYPES = ("uint8", "uint16", "float32")
#: What every entry point (CLI, HTTP, ``worker.solve.solve()``, ``maxfs demo``) does with no options.
DEFAULT_EPS = "auto"
DEFAULT_MODEL = "robust"
#: Per-pixel search budget of the exact solver before it falls back to the MILP.
DEFAULT_MAX_NODES = 200_000
#: Seconds the MILP may spend on one pixel (as reference, or as fallback).
DEFAULT_MILP_TIME_LIMIT = 30.0


class Solver(StrEnum):
    """Solver names; :data:`worker.solvers.SOLVERS` maps each to its implementation."""

    EXACT = "exact"  #: branch and bound, exact and fast (default)
    MILP = "milp"  #: the paper's big-M MILP with HiGHS (reference)
    L2 = "l2"  #: Woodham least squares on every image (baseline, not robust)


class DepthMethod(StrEnum):
    """Depth integration methods (:mod:`worker.depth`)."""

    LS = "ls"  #: least squares, smooth everywhere (default)
    BINI = "bini"  #: bilateral normal integration (Cao et al. 2022): keeps depth jumps
    NONE = "none"  #: no depth


#: bini's sharpness k (the paper's default): larger keeps more jumps.
DEFAULT_DEPTH_K = 2.0
#: Camera intrinsics, in pixels: all four or none (none: orthographic).
INTRINSICS = ("fx", "fy", "cx", "cy")


class Model(StrEnum):
    """Formulations: ``paper`` (Yu, Seo, Lee 2010, as published) and ``robust``."""

    PAPER = "paper"
    ROBUST = "robust"


@dataclass(frozen=True)
class ModelDefaults:
    """What a model sets for the options a caller leaves unset (None)."""

    dequantize: bool  # integer input: add half a step to non-zero values (floors)
    response: float | str  # g, or "auto" (estimated per job)
    eps_rel: float
    shadow_per_eps: float  # shadow = this * eps
    drop_bright: float
    fallback: bool
    noise_by_intensity: bool  # eps=auto: noise where the model fits best (worker.noise)
    shadow_slabs: bool = False  # a shadow is the one-sided slab L.n <= I + t, an inlier when it holds
    mirror_deg: float = 0.0  # reject lit candidates this close to the mirror direction (worker.outliers)


#: The defaults of each model; ``robust`` was chosen by measurement (bench/accuracy.py).
MODEL_DEFAULTS = {
    Model.PAPER: ModelDefaults(False, 1.0, 0.0, 1.0, 0.0, False, False),
    Model.ROBUST: ModelDefaults(True, "auto", 0.0, 1.0 / 3.0, 0.0, True, True, True, 20.0),
}
#: Range of the response exponent g (given or estimated).
RESPONSE_RANGE = (0.2, 5.0)
#: Largest relative tolerance: past 1 the slab of an observation I reaches below 0 and above 2 I.
MAX_EPS_REL = 1.0
#: Largest share of candidates ``drop_bright`` may remove.
MAX_DROP_BRIGHT = 0.9


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


@dataclass(frozen=True)
class Estimate:
    """What a job resolves before its tiles run."""

    eps: float  # tolerance, intensity units
    response: float  # g of I = (L.n)^g
    sigma: float  # robust noise sigma the eps came from (0 when eps was given)
    quantum: int = 1  # the raw values' step (storage.observations.raw_quantum)


def _finite_number(name: str, value: object) -> float:
    # numbers.Real holds numpy's floats and integers too (numpy registers them): no numpy import
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InvalidInputError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except OverflowError:  # an integer beyond float's range (a Python int is unbounded)
        v = math.inf
    if not math.isfinite(v):
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
    model: str | None = None,
    eps_rel: float | None = None,
    response: float | str | None = None,
    drop_bright: float | None = None,
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
        # the shadow threshold in force: given, or the model's default (paper: eps, robust: eps/3)
        per = MODEL_DEFAULTS[Model(model) if model in tuple(Model) else Model.PAPER].shadow_per_eps
        low = shadow if shadow is not None else (None if eps is None else per * eps)
        if low is not None and not saturation > low:
            default = "eps" if per == 1 else f"eps/{1 / per:g}"
            which = "shadow" if shadow is not None else f"the default shadow threshold, {default},"
            raise InvalidInputError(
                f"saturation ({saturation}) must be above {which} ({low:g}); otherwise every "
                "observation is a shadow or saturated and nothing can be solved"
            )
    if not _finite_number("box_factor", box_factor) >= 1:
        raise InvalidInputError(f"box_factor must be a finite number >= 1, got {box_factor!r}")
    if max_nodes is not None:
        if isinstance(max_nodes, bool) or not isinstance(max_nodes, numbers.Integral):
            raise InvalidInputError(f"max_nodes must be a whole number, got {max_nodes!r}")
        if not 1 <= max_nodes <= MAX_NODES_LIMIT:
            raise InvalidInputError(f"max_nodes must be between 1 and {MAX_NODES_LIMIT}, got {max_nodes}")
    if model is not None and model not in tuple(Model):
        raise InvalidInputError(f"unknown model {model!r}; choose one of {', '.join(Model)}")
    if eps_rel is not None and not 0 <= _finite_number("eps_rel", eps_rel) <= MAX_EPS_REL:
        raise InvalidInputError(
            f"eps_rel must be between 0 and {MAX_EPS_REL:g} (a tolerance of eps + eps_rel * I; at 1 "
            f"an image may be off by its whole value), got {eps_rel!r}"
        )
    if response is not None and response != "auto":
        lo_g, hi_g = RESPONSE_RANGE
        if isinstance(response, str) or not lo_g <= _finite_number("response", response) <= hi_g:
            raise InvalidInputError(
                f"response must be 'auto' or a number between {lo_g:g} and {hi_g:g}, got {response!r}"
            )
    if drop_bright is not None and not 0 <= _finite_number("drop_bright", drop_bright) <= MAX_DROP_BRIGHT:
        raise InvalidInputError(f"drop_bright must be between 0 and {MAX_DROP_BRIGHT:g}, got {drop_bright!r}")
    if milp_time_limit is not None:
        t = _finite_number("milp_time_limit", milp_time_limit)
        if not 0 < t <= MAX_MILP_TIME_LIMIT:
            raise InvalidInputError(
                f"milp_time_limit must be above 0 and at most {MAX_MILP_TIME_LIMIT:g} s, "
                f"got {milp_time_limit}"
            )


def check_depth_options(
    *,
    depth: str = DepthMethod.LS.value,
    depth_k: float = DEFAULT_DEPTH_K,
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    distance: float | None = None,
) -> None:
    """The validator of the depth options (method, bini's k, camera intrinsics, distance)."""
    if depth not in tuple(DepthMethod):
        raise InvalidInputError(f"unknown depth method {depth!r}; choose one of {', '.join(DepthMethod)}")
    if not _finite_number("depth_k", depth_k) > 0:
        raise InvalidInputError(f"depth_k must be a positive number (bini's sharpness; 2), got {depth_k!r}")
    given = {n: v for n, v in zip(INTRINSICS, (fx, fy, cx, cy), strict=True) if v is not None}
    if given and len(given) < 4:
        missing = ", ".join(n for n in INTRINSICS if n not in given)
        raise InvalidInputError(
            f"perspective depth needs all of fx, fy, cx, cy (pixels); {missing} missing. Give all four, "
            "or put the 3 x 3 intrinsic matrix in the dataset folder as K.txt"
        )
    for n, v in given.items():
        _finite_number(n, v)
    for n in ("fx", "fy"):
        if n in given and not given[n] > 0:
            raise InvalidInputError(f"{n} (focal length in pixels) must be > 0, got {given[n]!r}")
    if distance is not None:
        if not _finite_number("distance", distance) > 0:
            raise InvalidInputError(f"distance must be a positive number (camera units), got {distance!r}")
        if not given:
            raise InvalidInputError(
                "distance sets the scale of perspective depth: give the camera (fx, fy, cx, cy or K.txt) too"
            )


def light_singular_values(lights: ArrayLike) -> NDArray[np.float64]:
    """Singular values of the ``(k, 3)`` light matrix, largest first."""
    import numpy as np

    return np.linalg.svd(np.asarray(lights, dtype=np.float64), compute_uv=False)


def light_condition(lights: ArrayLike) -> float:
    """Condition number of the light matrix (inf when rank < 3)."""
    s = light_singular_values(lights)
    return float(s[0] / s[2]) if s.size == 3 and s[2] > 1e-12 * s[0] else float("inf")


def check_lights(lights: ArrayLike, k: int | None = None, rows: Sequence[str] = ()) -> NDArray[np.float64]:
    """Validate light directions: shape ``(k, 3)``, finite, unit length (1e-3), and able
    to determine a normal (rank 3, condition number at most :data:`MAX_LIGHT_CONDITION`).
    ``rows``: where each light came from (``"line 4"`` of a file), named in the messages."""
    import numpy as np

    def light(i: int) -> str:
        # numbered from 1, as images are (``--images``, "image 3 (003.png)")
        return f"light {i + 1}" + (f" ({rows[i]})" if i < len(rows) else "")

    try:
        arr = np.asarray(lights, dtype=np.float64)
    except (ValueError, TypeError):
        raise InvalidInputError("lights must be k rows of 3 numbers each (x, y, z)") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"lights must be k rows of 3 numbers (x, y, z), got shape {arr.shape}")
    if k is not None and arr.shape[0] != k:
        raise InvalidInputError(f"{arr.shape[0]} light directions for {k} images; give one per image")
    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        bad = int(np.argmin(finite))
        raise InvalidInputError(f"{light(bad)} contains NaN or infinite values; give three finite numbers")
    norms = np.linalg.norm(arr, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        bad = int(np.argmax(np.abs(norms - 1.0) > 1e-3))  # the first, as a reader of the file meets it
        raise InvalidInputError(
            f"{light(bad)} has length {norms[bad]:.4f}; light directions must be unit vectors "
            "(normalise them, and put the light's strength in the intensities instead)"
        )
    # normalise once: dividing unit vectors again can move them by an ulp, and the stored
    # lights must digest the same however often they were validated
    unit = arr if np.all(np.abs(norms - 1.0) <= 1e-12) else arr / norms[:, None]
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


@dataclass(frozen=True)
class Option:
    """One solve option as users give it: the CLI's flags (``service.cli.main``) and the HTTP
    ``POST /jobs`` fields (``service.http.models.CreateJob``) are generated from these rows, and
    :meth:`storage.params.JobParams.build` takes them by name and validates them
    (:func:`check_options`). Adding an option is a row here, a field of ``JobParams``, a
    check in :func:`check_options` and its use in ``worker``.

    ``kind`` is ``"float"``, ``"int"``, ``"bool"``, ``"choice"`` (one of ``choices``) or
    ``"float|auto"`` / ``"int|auto"`` (a number or the word ``auto``). ``default`` is what an
    unset option means to a user (None: ``JobParams.build``'s default, for the model's options
    the model's value, :data:`MODEL_DEFAULTS`).
    """

    name: str
    kind: str
    help: str
    default: Any = None
    choices: tuple[str, ...] = ()

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")


#: Every solve option, in the order the CLI's help and the OpenAPI schema list them.
SOLVE_OPTIONS: tuple[Option, ...] = (
    Option("eps", "float|auto", "Lambertian tolerance, or auto (estimated from the data)", DEFAULT_EPS),
    Option(
        "solver",
        "choice",
        "exact (branch and bound, proves each optimum), milp (the paper's MILP) or l2 (least squares)",
        "exact",
        tuple(s.value for s in Solver),
    ),
    Option(
        "tile",
        "int|auto",
        "tile edge in pixels (8-4096), or auto: from k, the task memory and (maxfs run) the mask",
        "auto",
    ),
    Option("shadow", "float", "intensities <= this are shadows (default: the model's, eps or eps/3)"),
    Option(
        "saturation",
        "float",
        "grey values >= this are saturated (integer input is also saturated at the top of its grid: the "
        "dtype's maximum, or its largest multiple of the raw step, e.g. 65520 for 12-bit data shifted)",
    ),
    Option(
        "box_factor", "float", f"box on n as a multiple of the brightest value (>= 1; {DEFAULT_BOX_FACTOR:g})"
    ),
    Option("max_nodes", "int", f"exact solver's node budget per pixel (1 to 1e9; {DEFAULT_MAX_NODES})"),
    Option("milp_time_limit", "float", f"MILP seconds per pixel (0 to 3600; {DEFAULT_MILP_TIME_LIMIT:g})"),
    Option(
        "model",
        "choice",
        "robust (dequantised input, response and eps estimated, shadows as one-sided slabs, "
        "near-mirror highlights rejected, a fallback fit) or paper (Yu, Seo, Lee 2010 as published)",
        DEFAULT_MODEL,
        tuple(m.value for m in Model),
    ),
    Option("response", "float|auto", "g of I = (L.n)^g, or auto (robust: auto; paper: 1)"),
    Option("eps_rel", "float", "tolerance eps + eps_rel * I (default 0)"),
    Option(
        "drop_bright", "float", "share of each pixel's brightest candidates that are outliers (default 0)"
    ),
    Option("dequantize", "bool", "integer input: read v > 0 as v + q/2, q the raw step (robust: true)"),
    Option("fallback", "bool", "least squares where Max-FS gives no normal (robust: true)"),
    Option(
        "depth",
        "choice",
        "depth from the normals after the run: ls (least squares: smooth objects), bini (bilateral "
        "normal integration: keeps depth jumps at occlusions, slower) or none",
        DepthMethod.LS.value,
        tuple(m.value for m in DepthMethod),
    ),
    Option("depth_k", "float", "bini's sharpness k (> 0): larger keeps more jumps", DEFAULT_DEPTH_K),
    Option("fx", "float", "perspective depth: focal length along x in pixels (with fy, cx, cy; or K.txt)"),
    Option("fy", "float", "perspective depth: focal length along y in pixels"),
    Option("cx", "float", "perspective depth: principal point, column in pixels"),
    Option("cy", "float", "perspective depth: principal point, row in pixels"),
    Option(
        "distance",
        "float",
        "perspective depth: the object's mean distance from the camera, in the units the depth should "
        "have (default: relative depth)",
    ),
)
