"""Where the time of ``maxfs run`` goes on a realistic capture (issue #12).

Builds a 96-image 16-bit RGB set of 612 x 512 pixels whose mask covers about 5 % of
the image (a DiLiGenT-style folder of PNGs, like a real capture), then runs
``maxfs run --timings`` on it: a fresh run into a new folder, repeated, and a re-run of
the finished job. Prints one markdown table (medians over the fresh runs).

    python -m bench.phases [--runs 3] [--k 96]
    python -m bench.phases --baseline /tmp/old --runs 6   # before/after, interleaved

``--baseline TREE``: a checkout of another commit (``git worktree add /tmp/old COMMIT``), run
with ``PYTHONPATH=TREE`` in this environment (so its own dependencies must be installed here),
in turn with this tree, a fresh run and a re-run each; on a shared machine whose speed drifts,
only interleaved runs compare.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import imagecodecs
import numpy as np

from maxfs.worker import synthetic

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


def timed_run(folder: Path, out: Path, tree: Path | None = None) -> tuple[float, dict[str, float]]:
    env = None if tree is None else {**os.environ, "PYTHONPATH": str(tree)}
    t0 = time.perf_counter()
    r = subprocess.run(
        [MAXFS, "run", str(folder), "-o", str(out), "--timings"],
        capture_output=True,
        text=True,
        timeout=900,
        env=env,
        cwd=folder.parent,  # not this checkout, whose packages would shadow the baseline's
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


def _median(rows: list[tuple[float, dict[str, float]]], name: str) -> float:
    return statistics.median(r[1].get(name, 0.0) for r in rows)


def compare(folder: Path, tmp: Path, baseline: Path, runs: int) -> None:
    """Fresh runs and re-runs of ``baseline`` and this tree in turn; a before/after table of medians."""
    fresh: dict[str, list] = {"before": [], "after": []}
    again: dict[str, list] = {"before": [], "after": []}
    for i in range(runs):
        for side in ("before", "after") if i % 2 == 0 else ("after", "before"):
            tree = baseline if side == "before" else None
            out = tmp / f"{side}{i}"
            fresh[side].append(timed_run(folder, out, tree))
            again[side].append(timed_run(folder, out, tree))
    names = list(dict.fromkeys([*fresh["before"][0][1], *fresh["after"][0][1]]))
    print(f"{runs} fresh runs and re-runs of each, interleaved; medians (s):\n")
    print("| phase | before | after |")
    print("|---|---|---|")
    for n in (n for n in names if n != "total"):
        cells = [f"{_median(fresh[s], n):.2f}" if n in fresh[s][0][1] else "-" for s in ("before", "after")]
        print(f"| {n} | {cells[0]} | {cells[1]} |")
    for label, rows in (("fresh run", fresh), ("re-run of the finished job", again)):
        b, a = (statistics.median(r[0] for r in rows[s]) for s in ("before", "after"))
        print(f"| wall clock, {label} | {b:.2f} | {a:.2f} ({b / a:.2f}x) |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--k", type=int, default=96)
    ap.add_argument("--baseline", type=Path, default=None, help="a checkout of another commit to compare")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="maxfs-bench-") as tmp:
        folder = Path(tmp) / "capture"
        px = make_capture(folder, args.k)
        print(
            f"`maxfs run --timings`, {args.k} images of {W} x {H}, 16-bit RGB PNG, {px} masked pixels "
            f"({px / (H * W):.1%})"
        )
        if args.baseline:
            compare(folder, Path(tmp), args.baseline.resolve(), args.runs)
            return
        runs = [timed_run(folder, Path(tmp) / f"out{i}") for i in range(args.runs)]
        rerun = timed_run(folder, Path(tmp) / "out0")
    names = list(runs[0][1])
    print(f"median of {args.runs} fresh runs, then a re-run of the finished job:\n")
    print("| phase | fresh run (s) | re-run of the finished job (s) |")
    print("|---|---|---|")
    for n in names:
        again = f"{rerun[1][n]:.2f}" if n in rerun[1] else "-"
        print(f"| {n} | {_median(runs, n):.2f} | {again} |")
    print(f"| **everything but tiles** | {_median(runs, 'total') - _median(runs, 'tiles'):.2f} | |")
    print(f"| wall clock of the command | {statistics.median(r[0] for r in runs):.2f} | {rerun[0]:.2f} |")


if __name__ == "__main__":
    main()
