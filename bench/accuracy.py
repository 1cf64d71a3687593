"""Accuracy of the default model against ``--model paper`` and ``--solver l2`` (issue #21).

Prints one markdown table: mean angular error (degrees; a masked pixel without a normal
counts as 180) per scene, bit depth and number of images k, for

* ``default``: what ``maxfs run`` does with no options (``model="robust"``, ``eps="auto"``);
* ``paper``: ``--model paper`` (Yu, Seo, Lee 2010 as published, ``eps="auto"``);
* ``l2``: ``--solver l2`` under the default model (least squares on every image).

All through :func:`worker.solve.solve` (the service's path). Scenes:

* DiLiGenT cat, cow, pot1 (``../shared/data/diligent-crop8``, 8-bit floors of the 16-bit
  originals): k of the 96 images, evenly spaced in the file order;
* synthetic, 32 x 32, noise sigma 0.5 on the 0..255 scale, rendered in floats and stored as
  16-bit (``round(257 v)``) or as the 8-bit floors of that (``floor(v16 / 256)``, as the
  DiLiGenT crops were made): a sphere (attached shadows only) and a sphere sunk into a
  textured plane (``bumps``: cast shadows too), each Lambertian (``lamb``) or with a
  Torrance-Sparrow lobe (``spec``); and ``sphere indirect``: a glossy sphere whose
  downward-facing part is also lit by a white floor (a smooth indirect term that is the
  same in every image up to the light's height), the rim problem of the 16-bit DiLiGenT
  ball;
* the paper's Table 2 case on its own line: sphere, k = 12, eps = 1, 8-bit rounding, no noise.

Pixels are subsampled (a regular stride over the mask) to keep the run short; eps and the
response g are estimated on the whole mask first, as a full run does.

Run: ``python -m bench.accuracy`` (``--k 8,12``, ``--only cat,sphere-lamb``, ``--pixels N``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.worker import synthetic
from maxfs.worker.solve import solve

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

#: The methods compared, as :func:`worker.solve.solve` keywords (given in full so that
#: the bench measures the same thing whatever the library's defaults).
METHODS: dict[str, dict] = {
    "default": {"model": "robust", "eps": "auto"},
    "paper": {"model": "paper", "eps": "auto"},
    "l2": {"model": "robust", "eps": "auto", "solver": "l2"},
}
KS = (8, 12, 24, 96)
SIZE = 32
NOISE = 0.5

#: images, lights, intensities, mask, ground-truth normals
Loaded = tuple[NDArray, NDArray, NDArray | None, NDArray, NDArray]


def _diligent(name: str) -> Callable[[int, int], Loaded]:
    cache: dict[str, Loaded] = {}

    def load(k: int, bits: int) -> Loaded:
        if bits != 8:
            raise FileNotFoundError("the shared crops are 8-bit only")
        if "all" not in cache:
            import scipy.io

            from maxfs.storage.inputs import load_folder

            folder = DATA / "diligent-crop8" / f"{name}PNG"
            ds = load_folder(folder)
            images = np.stack([ds.read(i) for i in range(ds.k)])
            gt = scipy.io.loadmat(folder / "Normal_gt.mat")["Normal_gt"].astype(np.float64)
            cache["all"] = (images, ds.lights, ds.intensities, ds.mask, gt)
        images, lights, inten, mask, gt = cache["all"]
        pick = np.unique(np.round(np.linspace(0, images.shape[0] - 1, k)).astype(np.int64))
        return images[pick], lights[pick], None if inten is None else inten[pick], mask, gt

    return load


def _store(radiance: NDArray, bits: int, seed: int) -> NDArray:
    """Float radiance (0..255 scale) plus noise, as 16-bit values or their 8-bit floors."""
    rng = np.random.default_rng(seed)
    v16 = np.clip(np.round(257.0 * (radiance + rng.normal(0.0, NOISE, radiance.shape))), 0, 65535)
    return v16.astype(np.uint16) if bits == 16 else np.floor(v16 / 256.0).astype(np.uint8)


def _indirect(sc: synthetic.Scene, strength: float = 0.02) -> NDArray:
    """A white floor below the object, lit by each light, lights what faces down: a term
    ``albedo * strength * max(-n_y, 0) * L_z`` in every image, shadowed or not."""
    ny = np.nan_to_num(sc.normals[..., 1])
    return sc.albedo[None] * strength * np.maximum(-ny, 0.0)[None] * sc.lights[:, 2, None, None]


def _synthetic(kind: str, spec: bool) -> Callable[[int, int], Loaded]:
    def load(k: int, bits: int) -> Loaded:
        seed = 1000 * k + bits
        if kind == "bumps":
            sc = synthetic.bump_scene(k, SIZE, specular=40.0 if spec else 0.0, bits=None, seed=seed)
            rad = sc.images
        else:
            sc = synthetic.sphere(k, SIZE, specular=60.0 if spec else 0.0, bits=None, seed=seed)
            rad = sc.images + (_indirect(sc) if kind == "indirect" else 0.0)
        return _store(rad, bits, seed), sc.lights, None, sc.mask, sc.normals

    return load


SCENES: dict[str, tuple[Callable[[int, int], Loaded], bool]] = {
    # name: (loader, Lambertian)
    "cat": (_diligent("cat"), False),
    "cow": (_diligent("cow"), False),
    "pot1": (_diligent("pot1"), False),
    "sphere-lamb": (_synthetic("sphere", False), True),
    "sphere-spec": (_synthetic("sphere", True), False),
    "bumps-lamb": (_synthetic("bumps", False), True),
    "bumps-spec": (_synthetic("bumps", True), False),
    "sphere-indirect": (_synthetic("indirect", True), False),
}


def angular_error(normal: NDArray, gt: NDArray) -> NDArray[np.float64]:
    """Degrees; 180 where no normal was found."""
    dot = np.clip(np.sum(normal.astype(np.float64) * gt, axis=-1), -1.0, 1.0)
    err = np.degrees(np.arccos(dot))
    return np.where(np.isfinite(err), err, 180.0)


def subsample(mask: NDArray[np.bool_], pixels: int) -> NDArray[np.bool_]:
    """About ``pixels`` of the masked pixels, a regular stride in raster order."""
    ys, xs = np.nonzero(mask)
    step = max(1, ys.size // pixels)
    out = np.zeros_like(mask)
    out[ys[::step], xs[::step]] = True
    return out


def measure(load: Callable[[int, int], Loaded], k: int, bits: int, pixels: int) -> dict[str, float]:
    images, lights, inten, mask, gt = load(k, bits)
    full = np.asarray(mask, bool) & np.isfinite(gt[..., 0])
    m = subsample(full, pixels)
    out = {}
    for name, kw in METHODS.items():
        # eps and g estimated on the whole mask, as a full run does (a least-squares solve
        # of the whole mask costs little), then the subsample solved with them
        est = solve(images, lights, full, intensities=inten, **kw | {"solver": "l2"})
        fixed = {"eps": est.eps, "response": est.response}
        sol = solve(images, lights, m, intensities=inten, **kw | fixed)
        out[name] = float(angular_error(sol.normal[m], gt[m]).mean())
    return out


def table2_case() -> dict[str, float]:
    """The paper's Table 2 case: sphere, k = 12, eps = 1, 8-bit rounding, no noise."""
    sc = synthetic.sphere(k=12, size=64)
    out = {}
    for name, kw in (("default", {"model": "robust"}), ("paper", {"model": "paper"})):
        sol = solve(sc.images.astype(np.uint8), sc.lights, sc.mask, eps=1.0, **kw)
        out[name] = float(angular_error(sol.normal[sc.mask], sc.normals[sc.mask]).mean())
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--k", default=",".join(map(str, KS)), help="comma list of image counts")
    ap.add_argument("--bits", default="8,16", help="comma list of 8, 16")
    ap.add_argument("--only", default=None, help=f"comma list of {', '.join(SCENES)}")
    ap.add_argument("--pixels", type=int, default=150, help="masked pixels per scene (a regular stride)")
    args = ap.parse_args(argv)
    ks = [int(v) for v in args.k.split(",")]
    bit_depths = [int(v) for v in args.bits.split(",")]
    names = args.only.split(",") if args.only else list(SCENES)
    t0 = time.perf_counter()
    print("| scene | bits | k | default | paper | l2 | default <= l2 | default <= 1.05 paper |")
    print("|---|---|---|---|---|---|---|---|")
    real: dict[str, list[float]] = {m: [] for m in METHODS}
    for name in names:
        load, lamb = SCENES[name]
        for bits in bit_depths:
            for k in ks:
                try:
                    r = measure(load, k, bits, args.pixels)
                except FileNotFoundError:
                    continue
                if name in ("cat", "cow", "pot1") and k == 96:
                    for m in METHODS:
                        real[m].append(r[m])
                ok_l2 = "yes" if r["default"] <= r["l2"] else "**no**"
                ok_p = ("yes" if r["default"] <= 1.05 * r["paper"] else "**no**") if lamb else "-"
                cells = [name, str(bits), str(k)] + [f"{r[m]:.3f}" for m in METHODS] + [ok_l2, ok_p]
                print("| " + " | ".join(cells) + " |", flush=True)
    if all(len(v) == 3 for v in real.values()):
        means = ", ".join(f"{m} {np.mean(v):.2f}" for m, v in real.items())
        print(f"\ncat/cow/pot1 at k = 96, mean of means (subsampled pixels): {means}")
    t2 = table2_case()
    print(
        f"\nTable 2 case (sphere 64^2, k = 12, eps = 1, 8-bit): default {t2['default']:.3f} deg, "
        f"paper {t2['paper']:.3f} deg (the paper reports 0.138)"
    )
    print(f"\n({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
