"""What researchers do with a finished job: evaluate against ground truth, integrate depth.

``maxfs eval``, ``maxfs run --gt`` and the post-run step of ``maxfs run`` call these. Files written next
to the arrays (``maxfs-eval.json``, ``previews/*.png``) are not Zarr and follow the job folder's other
non-Zarr files (record, run log, previews).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.imageio import encode_png
from maxfs.storage.layout import JobStore
from maxfs.storage.options import DepthMethod
from maxfs.worker.evaluate import Evaluation, error_map_rgb, evaluate, load_ground_truth

if TYPE_CHECKING:  # the depth module loads numba (its kernels): only where depth is made
    from maxfs.worker.depth import Camera, DepthResult

EVAL_JSON = "maxfs-eval-{gt}.json"
ERROR_MAP = "angular_error-{gt}.png"


def gt_name(gt_path: Path | str) -> str:
    """The ground truth's name in the files its evaluation writes: its folder and file name
    ("catPNG-Normal_gt"), so a second ground truth never overwrites the first one's numbers."""
    p = Path(gt_path).absolute()
    name = f"{p.parent.name}-{p.stem}" if p.parent.name else p.stem
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


DEPTH_PREVIEW = "depth.png"


def evaluate_store(
    path: Path | str,
    gt_path: Path | str,
    *,
    max_deg: float = 45.0,
    map_path: Path | str | None = None,
    json_path: Path | str | None = None,
) -> tuple[Evaluation, Path, Path]:
    """Evaluate a job store's normals against a ground-truth normal map.

    Writes the error map PNG (default ``previews/angular_error-GT.png``) and the statistics as JSON
    (default ``maxfs-eval-GT.json`` in the job folder, GT: :func:`gt_name`); returns the statistics
    and both paths.
    """
    store = JobStore.open(Path(path), mode="r")
    gt = load_ground_truth(gt_path)
    ev, err = evaluate(store.read_output("normal"), gt)
    name = gt_name(gt_path)
    map_path = Path(map_path) if map_path else store.path / "previews" / ERROR_MAP.format(gt=name)
    map_path.parent.mkdir(parents=True, exist_ok=True)
    map_path.write_bytes(encode_png(error_map_rgb(err, max_deg=max_deg, gt_mask=gt.mask)))
    json_path = Path(json_path) if json_path else store.path / EVAL_JSON.format(gt=name)
    doc = ev.to_json() | {
        "store": str(store.path),
        "ground_truth": str(Path(gt_path).absolute()),
        "error_map": str(map_path),
        "max_deg": max_deg,
    }
    counts = store.progress()  # tiles with masked pixels, as the job's record counts them
    doc["tiles_done"], doc["tiles_total"] = counts.tiles_done, counts.tiles_total
    json_path.write_text(json.dumps(doc, indent=1) + "\n")
    return ev, map_path, json_path


def find_ground_truth(folder: Path | str) -> Path | None:
    """A dataset folder's own ground truth (DiLiGenT ``Normal_gt.mat``), if it has one."""
    p = Path(folder) / "Normal_gt.mat"
    return p if p.is_file() else None


def camera_of(options: dict) -> Camera | None:
    """The perspective camera the options give (all of fx, fy, cx, cy), else None (orthographic)."""
    from maxfs.worker.camera import Camera

    if options.get("fx") is None:
        return None
    return Camera(options["fx"], options["fy"], options["cx"], options["cy"])


def write_depth(
    path: Path | str, normal: NDArray[np.floating] | None = None, **options: object
) -> DepthResult | None:
    """Integrate the store's normals (``normal``, when the caller has read them already) to ``depth``
    (H, W) float32, write it into the store (replacing an earlier one) with the method, its parameters and
    residual as its attributes, and ``previews/depth.png``.

    ``options`` are the depth options by name (``depth``, ``depth_k``, ``fx``, ``fy``, ``cx``, ``cy``,
    ``distance``, see :data:`storage.options.SOLVE_OPTIONS`); those not given are the job's. Returns None
    (and writes nothing) for ``depth="none"``.
    """
    from maxfs.service.results.previews import PNG_LEVEL
    from maxfs.storage.options import check_depth_options
    from maxfs.worker.depth import integrate, relief_rgb

    store = JobStore.open(Path(path), mode="r+")
    opts = store.params.depth_options() | {k: v for k, v in options.items() if v is not None}
    check_depth_options(**opts)
    if opts["depth"] == DepthMethod.NONE:
        return None
    camera = camera_of(opts)
    res = integrate(
        store.read_output("normal") if normal is None else normal,
        store.read_mask(),
        method=opts["depth"],
        camera=camera,
        distance=opts["distance"],
        k=opts["depth_k"],
    )
    what = (
        "height toward the camera (z), up to a constant per connected piece (mean 0)"
        if camera is None
        else "camera-frame z (x right, y up, z toward the camera: minus the distance along the axis), "
        + (
            "scaled so each piece's geometric mean distance is the given distance"
            if opts["distance"]
            else "up to a scale per connected piece (geometric mean distance 1)"
        )
    )
    store.write_depth(res.depth, res.attrs() | {"long_name": what})
    d = store.path / "previews"
    d.mkdir(exist_ok=True)
    (d / DEPTH_PREVIEW).write_bytes(encode_png(relief_rgb(res.depth), PNG_LEVEL))
    return res


def finish_results(path: Path | str, normal: NDArray[np.floating] | None = None) -> str:
    """What follows a finished run: the depth map, by the job's method (``normal`` as for
    :func:`write_depth`). Returns a note for the user."""
    res = write_depth(path, normal)
    if res is None:
        return "depth: none asked for"
    return (
        f"depth ({res.method}, {res.camera}): {res.pixels} pixels in {res.pieces} piece(s), "
        f"residual RMS {res.residual_rms:.3g} px"
    )
