"""The Python API against the command: ``maxfs.solve_folder(F)`` and ``maxfs run F`` on one folder.

Each round runs both, in fresh processes and in turn (so a drifting shared machine affects both
alike), and checks that the normals are bit-identical. Prints one markdown table of wall-clock
seconds (min / median / max over the rounds) and the ratio of medians.

    python -m bench.api [--runs 3] [--folder F]     # default: the bench.phases capture (k = 96, 16-bit)
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.phases import make_capture

MAXFS = str(Path(sys.executable).parent / "maxfs")
API = "import sys, numpy as np, maxfs; r = maxfs.solve_folder(sys.argv[1]); np.save(sys.argv[2], r.normal)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--folder", type=Path, default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        folder = args.folder
        if folder is None:
            folder = root / "capture"
            make_capture(folder, 96)
        times: dict[str, list[float]] = {"maxfs run": [], "maxfs.solve_folder": []}
        for i in range(args.runs):
            t = time.perf_counter()
            subprocess.run(
                [MAXFS, "run", str(folder), "-o", str(root / f"run{i}")], check=True, capture_output=True
            )
            times["maxfs run"].append(time.perf_counter() - t)
            t = time.perf_counter()
            npy = root / f"api{i}.npy"
            subprocess.run(
                [sys.executable, "-c", API, str(folder), str(npy)], check=True, capture_output=True
            )
            times["maxfs.solve_folder"].append(time.perf_counter() - t)
            from maxfs import open_result

            same = np.array_equal(open_result(root / f"run{i}").normal, np.load(npy), equal_nan=True)
            if not same:
                raise SystemExit("the normals differ: maxfs.solve_folder is not maxfs run")
        print(f"\n{folder}: {args.runs} interleaved rounds, normals bit-identical in each\n")
        print("| path | min s | median s | max s |")
        print("|---|---|---|---|")
        for name, ts in times.items():
            print(f"| {name} | {min(ts):.2f} | {statistics.median(ts):.2f} | {max(ts):.2f} |")
        ratio = statistics.median(times["maxfs.solve_folder"]) / statistics.median(times["maxfs run"])
        print(f"\nsolve_folder / run (medians): {ratio:.2f}x")


if __name__ == "__main__":
    main()
