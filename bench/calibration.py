"""The calibration checks (:mod:`worker.calibration`) on good and deliberately broken data.

Each dataset is run as ``maxfs run`` runs it (its folder read by the one loader, the CLI's default
options, solved in process), then every check is measured on the result. Broken variants are copies
of a DiLiGenT crop with one calibration mistake each:

* ``no intensities``: ``light_intensities.txt`` deleted; ``misnamed intensities``: renamed to
  ``light_intensity.txt``;
* ``lights permuted``: the rows of ``light_directions.txt`` in a random order; ``y down``: y negated;
  ``z negated``: z negated;
* ``no mask``: ``mask.png`` deleted (every pixel, background included, is solved).

Good data: the DiLiGenT crops cat, cow, pot1, the UW psm objects, and synthetic scenes of
:mod:`worker.synthetic` (sphere, bumps with cast shadows, realistic; several k).

A cell is the check's value, ``!`` when it trips (``-``: the data cannot tell); ``folder`` counts the
loader's notes about the folder (unknown or missing calibration files). The last column is the verdict
``maxfs run`` records.

Run: ``python -m bench.calibration`` (``--quick``: cat and its broken copies, two UW objects, two
synthetic scenes; ``--objects cat,cow``: the DiLiGenT crops to break).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from storage.datasets import Dataset, load_folder, write_npy_folder
from worker import calibration, synthetic

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
UW_OBJECTS = ("buddha", "cat", "chrome", "gray", "horse", "owl", "rock")
CHECKS = (
    "lights facing away",
    calibration.GAIN_CHECK,
    calibration.ORDER_CHECK,
    "normals facing away",
    "normals integrate (y flip)",
    "no mask",
)
SHORT = {
    "lights facing away": "lights z<=0",
    calibration.GAIN_CHECK: "gain spread",
    calibration.ORDER_CHECK: "order ratio",
    "normals facing away": "normals nz<0",
    "normals integrate (y flip)": "curl ratio",
    "no mask": "dark share",
}


def _rewrite_lights(folder: Path, fn: Callable[[np.ndarray], np.ndarray]) -> None:
    p = folder / "light_directions.txt"
    np.savetxt(p, fn(np.loadtxt(p)), fmt="%.6f")


BREAKS: dict[str, Callable[[Path], None]] = {
    "no intensities": lambda f: (f / "light_intensities.txt").unlink(),
    "misnamed intensities": lambda f: (f / "light_intensities.txt").rename(f / "light_intensity.txt"),
    "lights permuted": lambda f: _rewrite_lights(
        f, lambda L: L[np.random.default_rng(1).permutation(len(L))]
    ),
    "y down": lambda f: _rewrite_lights(f, lambda L: L * [1.0, -1.0, 1.0]),
    "z negated": lambda f: _rewrite_lights(f, lambda L: L * [1.0, 1.0, -1.0]),
    "no mask": lambda f: (f / "mask.png").unlink(),
}


def broken_copy(src: Path, dst: Path, mistake: str) -> Path:
    """A copy of the DiLiGenT folder ``src`` at ``dst`` with one mistake of :data:`BREAKS`."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("Normal_gt.mat"))
    BREAKS[mistake](dst)
    return dst


def synthetic_folders(root: Path, quick: bool) -> dict[str, Path]:
    """The synthetic scenes as NPY-stack folders (8-bit, or 16-bit for the realistic one)."""
    scenes = {
        "syn sphere k=12": lambda: synthetic.sphere(12, 64, noise=1.0),
        "syn bumps k=24": lambda: synthetic.bump_scene(24, 64, noise=1.0),
        "syn realistic k=48 16-bit": lambda: synthetic.realistic_scene(48, 64),
    }
    if not quick:
        scenes |= {
            "syn sphere k=8": lambda: synthetic.sphere(8, 64),
            "syn bumps k=8": lambda: synthetic.bump_scene(8, 64, noise=2.0),
            "syn bumps k=96": lambda: synthetic.bump_scene(96, 64),
            "syn realistic k=12 8-bit": lambda: synthetic.realistic_scene(12, 64, bits=8),
        }
    out = {}
    for name, make in scenes.items():
        sc = make()
        dtype = np.uint16 if sc.saturation > 255 else np.uint8
        out[name] = write_npy_folder(
            root / name.replace(" ", "_"), sc.images.astype(dtype), sc.lights, sc.mask
        )
    return out


def measure(ds: Dataset, out: Path) -> tuple[dict[str, calibration.Finding], list[str], float]:
    """Run ``ds`` as ``maxfs run`` does (default options, in process); its findings, the record's
    calibration messages and the seconds the checks took."""
    from service.cli import _params, parser
    from service.local import run_folder
    from service.settings import Settings
    from storage.layout import JobSpec, JobStore
    from storage.params import JobParams
    from worker.task import check_calibration

    kw = _params(parser().parse_args(["run", "x", "-o", "y"]))
    spec = JobSpec(ds.k, ds.height, ds.width, ds.channels, ds.dtype, ds.lights, ds.intensities).validate()
    params = JobParams.build(**kw | {"tile": spec.resolve_tile(kw["tile"], Settings().task_memory, "exact")})
    _, rec = run_folder(ds, out, params, workers=2)
    stack = np.stack([ds.read(i) for i in range(ds.k)])
    t0 = time.perf_counter()
    found = check_calibration(JobStore.open(out, mode="r"), lambda t: stack[:, t.y0 : t.y1, t.x0 : t.x1])
    took = time.perf_counter() - t0
    return {f.check: f for f in found}, list(rec.calibration), took


def _cell(f: calibration.Finding | None) -> str:
    if f is None or f.value is None:
        return "-"
    return f"{f.value:.3g}{' !' if f.tripped else ''}"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--objects", default="cat", help="DiLiGenT crops to break (comma list)")
    args = ap.parse_args(argv)
    diligent = DATA / "diligent-crop8"
    rows: list[tuple[str, str, Path]] = []
    with tempfile.TemporaryDirectory(prefix="maxfs-bench-cal-") as tmp:
        root = Path(tmp)
        for obj in ("cat",) if args.quick else ("cat", "cow", "pot1"):
            rows.append((f"diligent {obj}", "good", diligent / f"{obj}PNG"))
        for obj in args.objects.split(","):
            for mistake in BREAKS:
                dst = broken_copy(
                    diligent / f"{obj}PNG", root / f"{obj}-{mistake.replace(' ', '-')}", mistake
                )
                rows.append((f"diligent {obj}", mistake, dst))
        for obj in ("cat", "chrome") if args.quick else UW_OBJECTS:
            rows.append((f"uw-psm {obj}", "good", DATA / "uw-psm" / obj))
        for name, folder in synthetic_folders(root / "syn", args.quick).items():
            rows.append((name, "good", folder))
        head = ["data", "calibration", "folder", *(SHORT[c] for c in CHECKS), "checks s", "verdict"]
        print("thresholds: " + ", ".join(f"{SHORT[c]} > {t:g}" for c, t in _thresholds().items()))
        print("| " + " | ".join(head) + " |")
        print("|" + "---|" * len(head))
        for i, (name, what, folder) in enumerate(rows):
            ds = load_folder(folder)
            found, messages, took = measure(ds, root / f"out{i}")
            tripped = sorted({m.split(":")[0] for m in messages})
            verdict = "suspect: " + ", ".join(tripped) if tripped else "no warning"
            cells = [
                name,
                what,
                str(len(ds.notes)),
                *(_cell(found.get(c)) for c in CHECKS),
                f"{took:.1f}",
                verdict,
            ]
            print("| " + " | ".join(cells) + " |", flush=True)


def _thresholds() -> dict[str, float]:
    c = calibration
    return dict(
        zip(
            CHECKS,
            (
                c.LIGHTS_BEHIND_SHARE,
                c.GAIN_SPREAD,
                c.ORDER_RATIO,
                c.NORMALS_BEHIND_SHARE,
                c.FLIP_CURL_RATIO,
                c.BACKGROUND_SHARE,
            ),
            strict=True,
        )
    )


if __name__ == "__main__":
    main()
