"""The first exact kernel (commit 3570aa8), kept for before/after benchmarks only.

Unchanged except for this paragraph; the service uses :mod:`worker.exact`.
It takes a scalar ``eps`` and builds the paper's slabs inside.

Exact maximum feasible subsystem by branch and bound over boxes of n-space.

The Max-FS problem at one pixel is the maximum depth of an arrangement of k slabs
``a_i <= L_i . n <= b_i`` in 3-D, restricted to the box ``|n_j| <= U``.

Each box in the search carries three numbers: ``f`` slabs contain it wholly,
``p`` slabs cross it (their indices are kept), the rest miss it. ``f + p`` bounds
the depth of any point in the box from above; the box centre, which lies in the
``f`` full slabs and in some of the ``p`` crossing ones, bounds it from below.
Children only re-test their parent's crossing slabs, so deep boxes are cheap.
A box with one crossing slab is solved in closed form (depth ``f + 1`` is
reached on that slab's side of the box); a box shrunk below ``hmin`` is solved by
enumerating every vertex of its crossing planes and faces, which makes the search
finite and exact even in degenerate arrangements.

The search is depth-first, better child first, seeded with good incumbents (the
neighbouring pixel's solution and trimmed least squares), so most of the work is
the proof that no deeper point exists. ``max_nodes`` bounds the work per pixel;
a pixel that hits it is reported as not certified.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from maxfs.worker.problem import REL_TOL

_STACK = 256  # DFS depth bound; a box this deep is far below ``hmin`` already
_HMIN_REL = 1e-4  # enumerate the vertices of boxes narrower than this times eps


@njit(cache=True, nogil=True)
def _count(L, a, b, idx, m, x, y, z, tol):  # pragma: no cover - numba
    c = 0
    for q in range(m):
        j = idx[q]
        v = L[j, 0] * x + L[j, 1] * y + L[j, 2] * z
        if v >= a[j] - tol and v <= b[j] + tol:
            c += 1
    return c


@njit(cache=True, nogil=True)
def _lsq(L, inten, sel, k, out):  # pragma: no cover - numba
    """Least squares ``n`` over the selected images; False if ill-conditioned."""
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    r0 = r1 = r2 = 0.0
    for i in range(k):
        if sel[i]:
            l0 = L[i, 0]
            l1 = L[i, 1]
            l2 = L[i, 2]
            s00 += l0 * l0
            s01 += l0 * l1
            s02 += l0 * l2
            s11 += l1 * l1
            s12 += l1 * l2
            s22 += l2 * l2
            r0 += l0 * inten[i]
            r1 += l1 * inten[i]
            r2 += l2 * inten[i]
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


@njit(cache=True, nogil=True)
def _enum_leaf(L, a, b, lst, p, c, h, f, tol, best, bp):  # pragma: no cover - numba
    """Exact depth inside a tiny box: try every vertex of its planes."""
    npl = 2 * p + 6
    nrm = np.zeros((npl, 3))
    off = np.empty(npl)
    for q in range(p):
        j = lst[q]
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
                cnt = f + _count(L, a, b, lst, p, vx, vy, vz, tol)
                if cnt > best:
                    best = cnt
                    bp[0] = vx
                    bp[1] = vy
                    bp[2] = vz
    return best


@njit(cache=True, nogil=True)
def _bnb(
    L,
    absL,
    lo,
    hi,
    a,
    b,
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
    si,
    sv,
    sr,
):  # pragma: no cover - numba
    """Depth-first branch and bound; returns (best, nodes, certified).

    Each stack entry owns a pool row holding its crossing slabs' indices and, per
    slab, ``L.c`` at the box centre and the half-range ``|L|.h``. A child updates
    both by one term, so a slab test costs two adds and two compares.
    ``lo``/``hi`` are the slab bounds widened by ``tol``.
    """
    S = stf.shape[0]
    for s in range(S):
        strow[s] = s
    for d in range(3):
        stc[0, d] = 0.0
        sth[0, d] = U
    stf[0] = 0
    stp[0] = m
    for q in range(m):
        j = idx[q]
        pool[0, q] = j
        pv[0, q] = 0.0
        pr[0, q] = U * (absL[j, 0] + absL[j, 1] + absL[j, 2])
    top = 1
    nodes = 0
    c = np.empty(3)
    h = np.empty(3)
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
        for q in range(p):
            si[q] = pool[row, q]
            sv[q] = pv[row, q]
            sr[q] = pr[row, q]
        for d in range(3):
            c[d] = stc[top, d]
            h[d] = sth[top, d]
        if p == 1:
            # one crossing slab: a point of the box inside it has depth f + 1
            j = si[0]
            v = sv[0]
            rad = sr[0]
            t = min(max(v, max(a[j], v - rad)), min(b[j], v + rad))
            s = (t - v) / rad if rad > 0.0 else 0.0
            best = f + 1
            for d in range(3):
                bp[d] = c[d] + s * np.sign(L[j, d]) * h[d]
            continue
        ax = 0
        if h[1] > h[ax]:
            ax = 1
        if h[2] > h[ax]:
            ax = 2
        if h[ax] < hmin or top + 2 >= S:
            best = _enum_leaf(L, a, b, si, p, c, h, f, tol, best, bp)
            continue
        hh = 0.5 * h[ax]
        r0 = strow[top]
        r1 = strow[top + 1]
        f0 = f
        f1 = f
        p0 = 0
        p1 = 0
        c0 = 0
        c1 = 0
        for q in range(p):
            j = si[q]
            dv = L[j, ax] * hh
            rad = sr[q] - absL[j, ax] * hh
            lj = lo[j]
            hj = hi[j]
            v = sv[q] - dv  # child 0: centre moved by -hh along ax
            if v + rad >= lj and v - rad <= hj:
                if v - rad >= lj and v + rad <= hj:
                    f0 += 1
                else:
                    pool[r0, p0] = j
                    pv[r0, p0] = v
                    pr[r0, p0] = rad
                    p0 += 1
                    if v >= lj and v <= hj:
                        c0 += 1
            v = sv[q] + dv  # child 1
            if v + rad >= lj and v - rad <= hj:
                if v - rad >= lj and v + rad <= hj:
                    f1 += 1
                else:
                    pool[r1, p1] = j
                    pv[r1, p1] = v
                    pr[r1, p1] = rad
                    p1 += 1
                    if v >= lj and v <= hj:
                        c1 += 1
        for side in range(2):
            slot = top + side
            for d in range(3):
                stc[slot, d] = c[d]
                sth[slot, d] = h[d]
            stc[slot, ax] = c[ax] + (hh if side == 1 else -hh)
            sth[slot, ax] = hh
        stf[top] = f0
        stp[top] = p0
        stf[top + 1] = f1
        stp[top + 1] = p1
        if f0 + c0 > best:
            best = f0 + c0
            for d in range(3):
                bp[d] = stc[top, d]
        if f1 + c1 > best:
            best = f1 + c1
            for d in range(3):
                bp[d] = stc[top + 1, d]
        # the child with the larger bound goes on top, to be explored first
        if f0 + p0 > f1 + p1:
            for d in range(3):
                t0 = stc[top, d]
                stc[top, d] = stc[top + 1, d]
                stc[top + 1, d] = t0
                t0 = sth[top, d]
                sth[top, d] = sth[top + 1, d]
                sth[top + 1, d] = t0
            stf[top] = f1
            stf[top + 1] = f0
            stp[top] = p1
            stp[top + 1] = p0
            strow[top] = r1
            strow[top + 1] = r0
        top += 2
    return best, nodes, True


@njit(cache=True, nogil=True)
def _try_point(L, a, b, idx, m, U, tol, x, y, z, best, bp):  # pragma: no cover - numba
    if abs(x) > U or abs(y) > U or abs(z) > U or not (x == x and y == y and z == z):
        return best
    cnt = _count(L, a, b, idx, m, x, y, z, tol)
    if cnt > best:
        bp[0] = x
        bp[1] = y
        bp[2] = z
        return cnt
    return best


@njit(cache=True, nogil=True)
def solve_exact(
    I, valid, L, eps, box_factor, max_nodes, point, inl, count, nodes, certified
):  # pragma: no cover - numba
    """Solve every pixel of a batch; results are written into the output arrays.

    Parameters
    ----------
    I : (P, k) float64 intensities; valid : (P, k) bool usable observations;
    L : (k, 3) float64 unit lights; eps, box_factor : floats; max_nodes : int.
    point : (P, 3) float64 out, the Max-FS point (NaN where unsolved);
    inl : (P, k) bool out; count : (P,) int32 out; nodes : (P,) int64 out;
    certified : (P,) bool out, True where the optimum was proved.
    """
    P, k = I.shape
    absL = np.abs(L)
    a = np.zeros(k)
    b = np.zeros(k)
    idx = np.empty(k, np.int32)
    stc = np.empty((_STACK, 3))
    sth = np.empty((_STACK, 3))
    stf = np.empty(_STACK, np.int64)
    stp = np.empty(_STACK, np.int64)
    strow = np.empty(_STACK, np.int64)
    pool = np.empty((_STACK, k), np.int32)
    pv = np.empty((_STACK, k))
    pr = np.empty((_STACK, k))
    si = np.empty(k, np.int32)
    sv = np.empty(k)
    sr = np.empty(k)
    lo = np.zeros(k)
    hi = np.zeros(k)
    sel = np.zeros(k, np.bool_)
    prev_sel = np.zeros(k, np.bool_)
    prev_pt = np.zeros(3)
    has_prev = False
    bp = np.zeros(3)
    tmp = np.zeros(3)
    for px in range(P):
        m = 0
        maxb = 0.0
        for i in range(k):
            inl[px, i] = False
            if valid[px, i]:
                a[i] = max(I[px, i] - eps, eps)
                b[i] = I[px, i] + eps
                idx[m] = i
                m += 1
                maxb = max(maxb, b[i])
        count[px] = 0
        nodes[px] = 0
        certified[px] = True
        for d in range(3):
            point[px, d] = np.nan
        if m < 3:
            continue
        U = box_factor * maxb
        tol = REL_TOL * maxb
        best = -1
        # incumbents: the neighbour's point and inlier set, then trimmed least squares
        if has_prev:
            best = _try_point(L, a, b, idx, m, U, tol, prev_pt[0], prev_pt[1], prev_pt[2], best, bp)
            for i in range(k):
                sel[i] = prev_sel[i] and valid[px, i]
            if _lsq(L, I[px], sel, k, tmp):
                best = _try_point(L, a, b, idx, m, U, tol, tmp[0], tmp[1], tmp[2], best, bp)
        for i in range(k):
            sel[i] = valid[px, i]
        for it in range(5):
            if not _lsq(L, I[px], sel, k, tmp):
                break
            best = _try_point(L, a, b, idx, m, U, tol, tmp[0], tmp[1], tmp[2], best, bp)
            slack = eps * (3.0 - it) if it < 3 else 0.0
            for i in range(k):
                if valid[px, i]:
                    v = L[i, 0] * tmp[0] + L[i, 1] * tmp[1] + L[i, 2] * tmp[2]
                    sel[i] = v >= a[i] - slack and v <= b[i] + slack
        for q in range(m):
            lo[idx[q]] = a[idx[q]] - tol
            hi[idx[q]] = b[idx[q]] + tol
        hmin = _HMIN_REL * eps
        best, nn, cert = _bnb(
            L,
            absL,
            lo,
            hi,
            a,
            b,
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
            si,
            sv,
            sr,
        )
        c = 0
        for q in range(m):
            j = idx[q]
            v = L[j, 0] * bp[0] + L[j, 1] * bp[1] + L[j, 2] * bp[2]
            if v >= a[j] - tol and v <= b[j] + tol:
                inl[px, j] = True
                c += 1
        count[px] = c
        nodes[px] = nn
        certified[px] = cert
        for d in range(3):
            point[px, d] = bp[d]
            prev_pt[d] = bp[d]
        for i in range(k):
            prev_sel[i] = inl[px, i]
        has_prev = True


def exact_pixels(
    I: NDArray[np.float64],
    valid: NDArray[np.bool_],
    L: NDArray[np.float64],
    eps: float,
    box_factor: float,
    max_nodes: int,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.int32], NDArray[np.int64], NDArray[np.bool_]]:
    """Run :func:`solve_exact` on ``(P, k)`` arrays; returns (point, inliers, count, nodes, certified)."""
    P, k = I.shape
    point = np.empty((P, 3))
    inl = np.empty((P, k), dtype=np.bool_)
    count = np.empty(P, dtype=np.int32)
    nodes = np.empty(P, dtype=np.int64)
    cert = np.empty(P, dtype=np.bool_)
    solve_exact(
        np.ascontiguousarray(I, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        np.ascontiguousarray(L, dtype=np.float64),
        float(eps),
        float(box_factor),
        int(max_nodes),
        point,
        inl,
        count,
        nodes,
        cert,
    )
    return point, inl, count, nodes, cert
