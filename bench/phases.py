"""Where the time of ``maxfs run`` goes on a realistic capture (issue #12).

Builds a 96-image 16-bit RGB set of 612 x 512 pixels whose mask covers about 5 % of
the image (a DiLiGenT-style folder of PNGs, like a real capture), then runs
``maxfs run --timings`` on it: a fresh run into a new folder, repeated, and a re-run of
the finished job. Prints one markdown table (medians over the fresh runs).

    python -m bench.phases [--runs 3] [--k 96]
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import imagecodecs
import numpy as np

from worker import synthetic

MAXFS = str(Path(sys.executable).parent / "maxfs")
H, W = 512, 612


def make_capture(folder: Path, k: int, size: int = 160, seed: int = 7) -> int:
    """A DiLiGenT-layout folder; returns the number of masked pixels."""
    sc = synthetic.realistic_scene(k, size, seed=seed, bits=16)
    y0, x0 = 170, 240
    mask = np.zeros((H, W), bool)
    disc = np.hypot(*np.mgrid[-1 : 1 : size * 1j, -1 : 1 : size * 1j]) < 0.9
    mask[y0 : y0 + size, x0 : x0 + size] = disc & sc.mask
    tint = np.array([1.0, 0.92, 0.81])
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    names = []
    for i in range(k):
        img = rng.integers(0, 40, (H, W, 3)).astype(np.float64)  # a dark, noisy background
        img[y0 : y0 + size, x0 : x0 + size] = sc.images[i][..., None] * tint
        name = f"{i + 1:03d}.png"
        (folder / name).write_bytes(imagecodecs.png_encode(np.clip(img, 0, 65535).astype(np.uint16)))
        names.append(name)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", sc.lights)
    np.savetxt(folder / "light_intensities.txt", np.ones((k, 3)))
    (folder / "mask.png").write_bytes(imagecodecs.png_encode(mask.astype(np.uint8) * 255))
    return int(mask.sum())


def timed_run(folder: Path, out: Path) -> tuple[float, dict[str, float]]:
    t0 = time.perf_counter()
    r = subprocess.run(
        [MAXFS, "run", str(folder), "-o", str(out), "--timings"], capture_output=True, text=True, timeout=900
    )
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"maxfs run failed:\n{r.stderr}")
    table = r.stderr.split("seconds   share", 1)[1]
    phases = {}
    for line in table.strip().splitlines():
        m = re.match(r"(.+?)\s+([\d.]+)\s+\d+%$", line.strip())
        if not m:
            break
        phases[m.group(1)] = float(m.group(2))
    return wall, phases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--k", type=int, default=96)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="maxfs-bench-") as tmp:
        folder = Path(tmp) / "capture"
        px = make_capture(folder, args.k)
        runs = [timed_run(folder, Path(tmp) / f"out{i}") for i in range(args.runs)]
        rerun = timed_run(folder, Path(tmp) / "out0")
    names = list(runs[0][1])
    print(
        f"`maxfs run --timings`, {args.k} images of {W} x {H}, 16-bit RGB PNG, {px} masked pixels "
        f"({px / (H * W):.1%}); median of {args.runs} fresh runs, then a re-run of the finished job:\n"
    )
    print("| phase | fresh run (s) | re-run of the finished job (s) |")
    print("|---|---|---|")
    for n in names:
        med = statistics.median(r[1].get(n, 0.0) for r in runs)
        again = f"{rerun[1][n]:.2f}" if n in rerun[1] else "-"
        print(f"| {n} | {med:.2f} | {again} |")
    fresh_total = statistics.median(r[1]["total"] for r in runs)
    tiles = statistics.median(r[1].get("tiles", 0.0) for r in runs)
    print(f"| **everything but tiles** | {fresh_total - tiles:.2f} | |")
    print(f"| wall clock of the command | {statistics.median(r[0] for r in runs):.2f} | {rerun[0]:.2f} |")


if __name__ == "__main__":
    main()
