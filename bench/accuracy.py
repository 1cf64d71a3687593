"""Accuracy of the formulations on real and synthetic objects (issue #16).

Prints one markdown table per object. Methods (all through :func:`worker.solve.solve`,
the path the service takes, default tile):

* ``l2 paper``: least squares on every image, raw input (``--model paper --solver l2``,
  today's ``--solver l2``);
* ``l2 robust``: least squares on every image with the robust model's input
  (dequantised, estimated response g) (``--solver l2`` under the default model);
* ``paper``: the paper's Max-FS with ``eps=auto`` (``--model paper``, today's default);
* ``robust``: the new default (``maxfs run`` with no options);
* with ``--ablate``: ``robust`` with one part switched off (no dequantisation, g = 1,
  no bright-image rejection, no fallback).

Errors are angular, in degrees, over the whole mask; a pixel without a normal counts
as 180. ``solved`` is the share of masked pixels with a normal, ``cert`` the share whose
Max-FS optimum is proved. Objects:

* DiLiGenT cat, cow, pot1 (``../shared/data/diligent-crop8``: 8-bit floors of the
  16-bit originals, 96 images, ``Normal_gt.mat``);
* UW psm (``../shared/data/uw-psm``, 12 images, no ground truth): solved and certified
  shares, mean inliers per pixel, the estimates;
* synthetic (known normals): a sphere with broad Torrance-Sparrow lobes, noise and
  8-bit floors; :func:`worker.synthetic.realistic_scene` (Oren-Nayar + Cook-Torrance,
  cast shadows, shot and read noise) at 8 bits, and dark (DiLiGenT-like exposure)
  as 8-bit floors of its 16-bit rendering.

Run: ``python -m bench.accuracy`` (``--quick``: every 8th masked pixel; ``--only cat,cow``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.outputs import Source
from maxfs.worker import synthetic
from maxfs.worker.solve import Solution, solve

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

METHODS: dict[str, dict] = {
    "l2 paper": {"model": "paper", "solver": "l2"},
    "l2 robust": {"model": "robust", "solver": "l2"},
    "paper": {"model": "paper", "eps": "auto"},
    "robust": {"model": "robust", "eps": "auto"},
}
ABLATIONS: dict[str, dict] = {
    "robust, no dequantise": {"model": "robust", "eps": "auto", "dequantize": False},
    "robust, g = 1": {"model": "robust", "eps": "auto", "response": 1.0},
    "robust, no bright rejection": {"model": "robust", "eps": "auto", "drop_bright": 0.0},
    "robust, no fallback": {"model": "robust", "eps": "auto", "fallback": False},
}


@dataclass(frozen=True)
class Obj:
    name: str
    load: Callable[[], tuple[NDArray, NDArray, NDArray | None, NDArray, NDArray | None]]
    # images, lights, intensities, mask, ground truth normals (None: no ground truth)


def _diligent(name: str) -> Obj:
    def load():
        import scipy.io

        from maxfs.storage.inputs import load_folder

        folder = DATA / "diligent-crop8" / f"{name}PNG"
        ds = load_folder(folder)
        images = np.stack([ds.read(i) for i in range(ds.k)])
        gt = scipy.io.loadmat(folder / "Normal_gt.mat")["Normal_gt"].astype(np.float64)
        return images, ds.lights, ds.intensities, ds.mask, gt

    return Obj(f"DiLiGenT {name}", load)


def _uw(name: str) -> Obj:
    def load():
        from maxfs.storage.inputs import load_folder

        ds = load_folder(DATA / "uw-psm" / name)
        images = np.stack([ds.read(i) for i in range(ds.k)])
        return images, ds.lights, ds.intensities, ds.mask, None

    return Obj(f"UW {name}", load)


def _to_uint8(img: NDArray) -> NDArray:
    return np.clip(img, 0, 255).astype(np.uint8)


def _synthetic(kind: str) -> Obj:
    def load():
        if kind == "sphere":
            # broad lobes on a dark diffuse sphere, noise, 8-bit floors
            sc = synthetic.sphere(
                96, 64, albedo=60.0, specular=30.0, roughness=0.2, noise=1.0, bits=None, seed=3
            )
            images = _to_uint8(np.floor(sc.images))
        elif kind == "realistic8":
            sc = synthetic.realistic_scene(96, 64, seed=1, bits=8)
            images = _to_uint8(sc.images)
        else:  # dark 16-bit rendering, kept as floor(v / 256) like the DiLiGenT crops
            sc = synthetic.realistic_scene(96, 64, seed=2, bits=16, exposure=0.15)
            images = _to_uint8(np.floor(sc.images / 256.0))
        return images, sc.lights, None, sc.mask, sc.normals

    names = {
        "sphere": "synthetic sphere, broad lobes, 8-bit floors",
        "realistic8": "synthetic realistic, 8-bit",
        "dark8": "synthetic realistic, dark, 8-bit floors",
    }
    return Obj(names[kind], load)


OBJECTS = {
    "cat": _diligent("cat"),
    "cow": _diligent("cow"),
    "pot1": _diligent("pot1"),
    **{f"uw-{n}": _uw(n) for n in ("cat", "buddha", "gray", "horse", "owl", "rock")},
    "syn-sphere": _synthetic("sphere"),
    "syn-realistic8": _synthetic("realistic8"),
    "syn-dark8": _synthetic("dark8"),
}


def angular_error(normal: NDArray, gt: NDArray) -> NDArray[np.float64]:
    """Degrees; 180 where no normal was found."""
    dot = np.clip(np.sum(normal.astype(np.float64) * gt, axis=-1), -1.0, 1.0)
    err = np.degrees(np.arccos(dot))
    return np.where(np.isfinite(err), err, 180.0)


def _row(name: str, sol: Solution, mask: NDArray, gt: NDArray | None, seconds: float, l2: bool) -> dict:
    src = sol.source[mask]
    row = {
        "method": name,
        "l2": l2,
        "solved": float(np.isfinite(sol.normal[mask][:, 0]).mean()),
        "cert": float((src == Source.CERTIFIED).mean()),
        "fit": float((src == Source.FIT).mean()),
        "inliers": float(sol.inlier_count[mask].mean() / sol.inliers.shape[0]),
        "eps": sol.eps,
        "g": sol.response,
        "s": seconds,
    }
    if gt is not None:
        err = angular_error(sol.normal[mask], gt[mask])
        row |= {"mean": float(err.mean()), "median": float(np.median(err))}
    return row


def run_object(obj: Obj, methods: dict[str, dict], quick: bool) -> tuple[list[dict], int, int]:
    images, lights, inten, mask, gt = obj.load()
    mask = np.asarray(mask if mask is not None else np.ones(images.shape[1:3], bool), bool)
    if quick:
        ys, xs = np.nonzero(mask)
        mask = np.zeros_like(mask)
        mask[ys[::8], xs[::8]] = True
    rows = []
    for name, kw in methods.items():
        t0 = time.perf_counter()
        sol = solve(images, lights, mask, intensities=inten, **kw)
        rows.append(_row(name, sol, mask, gt, time.perf_counter() - t0, kw.get("solver") == "l2"))
    return rows, int(mask.sum()), images.shape[0]


def table(title: str, rows: list[dict], pixels: int, k: int) -> str:
    has_gt = "mean" in rows[0]
    head = ["method"] + (["mean", "median"] if has_gt else []) + [
        "solved",
        "cert",
        "fit",
        "inliers/k",
        "eps",
        "g",
        "s",
    ]
    out = [f"### {title} ({pixels} pixels, k = {k})", "", "| " + " | ".join(head) + " |"]
    out.append("|" + "---|" * len(head))
    for r in rows:
        cells = [r["method"]]
        if has_gt:
            cells += [f"{r['mean']:.2f}", f"{r['median']:.2f}"]
        cells += [
            f"{r['solved']:.1%}",
            f"{r['cert']:.1%}",
            f"{r['fit']:.1%}",
            f"{r['inliers']:.2f}",
            "-" if r["l2"] else f"{r['eps']:.3g}",
            f"{r['g']:.3g}",
            f"{r['s']:.1f}",
        ]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="every 8th masked pixel")
    ap.add_argument("--only", default=None, help=f"comma list of {', '.join(OBJECTS)}")
    ap.add_argument("--ablate", action="store_true", help="also robust with one part switched off")
    args = ap.parse_args(argv)
    names = args.only.split(",") if args.only else list(OBJECTS)
    methods = METHODS | (ABLATIONS if args.ablate else {})
    summary: dict[str, dict[str, float]] = {}
    for key in names:
        obj = OBJECTS[key]
        try:
            rows, pixels, k = run_object(obj, methods, args.quick)
        except FileNotFoundError as e:
            print(f"### {obj.name}: skipped ({e})\n", flush=True)
            continue
        print(table(obj.name, rows, pixels, k) + "\n", flush=True)
        if key in ("cat", "cow", "pot1"):
            summary[key] = {r["method"]: r["mean"] for r in rows}
    if len(summary) == 3:
        print("### Mean of the three DiLiGenT objects (mean angular error)\n")
        print("| method | mean of means |\n|---|---|")
        for m in methods:
            print(f"| {m} | {np.mean([summary[o][m] for o in summary]):.2f} |")
        print("| SBL (Ikehata et al., reported) | 13.32 |")


if __name__ == "__main__":
    main()
