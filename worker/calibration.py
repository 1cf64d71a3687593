"""Calibration checks: signs that the lights (or the mask) given with the images are wrong.

A wrong calibration does not stop the solver: it finds the best normals for the lights it is
given, proves them optimal and reports "certified". These checks look at the data and the
result for the few mistakes that are common and cheap to see. Each is a pure function over
arrays that returns a :class:`Finding` (the measured value, the threshold and a message) so
callers can both warn and print the figure (``python -m bench.calibration``).

* **lights facing away** (:func:`lights_facing`): the share of lights with ``z <= 0``. Light
  from behind the camera's side lights nothing the camera sees; a rig whose z points away
  from the camera (``z`` negated) has all of them there. Threshold: half.
* **normals facing away** (:func:`normals_facing`): the share of solved (Max-FS) normals with
  ``n_z < 0``. A surface the camera sees faces it (``n_z >= 0``); noise at silhouettes
  makes a few per cent negative. Threshold: a quarter.
* **image brightness vs light intensities** (:func:`light_checks`): on the fixed pixel sample
  of the eps estimate, each image's gain is fitted (alternating with the pixels' normals) so
  that ``g_i L_i . n`` fits the lit, unsaturated observations; with the right intensities every
  gain is 1 up to the model's misfit. The median ``|log g_i|`` is the typical error of the
  intensities; missing ones leave the rig's spread of brightness (DiLiGenT: a factor 6 between
  the dimmest and brightest light, 0.3 in this measure). Threshold: 0.15 (16 %).
* **light order** (:func:`light_checks`): a permutation test. The robust residual of the
  per-pixel fit with the given lights over the median residual with the same lights shuffled
  (:data:`PERMUTATIONS` fixed shuffles). The right order explains Lambertian data several
  times better than a random one (0.4 or less on every dataset here); lights in another order
  than the images are a random order (about 1). Threshold: 0.6. Both light checks abstain
  where the data cannot tell: fewer than :data:`MIN_LIT` images, or under half the pixels lit
  in that many (a mirror ball).
* **normals that do not integrate** (:func:`flip_integrability`): the curl of the normals'
  slope field against that of the same field with y negated. Lights with y pointing down
  (or x left) give the mirror image of the true normals, which is not the gradient of any
  surface: its curl is the true field's ``2 z_xy`` plus noise, so the mirrored field, which
  is the true one, integrates better. A sign test over the 2x2 cells: the share of cells where
  the mirror's |curl| is smaller, as sigmas above one half (right normals: 14 to 97 sigmas
  *below* on the DiLiGenT crops; y down: 15 to 97 above; shapes with ``z_xy = 0``, planes and
  cylinders, cannot tell and stay near 0). Threshold: 8 sigmas.
* **no mask** (:func:`no_mask`): without a mask every pixel is solved, including the
  background; more than 5 % of pixels dark in every image (no observation above 2 % of the
  data's 99th percentile, nor two quantisation steps) says there is one.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

#: More than this share of lights with z <= 0: the lights' z points away from the camera.
LIGHTS_BEHIND_SHARE = 0.5
#: More than this share of solved normals with n_z < 0: normals face away from the camera.
NORMALS_BEHIND_SHARE = 0.25
#: The images' brightness against the light intensities: above this median |log gain| (a
#: typical image 16 % brighter or darker than its light's intensity says), intensities are wrong.
GAIN_SPREAD = 0.15
#: The given order's residual over a random order's (median of :data:`PERMUTATIONS`): above
#: this, the order explains the data no better than chance.
ORDER_RATIO = 0.6
PERMUTATIONS = 5
#: The light checks use at most this many of the sampled pixels (evenly spread): with k images
#: that is k thousand observations, plenty for a median, and the checks stay under a second.
MAX_PIXELS = 1000
#: The checks' names (a record's calibration messages start with them).
LIGHTS_CHECK = "lights facing away"
NORMALS_CHECK = "normals facing away"
GAIN_CHECK = "image brightness vs light intensities"
ORDER_CHECK = "light order"
FLIP_CHECK = "normals integrate (y flip)"
MASK_CHECK = "no mask"
#: An observation is lit above this share of its pixel's brightest (unsaturated) one.
LIT_SHARE = 0.05
#: At least this share of the sampled pixels must have MIN_LIT lit observations.
MIN_LIT_SHARE = 0.5
#: The sign test of the normals' curl against their y-mirror's: above this many sigmas in the
#: mirror's favour, y (or x) is flipped. Far above a test's usual 3 or 5, since neighbouring
#: cells share pixels and so are fewer independent trials than the count says.
FLIP_Z = 8.0
#: Without a mask, more than this share of background-like pixels: say so.
BACKGROUND_SHARE = 0.05
#: A pixel is background-like when no image is above this share of the data's 99th percentile.
DARK_SHARE = 0.02
#: Pixels need this many lit observations to take part in the light checks (3 to fit, 3 to spare).
MIN_LIT = 6
#: Fewer sampled pixels than this: the light checks say nothing.
MIN_PIXELS = 50


@dataclass(frozen=True)
class Finding:
    """One check's outcome: ``value`` against ``threshold``; ``message`` when it trips."""

    check: str
    value: float | None  # None: the check could not be made on this data
    threshold: float
    message: str | None = None

    @property
    def tripped(self) -> bool:
        return self.message is not None


def lights_facing(lights: NDArray[np.floating]) -> Finding:
    """Share of lights whose z (toward the camera) is <= 0."""
    L = np.asarray(lights, dtype=np.float64)
    share = float(np.mean(L[:, 2] <= 0.0))
    msg = None
    if share > LIGHTS_BEHIND_SHARE:
        msg = (
            f"{share:.0%} of the lights have z <= 0, i.e. point away from the camera; z must point "
            "toward the camera (x right, y up): negate the lights' z"
        )
    return Finding(LIGHTS_CHECK, share, LIGHTS_BEHIND_SHARE, msg)


def normals_facing(normal: NDArray[np.floating], source: NDArray[np.integer] | None = None) -> Finding:
    """Share of solved normals (finite) with ``n_z < 0``; with ``source``, of the Max-FS normals
    only (a consistent Lambertian set: codes 1 and 2) where there are any. The least-squares
    fallback (code 3) fits whatever a pixel has (a mirror's glints, pure shadow) and says
    nothing about the calibration."""
    nz = np.asarray(normal)[..., 2]
    fine = np.isfinite(nz)
    if source is not None:
        maxfs = fine & np.isin(np.asarray(source), (1, 2))
        fine = maxfs if maxfs.any() else fine
    nz = nz[fine]
    if nz.size == 0:
        return Finding(NORMALS_CHECK, None, NORMALS_BEHIND_SHARE)
    share = float(np.mean(nz < 0.0))
    msg = None
    if share > NORMALS_BEHIND_SHARE:
        msg = (
            f"{share:.0%} of the solved normals face away from the camera (n_z < 0), which no "
            "visible surface does: the lights' z probably points away from the camera (negate it)"
        )
    return Finding(NORMALS_CHECK, share, NORMALS_BEHIND_SHARE, msg)


def _solve3(A: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched 3x3 solves; singular systems give zeros."""
    det = np.linalg.det(A)
    ok = np.abs(det) > 1e-12 * np.maximum(np.abs(A).max(axis=(1, 2)) ** 3, 1e-300)
    out = np.zeros(b.shape)
    if ok.any():
        out[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return out


def _fit_pixels(M: NDArray, W: NDArray, S: NDArray) -> NDArray:
    """Per-pixel weighted least squares ``M[:, p] ~ S @ b_p`` over the weighted entries; (P, 3)."""
    SS = (S[:, :, None] * S[:, None, :]).reshape(len(S), 9)
    return _solve3((W.T @ SS).reshape(-1, 3, 3), (W * M).T @ S)


def _fit_images(M: NDArray, W: NDArray, B: NDArray) -> NDArray:
    """Per-image weighted least squares ``M[i, :] ~ s_i @ B.T``; (k, 3)."""
    BB = (B[:, :, None] * B[:, None, :]).reshape(len(B), 9)
    return _solve3((W @ BB).reshape(-1, 3, 3), (W * M) @ B)


def _robust_scale(r: NDArray, on: NDArray[np.bool_]) -> float:
    """1.4826 times the median absolute ``r`` over the entries ``on`` (``W > 0``)."""
    return float(1.4826 * np.median(np.abs(r[on])))


def _trimmed(
    M: NDArray, W: NDArray, S: NDArray, rounds: int = 3, sigma: bool = True
) -> tuple[NDArray, NDArray, float | None]:
    """Fit ``B`` to fixed lights ``S``, dropping entries beyond 3 robust sigmas (specular lobes,
    cast shadows), refit; returns the pixel fits, the weights kept and the robust sigma (over all
    of ``W``: a median needs no trimming, and a sigma of the kept entries alone would shrink with
    every round; None without ``sigma``, for a caller that uses only the fits)."""
    w = W.copy()
    on = W > 0
    for _ in range(rounds):
        B = _fit_pixels(M, w, S)
        r = M - S @ B.T
        w = W * (np.abs(r) <= 3.0 * max(_robust_scale(r, on), 1e-12))
    B = _fit_pixels(M, w, S)
    return B, w, _robust_scale(M - S @ B.T, on) if sigma else None


def _prepare(grey: NDArray, usable: NDArray) -> tuple[NDArray, NDArray] | None:
    """The lit observations of pixels with at least :data:`MIN_LIT`, as ``(k, P)`` values (each
    pixel divided by its median, so dark and bright pixels weigh alike) and weights; None when
    under :data:`MIN_LIT_SHARE` of the pixels qualify (a mirror: the data cannot tell)."""
    I = np.asarray(grey, dtype=np.float64)
    lit = np.asarray(usable, dtype=bool) & np.isfinite(I)
    top = np.where(lit, I, 0.0).max(axis=1, keepdims=True)
    lit &= I > LIT_SHARE * top  # attached shadows and the clamp near them are not Lambertian
    rows = lit.sum(axis=1) >= MIN_LIT
    if I.shape[1] < MIN_LIT or rows.sum() < max(MIN_PIXELS, MIN_LIT_SHARE * len(I)):
        return None
    rows = np.flatnonzero(rows)
    rows = rows[np.linspace(0, rows.size - 1, min(rows.size, MAX_PIXELS)).astype(np.intp)]
    M = np.where(lit[rows], I[rows], 0.0).T
    W = lit[rows].T.astype(np.float64)
    return M / np.nanmedian(np.where(W > 0, M, np.nan), axis=0), W


def _gains(M: NDArray, W: NDArray, L: NDArray, rounds: int = 6) -> NDArray:
    """Each image's brightness relative to the fit with lights ``L`` (median 1): alternate the
    pixels' fit with lights ``g_i L_i`` and each image's least-squares gain over its kept entries."""
    g = np.ones(len(L))
    for _ in range(rounds):
        B, w, _ = _trimmed(M, W, L * g[:, None], rounds=1, sigma=False)
        pred = L @ B.T
        g = (w * M * pred).sum(axis=1) / np.maximum((w * pred * pred).sum(axis=1), 1e-300)
        g = np.where(g > 0, g, np.nan)
        g = g / np.nanmedian(g)
        g = np.where(np.isfinite(g), g, 1.0)
    return g


def light_checks(
    grey: NDArray[np.floating], usable: NDArray[np.bool_], lights: NDArray[np.floating]
) -> list[Finding]:
    """The lights against the data, before any solve: the images' brightness against the light
    intensities (:data:`GAIN_SPREAD`) and the order of the lights (:data:`ORDER_RATIO`).

    ``grey`` (P, k) intensities of sampled pixels after division by the light intensities,
    ``usable`` (P, k) the unsaturated observations. Findings with ``value`` None when the data
    cannot tell (fewer than 6 images, or a surface lit in few of them, such as a mirror).
    """
    L = np.asarray(lights, dtype=np.float64)
    prep = _prepare(grey, usable)
    if prep is None:
        return [Finding(GAIN_CHECK, None, GAIN_SPREAD), Finding(ORDER_CHECK, None, ORDER_RATIO)]
    M, W = prep
    g = _gains(M, W, L)
    spread = float(np.median(np.abs(np.log(g))))
    msg = None
    if spread > GAIN_SPREAD:
        worst = np.argsort(-np.abs(np.log(g)))[:3]
        shown = ", ".join(f"image {i + 1}: {g[i]:.2f}" for i in worst)
        msg = (
            f"the images' brightness does not follow the light intensities: each image is typically "
            f"{np.exp(spread):.2f} times brighter or darker than its light's given intensity ({shown}); "
            "the light intensities are probably missing (a DiLiGenT folder needs "
            "light_intensities.txt) or wrong, or the lights are in another order than the images"
        )
    gain = Finding(GAIN_CHECK, spread, GAIN_SPREAD, msg)
    # the order; on lights corrected by those gains when they are off (so missing intensities
    # do not trip it too), else as given (gains fitted to noise would only blur the test)
    Lg = L * g[:, None] if gain.tripped else L
    own = _trimmed(M, W, Lg)[2]
    rng = np.random.default_rng(0)
    shuffled = [_trimmed(M, W, Lg[rng.permutation(len(L))])[2] for _ in range(PERMUTATIONS)]
    ratio = own / max(float(np.median(shuffled)), 1e-300)
    msg = None
    if ratio > ORDER_RATIO:
        msg = (
            f"the lights explain the images hardly better than the same lights in a random order "
            f"(residual {ratio:.2f} times a shuffled order's; right lights give 0.4 or less): the "
            "lights are probably in another order than the images; check that line i of the lights "
            "file belongs to image i (filenames.txt, or the images' name order)"
        )
    return [gain, Finding(ORDER_CHECK, ratio, ORDER_RATIO, msg)]


def _curl(p: NDArray, q: NDArray, ok: NDArray) -> NDArray:
    """Discrete curl of the gradient field (dz/dc, dz/dr) over 2x2 cells whose 4 pixels are ok."""
    cell = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]
    dp_dr = 0.5 * (p[1:, :-1] + p[1:, 1:] - p[:-1, :-1] - p[:-1, 1:])
    dq_dc = 0.5 * (q[:-1, 1:] + q[1:, 1:] - q[:-1, :-1] - q[1:, :-1])
    return (dp_dr - dq_dc)[cell]


#: Slopes are used where the normal is within this of the view (n_z >= cos 60 deg).
MIN_NZ = 0.5
#: Fewer 2x2 cells than this: the integrability check says nothing.
MIN_CELLS = 100


def flip_integrability(normal: NDArray[np.floating]) -> Finding:
    """A sign test of the normals' curl against that of their y-mirror (see the module docstring):
    ``z = (share - 1/2) * 2 sqrt(N)`` over the N cells, ``share`` those where the mirror
    integrates better."""
    n = np.asarray(normal)
    ok = np.isfinite(n).all(axis=2)
    # the cells lie within the bounding box of the finite normals: the same cells, in the same order
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    if rows.size:
        box = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
        n, ok = n[box], ok[box]
    n = np.asarray(n, dtype=np.float64)
    nz = np.where(ok, n[..., 2], 1.0)
    ok &= np.abs(nz) >= MIN_NZ  # |n_z|: normals all facing away are another check's business
    nz = np.where(ok, nz, 1.0)
    p = np.where(ok, -n[..., 0] / nz, 0.0)  # dz/dx = dz/dc
    q = np.where(ok, n[..., 1] / nz, 0.0)  # dz/dr = -dz/dy (rows run down)
    given = np.abs(_curl(p, q, ok))
    if given.size < MIN_CELLS:
        return Finding(FLIP_CHECK, None, FLIP_Z)
    mirrored = np.abs(_curl(p, -q, ok))
    share = float(np.mean(given > mirrored))
    z = (share - 0.5) * 2.0 * np.sqrt(given.size)
    msg = None
    if z > FLIP_Z:
        msg = (
            f"the normals are not the slopes of a surface, but their mirror image is: it integrates "
            f"better in {share:.0%} of the pixels ({z:.0f} sigma above chance); the lights' y (or x) "
            "axis is probably flipped; lights use x right, y up (image rows run down), z toward "
            "the camera"
        )
    return Finding(FLIP_CHECK, float(z), FLIP_Z, msg)


def background_share(bright: NDArray[np.floating], level: float) -> float:
    """Share of pixels whose brightest observation is at most ``level`` (dark in every image)."""
    b = np.asarray(bright, dtype=np.float64)
    return float(np.mean(b <= level)) if b.size else 0.0


def no_mask(bright: NDArray[np.floating], level: float) -> Finding:
    """Without a mask: the share of pixels dark in every image (``bright`` (H, W): each pixel's
    brightest observation; ``level``: a value no lit surface stays under, e.g. a few noise sigmas)."""
    share = background_share(bright, level)
    msg = None
    if share > BACKGROUND_SHARE:
        msg = (
            f"no mask was given: every pixel was solved, background included ({share:.0%} of the "
            "pixels are dark in every image); give a mask (mask.png, non-zero = object) to solve the "
            "object only"
        )
    return Finding(MASK_CHECK, share, BACKGROUND_SHARE, msg)


# -- the mistakes, made on purpose (bench.calibration and the tests) --------------------------------
def _rewrite_lights(folder: Path, fn: Callable[[np.ndarray], np.ndarray]) -> None:
    p = folder / "light_directions.txt"
    np.savetxt(p, fn(np.loadtxt(p)), fmt="%.6f")


MISTAKES: dict[str, Callable[[Path], object]] = {
    "no intensities": lambda f: (f / "light_intensities.txt").unlink(),
    "misnamed intensities": lambda f: (f / "light_intensities.txt").rename(f / "light_intensity.txt"),
    "lights permuted": lambda f: _rewrite_lights(
        f, lambda L: L[np.random.default_rng(1).permutation(len(L))]
    ),
    "y down": lambda f: _rewrite_lights(f, lambda L: L * [1.0, -1.0, 1.0]),
    "z negated": lambda f: _rewrite_lights(f, lambda L: L * [1.0, 1.0, -1.0]),
    "no mask": lambda f: (f / "mask.png").unlink(),
}


def miscalibrated_copy(src: Path, dst: Path, mistake: str) -> Path:
    """A copy of the DiLiGenT folder ``src`` at ``dst`` (without its ground truth) with one mistake
    of :data:`MISTAKES`: what ``bench.calibration`` and the tests measure the checks on."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("Normal_gt.mat"))
    MISTAKES[mistake](dst)
    return dst
