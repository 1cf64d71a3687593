"""Compiled least trimmed squares per pixel, for the job-level estimates (:mod:`worker.noise`).

:func:`lts_normals` is :func:`worker.noise.lts_fit` pixel by pixel: the 3 x 3 normal equations
of the kept observations (summed over them, solved by cofactors with the same determinant test
as :func:`worker.lstsq.refit`), then the kth smallest residual by selection (the same value
``np.sort`` gives, NaN last) instead of sorting whole rows. It replaces about twenty numpy passes
over the ``(P, k)`` sample per round (each refit builds weights, a masked copy and two BLAS
products) with one pass per pixel, and releases the GIL, so the response candidates run on
threads as before. Its sums run over the kept observations in image order, numpy's through
BLAS: the normals agree to rounding (a few ulps), not bit for bit.

Only :mod:`worker.noise` imports it, when an estimate runs: numba loads its cache then.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: As :data:`worker.lstsq._COND`.
_COND = 1e-9


@njit(cache=True, nogil=True, inline="always")
def _refit_one(I, keep, L, out):  # pragma: no cover - compiled
    g00 = g01 = g02 = g11 = g12 = g22 = 0.0
    r0 = r1 = r2 = 0.0
    cnt = 0
    for i in range(I.shape[0]):
        if keep[i]:
            cnt += 1
            a, b, c = L[i, 0], L[i, 1], L[i, 2]
            g00 += a * a
            g01 += a * b
            g02 += a * c
            g11 += b * b
            g12 += b * c
            g22 += c * c
            v = I[i]
            r0 += v * a
            r1 += v * b
            r2 += v * c
    c00, c11, c22 = g11 * g22 - g12 * g12, g00 * g22 - g02 * g02, g00 * g11 - g01 * g01
    c01, c02, c12 = g02 * g12 - g01 * g22, g01 * g12 - g02 * g11, g01 * g02 - g00 * g12
    det = g00 * c00 + g01 * c01 + g02 * c02
    tr = g00 + g11 + g22
    if cnt >= 3 and det > _COND * tr**3:
        out[0] = (c00 * r0 + c01 * r1 + c02 * r2) / det
        out[1] = (c01 * r0 + c11 * r1 + c12 * r2) / det
        out[2] = (c02 * r0 + c12 * r1 + c22 * r2) / det
        return True
    out[0] = out[1] = out[2] = np.nan
    return False


@njit(cache=True, nogil=True, inline="always")
def _kth_smallest(a, b, m, kth):  # pragma: no cover - compiled
    """The ``kth`` (0-based) smallest of ``a[:m]`` (finite values); ``a`` and ``b`` (scratch, as
    long) are overwritten. Quickselect whose partition counts and compacts without branches
    (a comparison's outcome is added, not branched on): 3x faster than swapping in place at
    k = 96, where the selection is most of an LTS round."""
    while m > 12:
        x, y, z = a[0], a[m // 2], a[m - 1]
        pivot = max(min(x, y), min(max(x, y), z))  # the median of three
        lt = 0
        le = 0
        for i in range(m):
            lt += a[i] < pivot
            le += a[i] <= pivot
        if kth < lt:
            j = 0
            for i in range(m):
                b[j] = a[i]
                j += a[i] < pivot
            m = lt
        elif kth < le:
            return pivot
        else:
            j = 0
            for i in range(m):
                b[j] = a[i]
                j += a[i] > pivot
            m -= le
            kth -= le
        a, b = b, a
    for i in range(1, m):  # insertion sort of the last few
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v
    return a[kth]


@njit(cache=True, nogil=True, inline="always")
def _keep_closest(sel, r, buf, tmp, nfin, nnan, half, keep):  # pragma: no cover - compiled
    """``keep = sel & (r <= kth)``, ``kth`` the ``half``-th smallest of the row as numpy's sort
    sees it: the ``nfin`` finite residuals in ``buf``, then inf (unselected observations or
    infinite residuals), then the ``nnan`` NaN."""
    k = r.shape[0]
    if half - 1 < nfin:
        kth = _kth_smallest(buf, tmp, nfin, half - 1)
    elif half - 1 < k - nnan:
        kth = np.inf
    else:
        kth = np.nan
    for i in range(k):
        keep[i] = sel[i] and r[i] <= kth


@njit(cache=True, nogil=True, inline="always")
def _lts_row(I, sel, L, rounds, keep, r, buf, tmp, n):  # pragma: no cover - compiled
    """One pixel's LTS ``n`` (into ``n``; NaN when undetermined), with scratch ``keep``, ``r``,
    ``buf`` and ``tmp`` of the row's length; True when ``n`` is determined."""
    k = I.shape[0]
    m = 0
    for i in range(k):
        keep[i] = sel[i]
        if sel[i]:
            m += 1
    half = max(3, m // 2)
    ok = _refit_one(I, keep, L, n)
    for _ in range(rounds):
        if not ok:
            # NaN residuals keep nothing (np.sort puts NaN last; NaN <= kth is False)
            break
        nfin = 0  # finite residuals of the selected observations, into buf
        nnan = 0
        for i in range(k):
            if sel[i]:
                v = abs(I[i] - (n[0] * L[i, 0] + n[1] * L[i, 1] + n[2] * L[i, 2]))
                r[i] = v
                if np.isnan(v):
                    nnan += 1
                elif v < np.inf:
                    buf[nfin] = v
                    nfin += 1
        _keep_closest(sel, r, buf, tmp, nfin, nnan, half, keep)
        ok = _refit_one(I, keep, L, n)
    return ok


@njit(cache=True, nogil=True)
def lts_normals(I, sel, L, rounds):  # pragma: no cover - compiled
    """(P, 3) LTS ``n`` of ``I`` (P, k) on ``sel`` (P, k) with lights ``L`` (k, 3): refit on the
    ``max(3, m // 2)`` observations closest to the fit (``m``: the row's selected ones), ``rounds``
    times, then once more; NaN where a fit is undetermined (as :func:`worker.lstsq.refit`)."""
    P, k = I.shape
    out = np.empty((P, 3))
    keep = np.empty(k, np.bool_)
    r, buf, tmp, n = np.empty(k), np.empty(k), np.empty(k), np.empty(3)
    for p in range(P):
        _lts_row(I[p], sel[p], L, rounds, keep, r, buf, tmp, n)
        out[p, 0], out[p, 1], out[p, 2] = n[0], n[1], n[2]
    return out


@njit(cache=True, nogil=True)
def response_medians(I, sel, L, g, rounds):  # pragma: no cover - compiled
    """Per pixel, the median of ``|I - max(L.n, 0)^g|`` over ``sel`` after the LTS fit of ``L.n``
    to ``I^(1/g)`` (:func:`worker.noise.response_criterion` before its median over pixels); NaN
    where the fit is undetermined or no residual is finite."""
    P, k = I.shape
    out = np.full(P, np.nan)
    keep = np.empty(k, np.bool_)
    S, r, buf, tmp, n = np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(3)
    inv = 1.0 / g
    for p in range(P):
        Ip = I[p]
        sp = sel[p]
        if g == 1.0:  # (a branch per row, not per value: half the time of this loop)
            S[:] = Ip
        else:
            # the power only where the fit reads it (the selected observations): it is most
            # of a candidate g's cost, and a pixel's unselected values are never read
            for i in range(k):
                if sp[i]:
                    S[i] = Ip[i] ** inv
        if not _lts_row(S, sp, L, rounds, keep, r, buf, tmp, n):
            continue
        cnt = 0
        for i in range(k):
            if sel[p, i]:
                pred = max(n[0] * L[i, 0] + n[1] * L[i, 1] + n[2] * L[i, 2], 0.0)
                if g != 1.0:
                    pred = pred**g
                v = abs(I[p, i] - pred)
                if v < np.inf:
                    buf[cnt] = v
                    cnt += 1
        if cnt == 0:
            continue
        for i in range(cnt):
            r[i] = buf[i]
        lo = _kth_smallest(buf, tmp, cnt, (cnt - 1) // 2)
        # the next order statistic: lo again if enough values tie with it, else the least above
        le, hi = 0, np.inf
        for i in range(cnt):
            v = r[i]
            le += v <= lo
            if v > lo and v < hi:
                hi = v
        out[p] = 0.5 * (lo + (lo if le > cnt // 2 else hi))
    return out


@njit(cache=True, nogil=True)
def lts_keep(I, P, sel, half, keep):  # pragma: no cover - compiled
    """One round of :func:`worker.noise.lts_fit` after its refit, given the fit's predictions ``P``
    (``n @ L.T``, from numpy): ``keep = sel & (|I - P| <= kth)``, ``kth`` the ``half``-th smallest
    of the row with the unselected observations at inf (NaN last, as ``np.sort``). The same
    arithmetic as numpy's (one subtraction and an absolute value), and selection is exact, so
    ``keep`` is the same, bit for bit."""
    P_, k = I.shape
    r, buf, tmp = np.empty(k), np.empty(k), np.empty(k)
    for p in range(P_):
        h = half[p]
        nfin = 0
        nnan = 0
        for i in range(k):
            if sel[p, i]:
                v = abs(I[p, i] - P[p, i])
                r[i] = v
                if np.isnan(v):
                    nnan += 1
                elif v < np.inf:
                    buf[nfin] = v
                    nfin += 1
        _keep_closest(sel[p], r, buf, tmp, nfin, nnan, h, keep[p])


def warm_up() -> None:
    """Compile (after an install) or load both kernels: what ``maxfs warm`` does for them."""
    L = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])
    I = np.array([[1.0, 0.9, 0.8, 0.7]])
    sel = I > 0
    lts_normals(I, sel, L, 3)
    response_medians(I, sel, L, 1.0, 3)
    lts_keep(I, I, sel, np.array([3]), np.empty_like(sel))
