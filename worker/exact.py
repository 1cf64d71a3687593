"""Exact maximum feasible subsystem by branch and bound over boxes of n-space.

The Max-FS problem at one pixel is the maximum depth of an arrangement of k slabs
``lo_i <= L_i . n <= hi_i`` in 3-D, restricted to the box ``|n_j| <= U``. A slab with
``lo_i = -inf`` is one-sided (a shadow: ``L_i . n <= hi_i``); inside the box it equals the
slab whose lower face lies below the box, which is what the search uses.

Each box in the search carries three numbers: ``f`` slabs contain it wholly,
``p`` slabs cross it (their indices are kept), the rest miss it. ``f + p`` bounds
the depth of any point in the box from above. Children only re-test their
parent's crossing slabs, so deep boxes are cheap.

Most boxes are only a few slabs from being pruned (the seeds are good), and
there a sharper bound pays: the **1-D depth test**. Project every crossing slab,
intersected with the box, onto one axis; a point of the box lies in at most as
many slabs as its coordinate lies in projected intervals. With ``g = f + p - best
- 1`` slabs allowed to miss, the offsets along the axis where at most ``g``
intervals miss form a set whose hull only needs the ``g + 1`` largest interval
starts and ``g + 1`` smallest ends (no full sort). An empty set prunes the box;
otherwise the box **shrinks** to the hull, first in z (the lights' common
direction, where slabs are thinnest), then in x and y, and its slabs are
re-classified from fresh dot products. The x and y tests run only where z halved
the box and it is at most ``_XY_GAP`` slabs from being pruned: elsewhere they
rarely prune, and a split is cheaper than two more passes over the slabs (the
search visits more boxes but spends less time: 1.2-1.4x on the DiLiGenT crops).

In boxes with many crossing slabs (``_BIN_P``) the intervals are counted in
bins instead (O(p) where keeping the extremes costs O(p g)); starts are binned
rounded down and ends rounded up, so the binned hull holds the exact one.

Boxes with many crossing slabs (near the root; ``_VEC_P``, ``_VEC_SHARE``) keep no
row: their tests and split are **contiguous passes** over every usable slab, copied
once per pixel into arrays by axis (no index, no branch, so the compiler vectorises
them; 4 ns per slab where the row passes cost 6-9), from fresh dot products. They
decide exactly as the row passes on the same box; a box below the threshold, or one
an LP or the vertex enumeration decides, gets its row then and goes on with it.

A box **one slab** from being pruned needs a point inside every crossing slab:
a small LP (Seidel's incremental algorithm in 3-D, only the slab faces that
cut the box) decides it, a point (recounted, a new incumbent) or none (pruned),
where bisection would split it again and again along the faces. A box **two
slabs** away with few crossing slabs (``_LP_GAP_P``), or three away with fewer
(``_LP_GAP3_P``), is decided the same way:
where the LP has no point, its infeasible core (at most four slabs that with the
box already hold none, from the constraints the algorithm was moving between)
names the slabs one of which a better point must miss, and the LP runs again
without each in turn. The LP widens every slab and the box by a margin far
above rounding and calls near ties undecided (the box is then split as before),
so it prunes only boxes that hold no better point. Its point lies on the widened
faces, outside the slabs, so where it fails the recount the LP runs again with
the slabs and box narrowed by the margin: a point of that one lies inside them
(before, such boxes were split as undecided: 7.5 k of 18.5 k LPs on the cat crop).

A box with at most three crossing slabs is solved exactly by enumerating the
vertices of its crossing planes and faces, as is a box shrunk below ``hmin``,
which keeps the search finite and exact in degenerate arrangements.

**Every claimed incumbent is recounted from scratch** (a fresh dot product with
every usable light) before it is accepted. The cached, incrementally updated
``L . c`` of a box centre may differ from a fresh one in the last bits; a centre
exactly on a slab face would then claim an inlier it does not hold, and pruning
against that inflated count would discard the true optimum.

The search is depth-first, the child whose centre holds more slabs first (then
the larger bound), seeded with good incumbents (the
previous pixel's and, when given, the pixel above's solution, trimmed least
squares, and alternating projections onto the slabs when least squares misses
only a few usable images); it stops at once when an incumbent holds every usable
image. ``max_nodes`` bounds the work per pixel; a pixel that hits it is reported
as not certified.

The count is exact; which of several optimal points (and so which inlier set)
is returned among ties may differ from an earlier version of this kernel.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit
from numpy.typing import NDArray

from maxfs.worker import cancel
from maxfs.worker.problem import REL_TOL

_STACK = 256  # DFS depth bound; a box this deep is far below ``hmin`` already
_HMIN_REL = 1e-4  # enumerate the vertices of boxes narrower than this times the widest half-width
_SHRINK_GAP = 48  # run the 1-D depth test in boxes at most this many slabs from being pruned
_XY_GAP = 8  # the x and y tests only in boxes at most this many slabs from being pruned ...
_Z_XY = 0.5  # ... and where the z test cut the box's z width to at most this fraction
_BIN_P = 20  # in boxes with at least this many crossing slabs the 1-D test counts intervals in bins
_BINS = 64  # at most this many bins (two per crossing slab)
_SHRINK_KEEP = 0.9  # apply a shrink only when it cuts the box's width along the axis by 10 % or more
_ENUM_P = 3  # enumerate vertices in boxes with at most this many crossing slabs
_AP_GAP = 3  # alternating projections when the incumbent misses at most this many usable images
_AP_SWEEPS = 12
_SIGMA_REL = 1e-12  # rounding slack of box-slab tests, relative to U (far below REL_TOL)
# Integer constants that reach another kernel's arguments are written ``np.int64(...)``: numba types a
# bare ``0`` or ``-1`` as a literal, and while it infers a loop's types it compiles each callee once for
# the literal and once more for int64. Those duplicates were 14 of 25 compiled functions and made the
# first compile after an install 31 s instead of 19 s (tests/test_exact_kernel.py counts them).
# Every kernel but the entry point allocates nothing (work arrays come from ``solve_exact``) and is
# compiled with ``_nrt=False``: numba's reference counting otherwise increments and decrements each
# array argument atomically on every call, a cost paid per node and per slab pass.


@njit(cache=True, nogil=True, _nrt=False)
def _count(L, lo, hi, idx, m, x, y, z):  # pragma: no cover - numba
    """Slabs (widened bounds ``lo``, ``hi``) holding the point, from fresh dot products."""
    c = 0
    for q in range(m):
        j = idx[q]
        v = L[j, 0] * x + L[j, 1] * y + L[j, 2] * z
        if v >= lo[j] and v <= hi[j]:
            c += 1
    return c


@njit(cache=True, nogil=True, _nrt=False)
def _lsq(L, inten, sel, k, out):  # pragma: no cover - numba
    """Least squares ``n`` over the selected images; False if ill-conditioned."""
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    r0 = r1 = r2 = 0.0
    for i in range(k):
        # a weight, not a branch (the selection is data); an unselected row adds +-0.0,
        # which leaves every sum as it was. Its intensity may be NaN: 0 * NaN is not 0
        w = 1.0 if sel[i] else 0.0
        l0 = L[i, 0] * w
        l1 = L[i, 1] * w
        l2 = L[i, 2] * w
        t = inten[i] if sel[i] else 0.0
        s00 += l0 * l0
        s01 += l0 * l1
        s02 += l0 * l2
        s11 += l1 * l1
        s12 += l1 * l2
        s22 += l2 * l2
        r0 += l0 * t
        r1 += l1 * t
        r2 += l2 * t
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    det = s00 * c00 + s01 * c01 + s02 * c02
    tr = s00 + s11 + s22
    if not det > 1e-9 * tr * tr * tr:
        return False
    c11 = s00 * s22 - s02 * s02
    c12 = s01 * s02 - s00 * s12
    c22 = s00 * s11 - s01 * s01
    out[0] = (c00 * r0 + c01 * r1 + c02 * r2) / det
    out[1] = (c01 * r0 + c11 * r1 + c12 * r2) / det
    out[2] = (c02 * r0 + c12 * r1 + c22 * r2) / det
    return True


@njit(cache=True, nogil=True, _nrt=False)
def _countv(Lt, LO, HI, m, x, y, z):  # pragma: no cover - numba
    """:func:`_count` over the usable slabs in contiguous arrays (``Lt``: ``L`` by axis, ``LO``,
    ``HI``: the widened bounds, in the order of ``idx``): the same sums, so the same count,
    without a gather or a branch."""
    c = 0
    for q in range(m):
        v = Lt[0, q] * x + Lt[1, q] * y + Lt[2, q] * z
        c += (v >= LO[q]) & (v <= HI[q])
    return c


@njit(cache=True, nogil=True, _nrt=False)
def _claim(Lt, LO, HI, m, x, y, z, best, bp):  # pragma: no cover - numba
    """Accept ``(x, y, z)`` as the incumbent if its fresh count beats ``best``."""
    cnt = _countv(Lt, LO, HI, m, x, y, z)
    if cnt > best:
        bp[0] = x
        bp[1] = y
        bp[2] = z
        return cnt
    return best


@njit(cache=True, nogil=True, _nrt=False)
def _enum_leaf(
    L, a, b, lo, hi, tol, Lt, LO, HI, m, row, p, c, h, f, best, bp, nrm, off
):  # pragma: no cover - numba
    """Exact depth inside a box: try every vertex of its crossing planes and faces.

    ``row`` holds the ``p`` crossing slabs; a vertex whose count there (plus the
    ``f`` full slabs) beats ``best`` is recounted over all ``m`` before it is taken.
    ``nrm`` (at least ``2 p + 6`` rows of 3) and ``off`` are work arrays.
    """
    npl = 2 * p + 6
    for i in range(npl):
        for d in range(3):
            nrm[i, d] = 0.0
    for q in range(p):
        j = row[q]
        for d in range(3):
            nrm[2 * q, d] = L[j, d]
            nrm[2 * q + 1, d] = L[j, d]
        off[2 * q] = a[j]
        off[2 * q + 1] = b[j]
    for d in range(3):
        nrm[2 * p + 2 * d, d] = 1.0
        nrm[2 * p + 2 * d + 1, d] = 1.0
        off[2 * p + 2 * d] = c[d] - h[d]
        off[2 * p + 2 * d + 1] = c[d] + h[d]
    slack = tol + 1e-9 * max(h[0], max(h[1], h[2]))
    for i in range(npl):
        for j in range(i + 1, npl):
            # cross product of rows i, j (reused for Cramer's rule)
            x0 = nrm[i, 1] * nrm[j, 2] - nrm[i, 2] * nrm[j, 1]
            x1 = nrm[i, 2] * nrm[j, 0] - nrm[i, 0] * nrm[j, 2]
            x2 = nrm[i, 0] * nrm[j, 1] - nrm[i, 1] * nrm[j, 0]
            for l in range(j + 1, npl):
                det = x0 * nrm[l, 0] + x1 * nrm[l, 1] + x2 * nrm[l, 2]
                if abs(det) < 1e-12:
                    continue
                # solve [ni; nj; nl] v = [oi; oj; ol]
                y0 = nrm[j, 1] * nrm[l, 2] - nrm[j, 2] * nrm[l, 1]
                y1 = nrm[j, 2] * nrm[l, 0] - nrm[j, 0] * nrm[l, 2]
                y2 = nrm[j, 0] * nrm[l, 1] - nrm[j, 1] * nrm[l, 0]
                z0 = nrm[l, 1] * nrm[i, 2] - nrm[l, 2] * nrm[i, 1]
                z1 = nrm[l, 2] * nrm[i, 0] - nrm[l, 0] * nrm[i, 2]
                z2 = nrm[l, 0] * nrm[i, 1] - nrm[l, 1] * nrm[i, 0]
                vx = (off[i] * y0 + off[j] * z0 + off[l] * x0) / det
                vy = (off[i] * y1 + off[j] * z1 + off[l] * x1) / det
                vz = (off[i] * y2 + off[j] * z2 + off[l] * x2) / det
                if (
                    abs(vx - c[0]) > h[0] + slack
                    or abs(vy - c[1]) > h[1] + slack
                    or abs(vz - c[2]) > h[2] + slack
                ):
                    continue
                if f + _count(L, lo, hi, row, p, vx, vy, vz) > best:
                    best = _claim(Lt, LO, HI, m, vx, vy, vz, best, bp)
    return best


@njit(cache=True, nogil=True, _nrt=False)
def _keep_largest(buf, size, n, x):  # pragma: no cover - numba
    """Insert ``x`` into ``buf[:size]`` (descending) keeping at most the ``n`` largest; new size."""
    if size < n:
        i = size
        size += 1
    elif x > buf[n - 1]:
        i = n - 1
    else:
        return size
    while i > 0 and buf[i - 1] < x:
        buf[i] = buf[i - 1]
        i -= 1
    buf[i] = x
    return size


@njit(cache=True, nogil=True, _nrt=False)
def _interval(absL, invL, j, v, rad, lj, hj, d, hd):  # pragma: no cover - numba
    """Offsets ``s`` along axis ``d`` (within ``+-hd``) where slab ``j``, at ``L.c = v``
    with half-range ``rad`` over the box, can hold a point of the box."""
    # the slab, with the coordinate along d at c_d + s, reaches v + L_jd s +- ro
    ro = max(rad - absL[j, d] * hd, 0.0)
    iv = invL[j, d]
    if iv == 0.0:  # L_jd = 0: no information along this axis
        return -hd, hd
    t0 = (lj - v - ro) * iv  # sign-free: the interval lies between the two scaled bounds
    t1 = (hj - v + ro) * iv
    return max(min(t0, t1), -hd), min(max(t0, t1), hd)


@njit(cache=True, nogil=True, _nrt=False)
def _hull_pass(
    L, absL, invL, lo, hi, prow, pvrow, prrow, p, f, d, hd, pd, dc, dh, n, bs, bneg
):  # pragma: no cover - numba
    """One pass over a box's crossing slabs: apply a pending move of axis ``pd``
    (centre by ``dc``, half-width by ``dh``; zeros for none), re-classify and compact
    the row, and keep the ``n`` largest starts (``bs``) and ``n`` smallest ends (as
    negated values, ``bneg``) of the slabs' intervals along axis ``d`` (see :func:`_sweep`).

    Returns (f, p, slabs of the row holding the centre, starts kept).
    ``prrow`` holds ``|L|.h`` plus the rounding slack, so "touches" and "contains"
    both err toward "crosses".
    """
    ns = np.int64(0)
    ne = np.int64(0)
    q2 = 0
    cc = 0
    for q in range(p):
        j = prow[q]
        v = pvrow[q] + L[j, pd] * dc
        rad = prrow[q] + absL[j, pd] * dh
        lj = lo[j]
        hj = hi[j]
        full = (v - rad >= lj) & (v + rad <= hj)
        cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
        f += full
        prow[q2] = j
        pvrow[q2] = v
        prrow[q2] = rad
        cc += cross & (v >= lj) & (v <= hj)
        q2 += cross
        if cross:
            s0, s1 = _interval(absL, invL, j, v, rad, lj, hj, d, hd)
            ns = _keep_largest(bs, ns, n, s0)
            ne = _keep_largest(bneg, ne, n, -s1)
    return f, q2, cc, ns


@njit(cache=True, nogil=True, _nrt=False)
def _bins(absL, invL, j, v, rad, lj, hj, d, hd, nb, iw):  # pragma: no cover - numba
    """The bins of slab ``j``'s interval along axis ``d`` (as :func:`_interval`) among ``nb`` equal
    bins of ``[-hd, hd]`` (``iw`` = bins per unit): the start's bin rounded down and the end's
    rounded up, so the bins hold the exact interval."""
    ro = max(rad - absL[j, d] * hd, 0.0)
    iv = invL[j, d]
    t0 = (lj - v - ro) * iv
    t1 = (hj - v + ro) * iv
    wide = nb * (iv == 0.0)  # L_jd = 0 (t0 = t1 = 0): no information, every bin
    u0 = (min(t0, t1) + hd) * iw - 1e-6 - wide
    u1 = (max(t0, t1) + hd) * iw + 1e-6 + wide
    # np.int64, not int(): numba's int() of a float costs several times more here
    return np.int64(min(max(u0, 0.0), nb - 1.0)), np.int64(min(max(u1, 0.0), nb - 1.0))


@njit(cache=True, nogil=True, _nrt=False)
def _hull_pass_bins(
    L, absL, invL, lo, hi, prow, pvrow, prrow, p, f, d, hd, pd, dc, dh, hs, he
):  # pragma: no cover - numba
    """:func:`_hull_pass` for boxes with many crossing slabs: the intervals along axis ``d``
    are counted in ``nb`` equal bins of ``[-hd, hd]`` (``hs`` starts, ``he`` ends; see
    :func:`_sweep_bins`), O(p + nb) where keeping the extremes costs O(p g).
    A start is binned rounded down and an end rounded up, so the bins can only
    under-count the intervals that miss a point. Returns (f, p, slabs of the row
    holding the centre, nb). A separate function: the binned branch inside
    :func:`_hull_pass` slowed its small boxes by a third.
    """
    nb = min(_BINS, max(8, 2 * p))
    for i in range(nb):
        hs[i] = 0
        he[i] = 0
    iw = nb / (2.0 * hd)
    q2 = 0
    cc = 0
    for q in range(p):
        j = prow[q]
        v = pvrow[q] + L[j, pd] * dc
        rad = prrow[q] + absL[j, pd] * dh
        lj = lo[j]
        hj = hi[j]
        full = (v - rad >= lj) & (v + rad <= hj)
        cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
        f += full
        prow[q2] = j
        pvrow[q2] = v
        prrow[q2] = rad
        cc += cross & (v >= lj) & (v <= hj)
        q2 += cross
        # every slab's interval is binned, weighted by ``cross``, without a branch
        b0, b1 = _bins(absL, invL, j, v, rad, lj, hj, d, hd, nb, iw)
        hs[b0] += cross
        he[b1] += cross
    return f, q2, cc, nb


@njit(cache=True, nogil=True, _nrt=False)
def _bin_intervals(absL, invL, lo, hi, prow, pvrow, prrow, p, d, hd, hs, he):  # pragma: no cover - numba
    """:func:`_hull_pass_bins` for a row that holds exactly the box's crossing slabs (no move
    pending: a box as pushed, or after a pass that did not shrink it): the intervals only.
    Returns (slabs of the row holding the centre, nb)."""
    nb = min(_BINS, max(8, 2 * p))
    for i in range(nb):
        hs[i] = 0
        he[i] = 0
    iw = nb / (2.0 * hd)
    cc = 0
    for q in range(p):
        j = prow[q]
        v = pvrow[q]
        rad = prrow[q]
        lj = lo[j]
        hj = hi[j]
        cc += (v >= lj) & (v <= hj)
        b0, b1 = _bins(absL, invL, j, v, rad, lj, hj, d, hd, nb, iw)
        hs[b0] += 1
        he[b1] += 1
    return cc, nb


@njit(cache=True, nogil=True, _nrt=False)
def _sweep_bins(hs, he, nb, g, hd):  # pragma: no cover - numba
    """:func:`_sweep` on binned intervals: a hull ``[smin, smax]`` that holds every offset
    where at most ``g`` intervals miss. In bin ``b`` at least the starts of higher bins and
    the ends of lower ones miss; the hull spans the bins where those are at most ``g``.
    Returns (nonempty, smin, smax).
    """
    w = 2.0 * hd / nb
    tot = 0
    for i in range(nb):
        tot += hs[i]
    above = tot  # starts in bins > b
    below = 0  # ends in bins < b
    bmin = -1
    bmax = -1
    for b in range(nb):
        above -= hs[b]
        if above + below <= g:
            if bmin < 0:
                bmin = b
            bmax = b
        below += he[b]
    if bmin < 0:
        return False, 0.0, 0.0
    return True, -hd + bmin * w, hd if bmax == nb - 1 else -hd + (bmax + 1) * w


@njit(cache=True, nogil=True, _nrt=False)
def _sweep(bs, bneg, g):  # pragma: no cover - numba
    """Hull ``[smin, smax]`` of the offsets ``s`` where at most ``g`` intervals miss.

    ``bs`` holds (at least) the ``g + 1`` largest interval starts ``S_j``, descending,
    ``bneg`` the ``g + 1`` smallest ends ``E_j``, negated (so descending too). A point
    at ``s`` misses ``cnt(s) = #{S_j > s} + #{E_j < s}`` intervals; the leftmost ``s``
    with ``cnt(s) <= g`` is one of the ``g + 1`` largest starts and the rightmost one
    of the ``g + 1`` smallest ends, so nothing else is needed (no full sort).
    Returns (nonempty, smin, smax).
    """
    n = g + 1
    smin = 0.0
    found = False
    jb = 0
    for i in range(n - 1, -1, -1):  # starts, ascending; i = #starts strictly greater
        s = bs[i]
        if i > 0 and bs[i - 1] == s:
            continue
        while jb < n and -bneg[jb] < s:
            jb += 1
        if jb == n:
            break
        if i + jb <= g:
            smin = s
            found = True
            break
    if not found:
        return False, 0.0, 0.0
    smax = smin
    ja = 0
    for i in range(n - 1, -1, -1):  # ends, descending; i = #ends strictly smaller
        s = -bneg[i]
        if i > 0 and bneg[i - 1] == bneg[i]:
            continue
        while ja < n and bs[ja] > s:
            ja += 1
        if ja == n:
            break
        if i + ja <= g:
            smax = s
            break
    if smax < smin:
        smax = smin
    return True, smin, smax


_LP_GAP = 3  # LPs decide boxes at most this many slabs from being pruned (up to 4 ** (gap - 1) LPs) ...
_LP_GAP_P = 48  # ... two slabs only with at most this many crossing slabs (an LP costs O(p) or more) ...
_LP_GAP3_P = 12  # ... and three only with at most this many
_LP_PAR = 1e-6  # an LP row with coefficients below this (relative) is "parallel": decided by its constant
_LP_SLACK = (
    1e-6  # the LP's slabs and box are widened by this times the box's scale: it only prunes by a margin
)
_NONE = -1  # an LP row or constraint that is a face of the box, not of a slab


@njit(cache=True, nogil=True, _nrt=False)
def _lp_line(A2, b2, i, ulo, uhi, vlo, vhi, u0, v0, T):  # pragma: no cover - numba
    """The 1-D step of :func:`_lp_plane`: on the line ``A2[i] . y = b2[i]``, a point of the
    rows before ``i`` and the box. Returns (status, u, v, jlo, jhi) with status as
    :func:`_lp_box`'s; where there is no point, ``jlo`` and ``jhi`` are the rows (or
    ``_NONE`` for the box) that leave none with row ``i``."""
    none = np.int64(_NONE)
    a0 = A2[i, 0]
    a1 = A2[i, 1]
    par = _LP_PAR * T
    if abs(a0) < _LP_PAR and abs(a1) < _LP_PAR:  # no line: the row holds everywhere or nowhere
        st = np.int64(0) if b2[i] < -2.0 * par else np.int64(-1)
        return st, 0.0, 0.0, none, none
    swap = abs(a1) > abs(a0)  # y_k0 = (b - a_k1 t) / a_k0 along t = y_k1, with |a_k0| the larger
    ak0 = a1 if swap else a0
    ak1 = a0 if swap else a1
    r = ak1 / ak0
    y0 = b2[i] / ak0
    k0lo = vlo if swap else ulo
    k0hi = vhi if swap else uhi
    tlo = ulo if swap else vlo
    thi = uhi if swap else vhi
    jlo = none
    jhi = none
    # box of y_k0: y0 - r t in [k0lo, k0hi]
    if r > _LP_PAR:
        tlo = max(tlo, (y0 - k0hi) / r)
        thi = min(thi, (y0 - k0lo) / r)
    elif r < -_LP_PAR:
        tlo = max(tlo, (y0 - k0lo) / r)
        thi = min(thi, (y0 - k0hi) / r)
    elif y0 < k0lo - par or y0 > k0hi + par:
        return np.int64(0), 0.0, 0.0, none, none
    elif y0 < k0lo + par or y0 > k0hi - par:
        return np.int64(-1), 0.0, 0.0, none, none
    for j in range(i):
        g0 = A2[j, 1] if swap else A2[j, 0]
        g1 = A2[j, 0] if swap else A2[j, 1]
        al = g1 - g0 * r
        be = b2[j] - g0 * y0
        if al > _LP_PAR:
            t = be / al
            if t < thi:
                thi = t
                jhi = j
        elif al < -_LP_PAR:
            t = be / al
            if t > tlo:
                tlo = t
                jlo = j
        elif be < -par:
            return np.int64(0), 0.0, 0.0, j, none
        elif be < par:
            return np.int64(-1), 0.0, 0.0, none, none
    if tlo > thi:
        return (np.int64(0) if tlo > thi + 1e-7 * T else np.int64(-1)), 0.0, 0.0, jlo, jhi
    t = min(max(u0 if swap else v0, tlo), thi)  # stay near the previous point: fewer later moves
    yk0 = y0 - r * t
    if swap:
        return np.int64(1), t, yk0, none, none
    return np.int64(1), yk0, t, none, none


@njit(cache=True, nogil=True, _nrt=False)
def _lp_plane(A2, b2, n2, ulo, uhi, vlo, vhi, u, v, T):  # pragma: no cover - numba
    """The 2-D step of :func:`_lp_box` (Seidel's incremental LP): a point of ``A2 y <= b2``
    in the box ``[ulo, uhi] x [vlo, vhi]``. Returns (status, u, v, i, jlo, jhi): where there
    is no point, rows ``i``, ``jlo``, ``jhi`` (``_NONE``: the box) leave none."""
    u = min(max(u, ulo), uhi)
    v = min(max(v, vlo), vhi)
    for i in range(n2):
        if A2[i, 0] * u + A2[i, 1] * v <= b2[i]:
            continue
        st, u, v, jlo, jhi = _lp_line(A2, b2, i, ulo, uhi, vlo, vhi, u, v, T)
        if st != 1:
            return st, u, v, np.int64(i), jlo, jhi
    none = np.int64(_NONE)
    return np.int64(1), u, v, none, none, none


@njit(cache=True, nogil=True, _nrt=False)
def _lp_box(
    L, lo, hi, row, pv, pr, p, skip, c, h, H, hb, hq, A2, b2, x, core, slack=_LP_SLACK
):  # pragma: no cover - numba
    """Does the box ``c +- h`` hold a point inside every slab of ``row[:p]`` but those
    whose position ``q`` has ``skip[q]``?

    Seidel's incremental LP in 3-D (a point of the constraints so far; a violated one
    moves the point onto its plane, a 2-D problem, and so on to a line). Only a point is
    needed, so the objective is any generic direction. The slabs and the box are widened
    by ``_LP_SLACK`` times the box's scale and rows nearly parallel to a line are decided
    by a margin, so "no point" is said only with room to spare for rounding; a near call
    is -1 (unknown). Returns 1 (a point, in ``x``), 0 (none) or -1.

    Where there is none, ``core[:4]`` holds the positions ``q`` of at most four slabs that
    with the box already hold no point (``_NONE`` for unused entries): a point that
    was feasible for the constraints before a violated one, and their convex set does not
    meet the violated plane, so it lies wholly outside it; the same holds on the plane and
    on the line, so the violated constraints of the three levels and the two that empty
    the line hold no common point.
    """
    T = 0.0
    for d in range(3):
        T = max(T, abs(c[d]) + h[d])
    sl = slack * T
    n = 0
    for q in range(p):
        if skip[q]:
            continue
        j = row[q]
        # only the faces that cut the box: the box implies the others (pv +- pr bound L.n there)
        if pv[q] + pr[q] > hi[j]:
            for d in range(3):
                H[n, d] = L[j, d]
            hb[n] = hi[j] + sl
            hq[n] = q
            n += 1
        if pv[q] - pr[q] < lo[j]:
            for d in range(3):
                H[n, d] = -L[j, d]
            hb[n] = sl - lo[j]
            hq[n] = q
            n += 1
    for d in range(3):
        x[d] = c[d]
    for t in range(4):
        core[t] = _NONE
    for i in range(n):
        if H[i, 0] * x[0] + H[i, 1] * x[1] + H[i, 2] * x[2] <= hb[i]:
            continue
        e = 0  # eliminate the coordinate with the largest coefficient: x_e = e0 - r1 x_d1 - r2 x_d2
        if abs(H[i, 1]) > abs(H[i, e]):
            e = 1
        if abs(H[i, 2]) > abs(H[i, e]):
            e = 2
        d1 = (e + 1) % 3
        d2 = (e + 2) % 3
        piv = H[i, e]
        r1 = H[i, d1] / piv
        r2 = H[i, d2] / piv
        e0 = hb[i] / piv
        A2[0, 0] = -r1  # rows 0 and 1: the box along x_e
        A2[0, 1] = -r2
        b2[0] = c[e] + h[e] + sl - e0
        A2[1, 0] = r1
        A2[1, 1] = r2
        b2[1] = e0 - (c[e] - h[e] - sl)
        for j in range(i):
            A2[j + 2, 0] = H[j, d1] - H[j, e] * r1
            A2[j + 2, 1] = H[j, d2] - H[j, e] * r2
            b2[j + 2] = hb[j] - H[j, e] * e0
        st, u, v, i2, jlo, jhi = _lp_plane(
            A2,
            b2,
            i + 2,
            c[d1] - h[d1] - sl,
            c[d1] + h[d1] + sl,
            c[d2] - h[d2] - sl,
            c[d2] + h[d2] + sl,
            x[d1],
            x[d2],
            T,
        )
        if st != 1:
            if st == 0:
                core[0] = hq[i]
                if i2 >= 2:
                    core[1] = hq[i2 - 2]
                if jlo >= 2:
                    core[2] = hq[jlo - 2]
                if jhi >= 2:
                    core[3] = hq[jhi - 2]
            return st
        x[d1] = u
        x[d2] = v
        x[e] = e0 - r1 * u - r2 * v
    return np.int64(1)


@njit(cache=True, nogil=True, _nrt=False)
def _lp_search(L, lo, hi, Lt, LO, HI, m, row, pv, pr, p, f, c, h, best, bp, lpw):  # pragma: no cover - numba
    """Decide a box whose crossing slabs ``row[:p]`` may miss at most ``g = f + p - best - 1``
    by LPs, without splitting it: the LP over every crossing slab, and where it has no
    point, the same with one slab of its infeasible core (at most four) left out, and so on
    to depth ``g`` (a point must miss one of each core). Returns (status, best): 0 no point
    beats ``best`` (prune), 1 a better incumbent was claimed, -1 undecided (an LP was).
    """
    H, hb, hq, A2, b2, skip, x, cs, cores = (
        lpw[0],
        lpw[1],
        lpw[2],
        lpw[3],
        lpw[4],
        lpw[5],
        lpw[6],
        lpw[7],
        lpw[8],
    )
    g = f + p - best - 1
    for q in range(p):
        skip[q] = False
    # depth-first over the choices; level t drops core entry cs[t] of the core found there
    t = 0
    undecided = False
    while True:
        st = _lp_box(L, lo, hi, row, pv, pr, p, skip, c, h, H, hb, hq, A2, b2, x, cores[t], _LP_SLACK)
        if st == 1:
            for d in range(3):
                x[d] = min(max(x[d], c[d] - h[d]), c[d] + h[d])
            nb = _claim(Lt, LO, HI, m, x[0], x[1], x[2], best, bp)
            if nb > best:
                return np.int64(1), nb
            # the point lies on the widened faces, outside the slabs: again with them narrowed
            # by the margin, whose point (if any) lies inside them
            if (
                _lp_box(L, lo, hi, row, pv, pr, p, skip, c, h, H, hb, hq, A2, b2, x, cores[t], -_LP_SLACK)
                == 1
            ):
                for d in range(3):
                    x[d] = min(max(x[d], c[d] - h[d]), c[d] + h[d])
                nb = _claim(Lt, LO, HI, m, x[0], x[1], x[2], best, bp)
                if nb > best:
                    return np.int64(1), nb
            undecided = True
        elif st == -1:
            undecided = True
        elif t < g:  # descend: drop the first entry of this core
            cs[t] = -1
            t += 1
        # next choice: advance the deepest level with an untried core entry
        while t > 0:
            lvl = t - 1
            if cs[lvl] >= 0:
                skip[cores[lvl, cs[lvl]]] = False
            cs[lvl] += 1
            while cs[lvl] < 4 and cores[lvl, cs[lvl]] == _NONE:
                cs[lvl] += 1
            if cs[lvl] < 4:
                skip[cores[lvl, cs[lvl]]] = True
                break
            t -= 1
        if t == 0:
            break
    return (np.int64(-1) if undecided else np.int64(0)), best


_VEC_P = 24  # boxes with at least this many crossing slabs ...
_VEC_SHARE = 0.4  # ... and this share of the usable ones are tested by contiguous passes (no row)


@njit(cache=True, nogil=True, _nrt=False)
def _vscan(Lt, It, LO, HI, m, c, h, sig, d, p, bw0, bw1, cw, hs, he):  # pragma: no cover - numba
    """:func:`_hull_pass_bins` as one contiguous pass over every usable slab: classify them
    against the box ``c +- h`` from fresh dot products and count the crossing slabs' intervals
    along axis ``d`` in bins (``nb`` from the box's previous ``p``). ``Lt`` and ``It`` hold
    ``L`` and ``1 / L`` by axis, ``LO`` and ``HI`` the widened bounds, all in the order of
    ``idx`` (:func:`solve_exact`). Returns (f, p, slabs holding the centre, nb).

    Its first loop has no branch and no index, so it vectorises (4 ns per slab here against
    6-9 ns for the row passes, which gather through the row's indices); the histogram is a
    second loop. ``bw0``, ``bw1`` and ``cw`` are work arrays of ``m`` integers."""
    nb = min(_BINS, max(8, 2 * p))
    for i in range(nb):
        hs[i] = 0
        he[i] = 0
    hd = h[d]
    iw = nb / (2.0 * hd)
    fnb = nb - 1.0
    c0, c1, c2 = c[0], c[1], c[2]
    h0, h1, h2 = h[0], h[1], h[2]
    f = 0
    pp = 0
    cc = 0
    for q in range(m):
        v = Lt[0, q] * c0 + Lt[1, q] * c1 + Lt[2, q] * c2
        rad = abs(Lt[0, q]) * h0 + abs(Lt[1, q]) * h1 + abs(Lt[2, q]) * h2 + sig
        lj = LO[q]
        hj = HI[q]
        full = (v - rad >= lj) & (v + rad <= hj)
        cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
        f += full
        pp += cross
        cc += cross & (v >= lj) & (v <= hj)
        # the interval as _bins has it
        ro = max(rad - abs(Lt[d, q]) * hd, 0.0)
        iv = It[d, q]
        t0 = (lj - v - ro) * iv
        t1 = (hj - v + ro) * iv
        wide = nb * (iv == 0.0)
        u0 = (min(t0, t1) + hd) * iw - 1e-6 - wide
        u1 = (max(t0, t1) + hd) * iw + 1e-6 + wide
        bw0[q] = np.int64(min(max(u0, 0.0), fnb))
        bw1[q] = np.int64(min(max(u1, 0.0), fnb))
        cw[q] = cross
    for q in range(m):
        hs[bw0[q]] += cw[q]
        he[bw1[q]] += cw[q]
    return f, pp, cc, nb


@njit(cache=True, nogil=True, _nrt=False)
def _vsplit(Lt, LO, HI, m, c, h, sig, ax, hh):  # pragma: no cover - numba
    """Classify every usable slab (as :func:`_vscan`) against both halves of the box split at
    its centre along ``ax`` (their half-width there ``hh``): (f0, p0, c0, f1, p1, c1), ``c`` the
    crossing slabs that hold the half's centre. Half 0 is the lower one."""
    c0, c1, c2 = c[0], c[1], c[2]
    h0, h1, h2 = h[0], h[1], h[2]
    fa = 0
    pa = 0
    ca = 0
    fb = 0
    pb = 0
    cb = 0
    for q in range(m):
        vq = Lt[0, q] * c0 + Lt[1, q] * c1 + Lt[2, q] * c2
        rad = abs(Lt[0, q]) * h0 + abs(Lt[1, q]) * h1 + abs(Lt[2, q]) * h2 + sig - abs(Lt[ax, q]) * hh
        dv = Lt[ax, q] * hh
        lj = LO[q]
        hj = HI[q]
        v = vq - dv
        full = (v - rad >= lj) & (v + rad <= hj)
        cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
        fa += full
        pa += cross
        ca += cross & (v >= lj) & (v <= hj)
        v = vq + dv
        full = (v - rad >= lj) & (v + rad <= hj)
        cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
        fb += full
        pb += cross
        cb += cross & (v >= lj) & (v <= hj)
    return fa, pa, ca, fb, pb, cb


@njit(cache=True, nogil=True, _nrt=False)
def _vrow(Lt, LO, HI, idx, m, c, h, sig, prow, pvrow, prrow):  # pragma: no cover - numba
    """The row of the box ``c +- h`` (its crossing slabs' indices, ``L.c`` and ``|L|.h`` plus
    ``sig``) from fresh dot products, for a box that leaves the contiguous passes; (f, p)."""
    f = 0
    p = 0
    for q in range(m):
        v = Lt[0, q] * c[0] + Lt[1, q] * c[1] + Lt[2, q] * c[2]
        rad = abs(Lt[0, q]) * h[0] + abs(Lt[1, q]) * h[1] + abs(Lt[2, q]) * h[2] + sig
        lj = LO[q]
        hj = HI[q]
        full = (v - rad >= lj) & (v + rad <= hj)
        cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
        f += full
        prow[p] = idx[q]
        pvrow[p] = v
        prrow[p] = rad
        p += cross
    return f, p


@njit(cache=True, nogil=True, _nrt=False)
def _bnb(
    L,
    absL,
    invL,
    a,
    b,
    lo,
    hi,
    sig,
    idx,
    m,
    U,
    tol,
    hmin,
    max_nodes,
    best,
    bp,
    stc,
    sth,
    stf,
    stp,
    strow,
    pool,
    pv,
    pr,
    bs,
    bneg,
    lpw,
    hs,
    he,
    Lt,
    It,
    LO,
    HI,
    bw0,
    bw1,
    cw,
    stv,
):  # pragma: no cover - numba
    """Depth-first branch and bound; returns (best, nodes, certified).

    Each stack entry owns a pool row holding its crossing slabs' indices and, per
    slab, ``L.c`` at the box centre and the half-range ``|L|.h`` plus the rounding
    slack ``sig``. A child updates both by one term. ``lo``/``hi`` are the slab
    bounds widened by the count tolerance (a point holds slab ``j`` iff
    ``lo_j <= L_j.n <= hi_j``).

    The 1-D depth tests run fused with the re-classification that a shrink needs:
    the pass for the next axis first applies the previous axis's move, and the
    split applies the last one, so a shrink costs no extra pass over the slabs.

    A box with many crossing slabs (``stv``: at least ``_VEC_P`` and ``_VEC_SHARE`` of
    the usable ones) has no row: its tests and its split are contiguous passes over
    every usable slab (``Lt``, ``It``, ``LO``, ``HI``; :func:`_vscan`, :func:`_vsplit`),
    the same decisions from fresh dot products. A box below that, or one an LP or the
    vertex enumeration decides, gets its row then (:func:`_vrow`) and goes on as above.
    """
    S = stf.shape[0]
    for s in range(S):
        strow[s] = s
    for d in range(3):
        stc[0, d] = 0.0
        sth[0, d] = U
    # the root's row holds exactly its crossing slabs, as every pushed box's does
    f0 = 0
    p0 = 0
    for q in range(m):
        j = idx[q]
        rad = U * (absL[j, 0] + absL[j, 1] + absL[j, 2]) + sig
        full = (-rad >= lo[j]) & (rad <= hi[j])
        cross = (rad >= lo[j]) & (-rad <= hi[j]) & (not full)
        f0 += full
        pool[0, p0] = j
        pv[0, p0] = 0.0
        pr[0, p0] = rad
        p0 += cross
    stf[0] = f0
    stp[0] = p0
    vmin = max(np.int64(_VEC_P), np.int64(_VEC_SHARE * m))
    stv[0] = p0 >= vmin
    top = 1
    nodes = 0
    zero, one = np.int64(0), np.int64(1)  # not literals (see the note on np.int64 above)
    nrm, off, c, h = lpw[9], lpw[10], lpw[11], lpw[12]
    st = np.int64(0)
    while top > 0:
        top -= 1
        f = stf[top]
        p = stp[top]
        if f + p <= best:
            continue
        nodes += 1
        if nodes > max_nodes:
            return best, nodes, False
        row = strow[top]
        prow = pool[row]
        pvrow = pv[row]
        prrow = pr[row]
        for d in range(3):
            c[d] = stc[top, d]
            h[d] = sth[top, d]
        # a move of axis pd not yet applied to the row (none: dc = dh = 0)
        pd = np.int64(0)
        dc = 0.0
        dh = 0.0
        tested = False  # the 1-D tests ran in the contiguous passes
        if stv[top]:
            # a box without a row: the same tests and split as below, from contiguous passes
            if f <= best and f + p - best <= _SHRINK_GAP and p > _ENUM_P:
                pruned = False
                for t in range(3):
                    if t > 0 and f + p - best > _XY_GAP:
                        break
                    d = 2 if t == 0 else t - 1
                    f, p, cc, nbin = _vscan(Lt, It, LO, HI, m, c, h, sig, d, p, bw0, bw1, cw, hs, he)
                    if f + cc > best:
                        best = _claim(Lt, LO, HI, m, c[0], c[1], c[2], best, bp)
                    if f + p <= best:
                        pruned = True
                        break
                    if f > best or p <= _ENUM_P:
                        break
                    ok, smin, smax = _sweep_bins(hs, he, nbin, f + p - best - 1, h[d])
                    if not ok:
                        pruned = True
                        break
                    if smax - smin > _SHRINK_KEEP * 2.0 * h[d]:
                        if t == 0:
                            break
                        continue
                    hn = 0.5 * (smax - smin)
                    ho = h[d]
                    c[d] = c[d] + 0.5 * (smin + smax)
                    h[d] = hn
                    if t == 0 and hn > _Z_XY * ho:
                        break
                if pruned:
                    continue
            ax = _widest(h)
            if p < vmin or p <= _ENUM_P or f + p - best <= _LP_GAP or h[ax] < hmin or top + 2 >= S:
                f, p = _vrow(Lt, LO, HI, idx, m, c, h, sig, prow, pvrow, prrow)
                if f + p <= best:
                    continue
                tested = True
            else:
                hh = 0.5 * h[ax]
                f0, p0, c0, f1, p1, c1 = _vsplit(Lt, LO, HI, m, c, h, sig, ax, hh)
                r1 = strow[top + 1]
                _push_halves(stc, sth, top, c, h, ax, hh)
                for side in range(2):
                    slot = top + side
                    fs, ps = (f0, p0) if side == 0 else (f1, p1)
                    stf[slot] = fs
                    stp[slot] = ps
                    stv[slot] = ps >= vmin
                    if ps < vmin and fs + ps > best:  # a row box from here on
                        rs = row if side == 0 else r1
                        _vrow(Lt, LO, HI, idx, m, stc[slot], sth[slot], sig, pool[rs], pv[rs], pr[rs])
                if f0 + c0 > best:
                    best = _claim(Lt, LO, HI, m, stc[top, 0], stc[top, 1], stc[top, 2], best, bp)
                if f1 + c1 > best:
                    best = _claim(Lt, LO, HI, m, stc[top + 1, 0], stc[top + 1, 1], stc[top + 1, 2], best, bp)
                if f0 + c0 > f1 + c1 or (f0 + c0 == f1 + c1 and f0 + p0 > f1 + p1):
                    _swap_top(stc, sth, stf, stp, strow, stv, top)
                top += 2
                continue
        if not tested and f <= best and f + p - best <= _SHRINK_GAP and p > _ENUM_P:
            # 1-D depth tests: prune, or shrink the box to where it can still win
            pruned = False
            for t in range(3):
                if t > 0 and f + p - best > _XY_GAP:  # x, y rarely prune far from it: split instead
                    break
                d = 2 if t == 0 else t - 1
                # keep g + 1 = f + p - best ends: re-classification can only lower g
                nbin = np.int64(0)
                if p >= _BIN_P and dc == 0.0 and dh == 0.0:  # the row is the box's: intervals only
                    cc, nbin = _bin_intervals(absL, invL, lo, hi, prow, pvrow, prrow, p, d, h[d], hs, he)
                elif p >= _BIN_P:  # many slabs: a histogram of the intervals instead of kept extremes
                    f, p, cc, nbin = _hull_pass_bins(
                        L, absL, invL, lo, hi, prow, pvrow, prrow, p, f, d, h[d], pd, dc, dh, hs, he
                    )
                else:
                    f, p, cc, _ = _hull_pass(
                        L,
                        absL,
                        invL,
                        lo,
                        hi,
                        prow,
                        pvrow,
                        prrow,
                        p,
                        f,
                        d,
                        h[d],
                        pd,
                        dc,
                        dh,
                        f + p - best,
                        bs,
                        bneg,
                    )
                pd = np.int64(0)
                dc = 0.0
                dh = 0.0
                if f + cc > best:
                    best = _claim(Lt, LO, HI, m, c[0], c[1], c[2], best, bp)
                if f + p <= best:
                    pruned = True
                    break
                if f > best or p <= _ENUM_P:
                    break
                if nbin > 0:
                    ok, smin, smax = _sweep_bins(hs, he, nbin, f + p - best - 1, h[d])
                else:
                    ok, smin, smax = _sweep(bs, bneg, f + p - best - 1)
                if not ok:
                    pruned = True
                    break
                if smax - smin > _SHRINK_KEEP * 2.0 * h[d]:
                    if t == 0:  # z, where slabs are thinnest, did not shrink: x, y would not
                        break
                    continue
                pd = d
                dc = 0.5 * (smin + smax)
                hn = 0.5 * (smax - smin)
                dh = hn - h[d]
                c[d] = c[d] + dc
                h[d] = hn
                if t == 0 and hn > _Z_XY * (hn - dh):  # z shrank a little: x, y would barely
                    break
            if pruned:
                continue
        if f + p - best <= _LP_GAP and p > _ENUM_P:
            # a box a few slabs from being pruned: LPs decide it without splitting it
            if dc != 0.0 or dh != 0.0:
                f, p, _, _ = _hull_pass(
                    L, absL, invL, lo, hi, prow, pvrow, prrow, p, f, zero, h[0], pd, dc, dh, one, bs, bneg
                )
                pd = zero
                dc = 0.0
                dh = 0.0
            st = np.int64(-1)
            gap = _LP_GAP if p <= _LP_GAP3_P else (2 if p <= _LP_GAP_P else 1)
            while best < f + p <= best + gap:
                st, best = _lp_search(L, lo, hi, Lt, LO, HI, m, prow, pvrow, prrow, p, f, c, h, best, bp, lpw)
                if st != 1:
                    break
            if f + p <= best or st == 0:
                continue
        if p <= _ENUM_P:
            if dc != 0.0 or dh != 0.0:
                f, p, _, _ = _hull_pass(
                    L, absL, invL, lo, hi, prow, pvrow, prrow, p, f, zero, h[0], pd, dc, dh, one, bs, bneg
                )
                if f + p <= best:
                    continue
            if p == 1:
                # one crossing slab: a point of the box inside it has depth f + 1
                j = prow[0]
                v = pvrow[0]
                rad = prrow[0] - sig
                t0 = min(max(v, max(a[j], v - rad)), min(b[j], v + rad))
                s = (t0 - v) / rad if rad > 0.0 else 0.0
                x = c[0] + s * np.sign(L[j, 0]) * h[0]
                y = c[1] + s * np.sign(L[j, 1]) * h[1]
                z = c[2] + s * np.sign(L[j, 2]) * h[2]
                nb = _claim(Lt, LO, HI, m, x, y, z, best, bp)
                if nb > best:
                    best = nb
                    continue
            best = _enum_leaf(L, a, b, lo, hi, tol, Lt, LO, HI, m, prow, p, c, h, f, best, bp, nrm, off)
            continue
        ax = _widest(h)
        if h[ax] < hmin or top + 2 >= S:
            # the row may still miss the last move: a superset of the crossing slabs is exact here
            best = _enum_leaf(L, a, b, lo, hi, tol, Lt, LO, HI, m, prow, p, c, h, f, best, bp, nrm, off)
            continue
        hh = 0.5 * h[ax]
        r1 = strow[top + 1]
        q0 = pool[r1]
        v1row = pv[r1]
        r1row = pr[r1]
        f0 = f
        f1 = f
        p0 = 0
        p1 = 0
        c0 = 0
        c1 = 0
        # branchless split (after the pending move); child 0 compacts into the parent's row (p0 <= q)
        for q in range(p):
            j = prow[q]
            dv = L[j, ax] * hh
            rad = prrow[q] + absL[j, pd] * dh - absL[j, ax] * hh
            vq = pvrow[q] + L[j, pd] * dc
            lj = lo[j]
            hj = hi[j]
            v = vq - dv  # child 0: centre moved by -hh along ax
            full = (v - rad >= lj) & (v + rad <= hj)
            cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
            f0 += full
            prow[p0] = j
            pvrow[p0] = v
            prrow[p0] = rad
            c0 += cross & (v >= lj) & (v <= hj)
            p0 += cross
            v = vq + dv  # child 1
            full = (v - rad >= lj) & (v + rad <= hj)
            cross = (v + rad >= lj) & (v - rad <= hj) & (not full)
            f1 += full
            q0[p1] = j
            v1row[p1] = v
            r1row[p1] = rad
            c1 += cross & (v >= lj) & (v <= hj)
            p1 += cross
        _push_halves(stc, sth, top, c, h, ax, hh)
        stf[top] = f0
        stp[top] = p0
        stf[top + 1] = f1
        stp[top + 1] = p1
        if f0 + c0 > best:
            best = _claim(Lt, LO, HI, m, stc[top, 0], stc[top, 1], stc[top, 2], best, bp)
        if f1 + c1 > best:
            best = _claim(Lt, LO, HI, m, stc[top + 1, 0], stc[top + 1, 1], stc[top + 1, 2], best, bp)
        # the child with the larger bound goes on top, to be explored first
        stv[top] = False
        stv[top + 1] = False
        if f0 + c0 > f1 + c1 or (f0 + c0 == f1 + c1 and f0 + p0 > f1 + p1):
            _swap_top(stc, sth, stf, stp, strow, stv, top)
        top += 2
    return best, nodes, True


@njit(cache=True, nogil=True, _nrt=False)
def _widest(h):  # pragma: no cover - numba
    """The axis along which the box is widest (the first of equals): the one a split halves."""
    ax = np.int64(0)
    if h[1] > h[ax]:
        ax = np.int64(1)
    if h[2] > h[ax]:
        ax = np.int64(2)
    return ax


@njit(cache=True, nogil=True, _nrt=False)
def _push_halves(stc, sth, top, c, h, ax, hh):  # pragma: no cover - numba
    """Stack entries ``top`` and ``top + 1``: the lower and upper half of the box ``c +- h``
    split along ``ax`` (half-width ``hh`` there)."""
    for side in range(2):
        slot = top + side
        for d in range(3):
            stc[slot, d] = c[d]
            sth[slot, d] = h[d]
        stc[slot, ax] = c[ax] + (hh if side == 1 else -hh)
        sth[slot, ax] = hh


@njit(cache=True, nogil=True, _nrt=False)
def _swap_top(stc, sth, stf, stp, strow, stv, top):  # pragma: no cover - numba
    """Swap the stack entries ``top`` and ``top + 1`` (the child to explore first goes on top)."""
    for d in range(3):
        t0 = stc[top, d]
        stc[top, d] = stc[top + 1, d]
        stc[top + 1, d] = t0
        t0 = sth[top, d]
        sth[top, d] = sth[top + 1, d]
        sth[top + 1, d] = t0
    t = stf[top]
    stf[top] = stf[top + 1]
    stf[top + 1] = t
    t = stp[top]
    stp[top] = stp[top + 1]
    stp[top + 1] = t
    t = strow[top]
    strow[top] = strow[top + 1]
    strow[top + 1] = t
    b = stv[top]
    stv[top] = stv[top + 1]
    stv[top + 1] = b


@njit(cache=True, nogil=True, _nrt=False)
def _try_point(Lt, LO, HI, m, U, x, y, z, best, bp):  # pragma: no cover - numba
    if abs(x) > U or abs(y) > U or abs(z) > U or not (x == x and y == y and z == z):
        return best
    return _claim(Lt, LO, HI, m, x, y, z, best, bp)


@njit(cache=True, nogil=True, _nrt=False)
def _project(L, a, b, idx, m, U, margin, n0, sweeps, Lt, LO, HI, best, bp):  # pragma: no cover - numba
    """Alternating projections onto every usable slab (shrunk by ``margin``), from ``n0``.

    Returns the incumbent after testing the point reached after each sweep.
    """
    x = n0[0]
    y = n0[1]
    z = n0[2]
    for _ in range(sweeps):
        moved = False
        for q in range(m):
            j = idx[q]
            v = L[j, 0] * x + L[j, 1] * y + L[j, 2] * z
            w = L[j, 0] * L[j, 0] + L[j, 1] * L[j, 1] + L[j, 2] * L[j, 2]
            lim_lo = a[j] + margin[j]
            lim_hi = b[j] - margin[j]
            if v < lim_lo:
                s = (lim_lo - v) / w
            elif v > lim_hi:
                s = (lim_hi - v) / w
            else:
                continue
            x += s * L[j, 0]
            y += s * L[j, 1]
            z += s * L[j, 2]
            moved = True
        best = _try_point(Lt, LO, HI, m, U, x, y, z, best, bp)
        if best >= m or not moved:
            break
    return best


@njit(cache=True, nogil=True)
def _lp_work(k):  # pragma: no cover - numba
    """The LPs' work arrays for ``k`` slabs (then the vertex enumeration's, and the box centre and
    half-widths), made once per batch and passed to :func:`_lp_search`."""
    return (
        np.empty((2 * k, 3)),
        np.empty(2 * k),
        np.empty(2 * k, np.int64),
        np.empty((2 * k + 2, 2)),
        np.empty(2 * k + 2),
        np.zeros(k, np.bool_),
        np.empty(3),
        np.zeros(_LP_GAP, np.int64),
        np.empty((_LP_GAP + 1, 4), np.int64),
        np.empty((2 * k + 6, 3)),
        np.empty(2 * k + 6),
        np.empty(3),
        np.empty(3),
    )


@njit(cache=True, nogil=True)
def solve_exact(
    I,
    slab_lo,
    slab_hi,
    valid,
    L,
    box_factor,
    max_nodes,
    above,
    point,
    inl,
    count,
    nodes,
    certified,
    start=0,
    stop=-1,
):  # pragma: no cover - numba
    """Solve pixels ``start`` to ``stop`` (default: every pixel) of a batch; results are written
    into the output arrays. Pixels before ``start`` must hold their results already (an earlier
    call): they seed the first ones exactly as in one call, so a batch split into ranges gives
    the same answer bit for bit.

    Parameters
    ----------
    I : (P, k) float64 intensities (least-squares seeds only);
    slab_lo, slab_hi : (P, k) float64 slab bounds ``lo <= L_i . n <= hi``, read
    only where ``valid``; ``lo = -inf`` is the one-sided slab ``L_i . n <= hi`` (a shadow); valid : (P, k) bool usable observations;
    L : (k, 3) float64 unit lights; box_factor : float; max_nodes : int;
    above : (P,) int64, an earlier pixel of the batch whose solution seeds this
    one (the pixel above in the image), or -1.
    point : (P, 3) float64 out, the Max-FS point (NaN where unsolved);
    inl : (P, k) bool out; count : (P,) int32 out; nodes : (P,) int64 out;
    certified : (P,) bool out, True where the optimum was proved.
    """
    P, k = I.shape
    absL = np.abs(L)
    invL = np.zeros((k, 3))
    for i in range(k):
        for d in range(3):
            if L[i, d] != 0.0:
                invL[i, d] = 1.0 / L[i, d]
    a = np.zeros(k)
    b = np.zeros(k)
    idx = np.empty(k, np.uint32)  # unsigned: indexing skips the negative-index wraparound
    stc = np.empty((_STACK, 3))
    sth = np.empty((_STACK, 3))
    stf = np.empty(_STACK, np.int64)
    stp = np.empty(_STACK, np.int64)
    strow = np.empty(_STACK, np.int64)
    pool = np.empty((_STACK, k), np.uint32)
    pv = np.empty((_STACK, k))
    pr = np.empty((_STACK, k))
    bs = np.empty(k + 1)
    bneg = np.empty(k + 1)
    hs = np.zeros(_BINS, np.int64)
    he = np.zeros(_BINS, np.int64)
    lpw = _lp_work(k)
    lo = np.zeros(k)
    hi = np.zeros(k)
    # the usable slabs in contiguous arrays, in the order of idx (_vscan's passes)
    Lt = np.zeros((3, k))
    It = np.zeros((3, k))
    LO = np.zeros(k)
    HI = np.zeros(k)
    bw0 = np.zeros(k, np.int64)
    bw1 = np.zeros(k, np.int64)
    cw = np.zeros(k, np.int64)
    stv = np.zeros(_STACK, np.bool_)
    margin = np.zeros(k)
    sel = np.zeros(k, np.bool_)
    lit = np.zeros(k, np.bool_)  # two-sided slabs (finite lower bound)
    prev = start - 1  # the last solved pixel (at least 3 usable images) before start
    while prev >= 0:
        usable = 0
        for i in range(k):
            if valid[prev, i]:
                usable += 1
        if usable >= 3:
            break
        prev -= 1
    bp = np.zeros(3)
    tmp = np.zeros(3)
    for px in range(start, P if stop < 0 else stop):
        m = np.int64(0)
        maxb = 0.0
        eps = 0.0  # the widest half-width of a two-sided slab: the scale of seed slack and of hmin
        for i in range(k):
            inl[px, i] = False
            lit[i] = False
            if valid[px, i]:
                a[i] = slab_lo[px, i]
                b[i] = slab_hi[px, i]
                idx[m] = i
                m += 1
                maxb = max(maxb, b[i])
                if a[i] > -np.inf:
                    lit[i] = True
                    eps = max(eps, 0.5 * (b[i] - a[i]))
        count[px] = 0
        nodes[px] = 0
        certified[px] = True
        for d in range(3):
            point[px, d] = np.nan
        if m < 3:
            continue
        U = box_factor * maxb
        tol = REL_TOL * maxb
        sig = _SIGMA_REL * U
        if eps == 0.0:  # only one-sided slabs: the scale of the data instead
            eps = maxb
        for q in range(m):
            j = idx[q]
            if not lit[j]:
                # one-sided slab L.n <= b: a lower face below the whole box (L.n >= -U ||L||_1
                # there) is the same set inside the box and keeps every test finite
                a[j] = -U * (absL[j, 0] + absL[j, 1] + absL[j, 2]) - maxb
            lo[j] = a[j] - tol
            hi[j] = b[j] + tol
            margin[j] = 1e-3 * (b[j] - a[j])
            LO[q] = lo[j]
            HI[q] = hi[j]
            for d in range(3):
                Lt[d, q] = L[j, d]
                It[d, q] = invL[j, d]
        best = np.int64(-1)
        # incumbents: the previous and the upper pixel's points and inlier sets, then trimmed least squares
        for t in range(2):
            src = prev if t == 0 else above[px]
            if t == 1 and src == prev:
                continue
            if best >= m or src < 0 or src >= px or not point[src, 0] == point[src, 0]:
                continue
            best = _try_point(Lt, LO, HI, m, U, point[src, 0], point[src, 1], point[src, 2], best, bp)
            for i in range(k):
                sel[i] = inl[src, i] and lit[i]
            if _lsq(L, I[px], sel, k, tmp):
                best = _try_point(Lt, LO, HI, m, U, tmp[0], tmp[1], tmp[2], best, bp)
        if best < m:
            for i in range(k):
                sel[i] = lit[i]  # a one-sided slab says L.n <= b, not L.n = I: no least-squares row
            for it in range(5):
                if not _lsq(L, I[px], sel, k, tmp):
                    break
                best = _try_point(Lt, LO, HI, m, U, tmp[0], tmp[1], tmp[2], best, bp)
                if best >= m:
                    break
                slack = eps * (3.0 - it) if it < 3 else 0.0
                for i in range(k):
                    if lit[i]:
                        v = L[i, 0] * tmp[0] + L[i, 1] * tmp[1] + L[i, 2] * tmp[2]
                        sel[i] = v >= a[i] - slack and v <= b[i] + slack
        if 0 <= best < m and best >= m - _AP_GAP:
            tmp[0] = bp[0]
            tmp[1] = bp[1]
            tmp[2] = bp[2]
            best = _project(L, a, b, idx, m, U, margin, tmp, np.int64(_AP_SWEEPS), Lt, LO, HI, best, bp)
        nn = 0
        cert = True
        if best < m:
            hmin = _HMIN_REL * eps
            best, nn, cert = _bnb(
                L,
                absL,
                invL,
                a,
                b,
                lo,
                hi,
                sig,
                idx,
                m,
                U,
                tol,
                hmin,
                max_nodes,
                best,
                bp,
                stc,
                sth,
                stf,
                stp,
                strow,
                pool,
                pv,
                pr,
                bs,
                bneg,
                lpw,
                hs,
                he,
                Lt,
                It,
                LO,
                HI,
                bw0,
                bw1,
                cw,
                stv,
            )
        c = 0
        for q in range(m):
            j = idx[q]
            v = L[j, 0] * bp[0] + L[j, 1] * bp[1] + L[j, 2] * bp[2]
            if v >= lo[j] and v <= hi[j]:
                inl[px, j] = True
                c += 1
        count[px] = c
        nodes[px] = nn
        certified[px] = cert
        for d in range(3):
            point[px, d] = bp[d]
        prev = px


def exact_pixels(
    I: NDArray[np.float64],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    valid: NDArray[np.bool_],
    L: NDArray[np.float64],
    box_factor: float,
    max_nodes: int,
    above: NDArray[np.integer] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.int32], NDArray[np.int64], NDArray[np.bool_]]:
    """Run :func:`solve_exact` on ``(P, k)`` arrays; returns (point, inliers, count, nodes, certified).

    ``lo``, ``hi`` are the slab bounds (e.g. :func:`worker.problem.slabs`), read
    only where ``valid``; ``I`` seeds the least-squares incumbents. ``above``
    (optional, ``(P,)``) names for each pixel an earlier pixel of the batch whose
    solution is a second seed (the pixel above; see :func:`above_index`), -1 for
    none. Seeds change the work, never the count.

    In a thread with cancel points (:func:`worker.cancel.cancel_points`: a tile task) the
    pixels are solved in consecutive ranges of about :data:`worker.cancel.BATCH_SECONDS` of
    work each, with a cancel point between two; each range is seeded by the ones before it,
    so the answer is bit-identical to one call.
    """
    P, k = I.shape
    point = np.empty((P, 3))
    inl = np.empty((P, k), dtype=np.bool_)
    count = np.empty(P, dtype=np.int32)
    nodes = np.empty(P, dtype=np.int64)
    cert = np.empty(P, dtype=np.bool_)
    up = np.full(P, -1, dtype=np.int64) if above is None else np.ascontiguousarray(above, dtype=np.int64)
    if up.shape != (P,):
        raise ValueError(f"above must have shape ({P},), got {up.shape}")
    args = (
        np.ascontiguousarray(I, dtype=np.float64),
        np.ascontiguousarray(lo, dtype=np.float64),
        np.ascontiguousarray(hi, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        np.ascontiguousarray(L, dtype=np.float64),
        float(box_factor),
        int(max_nodes),
        up,
        point,
        inl,
        count,
        nodes,
        cert,
    )
    if not cancel.active():
        solve_exact(*args, 0, P)
        return point, inl, count, nodes, cert
    s, n = 0, 16
    while s < P:
        e = min(P, s + n)
        t0 = time.perf_counter()
        solve_exact(*args, s, e)
        took = time.perf_counter() - t0
        s = e
        if s < P:
            cancel.checkpoint(s, P)
        if took < cancel.BATCH_SECONDS / 2:
            n *= 2
        elif took > 2 * cancel.BATCH_SECONDS:
            n = max(1, n // 2)
    return point, inl, count, nodes, cert


def above_index(rows: NDArray[np.integer], width: int) -> NDArray[np.int64]:
    """For pixels ``rows`` (increasing flat indices into an image ``width`` wide), the
    position in ``rows`` of the pixel above each one, or -1 where that pixel is not in ``rows``."""
    r = np.asarray(rows, dtype=np.int64)
    want = r - int(width)
    pos = np.minimum(np.searchsorted(r, want), max(r.size - 1, 0))
    hit = (want >= 0) & (r[pos] == want) if r.size else np.zeros(0, dtype=bool)
    return np.where(hit, pos, -1).astype(np.int64)
