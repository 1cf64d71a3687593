"""Depth integration: time and peak memory against pixels, and accuracy on scenes with known depth.

    python -m bench.depth                       # sizes 0.25, 1, 4, 16 M pixels, then the accuracy table
    python -m bench.depth --sizes 0.25,1 --size 96   # smaller: a loaded machine, a quick look

Time and memory: a hemisphere's normals filling most of a square (synthetic normals are enough: the
solver's work does not depend on the shape), ``ls``; peak memory is tracemalloc's peak during
:func:`worker.depth.integrate` (numpy's and scipy's arrays, the normals given excluded; the modules it
imports are loaded by a small run first), per masked pixel; and, as a check on what tracemalloc cannot see
(memory that compiled code or C libraries take for themselves), how far the process's resident peak rose
above its size at the start (Linux: the peak is reset through ``/proc/self/clear_refs`` first).
Accuracy: RMS depth error after the best offset per region (the normals do not say how far apart a
step's two sides are) and, in perspective, the best scale too; at the steps (within 3 pixels of one)
and away from them; then the orthographic and the perspective model on perspective scenes.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import time
import tracemalloc

import numpy as np

from maxfs.worker import depth_scenes as S
from maxfs.worker.depth import integrate
from tests.attacks import proc_kb


def _reset_peak() -> bool:
    """Resets the process's resident peak (VmHWM) to its current size, after handing free heap memory
    back to the system (else the step could reuse it without its resident size growing); False where
    that is refused."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except (OSError, AttributeError):
        return False


def _sizes(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v]


def scaling(sizes: list[float], method: str) -> None:
    print(f"\n{method}: time and peak memory of the depth step against pixels")
    print(
        "| pixels (M) | masked (M) | seconds | s per M masked | peak MB | bytes / masked px "
        "| RSS peak rise MB | CG its |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    # a small run first: the lazy imports and the compiled kernels are a fixed cost, not memory per pixel
    warm = S.sphere_ortho(32)
    integrate(warm.normal, warm.mask, method=method)
    for mpx in sizes:
        side = int(np.sqrt(mpx * 1e6) + 0.5)
        sc = S.sphere_ortho(side, radius=0.7 * side)
        n, m = sc.normal, sc.mask
        del sc
        npx = int(m.sum())
        rss = proc_kb(os.getpid(), "VmRSS") if _reset_peak() else None
        tracemalloc.start()
        t = time.perf_counter()
        r = integrate(n, m, method=method)
        dt = time.perf_counter() - t
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        rise = "-" if rss is None else f"{(proc_kb(os.getpid(), 'VmHWM') - rss) / 1024:.0f}"
        its = r.cg_iterations
        del r
        print(
            f"| {side * side / 1e6:.2f} | {npx / 1e6:.2f} | {dt:.1f} | {dt / (npx / 1e6):.1f} | "
            f"{peak / 1e6:.0f} | {peak / npx:.0f} | {rise} | {its} |",
            flush=True,
        )


def _rms(e: np.ndarray, sel: np.ndarray) -> str:
    v = e[sel & np.isfinite(e)]
    return f"{np.sqrt(np.mean(v**2)):.3g}" if v.size else "-"


def _median(e: np.ndarray, sel: np.ndarray) -> str:
    v = np.abs(e[sel & np.isfinite(e)])
    return f"{np.median(v):.3g}" if v.size else "-"


def accuracy(size: int) -> None:
    scenes = {
        "sphere, orthographic": S.sphere_ortho(size),
        "step, orthographic": S.step_ortho(size),
        "sphere, perspective": S.sphere_perspective(size),
        "step, perspective": S.step_perspective(size),
    }
    print(f"\naccuracy, {size} x {size}: RMS depth error (orthographic: pixels; perspective: scene units)")
    print("| scene | method | model | at steps RMS | at steps median | away RMS | seconds | bini its |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for name, sc in scenes.items():
        persp = sc.camera is not None
        far = sc.mask & ~sc.step_band
        runs = [("ls", sc.camera), ("bini", sc.camera)] + ([("ls", None)] if persp else [])
        for method, cam in runs:
            t = time.perf_counter()
            r = integrate(sc.normal, sc.mask, method=method, camera=cam)
            dt = time.perf_counter() - t
            e = S.aligned_error(r.depth, sc, scale=persp)
            model = "orthographic" if cam is None else "perspective"
            print(
                f"| {name} | {method} | {model} | {_rms(e, sc.step_band)} | {_median(e, sc.step_band)} | "
                f"{_rms(e, far)} | {dt:.2f} | {r.params.get('iterations', '-')} |",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=_sizes, default=[0.25, 1, 4, 16], help="M pixels, comma list")
    ap.add_argument("--bini-sizes", type=_sizes, default=[0.25], help="M pixels for bini's row (slower)")
    ap.add_argument("--size", type=int, default=128, help="side of the accuracy scenes (0: none)")
    args = ap.parse_args()
    scaling(args.sizes, "ls")
    if args.bini_sizes:
        scaling(args.bini_sizes, "bini")
    if args.size:
        accuracy(args.size)


if __name__ == "__main__":
    main()
