"""The Python API: solve a folder or arrays with the CLI's defaults, open results as numpy.

>>> import maxfs
>>> r = maxfs.solve_folder("../shared/data/diligent-crop8/cat")   # doctest: +SKIP
>>> r.normal.shape, r.albedo.shape, r.inliers.shape                # doctest: +SKIP
((H, W, 3), (H, W), (k, H, W))

Both solve functions run the same in-process runner as ``maxfs run`` (tiles on threads, the
numba kernel releasing the GIL), so the normals are bit-identical to the command's. Without
``output`` the job store is made in a temporary folder and removed once the arrays are read;
with it, the store stays there (and a second call resumes it, exactly as ``maxfs run -o``).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from maxfs.storage.errors import InvalidInputError, MaxfsError
from maxfs.storage.options import INTRINSICS

__all__ = ["Result", "open_result", "solve", "solve_folder"]


@dataclass
class Result:
    """A finished job's per-pixel arrays, in memory (numpy), one attribute per output array of
    :data:`maxfs.storage.outputs.OUTPUT_TABLE` (an array the job does not have is None):

    ``normal``
        (H, W, 3) float32 unit normals (x right, y up, z toward the camera); NaN where unsolved.
    ``albedo``
        (H, W) float32 grey albedo in image units; 0 where unsolved (``albedo_rgb``: (H, W, C)
        per colour channel of colour input).
    ``inliers``
        (k, H, W) bool: image i obeys the Lambertian law at the pixel (the optimal inlier set);
        ``inlier_count`` (H, W) uint16 its size; ``optimal`` (H, W) bool: the optimum is proved.
    ``source``
        (H, W) uint8: 0 outside the mask, 1 optimum proved, 2 best found within the budget,
        3 least-squares fit, 4 undetermined (:class:`maxfs.storage.outputs.Source`).
    ``mask``
        (H, W) bool, the pixels that were solved.
    ``depth``
        (H, W) float32 height toward the camera, NaN outside the mask (None if not integrated).

    Besides: ``eps`` and ``response`` (what the job used, "auto" resolved), ``params`` (every
    solve parameter by name), ``warnings`` (what a user must hear about the result) and ``path``
    (the job store's folder, None when it was a temporary one).
    """

    arrays: dict[str, NDArray[Any] | None]
    eps: float | None = None
    response: float | None = None
    params: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    path: Path | None = None

    def __getattr__(self, name: str) -> Any:
        arrays = self.__dict__.get("arrays", {})
        if name in arrays:
            return arrays[name]
        raise AttributeError(f"Result has no {name!r}; its arrays: {', '.join(arrays)}")

    def __dir__(self) -> list[str]:
        return sorted({*super().__dir__(), *self.arrays})

    @property
    def N(self) -> NDArray[np.float32]:
        """The normals, as photometric stereo libraries call them."""
        return self.arrays["normal"]  # type: ignore[return-value]

    def to_xarray(self) -> Any:
        """The arrays as an ``xarray.Dataset`` with the store's dimension names and coordinates:
        ``xyz`` ("x", "y", "z"), ``image`` (1..k, as ``--images`` counts), ``channel`` ("r", "g", "b"
        for colour input), ``y`` and ``x`` (pixel rows and columns). Needs xarray
        (``pip install "maxfs-ps[research]"``)."""
        import xarray as xr

        from maxfs.storage.outputs import OUTPUTS_BY_NAME

        data = {name: (OUTPUTS_BY_NAME[name].dims, a) for name, a in self.arrays.items() if a is not None}
        sizes = {d: n for dims, a in data.values() for d, n in zip(dims, a.shape, strict=True)}
        coords: dict[str, Any] = {
            "y": np.arange(sizes["y"]),
            "x": np.arange(sizes["x"]),
            "xyz": ["x", "y", "z"],
        }
        if "image" in sizes:
            coords["image"] = np.arange(1, sizes["image"] + 1)
        if "channel" in sizes:
            c = sizes["channel"]
            coords["channel"] = ["r", "g", "b"][:c] if c <= 3 else np.arange(c)
        attrs = {"eps": self.eps, "response": self.response}
        attrs |= {f"param_{k}": str(v) for k, v in self.params.items()}
        return xr.Dataset(data, coords=coords, attrs={k: v for k, v in attrs.items() if v is not None})


def open_result(folder: str | Path) -> Result:
    """The results of a job store (a ``maxfs run -o`` folder, or a fetched server job) in memory."""
    from maxfs.storage.layout import JobStore
    from maxfs.storage.outputs import OUTPUT_TABLE
    from maxfs.storage.records import load_record

    store = JobStore.open(Path(folder), mode="r")
    present = set(store.output_names())
    arrays = {o.name: store.read_output(o.name) if o.name in present else None for o in OUTPUT_TABLE}
    try:
        warnings = load_record(store.path).warnings()
    except MaxfsError:
        warnings = []
    # what the tiles were solved with: the store's parameters (the record keeps no response)
    p = store.params
    eps, response = (p.eps, p.response) if p.resolved else (None, None)
    return Result(arrays, eps=eps, response=response, params=p.to_json(), warnings=warnings, path=store.path)


def solve_folder(
    folder: str | Path,
    output: str | Path | None = None,
    *,
    images: str | Sequence[int] | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    **options: Any,
) -> Result:
    """Solve a dataset folder (any layout ``maxfs run`` reads) exactly as ``maxfs run`` does.

    Parameters
    ----------
    folder
        The dataset folder (DiLiGenT, NPY stack, UW psm, TIFF stack or plain images + lights).
    output
        Keep the job store here (resumable, openable with :func:`open_result`); default: a
        temporary folder, removed once the arrays are read.
    images
        Use only these images: ``"1-20,25"`` or a sequence of 1-based numbers.
    workers
        Threads (default ``MAXFS_WORKERS``).
    overwrite
        Replace an ``output`` that holds other inputs or other parameters (otherwise refused).
    **options
        Solve options by the CLI's names (``eps``, ``solver``, ``model``, ``tile``, ``depth``, ``fx``,
        ...; ``maxfs run -h`` lists them); unset ones take the CLI's defaults. A ``K.txt`` in the folder
        gives the camera for perspective depth unless ``fx, fy, cx, cy`` are given.
    """
    from maxfs.storage.folders import parse_selection, select_images
    from maxfs.storage.inputs import load_folder

    ds = load_folder(folder)
    if not any(options.get(n) is not None for n in INTRINSICS):
        from maxfs.worker.camera import folder_camera

        options = dict(options) | folder_camera(folder)  # perspective depth from the folder's K.txt
    if images is not None:
        text = images if isinstance(images, str) else ",".join(str(int(i)) for i in images)
        ds = select_images(ds, parse_selection(text, ds.k))
    return _run(ds, output, workers, overwrite, options)


def solve(
    images: ArrayLike,
    lights: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    intensities: ArrayLike | None = None,
    output: str | Path | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    **options: Any,
) -> Result:
    """Solve an image stack held in memory, with the CLI's defaults and speed.

    Parameters
    ----------
    images
        (k, H, W) grey or (k, H, W, 3) colour; uint8 and uint16 are raw sensor values (a value
        at the top of the data's grid is saturated: the dtype's maximum, or its largest multiple
        of the raw step), floats are used as float32.
    lights
        (k, 3) unit light directions (x right, y up, z toward the camera).
    mask
        Optional (H, W) bool: the pixels to solve (default: all).
    intensities
        Optional (k,) or (k, C) light intensities; images are divided by them.
    output, workers, overwrite, **options
        As for :func:`solve_folder`.
    """
    from maxfs.storage.datasets import Dataset

    stack = np.asarray(images)
    if stack.ndim not in (3, 4) or (stack.ndim == 4 and stack.shape[3] not in (1, 3)):
        raise InvalidInputError(f"images must be (k, H, W) or (k, H, W, 3), got shape {stack.shape}")
    if stack.ndim == 4 and stack.shape[3] == 1:
        stack = stack[..., 0]
    if stack.dtype.kind == "f" and stack.dtype != np.float32:
        stack = stack.astype(np.float32)
    if stack.dtype.name not in ("uint8", "uint16", "float32"):
        raise InvalidInputError(f"images must be uint8, uint16 or float, got {stack.dtype}")
    k, h, w = stack.shape[:3]
    lights_arr = np.asarray(lights, dtype=np.float64)
    if lights_arr.shape != (k, 3):
        raise InvalidInputError(f"lights must be ({k}, 3) for {k} images, got shape {lights_arr.shape}")
    m = None if mask is None else np.asarray(mask).astype(bool)
    if m is not None and m.shape != (h, w):
        raise InvalidInputError(f"mask must be ({h}, {w}) like the images, got shape {m.shape}")
    inten = None if intensities is None else np.asarray(intensities, dtype=np.float64)
    if inten is not None and inten.ndim == 1:
        inten = inten[:, None]
    ds = Dataset(
        name="arrays",
        layout="arrays",
        k=k,
        height=h,
        width=w,
        channels=stack.shape[3] if stack.ndim == 4 else None,
        dtype=stack.dtype.name,
        lights=lights_arr,
        intensities=inten,
        mask=m,
        _reader=lambda i: stack[i],
    )
    return _run(ds, output, workers, overwrite, options)


def _run(
    ds: Any, output: str | Path | None, workers: int | None, overwrite: bool, options: Mapping[str, Any]
) -> Result:
    from maxfs.service.runs.local import run_folder
    from maxfs.service.settings import Settings
    from maxfs.storage.layout import JobSpec
    from maxfs.storage.records import JobState
    from maxfs.storage.requests import job_params, tile_is_auto

    settings = Settings()
    spec = JobSpec.of(ds)
    params = job_params(spec, options, settings.task_memory, ds.mask)
    temp = output is None
    out = Path(tempfile.mkdtemp(prefix="maxfs-")) / "result" if temp else Path(output)  # type: ignore[arg-type]
    try:
        store, rec = run_folder(
            ds,
            out,
            params,
            overwrite=overwrite,
            workers=workers or settings.workers,
            in_process_bytes=settings.in_process_bytes,  # larger stacks: the embedded cluster, as maxfs run
            tile_auto=tile_is_auto(options),
        )
        if rec.state is not JobState.DONE:
            raise MaxfsError(f"the job ended {rec.state.value}: {rec.error or 'no reason recorded'}")
        result = open_result(store.path)
        if temp:
            result.path = None
        return result
    finally:
        if temp:
            shutil.rmtree(out.parent, ignore_errors=True)
