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
import tempfile
import time
from pathlib import Path

import numpy as np

from maxfs.storage.datasets import Dataset, write_npy_folder
from maxfs.storage.inputs import load_folder
from maxfs.worker import calibration, synthetic
from maxfs.worker.calibration import MISTAKES, miscalibrated_copy

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
UW_OBJECTS = ("buddha", "cat", "chrome", "gray", "horse", "owl", "rock")
#: Every check (worker.calibration), its column's name and its threshold.
CHECKS = {
    calibration.LIGHTS_CHECK: ("lights z<=0", calibration.LIGHTS_BEHIND_SHARE),
    calibration.GAIN_CHECK: ("gain spread", calibration.GAIN_SPREAD),
    calibration.ORDER_CHECK: ("order ratio", calibration.ORDER_RATIO),
    calibration.NORMALS_CHECK: ("normals nz<0", calibration.NORMALS_BEHIND_SHARE),
    calibration.FLIP_CHECK: ("mirror z", calibration.FLIP_Z),
    calibration.MASK_CHECK: ("dark share", calibration.BACKGROUND_SHARE),
}


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
    from maxfs.service.cli.main import _params, parser
    from maxfs.service.runs.local import run_folder
    from maxfs.service.settings import Settings
    from maxfs.storage.layout import JobSpec, JobStore
    from maxfs.storage.params import JobParams
    from maxfs.worker.task import check_calibration

    kw = _params(parser().parse_args(["run", "x", "-o", "y"]))
    spec = JobSpec.of(ds)
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
            for mistake in MISTAKES:
                dst = miscalibrated_copy(
                    diligent / f"{obj}PNG", root / f"{obj}-{mistake.replace(' ', '-')}", mistake
                )
                rows.append((f"diligent {obj}", mistake, dst))
        for obj in ("cat", "chrome") if args.quick else UW_OBJECTS:
            rows.append((f"uw-psm {obj}", "good", DATA / "uw-psm" / obj))
        for name, folder in synthetic_folders(root / "syn", args.quick).items():
            rows.append((name, "good", folder))
        head = ["data", "calibration", "folder", *(col for col, _ in CHECKS.values()), "checks s", "verdict"]
        print("thresholds: " + ", ".join(f"{col} > {t:g}" for col, t in CHECKS.values()))
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


if __name__ == "__main__":
    main()
