"""The CPU a finished tile costs to store: :meth:`JobStore.write_tile` on a finished job's tiles.

Takes a finished ``maxfs run`` output (``--store``; by default it runs one on bench.phases's
96-image capture), reads each finished tile's outputs back, then in fresh processes writes them
all again, in two cases: **fresh** (into a copy of the store whose tile chunks were removed, as a
run writes them) and **rewrite** (over the chunks already there, as a re-run with other
parameters does). Prints CPU milliseconds per tile, min / median / max over the rounds.

    python -m bench.tile_writes [--rounds 5] [--store OUT]
    python -m bench.tile_writes --baseline /tmp/old --rounds 5   # before/after, interleaved

``--baseline TREE``: a checkout of another commit, run with ``PYTHONPATH`` pointing at it (as
bench.phases does), in turn with this tree.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.phases import MAXFS, importable, make_capture

#: Run in a fresh process: ``python -c WRITER STORE CASE REPEATS``; prints CPU ms per tile as JSON.
WRITER = """
import json, shutil, sys, time
from pathlib import Path
from maxfs.storage.layout import JobStore
from maxfs.storage.outputs import TILE_OUTPUTS

src, case, reps = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
store = JobStore.open(src)
tok = store.params.token()
done = [t for t in store.tiles() if store.tile_done(t)]
data = []
for t in done:
    arrays = {}
    for o in TILE_OUTPUTS:
        if o.exists(store.spec.channels):
            region = (slice(None), slice(t.y0, t.y1), slice(t.x0, t.x1)) if o.per == "image" else (
                slice(t.y0, t.y1), slice(t.x0, t.x1))
            arrays[o.name] = store.read_array(o.name, region)
    data.append((t, arrays))
names = [o.name for o in TILE_OUTPUTS] + ["tiles/tile_stats", "tiles/done"]
out = []
for r in range(reps):
    if case == "fresh":
        dst = src.parent / f"{src.name}-fresh"
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(src, dst)
        for n in names:
            shutil.rmtree(dst / "results.zarr" / n / "c", ignore_errors=True)
        s = JobStore.open(dst)
    else:
        s = JobStore.open(src)
    c0 = time.process_time()
    for t, arrays in data:
        s.write_tile(t, arrays, tok, (1, 1, 1))
    out.append(1000 * (time.process_time() - c0) / len(data))
import maxfs.storage.layout as layout
print(json.dumps({"tiles": len(data), "ms": out, "module": layout.__file__}))
"""


def run_writer(store: Path, case: str, reps: int, path: Path | None) -> tuple[int, list[float]]:
    env = dict(os.environ)
    if path is not None:
        env["PYTHONPATH"] = str(path)
    p = subprocess.run(
        [sys.executable, "-c", WRITER, str(store), case, str(reps)],
        cwd=store.parent,  # not this checkout: ``python -c`` puts the working folder first on sys.path
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    got = json.loads(p.stdout.strip().splitlines()[-1])
    if path is not None and not got["module"].startswith(str(path)):
        raise SystemExit(f"the baseline imported {got['module']}, not the tree under {path}")
    return int(got["tiles"]), [float(v) for v in got["ms"]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=3, help="writes of every tile per process (median kept)")
    ap.add_argument("--store", type=Path, default=None, help="a finished maxfs run output")
    ap.add_argument("--baseline", type=Path, default=None, help="a checkout of another commit to compare")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="maxfs-bench-") as tmp:
        if args.store is None:
            folder = Path(tmp) / "capture"
            make_capture(folder, 96)
            src = Path(tmp) / "out"
            subprocess.run([MAXFS, "run", str(folder), "-o", str(src)], check=True, capture_output=True)
        else:
            src = Path(tmp) / "out"
            shutil.copytree(args.store, src)
        trees: dict[str, Path | None] = {"this": None}
        if args.baseline:
            trees = {"before": importable(args.baseline.resolve(), Path(tmp) / "baseline"), "after": None}
        res: dict[tuple[str, str], list[float]] = {}
        tiles = 0
        for r in range(args.rounds):
            for case in ("fresh", "rewrite"):
                order = list(trees) if r % 2 == 0 else list(trees)[::-1]
                for side in order:
                    tiles, ms = run_writer(src, case, args.reps, trees[side])
                    res.setdefault((side, case), []).append(statistics.median(ms))
    print(f"\n{tiles} tiles, {args.rounds} rounds; CPU ms per tile, min / median / max:\n")
    print("| case | " + " | ".join(trees) + (" | after / before (medians) |" if args.baseline else " |"))
    print("|---|" + "---|" * (len(trees) + (1 if args.baseline else 0)))
    for case in ("fresh", "rewrite"):
        cells = []
        for side in trees:
            v = res[(side, case)]
            cells.append(f"{min(v):.2f} / {statistics.median(v):.2f} / {max(v):.2f}")
        if args.baseline:
            ratio = statistics.median(res[("after", case)]) / statistics.median(res[("before", case)])
            cells.append(f"{ratio:.2f}x")
        print(f"| {case} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
