"""Solver speed and accuracy: the paper's sphere, and the exact kernel on real and realistic pixels.

Prints markdown tables.

**sphere** (``--tables sphere``): per k and solver, ms per pixel and mean angular error.

* ``batch ms/px``: a whole image solved in one call (the service's path; the
  exact solver seeds each pixel with its neighbour's solution).
* ``median`` / ``p95``: the solver kernel called on one pixel at a time, on the
  same sampled pixels for every solver (no neighbour seed for ``exact``, so a
  conservative figure; the refit is not included).
* ``milp/solver``: MILP time over the solver's on the same pixels, as a ratio of
  medians and of means (the MILP's cost is in its tail).

**kernel** (``--tables kernel``): the exact kernel's CPU time and search nodes per pixel
(mean and p99) on :func:`worker.synthetic.realistic_scene` (16-bit, cast and attached
shadows, glossy lobes, shot and read noise) for several k, the seven UW psm
objects (12 images, a centre crop of the mask), the three DiLiGenT crops
(96 images, a centre crop), each as the raw stack a job gets, and (``--capture K``) the
capture ``python -m bench.phases`` times, as ``maxfs run`` gives it to the kernel. eps is the job's
automatic rule (:func:`worker.solve.estimate_job_eps`) and the slabs are the paper
model's; ``--model robust`` instead gives the kernel exactly what ``maxfs run`` with its
defaults gives it (the robust model's slabs, shadows and excluded highlights, captured
from :func:`worker.solve.solve` on the same stack). Times are CPU time of
the solving thread for a whole batch in raster order (the service's path), the
best of ``--reps`` runs; ``count == MILP`` compares the count on a sample of pixels with outliers
(HiGHS, ``--milp-cap`` seconds each). ``--baseline FILE`` (an earlier ``worker/exact.py``,
e.g. ``git show main:worker/exact.py > /tmp/exact_main.py``) times that kernel on the same
pixels, its runs interleaved with the current one's, and adds its ms/px (best and median), nodes,
the speed-up and whether every count is the same. ``--oracle`` adds the nodes the current kernel
needs when every pixel's first incumbent is already optimal (its own solution as the ``above``
seed, solved again in a second copy of the batch): what better seeds could save at most.

Run: ``python -m bench.solvers`` (``--quick`` for a smaller run).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import numpy as np

from maxfs.storage.inputs import load_folder
from maxfs.storage.observations import ObservationModel
from maxfs.storage.tiles import DEFAULT_TILE
from maxfs.worker import exact as exact_module
from maxfs.worker import synthetic
from maxfs.worker.exact import exact_pixels
from maxfs.worker.lstsq import refit
from maxfs.worker.milp import MilpSolver
from maxfs.worker.problem import make_thresholds, slabs, usable
from maxfs.worker.solve import estimate_job_eps, solve, solve_pixels

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
UW_OBJECTS = ("buddha", "cat", "chrome", "gray", "horse", "owl", "rock")
DILIGENT_OBJECTS = ("catPNG", "cowPNG", "pot1PNG")


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


@dataclass(frozen=True)
class Pixels:
    """The usable pixels of one scene, as the exact kernel sees them."""

    name: str
    I: np.ndarray  # (P, k)
    V: np.ndarray  # (P, k) usable
    L: np.ndarray  # (k, 3)
    eps: float
    box_factor: float
    lo: np.ndarray | None = None  # (P, k) slab bounds; None: the paper model's at eps
    hi: np.ndarray | None = None


def _job_pixels(name: str, raw: np.ndarray, L: np.ndarray, mask: np.ndarray, intensities=None) -> Pixels:
    """The pixels a job on the raw stack ``(k, H, W[, C])`` would solve, with eps by the
    job's automatic rule (:func:`worker.solve.estimate_job_eps`), in raster order."""
    k, H, W = raw.shape[:3]
    obs = ObservationModel.for_input(raw.dtype, k, raw.shape[3] if raw.ndim == 4 else None, intensities)
    eps = estimate_job_eps(lambda t: raw[:, t.y0 : t.y1, t.x0 : t.x1], L, obs, mask, (H, W), DEFAULT_TILE)
    grey, _, saturated = obs.prepare(raw)
    th = make_thresholds(k, eps)
    V = usable(grey.T, th).T & ~saturated & mask.ravel()[:, None]
    rows = np.flatnonzero(V.sum(axis=1) >= 3)
    return Pixels(name, grey[rows], V[rows], L, eps, th.box_factor)


def realistic_pixels(k: int, size: int, seed: int = 0) -> Pixels:
    """:func:`worker.synthetic.realistic_scene` as a 16-bit raw stack."""
    sc = synthetic.realistic_scene(k, size, seed=seed)
    return _job_pixels(f"realistic {size}x{size}", sc.images.astype(np.uint16), sc.lights, sc.mask)


def robust_pixels(name: str, raw: np.ndarray, L: np.ndarray, mask: np.ndarray, intensities=None) -> Pixels:
    """The kernel's arguments when :func:`worker.solve.solve` (``maxfs run``'s defaults: the
    robust model, eps auto) solves the raw stack in one tile; eps is the estimated one."""
    calls = []
    kernel = exact_module.exact_pixels

    def record(S, lo, hi, valid, L_, box_factor, max_nodes, above=None):
        calls.append((S.copy(), lo.copy(), hi.copy(), valid.copy(), box_factor))
        return kernel(S, lo, hi, valid, L_, box_factor, max_nodes, above)

    with mock.patch.object(exact_module, "exact_pixels", record):  # the solvers import it per call
        sol = solve(raw, L, mask, intensities=intensities, tile=max(raw.shape[1:3]))
    S, lo, hi, valid, box_factor = calls[0]
    return Pixels(f"{name} (robust)", S, valid, L, float(sol.eps), box_factor, lo, hi)


def dataset_pixels(folder: Path, crop: int, model: str = "paper") -> Pixels:
    """A ``crop`` x ``crop`` window centred on the mask's centroid."""
    ds = load_folder(folder)
    mask = ds.mask if ds.mask is not None else np.ones((ds.height, ds.width), bool)
    ys, xs = np.nonzero(mask)
    y0 = int(np.clip(ys.mean() - crop / 2, 0, max(ds.height - crop, 0)))
    x0 = int(np.clip(xs.mean() - crop / 2, 0, max(ds.width - crop, 0)))
    win = (slice(y0, y0 + crop), slice(x0, x0 + crop))
    raw = np.stack([ds.read(i)[win] for i in range(ds.k)])
    if model == "robust":
        return robust_pixels(f"{ds.name} {crop}x{crop}", raw, ds.lights, mask[win], ds.intensities)
    return _job_pixels(f"{ds.name} {crop}x{crop}", raw, ds.lights, mask[win], ds.intensities)


def _cpu_ms(fn) -> tuple[float, object]:
    t = time.thread_time()
    out = fn()
    return (time.thread_time() - t) * 1e3, out


def load_baseline(path: Path) -> Callable:
    """``exact_pixels`` of an earlier copy of ``worker/exact.py``, imported by its file name
    from its folder (numba's cache beside it can then load it again)."""
    if not path.is_file() or path.suffix != ".py":
        raise SystemExit(
            f"--baseline {path}: no such Python file (e.g. git show main:worker/exact.py > {path})"
        )
    sys.path.insert(0, str(path.resolve().parent))
    return importlib.import_module(path.stem).exact_pixels


def oracle_nodes(px: Pixels, lo: np.ndarray, hi: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Nodes per pixel when each pixel's first incumbent is optimal: the batch solved again
    behind a copy of itself, each pixel seeded (``above``) by its copy's solution."""
    P = len(px.I)

    def twice(x: np.ndarray) -> np.ndarray:
        return np.concatenate([x, x])

    above = np.concatenate([np.full(P, -1), np.arange(P)])
    res = exact_pixels(twice(px.I), twice(lo), twice(hi), twice(px.V), px.L, px.box_factor, 10**8, above)
    assert np.array_equal(res[0][:P], point, equal_nan=True)  # the first copy is the batch as timed
    return res[3][P:]


def kernel_row(
    px: Pixels,
    reps: int,
    milp_sample: int,
    milp_cap: float,
    baseline: Callable | None = None,
    oracle: bool = False,
) -> dict:
    """The exact kernel on a batch of pixels (best of ``reps``), its nodes, and a MILP check;
    with ``baseline`` (another ``exact_pixels``) that one too, run for run interleaved."""
    I, V, L = px.I, px.V, px.L
    lo, hi = slabs(I, px.eps) if px.lo is None else (px.lo, px.hi)
    kernels = {"new": exact_pixels} | ({"base": baseline} if baseline else {})
    times: dict[str, list[float]] = {name: [] for name in kernels}
    out = {}
    for fn in kernels.values():
        fn(I[:2], lo[:2], hi[:2], V[:2], L, px.box_factor, 10**8)  # JIT load
    for _ in range(reps):
        for name, fn in kernels.items():
            t, out[name] = _cpu_ms(lambda fn=fn: fn(I, lo, hi, V, L, px.box_factor, 10**8))
            times[name].append(t)
    res = out["new"]
    P = len(I)
    counts, nodes = res[2], res[3]
    hard = np.flatnonzero(counts < V.sum(axis=1))
    pick = hard[np.linspace(0, hard.size - 1, min(milp_sample, hard.size)).astype(int)] if hard.size else hard
    milp = "-"
    if pick.size:
        _, _, mc, mcert, _ = MilpSolver(L, milp_cap).solve_rows(
            I[pick], V[pick], (lo[pick], hi[pick]), px.box_factor
        )
        milp = f"{int((mc == counts[pick]).sum())}/{pick.size}"
        low = int((mc < counts[pick]).sum())
        if low:
            milp += f" (MILP lower on {low}{', capped' if not mcert.all() else ''})"
    row = {
        "scene": px.name,
        "k": L.shape[0],
        "pixels": P,
        "eps": px.eps,
        "ms": min(times["new"]) / P,
        "ms_med": float(np.median(times["new"])) / P,
        "nodes": float(nodes.mean()),
        "p99": float(np.percentile(nodes, 99)),
        "cert": bool(res[4].all()),
        "milp": milp,
    }
    if oracle:
        on = oracle_nodes(px, lo, hi, res[0])
        row |= {"oracle_nodes": float(on.mean()), "oracle_p99": float(np.percentile(on, 99))}
    if baseline:
        b = out["base"]
        row |= {
            "base_ms": min(times["base"]) / P,
            "base_ms_med": float(np.median(times["base"])) / P,
            "base_nodes": float(b[3].mean()),
            "base_p99": float(np.percentile(b[3], 99)),
            "same": bool((b[2] == counts).all()),
        }
    return row


def print_kernel_table(rows: list[dict], title: str) -> None:
    print(f"\n{title}\n")
    if rows and "base_ms" in rows[0]:
        print(
            "| scene | k | pixels | eps | base ms/px (best / median) | ms/px (best / median) | speed-up "
            "| base nodes/px | nodes/px | base p99 nodes | p99 nodes | counts == base | count == MILP |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    else:
        print("| scene | k | pixels | eps | ms/px | nodes/px | p99 nodes | count == MILP |")
        print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        cert = "" if r["cert"] else " (budget hit)"
        head = f"| {r['scene']} | {r['k']} | {r['pixels']} | {r['eps']:.3g} "
        if "base_ms" in r:
            print(
                head + f"| {r['base_ms']:.4f} / {r['base_ms_med']:.4f} | {r['ms']:.4f} / {r['ms_med']:.4f} "
                f"| {r['base_ms'] / r['ms']:.2f}x | {r['base_nodes']:.1f} | {r['nodes']:.1f} "
                f"| {r['base_p99']:.0f} | {r['p99']:.0f} | {'yes' if r['same'] else 'NO'} "
                f"| {r['milp']}{cert} |"
            )
        else:
            print(head + f"| {r['ms']:.4f} | {r['nodes']:.0f} | {r['p99']:.0f} | {r['milp']}{cert} |")
    if rows and "oracle_nodes" in rows[0]:
        print("\nwith an optimal first incumbent (--oracle): nodes/px, p99 nodes\n")
        for r in rows:
            print(
                f"- {r['scene']}: {r['nodes']:.1f} -> {r['oracle_nodes']:.1f}, "
                f"p99 {r['p99']:.0f} -> {r['oracle_p99']:.0f}"
            )


def capture_pixels(k: int) -> Pixels:
    """The capture ``python -m bench.phases`` times (:func:`bench.phases.make_capture`: a realistic
    16-bit scene written as a DiLiGenT-layout folder of PNGs), read back from its files and given
    to the kernel as :func:`robust_pixels` does: the mask's bounding box in one tile."""
    from bench.phases import make_capture

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "capture"
        make_capture(folder, k)
        ds = load_folder(folder)
        assert ds.mask is not None
        ys, xs = np.nonzero(ds.mask)
        win = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
        raw = np.stack([ds.read(i)[win] for i in range(ds.k)])
        return robust_pixels(f"bench capture ({k} images)", raw, ds.lights, ds.mask[win], ds.intensities)


def kernel_tables(args: argparse.Namespace) -> None:
    baseline = load_baseline(args.baseline) if args.baseline else None

    def run(px: Pixels) -> dict:
        return kernel_row(px, args.reps, args.milp_sample, args.milp_cap, baseline, args.oracle)

    rows = [run(realistic_pixels(k, args.real_size)) for k in args.real_ks]
    print_kernel_table(rows, "exact kernel, realistic scene (16-bit, auto eps)")
    if args.uw_crop > 0 and (DATA / "uw-psm").is_dir():
        rows = [run(dataset_pixels(DATA / "uw-psm" / o, args.uw_crop)) for o in UW_OBJECTS]
        print_kernel_table(rows, "exact kernel, UW psm objects (12 images, 8-bit, auto eps)")
    if args.diligent_crop > 0 and (DATA / "diligent-crop8").is_dir():
        dil = DATA / "diligent-crop8"
        rows = [run(dataset_pixels(dil / o, args.diligent_crop, args.model)) for o in DILIGENT_OBJECTS]
        print_kernel_table(
            rows, f"exact kernel, DiLiGenT crops (96 images, 8-bit, auto eps, {args.model} model)"
        )
    if args.capture > 0:
        rows = [run(capture_pixels(args.capture))]
        print_kernel_table(rows, "exact kernel, the capture of bench.phases (16-bit, robust model, auto eps)")


def sphere_table(args: argparse.Namespace) -> None:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tables", nargs="+", choices=["sphere", "kernel"], default=["sphere", "kernel"])
    ap.add_argument("--ks", type=int, nargs="+", default=[12, 24, 48, 96, 196])
    ap.add_argument("--size", type=int, default=64, help="sphere image edge in pixels")
    ap.add_argument("--sample", type=int, default=40, help="pixels timed one by one (and for milp)")
    ap.add_argument("--milp-cap", type=float, default=5.0, help="MILP seconds per pixel")
    ap.add_argument("--eps", type=float, default=1.0)
    ap.add_argument("--real-ks", type=int, nargs="+", default=[48, 96, 196, 400], help="kernel: realistic k")
    ap.add_argument("--real-size", type=int, default=40, help="kernel: realistic scene edge in pixels")
    ap.add_argument("--uw-crop", type=int, default=96, help="kernel: UW crop edge (0: skip)")
    ap.add_argument("--diligent-crop", type=int, default=64, help="kernel: DiLiGenT crop edge (0: skip)")
    ap.add_argument(
        "--capture", type=int, default=96, help="kernel: images of bench.phases' capture (0: skip)"
    )
    ap.add_argument("--reps", type=int, default=3, help="kernel: interleaved timing runs (best taken)")
    ap.add_argument("--milp-sample", type=int, default=5, help="kernel: pixels checked against the MILP")
    ap.add_argument(
        "--model",
        choices=["paper", "robust"],
        default="paper",
        help="kernel: the DiLiGenT crops' slabs (robust: as maxfs run's defaults give them)",
    )
    ap.add_argument("--baseline", type=Path, help="kernel: an earlier worker/exact.py to time alongside")
    ap.add_argument(
        "--oracle",
        action="store_true",
        help="kernel: also the nodes with each pixel's optimum as its first incumbent",
    )
    ap.add_argument("--quick", action="store_true", help="smaller runs of every table")
    args = ap.parse_args()
    if args.quick:
        args.ks, args.size, args.sample = [12, 48], 32, 15
        args.real_ks, args.real_size, args.uw_crop, args.diligent_crop = [48, 96], 24, 48, 32
        args.reps, args.milp_sample, args.capture = 2, 3, 0

    if "sphere" in args.tables:
        sphere_table(args)
    if "kernel" in args.tables:
        kernel_tables(args)


if __name__ == "__main__":
    main()
