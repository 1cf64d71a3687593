"""From raw sensor values to the intensities the solver sees.

Every path (in-process solve, Dask tile tasks) goes through
:meth:`ObservationModel.prepare`, so they see bit-identical inputs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from maxfs.storage.errors import InvalidInputError

#: A raw step above 1 is taken only when at least this many distinct non-zero values share it:
#: data with steps of 1 put 8 distinct values on multiples of 2 by chance with odds 1/256, and
#: data so dark that the sample holds fewer levels than that tell nothing (the 8-bit DiLiGenT
#: pot1 crop at k = 8 holds 31).
QUANTUM_EVIDENCE = 8
#: The step is looked for in this many runs of the values (a stray value spoils one run)...
QUANTUM_CHUNKS = 64
#: ...and taken when at most this share of the values is off its grid.
OFF_GRID = 1e-3

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
    channels
        None for grey input, else the number of colour channels.
    dequantize
        Integer input only: a raw value ``v > 0`` is read as ``v + q / 2`` (``q`` =
        ``quantum``), the middle of the interval ``[v, v + q)`` it stands for when the
        sensor (or a conversion such as 16 -> 8 bits by ``v >> 8``) truncates. Zero stays
        zero (a shadow); saturation is decided on the raw value. Measured on the 8-bit
        DiLiGenT crops: mean error cat 7.1 -> 6.5, pot1 9.3 -> 7.7 (bench/accuracy.py).
    quantum
        Integer input only: the raw values' step (:func:`raw_quantum`), 1 for data that
        use every value of the dtype; 16 for 12-bit data shifted into 16 bits, 256 for
        8-bit data shifted, 257 for 8-bit data scaled to 16 bits (``v * 257``). It sets
        the dequantisation, the quantisation step (:attr:`step`) and the saturation level,
        so a stack gives the same normals in any container its values fit.
    dtype_max
        The dtype's maximum for integer input, None for float input.
    """

    intensities: NDArray[np.float64]
    channels: int | None
    dequantize: bool = False
    quantum: int = 1
    dtype_max: int | None = None

    @property
    def sensor_max(self) -> float | None:
        """For integer input the top of the data's grid, the largest multiple of ``quantum``
        the dtype holds (a raw value there is saturated); None for float input."""
        return None if self.dtype_max is None else float(self.dtype_max // self.quantum * self.quantum)

    @property
    def integer_valued(self) -> bool:
        return self.dtype_max is not None

    @property
    def step(self) -> float | None:
        """One raw step in grey units (``quantum`` times the median over images of
        ``mean_c 1/intensity``), None for float input: the scale of the quantisation error."""
        if self.dtype_max is None:
            return None
        return self.quantum * float(np.median((1.0 / self.intensities).mean(axis=1)))

    @classmethod
    def for_input(
        cls,
        dtype: np.dtype,
        k: int,
        channels: int | None,
        intensities: ArrayLike | None = None,
        dequantize: bool = False,
        quantum: int = 1,
    ) -> ObservationModel:
        """Validate the light intensities and build the model for a stack (``quantum``:
        the raw step, :func:`raw_quantum`; ignored for float input)."""
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
            top: int | None = int(np.iinfo(dt).max)
        elif np.issubdtype(dt, np.floating):
            top = None
        else:
            raise InvalidInputError(f"images must be integer or float, got dtype {dt}")
        return cls(inten, channels, bool(dequantize) and top is not None, 1, top).with_quantum(quantum)

    def with_quantum(self, quantum: int) -> ObservationModel:
        """This model for raw values on a grid of step ``quantum`` (float input: itself)."""
        if self.dtype_max is None:
            return self
        q = int(quantum)
        if not 1 <= q <= self.dtype_max:
            raise InvalidInputError(f"the raw step must be between 1 and {self.dtype_max}, got {q}")
        return replace(self, quantum=q)

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
            # + q/2 where v > 0 (adding 0.0 elsewhere, as before, changed nothing)
            np.add(f, 0.5 * self.quantum, out=f, where=v > 0)
        f /= self.intensities[None, :, :]
        # grey input: the one channel itself (a view; x / 1 is x); colour: grey is a new array
        grey = f.reshape(f.shape[:2]) if self.channels is None else _channel_mean(f)
        top = self.sensor_max
        if top is None:
            # numpy's mean sums from +0.0, so it never returned -0.0; only float input has any
            grey += 0.0
        rgb = f if self.channels is not None else None
        if top is None:
            saturated = np.zeros(grey.shape, dtype=bool)
        else:
            saturated = v[..., 0] >= top
            for c in range(1, C):
                saturated |= v[..., c] >= top
        return grey, rgb, saturated


def raw_quantum(raw: NDArray) -> int:
    """The step of integer raw values: the grid nearly all of them lie on, or 1.

    Cameras with 10, 12 or 14 bits often store them in 16-bit files shifted left (every
    value a multiple of 64, 16 or 4), and 8-bit data converted to 16 bits are multiples of
    256 (shifted) or 257 (scaled). Such a stack quantises as coarsely as its source: its
    truncation error is up to a whole step, not one unit, and it saturates at the grid's
    top (65520 for 12 bits shifted).

    Zeros and values at the dtype's maximum say nothing about the grid (a converter may
    write clipped highlights as 65535) and are left out. The step is the greatest common
    divisor of most of :data:`QUANTUM_CHUNKS` runs of the rest, taken when at least
    ``1 - OFF_GRID`` of the values lie on it (a hot pixel or a stray value does not turn it
    off; one image of 96 left unshifted does) and :data:`QUANTUM_EVIDENCE` distinct values
    share it. Float input, or too little evidence, gives 1.
    """
    a = np.asarray(raw)
    if not np.issubdtype(a.dtype, np.integer):
        return 1
    v = a.ravel()
    v = v[(v != 0) & (v != np.iinfo(a.dtype).max)]
    if v.size == 0:
        return 1
    gcds = [int(np.gcd.reduce(c)) for c in np.array_split(v, min(QUANTUM_CHUNKS, v.size))]
    values, counts = np.unique(gcds, return_counts=True)
    q = int(values[np.argmax(counts)])  # the most common; ties to the smaller step
    if q <= 1:
        return 1
    on = v % q == 0
    if np.count_nonzero(on) < (1.0 - OFF_GRID) * v.size:
        return 1
    # distinct values among the first 64 k on the grid: enough to see 8, and a few ms at any k
    return q if np.unique(v[on][: 1 << 16]).size >= QUANTUM_EVIDENCE else 1


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
