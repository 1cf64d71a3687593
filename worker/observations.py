"""From raw sensor values to the intensities the solver sees.

Every path (in-process solve, Dask tile tasks) goes through
:meth:`ObservationModel.prepare`, so they see bit-identical inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from worker.errors import InvalidInputError


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
    """

    intensities: NDArray[np.float64]
    sensor_max: float | None
    channels: int | None

    @property
    def integer_valued(self) -> bool:
        return self.sensor_max is not None

    @classmethod
    def for_input(
        cls, dtype: np.dtype, k: int, channels: int | None, intensities: ArrayLike | None = None
    ) -> ObservationModel:
        """Validate the light intensities and build the model for a stack."""
        C = channels or 1
        if intensities is None:
            inten = np.ones((k, C))
        else:
            raw = np.asarray(intensities, dtype=np.float64)
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
        dt = np.dtype(dtype)
        if np.issubdtype(dt, np.integer):
            sensor_max: float | None = float(np.iinfo(dt).max)
        elif np.issubdtype(dt, np.floating):
            sensor_max = None
        else:
            raise InvalidInputError(f"images must be integer or float, got dtype {dt}")
        return cls(inten, sensor_max, channels)

    def prepare(
        self, raw: NDArray
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.bool_]]:
        """Raw ``(k, ...spatial[, C])`` to ``(P, k)`` grey, ``(P, k, C)`` colour, ``(P, k)`` saturated.

        Grey is the mean of the channels after division by the intensities
        ((R + G + B) / 3 as in the paper). An observation is saturated when any of
        its channels is at the sensor maximum.
        """
        k = raw.shape[0]
        if self.channels is None:
            vals = raw.reshape(k, -1, 1)
        else:
            vals = raw.reshape(k, -1, self.channels)
        f = vals.astype(np.float64) / self.intensities[:, None, :]
        grey = f.mean(axis=2).T
        rgb = np.ascontiguousarray(np.moveaxis(f, 0, 1)) if self.channels is not None else None
        if self.sensor_max is None:
            saturated = np.zeros(grey.shape, dtype=bool)
        else:
            saturated = (vals >= self.sensor_max).any(axis=2).T
        return np.ascontiguousarray(grey), rgb, saturated
