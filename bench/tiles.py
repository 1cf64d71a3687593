"""What a capture's tiles cost with each solver, and which part of the exact ones is the kernel.

Solves bench.phases' 96-image 16-bit capture (or ``--folder``) once as ``maxfs run``'s defaults
do (:func:`worker.solve.solve`, the robust model, eps estimated, tiles of ``--tile``), recording
each tile's :func:`worker.solve.solve_pixels` call, then replays those calls in this thread with
each solver, interleaved, ``--reps`` times. Prints thread CPU seconds, min / median / max: the
whole replay, and for the exact solver its parts (the kernel, the highlight rule's first-pass
trimmed least squares, its near-mirror test, the rest), then the difference exact - l2, which is
what separates ``maxfs run`` from ``maxfs run --solver l2`` beyond the shared phases that
``python -m bench.phases`` times.

    python -m bench.tiles [--reps 5] [--k 96] [--tile 32] [--folder PATH]

BLAS runs on one thread here (set before numpy loads), so thread CPU is all the CPU.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: a replay's CPU is this thread's
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from unittest import mock

import numpy as np

from maxfs.storage.inputs import load_folder
from maxfs.worker import exact as exact_module
from maxfs.worker import solve as solve_module
from maxfs.worker import solvers as solvers_module

#: The exact tiles' parts timed on their own: (label, module, attribute). The solvers module
#: imports the highlight rule's functions by name, and the kernel per call from its module.
PARTS = (
    ("kernel (exact_pixels)", exact_module, "exact_pixels"),
    ("highlight rule: first-pass trimmed LS", solvers_module, "first_pass"),
    ("highlight rule: near-mirror test", solvers_module, "near_mirror"),
)
SOLVERS = ("exact", "l2")


def record_calls(folder: Path, tile: int) -> tuple[list[tuple[tuple, dict]], int]:
    """The ``solve_pixels`` calls of one :func:`worker.solve.solve` of ``folder``, and its pixels."""
    ds = load_folder(folder)
    raw = np.stack([ds.read(i) for i in range(ds.k)])
    calls: list[tuple[tuple, dict]] = []
    inner = solve_module.solve_pixels

    def record(*args, **kwargs):
        calls.append((args, kwargs))
        return inner(*args, **kwargs)

    with mock.patch.object(solve_module, "solve_pixels", record):
        solve_module.solve(raw, ds.lights, ds.mask, intensities=ds.intensities, tile=tile)
    pixels = int(ds.mask.sum()) if ds.mask is not None else ds.height * ds.width
    return calls, pixels


def _timed(fn: Callable, into: dict[str, float], label: str) -> Callable:
    def wrapper(*args, **kwargs):
        t = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            into[label] += time.thread_time() - t

    return wrapper


def replay(calls: list[tuple[tuple, dict]], solver: str) -> dict[str, float]:
    """Thread CPU seconds of every call with ``solver``: ``total`` and, for exact, :data:`PARTS`."""
    parts: dict[str, float] = defaultdict(float)
    with mock.patch.multiple(solvers_module, **_wrapped(solvers_module, parts)):
        with mock.patch.multiple(exact_module, **_wrapped(exact_module, parts)):
            t = time.thread_time()
            for args, kwargs in calls:
                solve_module.solve_pixels(args[0], args[1], args[2], solver, **kwargs)
            parts["total"] = time.thread_time() - t
    return dict(parts)


def _wrapped(module: object, into: dict[str, float]) -> dict[str, Callable]:
    return {attr: _timed(getattr(mod, attr), into, label) for label, mod, attr in PARTS if mod is module}


def _spread(xs: list[float]) -> str:
    return f"{min(xs):.3f} / {statistics.median(xs):.3f} / {max(xs):.3f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--k", type=int, default=96, help="images of the generated capture")
    ap.add_argument("--tile", type=int, default=32, help="tile side, as maxfs run's default")
    ap.add_argument("--folder", type=Path, help="a folder maxfs run reads, instead of the capture")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.folder
        if folder is None:
            from bench.phases import make_capture

            folder = Path(tmp) / "capture"
            make_capture(folder, args.k)
        calls, pixels = record_calls(folder, args.tile)
    for solver in SOLVERS:  # load and compile outside the timed runs
        replay(calls, solver)
    runs: dict[str, list[dict[str, float]]] = {s: [] for s in SOLVERS}
    for r in range(args.reps):
        for solver in SOLVERS if r % 2 == 0 else reversed(SOLVERS):
            runs[solver].append(replay(calls, solver))
    print(
        f"{folder.name}: {pixels} masked pixels in {len(calls)} tiles of {args.tile}; "
        f"{args.reps} interleaved replays"
    )
    print()
    print("| solver | part | thread CPU s (min / median / max) |")
    print("|---|---|---|")
    for solver in SOLVERS:
        total = _spread([r["total"] for r in runs[solver]])
        print(f"| {solver} | all of the tiles' solve_pixels | {total} |")
    exact = runs["exact"]
    for label, _, _ in PARTS:
        print(f"| exact | {label} | {_spread([r.get(label, 0.0) for r in exact])} |")
    rest = [r["total"] - sum(r.get(label, 0.0) for label, _, _ in PARTS) for r in exact]
    print(f"| exact | the rest (usable, slabs, candidates, refit, albedo) | {_spread(rest)} |")
    diff = [e["total"] - l2["total"] for e, l2 in zip(exact, runs["l2"], strict=True)]
    print(f"| exact - l2 | within each round | {_spread(diff)} |")


if __name__ == "__main__":
    main()
