"""Accuracy of a normal map against ground truth: angular error statistics and an error map.

Ground truth is read from:

* a MATLAB ``.mat`` file (DiLiGenT ``Normal_gt.mat``: variable ``Normal_gt``, H x W x 3, zero outside the
  object; any single H x W x 3 variable is accepted), read with :func:`scipy.io.loadmat`;
* an ``.npy`` file, (H, W, 3) float, NaN or zero outside the object;
* a PNG/TIFF normal map coloured ``(n + 1) / 2`` in all three channels (8 or 16 bit), black outside.

The ground truth's mask is where its normal is finite and non-zero (length > 0.5). Statistics are taken
over that mask where the estimate has a normal; mask pixels without an estimate (NaN: too few usable
images) are counted in ``missing`` and left out of the statistics.

Angles are ``atan2(|a x b|, a . b)`` of the normalised vectors in float64, which stays accurate near 0 deg
(``arccos`` loses digits there).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.errors import InvalidInputError

THRESHOLDS = (5.0, 10.0, 15.0, 20.0)


@dataclass(frozen=True)
class GroundTruth:
    normal: NDArray[np.float64]  # (H, W, 3) unit, NaN outside mask
    mask: NDArray[np.bool_]  # (H, W)
    source: str


def _from_vectors(n: NDArray, source: str) -> GroundTruth:
    n = np.asarray(n, dtype=np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise InvalidInputError(f"{source}: a normal map is H x W x 3, got shape {n.shape}")
    length = np.linalg.norm(np.nan_to_num(n, nan=0.0), axis=2)
    mask = np.isfinite(n).all(axis=2) & (length > 0.5)
    if not mask.any():
        raise InvalidInputError(f"{source}: the normal map has no non-zero normal")
    unit = np.full_like(n, np.nan)
    unit[mask] = n[mask] / length[mask, None]
    return GroundTruth(unit, mask, source)


def load_ground_truth(path: Path | str) -> GroundTruth:
    """Read a ground-truth normal map (``.mat``, ``.npy``, or a ``(n+1)/2`` coloured PNG/TIFF)."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"ground truth {path} is not a file")
    suffix = path.suffix.lower()
    if suffix == ".mat":
        import scipy.io

        try:
            m = scipy.io.loadmat(path)
        except Exception as e:  # scipy raises several types for bad files
            raise InvalidInputError(f"{path}: not a readable MATLAB file ({e})") from None
        if "Normal_gt" in m:
            return _from_vectors(m["Normal_gt"], str(path))
        cands = [k for k, v in m.items() if not k.startswith("__") and np.ndim(v) == 3 and v.shape[2] == 3]
        if len(cands) != 1:
            raise InvalidInputError(
                f"{path}: expected a variable Normal_gt (or exactly one H x W x 3 variable), found "
                f"{[k for k in m if not k.startswith('__')]}"
            )
        return _from_vectors(m[cands[0]], str(path))
    if suffix == ".npy":
        from maxfs.storage.imageio import load_npy

        return _from_vectors(load_npy(path, f"ground truth {path}"), str(path))
    from maxfs.storage.imageio import read_image

    img = read_image(path)
    if img.ndim != 3:
        raise InvalidInputError(f"{path}: a normal map image must be RGB, got shape {img.shape}")
    if img.dtype == np.float32:
        v = img.astype(np.float64)
        background = ~img.any(axis=2)
    else:
        v = img.astype(np.float64) / np.iinfo(img.dtype).max
        background = ~img.any(axis=2)
    n = 2.0 * v - 1.0
    n[background] = 0.0
    return _from_vectors(n, str(path))


def angular_error_deg(est: NDArray[np.floating], truth: NDArray[np.floating]) -> NDArray[np.float64]:
    """Angle in degrees between (..., 3) vectors, each normalised first; NaN where either is undefined."""
    a = np.asarray(est, dtype=np.float64)
    b = np.asarray(truth, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = a / np.linalg.norm(a, axis=-1, keepdims=True)
        b = b / np.linalg.norm(b, axis=-1, keepdims=True)
        cross = np.linalg.norm(np.cross(a, b), axis=-1)
        dot = np.sum(a * b, axis=-1)
    return np.degrees(np.arctan2(cross, dot))


@dataclass(frozen=True)
class Evaluation:
    """Angular error statistics of an estimated normal map against ground truth."""

    mean_deg: float
    median_deg: float
    under: dict[str, float]  # "5": share of evaluated pixels with error < 5 deg, ...
    pixels: int  # ground-truth mask pixels
    evaluated: int  # of those, with an estimated normal
    missing: int  # of those, without one (not in the statistics)
    ground_truth: str = ""
    thresholds: tuple[float, ...] = field(default=THRESHOLDS)

    def to_json(self) -> dict:
        d = asdict(self)
        d["thresholds"] = list(self.thresholds)
        return d

    def summary(self) -> str:
        under = ", ".join(f"<{k} deg {v:.1%}" for k, v in self.under.items())
        # the mean is over solved pixels only: a run that leaves more unsolved looks better by it
        unsolved = (
            f" ({_share(self.missing, self.pixels)} without a normal (unsolved, or outside the job's "
            "mask), not in the mean)"
            if self.missing and self.pixels
            else ""
        )
        return (
            f"angular error over {self.evaluated} of {self.pixels} ground-truth pixels: "
            f"mean {self.mean_deg:.3f} deg{unsolved}, median {self.median_deg:.3f} deg; {under}"
        )


def _share(part: int, whole: int) -> str:
    """``part / whole`` as a percentage that reads 0 % or 100 % only when it is (4 of 9,142
    pixels evaluated is not "100.0 % unsolved")."""
    text = f"{part / whole:.1%}"
    if part < whole and text == "100.0%":
        return ">99.9%"
    if part > 0 and text == "0.0%":
        return "<0.1%"
    return text


def evaluate(
    est_normal: NDArray[np.floating],
    gt: GroundTruth,
    thresholds: tuple[float, ...] = THRESHOLDS,
) -> tuple[Evaluation, NDArray[np.float64]]:
    """Statistics and the (H, W) error map (NaN outside the ground truth's mask or without an estimate)."""
    est = np.asarray(est_normal)
    if est.shape != gt.normal.shape:
        raise InvalidInputError(
            f"the result is {est.shape[0]} x {est.shape[1]} but the ground truth {gt.source} is "
            f"{gt.normal.shape[0]} x {gt.normal.shape[1]}; they must be the same image size"
        )
    err = angular_error_deg(est, gt.normal)
    err[~gt.mask] = np.nan
    e = err[gt.mask]
    ok = np.isfinite(e)
    e = e[ok]
    if e.size == 0:
        raise InvalidInputError("no pixel of the ground truth's mask has an estimated normal")
    ev = Evaluation(
        mean_deg=float(e.mean()),
        median_deg=float(np.median(e)),
        under={f"{t:g}": float((e < t).mean()) for t in thresholds},
        pixels=int(gt.mask.sum()),
        evaluated=int(e.size),
        missing=int((~ok).sum()),
        ground_truth=gt.source,
        thresholds=tuple(thresholds),
    )
    return ev, err


# -- error map --------------------------------------------------------------------------------------------
# viridis, sampled at 11 points (matplotlib's data, public domain colour map by van der Walt and Smith)
_VIRIDIS = np.array(
    [
        [0.267, 0.005, 0.329],
        [0.283, 0.141, 0.458],
        [0.254, 0.265, 0.530],
        [0.207, 0.372, 0.553],
        [0.164, 0.471, 0.558],
        [0.128, 0.567, 0.551],
        [0.135, 0.659, 0.518],
        [0.267, 0.749, 0.441],
        [0.478, 0.821, 0.318],
        [0.741, 0.873, 0.150],
        [0.993, 0.906, 0.144],
    ]
)


def colormap(t: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Viridis colours of values in [0, 1] (clipped): (..., 3) uint8."""
    t = np.clip(np.nan_to_num(np.asarray(t, dtype=np.float64)), 0.0, 1.0)
    x = t * (len(_VIRIDIS) - 1)
    i = np.minimum(x.astype(int), len(_VIRIDIS) - 2)
    f = (x - i)[..., None]
    rgb = _VIRIDIS[i] * (1 - f) + _VIRIDIS[i + 1] * f
    return np.round(255 * rgb).astype(np.uint8)


def error_map_rgb(
    err: NDArray[np.floating], max_deg: float = 45.0, gt_mask: NDArray[np.bool_] | None = None
) -> NDArray[np.uint8]:
    """The error map with a colour bar and labelled ticks beneath it (RGB uint8).

    0..``max_deg`` maps to viridis (larger errors get the top colour); black outside the ground truth's
    mask; white where the mask has no estimated normal.
    """
    from PIL import Image, ImageDraw, ImageFont

    H, W = err.shape
    img = colormap(np.asarray(err, dtype=np.float64) / max_deg)
    outside = ~np.isfinite(err)
    img[outside] = 0
    if gt_mask is not None:
        img[gt_mask & outside] = 255
    scale = max(1, 256 // max(W, 1)) if W < 256 else 1  # enlarge small maps so the legend stays legible
    pic = Image.fromarray(img).resize((W * scale, H * scale), Image.NEAREST)
    W2, H2 = pic.size
    width = max(W2, 260)
    bar_h, pad, text_h = 14, 8, 14
    canvas = Image.new("RGB", (width, H2 + 2 * pad + bar_h + 2 * text_h + 4), (255, 255, 255))
    canvas.paste(pic, ((width - W2) // 2, 0))
    x0, x1 = pad, width - pad
    ramp = colormap(np.linspace(0.0, 1.0, x1 - x0))[None].repeat(bar_h, axis=0)
    y0 = H2 + pad
    canvas.paste(Image.fromarray(ramp), (x0, y0))
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default()
    ticks = np.linspace(0.0, max_deg, 4)
    for v in ticks:
        x = round(x0 + (x1 - x0 - 1) * float(v) / max_deg)
        draw.line([(x, y0 + bar_h), (x, y0 + bar_h + 3)], fill=(0, 0, 0))
        label = f"{v:g}" + ("+" if v == ticks[-1] else "")
        tw = draw.textlength(label, font=font)
        draw.text((min(max(x - tw / 2, 0), width - tw), y0 + bar_h + 4), label, fill=(0, 0, 0), font=font)
    caption = "angular error (deg); white: no estimate"
    tw = draw.textlength(caption, font=font)
    draw.text(((width - tw) / 2, y0 + bar_h + 4 + text_h), caption, fill=(0, 0, 0), font=font)
    return np.asarray(canvas)
