"""The same values in other containers: does a stack give the same normals in any file type its
values fit (the raw step, :func:`storage.observations.raw_quantum`)?

Prints one markdown table: mean angular error (degrees) of the default model (``maxfs run`` with
no options) per scene and k, for

* the 8-bit scenes of :mod:`bench.accuracy` (the DiLiGenT crops, and the glossy synthetic scenes
  stored as 8-bit floors) as 8-bit files, shifted into 16 bits (``v << 8``) and scaled to 16 bits
  (``v * 257``, as image converters do);
* the glossy synthetic scenes as 16-bit files, their 12-bit floors shifted into 16 bits (``v16 >> 4 << 4``,
  as 12-bit cameras write them) and unshifted (``v16 >> 4``, values 0..4095 in a 16-bit file).

Within a group the first three columns must be equal; the 12-bit ones are another stack (coarser
values) and may differ from the 16-bit one. Same protocol as :mod:`bench.accuracy` (eps and the
response estimated on the whole mask, a regular subsample of pixels solved).

Run: ``python -m bench.containers`` (``--k 8,12``, ``--only pot1,sphere-spec``, ``--pixels N``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from bench.accuracy import SCENES, angular_error, subsample
from maxfs.worker.solve import solve

KS = (8, 12, 24)
NAMES = ("cat", "cow", "pot1", "sphere-spec", "bumps-spec")

#: column name: (bit depth the scene is loaded at, conversion of its stack)
CONTAINERS: dict[str, tuple[int, Callable[[NDArray], NDArray]]] = {
    "8-bit file": (8, lambda a: a),
    "8 bits << 8": (8, lambda a: a.astype(np.uint16) << 8),
    "8 bits * 257": (8, lambda a: a.astype(np.uint16) * 257),
    "16-bit file": (16, lambda a: a),
    "12 bits << 4": (16, lambda a: (a >> 4) << 4),
    "12 bits unshifted": (16, lambda a: a >> 4),
}


def error(
    images: NDArray, lights: NDArray, inten: NDArray | None, full: NDArray, m: NDArray, gt: NDArray
) -> float:
    est = solve(images, lights, full, intensities=inten, solver="l2")
    sol = solve(images, lights, m, intensities=inten, eps=est.eps, response=est.response)
    return float(angular_error(sol.normal[m], gt[m]).mean())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--k", default=",".join(map(str, KS)), help="comma list of image counts")
    ap.add_argument("--only", default=",".join(NAMES), help=f"comma list of {', '.join(SCENES)}")
    ap.add_argument("--pixels", type=int, default=1500, help="masked pixels per scene (a regular stride)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    print("| scene | k | " + " | ".join(CONTAINERS) + " |")
    print("|---|---|" + "---|" * len(CONTAINERS))
    for name in args.only.split(","):
        load = SCENES[name][0]
        for k in (int(v) for v in args.k.split(",")):
            cells = []
            for bits, convert in CONTAINERS.values():
                try:
                    images, lights, inten, mask, gt = load(k, bits)
                except FileNotFoundError:  # the DiLiGenT crops are 8-bit only
                    cells.append("-")
                    continue
                full = np.asarray(mask, bool) & np.isfinite(gt[..., 0])
                cells.append(
                    f"{error(convert(images), lights, inten, full, subsample(full, args.pixels), gt):.3f}"
                )
            print(f"| {name} | {k} | " + " | ".join(cells) + " |", flush=True)
    print(f"\n({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
