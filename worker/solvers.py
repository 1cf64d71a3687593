"""The solver registry: each name of :class:`storage.options.Solver` mapped to its search.

Every search takes the same :class:`Batch` and returns the same :class:`Search`, so
:func:`worker.solve.solve_pixels` does the common parts (the refit, the fallback, the
``source`` codes) once and never branches on a solver's name. Adding a solver is adding
a name to :class:`~storage.options.Solver` and an entry to :data:`SOLVERS`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.options import Solver
from maxfs.storage.outputs import Source
from maxfs.worker.lstsq import refit
from maxfs.worker.milp import MilpSolver
from maxfs.worker.outliers import first_pass, near_mirror
from maxfs.worker.problem import Thresholds, candidates, slabs, usable


@dataclass(frozen=True)
class Batch:
    """What every solver sees of a batch of P pixels with k images."""

    I: NDArray[np.float64]  # (P, k) grey intensities, divided by the light intensities
    S: NDArray[np.float64]  # (P, k) what L.n should match (I, or I^(1/g) under a response)
    L: NDArray[np.float64]  # (k, 3) unit light directions
    th: Thresholds
    active: NDArray[np.bool_]  # (P,) pixels to solve
    outlier: NDArray[np.bool_] | None  # (P, k) observations known to be unusable
    max_nodes: int
    milp_time_limit: float
    usable: NDArray[np.bool_] | None = None  # (P, k) :func:`~worker.problem.usable` of I, if known


@dataclass(frozen=True)
class Search:
    """A solver's answer before the common refit."""

    point: NDArray[np.float64]  # (P, 3) the point found (NaN where none)
    inliers: NDArray[np.bool_]  # (P, k)
    optimal: NDArray[np.bool_]  # (P,) the optimum is proved
    nodes: NDArray[np.int64]  # (P,) search nodes (exact solver)
    source: NDArray[np.uint8]  # (P,) :class:`~storage.outputs.Source` before the refit


@dataclass(frozen=True)
class SolverImpl:
    """A registered solver: its search, and whether the model's fallback applies to it
    (a Max-FS search can leave a pixel without a normal; least squares cannot)."""

    search: Callable[[Batch], Search]
    max_fs: bool


def _least_squares(b: Batch) -> Search:
    """Woodham: every finite observation is an inlier; nothing is proved."""
    P = b.I.shape[0]
    inl = np.isfinite(b.I) & b.active[:, None]
    return Search(
        refit(b.S, inl, b.L),
        inl,
        np.zeros(P, dtype=bool),
        np.zeros(P, dtype=np.int64),
        np.full(P, Source.FIT, dtype=np.uint8),
    )


#: A Max-FS search over the rows that have 3 or more candidates:
#: ``(S, lo, hi, valid, L, batch) -> (point, inliers, nodes, proved)``.
RowSearch = Callable[
    [NDArray, NDArray, NDArray, NDArray, NDArray, Batch],
    tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.int64], NDArray[np.bool_]],
]


def _exact_rows(S, lo, hi, valid, L, b: Batch):
    from maxfs.worker.exact import exact_pixels  # numba: only for the exact solver, not l2 or milp

    pt, il, _, nd, cert = exact_pixels(S, lo, hi, valid, L, b.th.box_factor, b.max_nodes)
    redo = np.flatnonzero(~cert)
    if redo.size:  # budget exhausted: the MILP decides
        mpt, mil, _, mcert = _milp_rows(S[redo], lo[redo], hi[redo], valid[redo], L, b)
        better = mil.sum(axis=1) >= il[redo].sum(axis=1)
        pt[redo[better]] = mpt[better]
        il[redo[better]] = mil[better]
        cert[redo] = mcert
    return pt, il, nd, cert


def _milp_rows(S, lo, hi, valid, L, b: Batch):
    pt, il, _, cert, _ = MilpSolver(L, b.milp_time_limit).solve_rows(S, valid, (lo, hi), b.th.box_factor)
    return pt, il, np.zeros(len(S), dtype=np.int64), cert


def _max_fs(rows_search: RowSearch) -> Callable[[Batch], Search]:
    def search(b: Batch) -> Search:
        P, k = b.I.shape
        use = usable(b.I.T, b.th).T if b.usable is None else b.usable
        valid = candidates(b.I, b.th, b.outlier, b.active, use=use)
        lit = valid & use  # two-sided slabs; the rest are one-sided shadows
        bounds = None  # every pixel's slabs, when the shadow test needs them anyway
        if b.th.mirror_deg > 0 or b.th.shadow_slabs:
            n0 = first_pass(b.S, lit, b.L)
            if b.th.shadow_slabs:
                # a shadow is a one-sided slab only where the first pass agrees the light is
                # behind the surface; a dark image the first pass calls lit is a cast shadow
                bounds = slabs(b.I, b.th)
                with np.errstate(invalid="ignore"):
                    valid &= lit | ~(n0 @ b.L.T > bounds[1])
            if b.th.mirror_deg > 0:
                bright = near_mirror(b.S, lit, b.L, b.th.mirror_deg, _one_sigma(b), n0)
                valid &= ~bright
                lit &= ~bright
        point = np.full((P, 3), np.nan)
        inl = np.zeros((P, k), dtype=bool)
        optimal = np.zeros(P, dtype=bool)
        nodes = np.zeros(P, dtype=np.int64)
        source = np.full(P, Source.UNDETERMINED, dtype=np.uint8)
        rows = np.flatnonzero(lit.sum(axis=1) >= 3)
        if rows.size:
            if bounds is not None and b.th.response == 1.0:
                # the same slabs as computing them on the rows: add, subtract and max are exact
                # per value (a power, under a response, may round differently by position)
                lo, hi = bounds if rows.size == P else (bounds[0][rows], bounds[1][rows])
            else:
                lo, hi = slabs(b.I[rows], b.th)
            if rows.size == P:  # every pixel (a tile inside the object): no copies (searches read them)
                pt, il, nd, cert = rows_search(b.S, lo, hi, valid, b.L, b)
                point, inl = np.asarray(pt, np.float64), np.asarray(il, bool)
                optimal, nodes = np.asarray(cert, bool), np.asarray(nd, np.int64)
            else:
                pt, il, nd, cert = rows_search(b.S[rows], lo, hi, valid[rows], b.L, b)
                point[rows], inl[rows], optimal[rows], nodes[rows] = pt, il, cert, nd
            source[rows] = np.where(cert, Source.CERTIFIED, Source.BEST_FOUND)
        return Search(point, inl, optimal, nodes, source)

    return search


def _one_sigma(b: Batch) -> float:
    """One noise sigma (eps is three) in the units of ``S``: the highlight test's margin."""
    s = b.th.eps / 3.0
    return s ** (1.0 / b.th.response) if b.th.response != 1.0 else s


#: Name -> implementation; the one place a solver's name meets its code.
SOLVERS: dict[Solver, SolverImpl] = {
    Solver.EXACT: SolverImpl(_max_fs(_exact_rows), max_fs=True),
    Solver.MILP: SolverImpl(_max_fs(_milp_rows), max_fs=True),
    Solver.L2: SolverImpl(_least_squares, max_fs=False),
}
