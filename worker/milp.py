"""The paper's big-M MILP (eq. 12) solved with HiGHS: the reference solver.

Variables: ``n`` (3, continuous, in the box ``[-U, U]``) and ``y_i`` (binary,
1 = image i is an outlier). Minimise ``sum y`` subject to, per usable image,

    L_i . n - Mp_i y_i <= b_i        L_i . n + Mm_i y_i >= a_i

The big-M values are the largest violation over the box (eq. 5), so they never
cut off an optimum: ``Mp_i = U ||L_i||_1 - b_i``, ``Mm_i = a_i + U ||L_i||_1``.
A one-sided slab (``a_i = -inf``, a shadow: ``L_i . n <= b_i``) has only the first
row; its second is free (bounds ``-inf, inf``), so ``Mp_i`` alone must be valid, and is.
(The paper's ``M = 255 + eps`` is not valid for a box of +-255.) Unusable images
get ``y_i`` fixed to 1 and free rows.

The slab bounds ``a_i, b_i`` are given per observation, exactly as the exact solver
takes them (``lo, hi`` of :func:`worker.problem.slabs`, whatever the tolerance model),
so both solve the identical problem; a number ``eps`` stands for the paper's slabs.

One ``Highs`` object is built per batch and re-used: each pixel changes row
bounds, column bounds and the big-M coefficients only. HiGHS objects cannot be
pickled, so build them inside the task that uses them. ``threads=1`` everywhere.
"""

from __future__ import annotations

import os
import sys
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from maxfs.worker.cancel import checkpoint
from maxfs.worker.problem import box_halfwidth, slabs

if TYPE_CHECKING:  # imported where a model is built: a run that needs no MILP never loads HiGHS
    import highspy

#: Slab bounds of a pixel batch: ``(lo, hi)``, or ``eps`` for the paper's slabs.
Bounds = float | tuple[NDArray[np.float64], NDArray[np.float64]]

_banner_lock = threading.Lock()
_banner_done = False


def new_highs(highspy: Any) -> Any:
    """``highspy.Highs()`` without the banner HiGHS (1.16) writes to the process's stdout the first
    time one is made, whatever ``output_flag`` says: a MILP fallback would print its copyright
    between ``maxfs run``'s progress lines. The first one is made with fd 1 on /dev/null."""
    global _banner_done
    with _banner_lock:
        if _banner_done:
            return highspy.Highs()
        sys.stdout.flush()
        saved = os.dup(1)
        try:
            with open(os.devnull, "w") as null:
                os.dup2(null.fileno(), 1)
                h = highspy.Highs()
        finally:
            os.dup2(saved, 1)
            os.close(saved)
        _banner_done = True
        return h


#: Re-check tolerance for claimed inliers, relative to the pixel's largest b.
#: HiGHS accepts y_i within integrality tolerance of 0, which lets a big-M row
#: be violated by about M * 1e-9; anything beyond this is reported.
RECHECK_REL_TOL = 1e-6


@dataclass(frozen=True)
class MilpStats:
    """Per-pixel solve facts: which pixels stopped at the time limit."""

    capped: NDArray[np.bool_]
    claimed: NDArray[np.int32]  # k - objective: the inlier count HiGHS reports


class MilpSolver:
    """A reusable HiGHS model for pixels of one light set.

    Parameters
    ----------
    lights
        ``(k, 3)`` unit light directions.
    time_limit
        Seconds per pixel; a pixel that hits it is reported as not certified.
    """

    def __init__(self, lights: NDArray[np.float64], time_limit: float = 60.0) -> None:
        self.L = np.ascontiguousarray(lights, dtype=np.float64)
        self.k = self.L.shape[0]
        self.l1 = np.abs(self.L).sum(axis=1)
        self.time_limit = float(time_limit)
        import highspy

        self._highspy = highspy
        h = new_highs(highspy)
        for name, value in (
            ("output_flag", False),
            ("threads", 1),
            ("mip_rel_gap", 0.0),
            # the objective is an integer: a gap below 1 proves optimality
            ("mip_abs_gap", 0.5),
            ("mip_feasibility_tolerance", 1e-9),
            ("primal_feasibility_tolerance", 1e-9),
            # feasibility jump alone costs ~4 ms per tiny solve and we pass a start
            ("mip_heuristic_run_feasibility_jump", False),
            ("mip_heuristic_effort", 0.3),
            ("time_limit", self.time_limit),
        ):
            h.setOptionValue(name, value)
        inf = highspy.kHighsInf
        k = self.k
        h.addVars(3, np.full(3, -1.0), np.full(3, 1.0))
        h.addVars(k, np.zeros(k), np.ones(k))
        h.changeColsIntegrality(
            k, np.arange(3, 3 + k, dtype=np.int32), np.full(k, highspy.HighsVarType.kInteger)
        )
        h.changeColsCost(k, np.arange(3, 3 + k, dtype=np.int32), np.ones(k))
        for i in range(k):
            cols = np.array([0, 1, 2, 3 + i], dtype=np.int32)
            h.addRow(-inf, 0.0, 4, cols, np.array([*self.L[i], -1.0]))
            h.addRow(0.0, inf, 4, cols, np.array([*self.L[i], 1.0]))
        self.h = h
        self.inf = inf

    def solve_pixel(
        self, intensities: NDArray[np.float64], valid: NDArray[np.bool_], bounds: Bounds, box_factor: float
    ) -> tuple[NDArray[np.float64], int, bool]:
        """Solve one pixel: returns (point n, claimed optimal count, finished).

        ``bounds`` is ``(a, b)`` of shape ``(k,)`` each (``intensities`` then only seed
        the least-squares start), or ``eps`` for the paper's slabs of ``intensities``.
        """
        h, k, L, inf = self.h, self.k, self.L, self.inf
        I = np.asarray(intensities, dtype=np.float64)
        a, b = _bounds(I, bounds)
        U = box_halfwidth(b, valid, box_factor)
        h.changeColsBounds(3, np.arange(3, dtype=np.int32), np.full(3, -U), np.full(3, U))
        lo_y = np.where(valid, 0.0, 1.0)
        h.changeColsBounds(k, np.arange(3, 3 + k, dtype=np.int32), lo_y, np.ones(k))
        mp = U * self.l1 - b
        # a one-sided slab (a = -inf, a shadow: L.n <= b) has no lower row: it is free
        two = valid & np.isfinite(a)
        mm = np.where(two, a, 0.0) + U * self.l1
        rows = np.arange(2 * k, dtype=np.int32)
        lower = np.empty(2 * k)
        upper = np.empty(2 * k)
        lower[0::2], upper[0::2] = -inf, np.where(valid, b, inf)
        lower[1::2], upper[1::2] = np.where(two, a, -inf), inf
        h.changeRowsBounds(2 * k, rows, lower, upper)
        for i in range(k):
            h.changeCoeff(2 * i, 3 + i, -mp[i])
            h.changeCoeff(2 * i + 1, 3 + i, mm[i])
        # a feasible start: the least-squares point (of the two-sided slabs) and the y it implies
        start = _lsq_start(L, I, two if two.sum() >= 3 else valid, U)
        v = L @ start
        y = np.where(valid & (v >= a) & (v <= b), 0.0, 1.0)
        h.setSolution(_solution(np.concatenate([start, y])))
        h.run()
        status = h.getModelStatus()
        finished = status == self._highspy.HighsModelStatus.kOptimal
        sol = np.asarray(h.getSolution().col_value)
        obj = h.getInfo().objective_function_value
        claimed = int(k - round(obj)) if np.isfinite(obj) else 0
        # Clear the solver's search state, keep the model (the next pixel edits it).
        h.clearSolver()
        return sol[:3].copy(), claimed, bool(finished)

    def solve_rows(
        self, I: NDArray[np.float64], valid: NDArray[np.bool_], bounds: Bounds, box_factor: float
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.int32], NDArray[np.bool_], MilpStats]:
        """Solve ``(P, k)`` pixels: (point, inliers, count, certified, stats).

        ``bounds`` is ``(lo, hi)`` of shape ``(P, k)`` each, or ``eps`` (the paper's
        slabs of ``I``); see :meth:`solve_pixel`.

        ``count`` is the number of usable images that really lie in their slab at
        the returned point (tolerance :data:`RECHECK_REL_TOL`); ``stats.claimed``
        is what HiGHS reported.
        """
        P, k = I.shape
        point = np.full((P, 3), np.nan)
        inl = np.zeros((P, k), dtype=bool)
        count = np.zeros(P, dtype=np.int32)
        cert = np.ones(P, dtype=bool)
        capped = np.zeros(P, dtype=bool)
        claimed = np.zeros(P, dtype=np.int32)
        lo, hi = _bounds(np.asarray(I, dtype=np.float64), bounds)
        for p in range(P):
            if p:
                checkpoint(p, P)  # a tile task notices a cancel between pixels (worker.cancel)
            v = valid[p]
            if v.sum() < 3:
                continue
            a, b = lo[p], hi[p]
            n, c, done = self.solve_pixel(I[p], v, (a, b), box_factor)
            tol = RECHECK_REL_TOL * b[v].max()
            d = self.L @ n
            inl[p] = v & (d >= a - tol) & (d <= b + tol)
            point[p] = n
            count[p] = inl[p].sum()
            claimed[p] = c
            cert[p] = done
            capped[p] = not done
        return point, inl, count, cert, MilpStats(capped, claimed)


def _bounds(I: NDArray[np.float64], bounds: Bounds) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if isinstance(bounds, tuple):
        a, b = (np.asarray(x, dtype=np.float64) for x in bounds)
        if a.shape != I.shape or b.shape != I.shape:
            raise ValueError(f"slab bounds have shapes {a.shape}, {b.shape}; the intensities {I.shape}")
        return a, b
    return slabs(I, float(bounds))


def _solution(values: NDArray[np.float64]) -> highspy.HighsSolution:
    import highspy

    sol = highspy.HighsSolution()
    sol.col_value = list(values)
    sol.value_valid = True
    return sol


def _lsq_start(
    L: NDArray[np.float64], I: NDArray[np.float64], valid: NDArray[np.bool_], U: float
) -> NDArray[np.float64]:
    n, *_ = np.linalg.lstsq(L[valid], I[valid], rcond=None)
    return np.clip(n, -U, U)
