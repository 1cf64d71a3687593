"""Solver speed and accuracy on the paper's synthetic sphere.

Prints one markdown table: per k and solver, ms per pixel and mean angular error.

* ``batch ms/px``: a whole image solved in one call (the service's path; the
  exact solver seeds each pixel with its neighbour's solution).
* ``median`` / ``p95``: the solver kernel called on one pixel at a time, on the
  same sampled pixels for every solver (no neighbour seed for ``exact``, so a
  conservative figure; the refit is not included).
* ``milp/solver``: MILP time over the solver's on the same pixels, as a ratio of
  medians and of means (the MILP's cost is in its tail).

Run: ``python -m bench.solvers`` (``--quick`` for a smaller run).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from worker import synthetic
from worker.exact import exact_pixels
from worker.lstsq import refit
from worker.milp import MilpSolver
from worker.problem import make_thresholds, slabs, usable
from worker.solve import solve_pixels


def _time_each(fn, rows: list) -> np.ndarray:
    """Milliseconds of ``fn(row)`` for each row, one call at a time."""
    out = np.empty(len(rows))
    for i, row in enumerate(rows):
        t = time.perf_counter()
        fn(*row)
        out[i] = (time.perf_counter() - t) * 1e3
    return out


def _bench_k(k: int, args: argparse.Namespace) -> list[tuple]:
    rows: list[tuple] = []
    sc = synthetic.sphere(k, args.size)
    th = make_thresholds(k, args.eps, saturation=sc.saturation)
    I = sc.images[:, sc.mask].T.copy()
    V = usable(I.T, th).T
    truth = sc.normals[sc.mask]
    pick = np.linspace(0, len(I) - 1, args.sample).astype(int)
    lo, hi = slabs(I, args.eps)
    exact_pixels(I[:2], lo[:2], hi[:2], V[:2], sc.lights, th.box_factor, 10**7)  # JIT warm-up
    ms = MilpSolver(sc.lights, time_limit=args.milp_cap)
    one = [(I[i : i + 1], V[i : i + 1], lo[i : i + 1], hi[i : i + 1]) for i in pick]
    kernels = {
        "milp": lambda Ii, Vi, *_: ms.solve_pixel(Ii[0], Vi[0], args.eps, th.box_factor),
        "exact": lambda Ii, Vi, li, hi_: exact_pixels(Ii, li, hi_, Vi, sc.lights, th.box_factor, 10**7),
        "l2": lambda Ii, Vi, *_: refit(Ii, np.isfinite(Ii), sc.lights),
    }
    times = {name: _time_each(fn, one) for name, fn in kernels.items()}
    capped = int((times["milp"] >= args.milp_cap * 1e3 * 0.95).sum())
    for name in ("exact", "milp", "l2"):
        if name == "milp":  # too slow for the whole image: the sampled pixels only
            res = solve_pixels(I[pick], sc.lights, th, "milp", milp_time_limit=args.milp_cap)
            err = synthetic.angular_error_deg(res.normal, truth[pick])
            batch = float("nan")
        else:
            t0 = time.perf_counter()
            res = solve_pixels(I, sc.lights, th, name)
            batch = (time.perf_counter() - t0) * 1e3 / len(I)
            err = synthetic.angular_error_deg(res.normal, truth)
        t_one = times[name]
        ratio = np.median(times["milp"]) / np.median(t_one)
        rows.append(
            (
                k,
                name,
                batch,
                np.median(t_one),
                np.percentile(t_one, 95),
                ratio,
                np.mean(times["milp"]) / np.mean(t_one),
                np.nanmean(err),
                capped if name == "milp" else "",
            )
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ks", type=int, nargs="+", default=[12, 24, 48, 96, 196])
    ap.add_argument("--size", type=int, default=64, help="sphere image edge in pixels")
    ap.add_argument("--sample", type=int, default=40, help="pixels timed one by one (and for milp)")
    ap.add_argument("--milp-cap", type=float, default=5.0, help="MILP seconds per pixel")
    ap.add_argument("--eps", type=float, default=1.0)
    ap.add_argument("--quick", action="store_true", help="k = 12, 48 on a 32 px sphere")
    args = ap.parse_args()
    if args.quick:
        args.ks, args.size, args.sample = [12, 48], 32, 15

    rows = [row for k in args.ks for row in _bench_k(k, args)]
    print(f"sphere {args.size}x{args.size}, eps={args.eps}, 8-bit, {args.sample} pixels timed one by one\n")
    print(
        "| k | solver | batch ms/px | median ms/px | p95 ms/px "
        "| milp/solver (median) | milp/solver (mean) | mean err (deg) | milp caps hit |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for k, name, batch, med, p95, ratio, mean_ratio, err, capped in rows:
        b = "-" if np.isnan(batch) else f"{batch:.4f}"
        print(
            f"| {k} | {name} | {b} | {med:.4f} | {p95:.4f} | {ratio:.0f}x | {mean_ratio:.0f}x "
            f"| {err:.4f} | {capped} |"
        )


if __name__ == "__main__":
    main()
