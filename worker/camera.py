"""The pinhole camera of perspective depth, and a dataset folder's ``K.txt``.

Its own module, numpy only: ``maxfs submit`` and ``maxfs.solve_folder`` read a folder's camera before
anything is solved, and :mod:`worker.depth` loads numba (its kernels, ~0.3 s).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.errors import InvalidInputError

#: The camera intrinsics file a dataset folder may hold (3 rows of 3 numbers).
INTRINSICS_FILE = "K.txt"


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels (``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if not np.isfinite(v):
                raise InvalidInputError(f"camera {name} must be a finite number, got {v!r}")
        if not (self.fx > 0 and self.fy > 0):
            raise InvalidInputError(f"focal lengths must be > 0 pixels, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_matrix(cls, K: NDArray[np.floating]) -> Camera:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise InvalidInputError(
                f"an intrinsic matrix K must be 3 x 3 finite numbers, got shape {K.shape}"
            )
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]):
            raise InvalidInputError("K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    @classmethod
    def from_file(cls, path: Path | str) -> Camera:
        """A ``K.txt`` (3 rows of 3 numbers, as most photometric-stereo datasets with intrinsics ship it)."""
        try:
            K = np.loadtxt(path, dtype=np.float64, ndmin=2)
        except ValueError as e:
            raise InvalidInputError(
                f"{path}: cannot read an intrinsic matrix ({e}); write 3 rows of 3 numbers"
            ) from None
        return cls.from_matrix(K)

    def rays(self, H: int, W: int) -> tuple[NDArray, NDArray]:
        """``(u, v)`` of every pixel, (1, W) and (H, 1): the ray through it is ``(u, v, -1)``."""
        u = (np.arange(W, dtype=np.float64) - self.cx) / self.fx
        v = (self.cy - np.arange(H, dtype=np.float64)) / self.fy
        return u[None, :], v[:, None]


def folder_camera(folder: Path | str) -> dict[str, float]:
    """``{fx, fy, cx, cy}`` from a dataset folder's ``K.txt``, or ``{}`` when it has none."""
    p = Path(folder) / INTRINSICS_FILE
    if not p.is_file():
        return {}
    c = Camera.from_file(p)
    return {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy}
