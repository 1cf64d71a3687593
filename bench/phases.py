"""Where the time of ``maxfs run`` goes on a realistic capture, and what it costs next to its floor.

Builds a 96-image 16-bit RGB set of 612 x 512 pixels whose mask covers about 5 % of
the image (a DiLiGenT-style folder of PNGs, like a real capture), or takes ``--folder``
(a DiLiGenT-layout folder: ``filenames.txt``, ``light_directions.txt``, optional
``light_intensities.txt`` and ``mask.png``), then, in turn, in fresh processes:

* ``maxfs run --timings`` (the defaults: exact solver, robust model, eps estimated) into a new
  folder, and a re-run of the finished job;
* ``maxfs run --solver l2`` (least squares instead of the exact solve, everything else the same);
* the **floor**: a minimal script that imports numpy and imagecodecs, decodes the same PNGs,
  divides them by the light intensities, takes grey (the channels' mean) and solves numpy least
  squares on the masked pixels: what any photometric stereo program must at least spend.

It prints the phases (medians over the fresh runs), then the CPU seconds (user + system, from
the kernel's accounting of each child process) of each command, min / median / max, and the
ratios of ``maxfs run`` to the floor and to ``--solver l2``, taken within each round and then
min / median / max over rounds: on a shared machine whose speed drifts, only interleaved runs
compare.

    python -m bench.phases [--runs 3] [--k 96] [--folder PATH] [--workers N]
    python -m bench.phases --baseline /tmp/old --runs 6   # before/after, interleaved

``--baseline TREE``: a checkout of another commit (``git worktree add /tmp/old COMMIT``), run
with ``PYTHONPATH=TREE`` in this environment (so its own dependencies must be installed here),
in turn with this tree.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import imagecodecs
import numpy as np

from maxfs.worker import synthetic

MAXFS = str(Path(sys.executable).parent / "maxfs")
H, W = 512, 612

#: The floor: run as ``python -c FLOOR FOLDER`` in a fresh process (numpy and imagecodecs only).
FLOOR = """
import sys
from pathlib import Path
import imagecodecs
import numpy as np
d = Path(sys.argv[1])
names = (d / "filenames.txt").read_text().split()
L = np.loadtxt(d / "light_directions.txt").reshape(len(names), 3)
p = d / "light_intensities.txt"
inten = np.loadtxt(p).reshape(len(names), -1) if p.exists() else np.ones((len(names), 1))
m = imagecodecs.png_decode((d / "mask.png").read_bytes())
m = (m.max(axis=2) if m.ndim == 3 else m) > 0
I = np.empty((len(names), int(m.sum())))
for i, name in enumerate(names):
    img = imagecodecs.png_decode((d / name).read_bytes()) / inten[i]
    I[i] = (img.mean(axis=2) if img.ndim == 3 else img)[m]
n = np.linalg.lstsq(L, I, rcond=None)[0]
print(n.shape[1], float(np.nanmean(np.linalg.norm(n, axis=0))))
"""


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


@dataclass
class Timed:
    """One command: its wall clock and CPU seconds, and the phases ``--timings`` printed."""

    wall: float
    cpu: float
    phases: dict[str, float] = field(default_factory=dict)


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _timed(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> tuple[Timed, str]:
    cpu0, t0 = _children_cpu(), time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=env, cwd=cwd)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - cpu0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd[:3])} failed:\n{r.stderr}")
    return Timed(wall, cpu), r.stderr


def importable(tree: Path, into: Path) -> Path:
    """A folder to put on PYTHONPATH so that ``maxfs`` and its sub-packages come from the checkout
    ``tree``: its ``maxfs/`` with ``service``, ``worker`` and ``storage`` linked in, as the
    install maps them (``tree`` alone on PYTHONPATH would give its ``maxfs/`` but this install's
    sub-packages)."""
    pkg = into / "maxfs"
    pkg.mkdir(parents=True)
    for p in (tree / "maxfs").iterdir():
        (pkg / p.name).symlink_to(p)
    for sub in ("service", "worker", "storage"):
        (pkg / sub).symlink_to(tree / sub)
    return into


def timed_run(
    folder: Path, out: Path, tree: Path | None = None, extra: tuple[str, ...] = (), workers: int | None = None
) -> Timed:
    """``maxfs run FOLDER -o OUT --timings`` in a fresh process (``tree``: a folder from
    :func:`importable`, on PYTHONPATH first)."""
    env = None if tree is None else {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [MAXFS, "run", str(folder), "-o", str(out), "--timings", *extra]
    if workers:
        cmd += ["--workers", str(workers)]
    # cwd: not this checkout, whose packages would shadow the baseline's
    res, stderr = _timed(cmd, out.parent, env)
    table = stderr.split("seconds   share", 1)[1]
    for line in table.strip().splitlines():
        m = re.match(r"(.+?)\s+([\d.]+)\s+\d+%$", line.strip())
        if not m:
            break
        res.phases[m.group(1)] = float(m.group(2))
    return res


def floor_run(folder: Path) -> Timed:
    """The floor script (:data:`FLOOR`) on ``folder`` in a fresh process."""
    return _timed([sys.executable, "-c", FLOOR, str(folder)], folder.parent)[0]


def _median(rows: list[Timed], name: str) -> float:
    return statistics.median(r.phases.get(name, 0.0) for r in rows)


def _spread(xs: list[float], unit: str = "") -> str:
    return f"{min(xs):.2f} / {statistics.median(xs):.2f} / {max(xs):.2f}{unit}"


def rounds(
    folder: Path, tmp: Path, runs: int, trees: dict[str, Path | None], workers: int | None
) -> dict[str, list[Timed]]:
    """``runs`` rounds of: the floor, and per tree a fresh ``maxfs run``, its re-run and a fresh
    ``--solver l2``; the order rotates from round to round so that drift spreads evenly."""
    jobs: list[tuple[str, object]] = [("floor", lambda i: floor_run(folder))]
    for side, tree in trees.items():

        def fresh(i: int, side: str = side, tree: Path | None = tree) -> Timed:
            return timed_run(folder, tmp / f"{side}-run{i}", tree, workers=workers)

        def again(i: int, side: str = side, tree: Path | None = tree) -> Timed:
            return timed_run(folder, tmp / f"{side}-run{i}", tree, workers=workers)

        def l2(i: int, side: str = side, tree: Path | None = tree) -> Timed:
            return timed_run(folder, tmp / f"{side}-l2-{i}", tree, ("--solver", "l2"), workers)

        jobs += [(f"{side} run", fresh), (f"{side} re-run", again), (f"{side} l2", l2)]
    for (
        side,
        tree,
    ) in trees.items():  # untimed: the solver's cache (compiled on a first run) and the page cache
        timed_run(folder, tmp / f"{side}-warm", tree, workers=workers)
    out: dict[str, list[Timed]] = {name: [] for name, _ in jobs}
    groups = [jobs[:1]] + [jobs[i : i + 3] for i in range(1, len(jobs), 3)]  # a re-run follows its run
    for i in range(runs):
        shift = i % len(groups)
        for group in groups[shift:] + groups[:shift]:
            for name, job in group:
                out[name].append(job(i))  # type: ignore[operator]
    return out


def print_costs(res: dict[str, list[Timed]], sides: list[str]) -> None:
    """CPU seconds of each command and the ratios of ``maxfs run`` to the floor and to l2."""
    print("\nCPU seconds (user + system) and wall clock, min / median / max over the rounds:\n")
    print("| command | CPU s | wall s |")
    print("|---|---|---|")
    labels = {
        "run": "`maxfs run` (exact, defaults)",
        "re-run": "re-run of the finished job",
        "l2": "`--solver l2`",
    }
    print(
        f"| floor (decode, divide, grey, numpy lstsq) | {_spread([t.cpu for t in res['floor']])} | "
        f"{_spread([t.wall for t in res['floor']])} |"
    )
    for side in sides:
        for what, label in labels.items():
            rows = res[f"{side} {what}"]
            name = label if len(sides) == 1 else f"{side}: {label}"
            print(f"| {name} | {_spread([t.cpu for t in rows])} | {_spread([t.wall for t in rows])} |")
    print("\nRatios within each round (CPU, then wall clock), min / median / max:\n")
    print("| ratio | CPU | wall |")
    print("|---|---|---|")
    for side in sides:
        run, l2, floor = res[f"{side} run"], res[f"{side} l2"], res["floor"]
        pre = "" if len(sides) == 1 else f"{side}: "
        for label, den in (("the floor", floor), ("`--solver l2`", l2)):
            cpu = [a.cpu / b.cpu for a, b in zip(run, den, strict=True)]
            wall = [a.wall / b.wall for a, b in zip(run, den, strict=True)]
            print(f"| {pre}`maxfs run` / {label} | {_spread(cpu, 'x')} | {_spread(wall, 'x')} |")


def balance(out: Path, workers: tuple[int, ...] = (2, 4, 8)) -> str:
    """The tile grid of a finished job and what it means for ``workers`` threads or workers: the
    largest tile's share of the masked pixels, and the critical path when tiles start largest
    first (as the runners do), in masked pixels as the work, over the ideal ``total / workers``."""
    import zarr

    g = zarr.open_group(out / "results.zarr", mode="r")
    tile = int(g.attrs["params"]["tile"])
    m = np.asarray(g["mask"][...])
    ny, nx = -(-m.shape[0] // tile), -(-m.shape[1] // tile)
    padded = np.zeros((ny * tile, nx * tile), bool)
    padded[: m.shape[0], : m.shape[1]] = m
    work = np.sort(padded.reshape(ny, tile, nx, tile).sum(axis=(1, 3)).ravel())[::-1]
    work = work[work > 0]
    paths = []
    for w in workers:
        free = np.zeros(w)
        for x in work:  # each tile goes to the worker that frees up first
            free[np.argmin(free)] += x
        paths.append(f"{w}: {free.max() / (work.sum() / w):.2f}x")
    return (
        f"tile {tile}: {len(work)} of {ny * nx} tiles hold masked pixels, the largest "
        f"{work[0] / work.sum():.1%} of them; critical path / ideal with N workers: {', '.join(paths)}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--k", type=int, default=96)
    ap.add_argument(
        "--folder", type=Path, default=None, help="a DiLiGenT-layout folder instead of the synthetic one"
    )
    ap.add_argument("--workers", type=int, default=None, help="maxfs run --workers (default: its own)")
    ap.add_argument("--baseline", type=Path, default=None, help="a checkout of another commit to compare")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="maxfs-bench-") as tmp:
        if args.folder:
            folder = args.folder.resolve()
            if not (folder / "filenames.txt").exists() or not (folder / "mask.png").exists():
                raise SystemExit(f"{folder}: the floor reads a DiLiGenT layout (filenames.txt, mask.png)")
            names = (folder / "filenames.txt").read_text().split()
            mask = imagecodecs.png_decode((folder / "mask.png").read_bytes())
            mask = (mask.max(axis=2) if mask.ndim == 3 else mask) > 0
            first = imagecodecs.png_decode((folder / names[0]).read_bytes())
            print(
                f"{folder.name}: {len(names)} images of {first.shape[1]} x {first.shape[0]}, {first.dtype} "
                f"PNG, {int(mask.sum())} masked pixels ({mask.mean():.1%})"
            )
        else:
            folder = Path(tmp) / "capture"
            px = make_capture(folder, args.k)
            print(f"{args.k} images of {W} x {H}, 16-bit RGB PNG, {px} masked pixels ({px / (H * W):.1%})")
        sides = ["before", "after"] if args.baseline else ["this"]
        base = importable(args.baseline.resolve(), Path(tmp) / "baseline") if args.baseline else None
        trees = {"before": base, "after": None} if args.baseline else {"this": None}
        res = rounds(folder, Path(tmp), args.runs, trees, args.workers)
        print()
        for side in trees:
            print(f"- {side}: {balance(Path(tmp) / f'{side}-run0')}")
    fresh = {s: res[f"{s} run"] for s in sides}
    rerun = {s: res[f"{s} re-run"] for s in sides}
    names = list(dict.fromkeys(n for s in sides for n in fresh[s][0].phases if n != "total"))
    print(f"\n`maxfs run --timings`, {args.runs} rounds; median seconds of each phase, fresh run (re-run):\n")
    print("| phase | " + " | ".join(sides) + " |")
    print("|---|" + "---|" * len(sides))
    for n in names:
        cells = []
        for s in sides:
            cell = f"{_median(fresh[s], n):.2f}" if n in fresh[s][0].phases else "-"
            cells.append(cell + (f" ({_median(rerun[s], n):.2f})" if n in rerun[s][0].phases else ""))
        print(f"| {n} | " + " | ".join(cells) + " |")
    cells = [f"{_median(fresh[s], 'total') - _median(fresh[s], 'tiles'):.2f}" for s in sides]
    print("| **everything but tiles** | " + " | ".join(cells) + " |")
    print_costs(res, sides)


if __name__ == "__main__":
    main()
