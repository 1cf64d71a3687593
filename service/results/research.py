"""What researchers do with a finished job: evaluate against ground truth, integrate depth.

``maxfs eval``, ``maxfs run --gt`` and the post-run step of ``maxfs run`` call these. Files written next
to the arrays (``maxfs-eval.json``, ``previews/*.png``) are not Zarr and follow the job folder's other
non-Zarr files (record, run log, previews).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.imageio import encode_png
from maxfs.storage.layout import JobStore
from maxfs.worker.depth import DepthResult, integrate, relief_rgb
from maxfs.worker.evaluate import Evaluation, error_map_rgb, evaluate, load_ground_truth

EVAL_JSON = "maxfs-eval-{gt}.json"
ERROR_MAP = "angular_error-{gt}.png"


def gt_name(gt_path: Path | str) -> str:
    """The ground truth's name in the files its evaluation writes: its folder and file name
    ("catPNG-Normal_gt"), so a second ground truth never overwrites the first one's numbers."""
    p = Path(gt_path).absolute()
    name = f"{p.parent.name}-{p.stem}" if p.parent.name else p.stem
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


DEPTH_PREVIEW = "depth.png"
#: ``maxfs run`` integrates depth by itself up to this many solved pixels (a sparse direct solve: about
#: 2 s at 0.2 MP and 13 s at 0.8 MP on one core); larger results get it from ``maxfs export``.
AUTO_DEPTH_PIXELS = 4_000_000


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
    done = store.done_grid()
    doc["tiles_done"], doc["tiles_total"] = int(done.sum()), int(done.size)
    json_path.write_text(json.dumps(doc, indent=1) + "\n")
    return ev, map_path, json_path


def find_ground_truth(folder: Path | str) -> Path | None:
    """A dataset folder's own ground truth (DiLiGenT ``Normal_gt.mat``), if it has one."""
    p = Path(folder) / "Normal_gt.mat"
    return p if p.is_file() else None


def write_depth(path: Path | str, normal: NDArray[np.floating] | None = None) -> DepthResult:
    """Integrate the store's normals (``normal``, when the caller has read them already) to ``depth``
    (H, W) float32, write it into the store (replacing an earlier one) with the method and residual as
    its attributes, and ``previews/depth.png``."""
    store = JobStore.open(Path(path), mode="r+")
    res = integrate(store.read_output("normal") if normal is None else normal, store.read_mask())
    store.write_depth(
        res.depth,
        res.attrs()
        | {
            "units": "pixels",
            "long_name": "height toward the camera (z), up to a constant per connected piece (mean 0)",
        },
    )
    d = store.path / "previews"
    d.mkdir(exist_ok=True)
    (d / DEPTH_PREVIEW).write_bytes(encode_png(relief_rgb(res.depth)))
    return res


def finish_results(path: Path | str) -> str:
    """What follows a finished run: the depth map (when not too large). Returns a note for the user."""
    normal = JobStore.open(Path(path), mode="r").read_output("normal")
    solved = int(np.isfinite(normal[..., 2]).sum())
    if solved > AUTO_DEPTH_PIXELS:
        return f"depth not integrated ({solved} pixels > {AUTO_DEPTH_PIXELS}); `maxfs export` makes it"
    res = write_depth(path, normal)
    return f"depth: {res.pixels} pixels in {res.pieces} piece(s), residual RMS {res.residual_rms:.3g} px"
