"""From raw sensor values to the intensities the solver sees.

Every path (in-process solve, Dask tile tasks) goes through
:meth:`ObservationModel.prepare`, so they see bit-identical inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from maxfs.storage.errors import InvalidInputError

#: Accepted light intensities: relative brightnesses; outside this range dividing the images by
#: them under- or overflows what the tolerance and the response estimate can represent.
INTENSITY_RANGE = (1e-6, 1e6)


@dataclass(frozen=True)
class ObservationModel:
    """How raw values of one stack become grey intensities.

    Attributes
    ----------
    intensities
        (k, C) light intensities per image and channel (C = 1 for grey input).
    sensor_max
        The dtype's maximum for integer input (a raw value there is saturated),
        or None for float input.
    channels
        None for grey input, else the number of colour channels.
    dequantize
        Integer input only: a raw value ``v > 0`` is read as ``v + 0.5``, the middle of
        the interval ``[v, v + 1)`` it stands for when the sensor (or a conversion such as
        16 -> 8 bits by ``v >> 8``) truncates. Zero stays zero (a shadow); saturation
        is decided on the raw value. Measured on the 8-bit DiLiGenT crops: mean error
        cat 7.1 -> 6.5, pot1 9.3 -> 7.7 (bench/accuracy.py).
    """

    intensities: NDArray[np.float64]
    sensor_max: float | None
    channels: int | None
    dequantize: bool = False

    @property
    def integer_valued(self) -> bool:
        return self.sensor_max is not None

    @property
    def step(self) -> float | None:
        """One raw step in grey units (the median over images of ``mean_c 1/intensity``),
        None for float input: the scale of the quantisation error."""
        if self.sensor_max is None:
            return None
        return float(np.median((1.0 / self.intensities).mean(axis=1)))

    @classmethod
    def for_input(
        cls,
        dtype: np.dtype,
        k: int,
        channels: int | None,
        intensities: ArrayLike | None = None,
        dequantize: bool = False,
    ) -> ObservationModel:
        """Validate the light intensities and build the model for a stack."""
        C = channels or 1
        if intensities is None:
            inten = np.ones((k, C))
        else:
            try:
                raw = np.asarray(intensities, dtype=np.float64)
            except (ValueError, TypeError, OverflowError):  # words, ragged rows, ints beyond a float
                raise InvalidInputError(
                    f"light intensities must be numbers, one per image (or per image and channel), "
                    f"got {str(intensities)[:80]}"
                ) from None
            if raw.ndim == 1:
                raw = raw[:, None]
            if raw.shape[0] != k or raw.shape[1] not in (1, C):
                raise InvalidInputError(
                    f"light intensities have shape {np.asarray(intensities).shape}; "
                    f"give one value per image ({k},) or one per image and channel ({k}, {C})"
                )
            inten = np.broadcast_to(raw, (k, C)).copy()
        if not np.all(np.isfinite(inten)) or np.any(inten <= 0):
            raise InvalidInputError("light intensities must be finite and positive")
        lo, hi = INTENSITY_RANGE
        if np.any(inten < lo) or np.any(inten > hi):
            raise InvalidInputError(
                f"light intensities must be between {lo:g} and {hi:g} (each light's brightness, "
                f"relative: the images are divided by them), got {inten.min():g} to {inten.max():g}; "
                "scale them, e.g. divide them all by the largest"
            )
        dt = np.dtype(dtype)
        if np.issubdtype(dt, np.integer):
            sensor_max: float | None = float(np.iinfo(dt).max)
        elif np.issubdtype(dt, np.floating):
            sensor_max = None
        else:
            raise InvalidInputError(f"images must be integer or float, got dtype {dt}")
        return cls(inten, sensor_max, channels, bool(dequantize) and sensor_max is not None)

    def prepare(
        self, raw: NDArray, pixels: NDArray[np.intp] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.bool_]]:
        """Raw ``(k, ...spatial[, C])`` to ``(P, k)`` grey, ``(P, k, C)`` colour, ``(P, k)`` saturated.

        Grey is the mean of the channels after division by the intensities
        ((R + G + B) / 3 as in the paper). An observation is saturated when any of
        its channels is at the sensor maximum. ``pixels``: only these (flat, raster-order)
        spatial positions, in this order, as ``prepare(raw.reshape(k, -1[, C])[:, pixels])``.
        """
        C = self.channels or 1
        # pixel-major first, in the raw dtype (2 bytes a value, not 8), one channel group at a
        # time: every later pass is then contiguous and grey, rgb and saturated come out in
        # their final (P, k) layout without a float64 transpose (same values, same arithmetic)
        v = _pixel_major(raw if self.channels is not None else raw[..., None], pixels)
        f = v.astype(np.float64)  # always a copy: ``v`` may be ``raw`` itself (one pixel)
        if self.dequantize:
            # + 0.5 where v > 0 (adding 0.0 elsewhere, as before, changed nothing)
            np.add(f, 0.5, out=f, where=v > 0)
        f /= self.intensities[None, :, :]
        # grey input: the one channel itself (a view; x / 1 is x); colour: grey is a new array
        grey = f.reshape(f.shape[:2]) if self.channels is None else _channel_mean(f)
        if self.sensor_max is None:
            # numpy's mean sums from +0.0, so it never returned -0.0; only float input has any
            grey += 0.0
        rgb = f if self.channels is not None else None
        if self.sensor_max is None:
            saturated = np.zeros(grey.shape, dtype=bool)
        else:
            saturated = v[..., 0] >= self.sensor_max
            for c in range(1, C):
                saturated |= v[..., c] >= self.sensor_max
        return grey, rgb, saturated


def _pixel_major(vals: NDArray, pixels: NDArray[np.intp] | None = None) -> NDArray:
    """``(k, ...spatial, C)`` (any strides) as a C-contiguous ``(P, k, C)`` array of the same
    dtype, of the flat spatial positions ``pixels`` only if given: gathered and transposed in
    one copy, from a tile's view of the stack as it is (no copy of the whole tile first).
    Several channels move as one opaque item (a void view of the C values, where they are
    adjacent): numpy's copy is then one element per observation instead of C, 2x faster for RGB."""
    k, spatial, C = vals.shape[0], vals.shape[1:-1], vals.shape[-1]
    items = vals
    if C > 1 and vals.strides[-1] == vals.itemsize:
        try:
            items = vals.view(np.dtype((np.void, vals.itemsize * C)))  # (k, ...spatial, 1)
        except ValueError:  # a layout numpy will not reinterpret: value by value, as numbers
            items = vals
    t = np.moveaxis(items, 0, -2)  # (...spatial, k, 1 or C)
    if pixels is None:
        out = np.ascontiguousarray(t).reshape(-1, k, t.shape[-1])
    else:
        out = t[np.unravel_index(pixels, spatial)] if len(spatial) > 1 else t[pixels]
    return out.view(vals.dtype) if items is not vals else out


def _channel_mean(f: NDArray[np.float64]) -> NDArray[np.float64]:
    """``f.mean(axis=2)`` of ``(P, k, C)`` bit for bit but for the sign of a zero (numpy's sum starts
    from +0.0; the caller adds it where a -0.0 can occur): numpy reduces a short last axis (fewer
    than 8, its pairwise sum's block) left to right, then divides by C; spelled out, the sums run
    on whole (P, k) planes instead of a 3-long inner loop per value (4x faster for RGB)."""
    C = f.shape[2]
    if C == 1:
        return f[..., 0].copy()  # x / 1 is x
    if C >= 8:
        return f.mean(axis=2)
    grey = f[..., 0] + f[..., 1]
    for c in range(2, C):
        grey += f[..., c]
    grey /= C
    return grey
