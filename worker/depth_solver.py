"""The depth step's linear solver: a weighted graph Laplacian on the pixel grid, applied matrix-free from
per-edge weights, solved by conjugate gradients preconditioned with a geometric aggregation multigrid.

The fine level is a stencil: for the domain's pixels in raster order, ``wh[i]`` is the weight of the edge
from pixel ``i`` to its right neighbour (which is then pixel ``i + 1``; 0 when there is none) and
``wv[i]`` the weight of the edge to the pixel below, ``down[i]`` (-1 when there is none; ``up`` is its
inverse). Nothing else is stored for the operator: ``(A x)_i = sum_j w_ij (x_i - x_j)`` over its four
neighbours, and the diagonal is the sum of the four weights.

Coarse levels aggregate: each 2 x 2 block of the grid (of blocks, on coarser levels) becomes as many coarse
nodes as it has connected pieces under strong edges, so that blocks cut by a one-pixel slot, pieces that only
touch at a corner and the two sides of a depth jump (bini's all-but-cut edges) are not forced to move
together. The coarse operator is the Galerkin product of this piecewise-constant prolongation: the weight
between two coarse nodes is the sum of the fine weights across them; it is stored as an adjacency list
(coarse levels together hold about a third of the fine level's nodes). A node with no edge left (an isolated
pixel, or a whole piece that became one node) has no coarse correction. The coarsest level (a few hundred
nodes) is solved directly with one node of each connected piece held at 0 (the Laplacian is singular per
piece; any solution of a consistent system is as good for a preconditioner).

The V-cycle smooths with Gauss-Seidel: red-black on the fine level (red then black before the coarse
correction, black then red after; a colour's updates are independent), forward then backward on the coarse
levels, so the preconditioner is symmetric positive semi-definite and CG applies. The coarse correction is
scaled by ``OVERCORRECT`` (over-correction): with a piecewise-constant prolongation the Galerkin coarse
operator is twice too stiff for a smooth error, on 2 x 2 aggregates as on the 1 x 2 of a one-pixel strand, and
doubling the correction keeps CG's iterations nearly flat with the image size (10-11 from 0.25 to 16 M pixels
on a solid object, against 20 and more without).

Precision: the weights and the preconditioner's vectors are float32; CG's solution, residual, search direction
and its product with the matrix are float64, as is every sum. The residual has to resolve modes that the
preconditioner amplifies a thousandfold (two sides of a depth jump joined by bini's all-but-cut edges are
nearly a null vector), so a float32 search direction or product stalls CG near a relative residual of 1e-6;
the depth itself is large against its Laplacian, so the solution must be float64 too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

#: Coarsening stops at this many nodes (solved directly).
COARSEST = 400
#: An edge joins an aggregate when ``w_ij >= THETA * sqrt(d_i d_j)`` (the symmetric strength test).
THETA = 0.1
#: Scale of the coarse-grid correction (see the module docstring).
OVERCORRECT = 2.0
#: Gauss-Seidel sweeps before and after the coarse correction.
SWEEPS = 1


# -- the fine level: the stencil ------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _grid_links(dom, up, down):  # pragma: no cover - numba
    W = dom.shape[1]
    prev = np.full(W, -1, dtype=np.int32)
    i = 0
    for r in range(dom.shape[0]):
        for c in range(W):
            if dom[r, c]:
                j = prev[c]
                if j >= 0:
                    up[i] = j
                    down[j] = i
                prev[c] = i
                i += 1
            else:
                prev[c] = -1


def grid_links(dom: NDArray[np.bool_]) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """``(up, down)``: each domain pixel's neighbour above and below (raster indices, -1 for none)."""
    n = int(np.count_nonzero(dom))
    up = np.full(n, -1, dtype=np.int32)
    down = np.full(n, -1, dtype=np.int32)
    _grid_links(dom, up, down)
    return up, down


@njit(cache=True, nogil=True, inline="always")
def _fine_row(wh, wv, up, down, x, i):  # pragma: no cover - numba
    """``(sum_j w_ij x_j, d_i)`` of pixel ``i`` in float64."""
    s = 0.0
    d = 0.0
    w = float(wh[i])
    if w != 0.0:
        s += w * x[i + 1]
        d += w
    if i > 0:
        w = float(wh[i - 1])
        if w != 0.0:
            s += w * x[i - 1]
            d += w
    j = down[i]
    if j >= 0:
        w = float(wv[i])
        s += w * x[j]
        d += w
    j = up[i]
    if j >= 0:
        w = float(wv[j])
        s += w * x[j]
        d += w
    return s, d


@njit(cache=True, nogil=True)
def fine_apply(wh, wv, up, down, x, out):  # pragma: no cover - numba
    """``out = A x`` and returns ``x . A x`` (float64 sums)."""
    dot = 0.0
    for i in range(x.size):
        s, d = _fine_row(wh, wv, up, down, x, i)
        v = d * x[i] - s
        out[i] = v
        dot += float(x[i]) * v
    return dot


@njit(cache=True, nogil=True)
def _residual(wh, wv, up, down, x, r):  # pragma: no cover - numba
    """``r -= A x``."""
    for i in range(x.size):
        s, d = _fine_row(wh, wv, up, down, x, i)
        r[i] -= d * x[i] - s


@njit(cache=True, nogil=True)
def _fine_gs(dom, wh, wv, up, down, b, x, color):  # pragma: no cover - numba
    """A Gauss-Seidel half-sweep over the pixels of one colour (``(row + column) % 2``): their
    neighbours all have the other colour, so the updates are independent."""
    H, W = dom.shape
    i = 0
    for r in range(H):
        for c in range(W):
            if dom[r, c]:
                if (r + c) % 2 == color:
                    s, d = _fine_row(wh, wv, up, down, x, i)
                    x[i] = (b[i] + s) / d if d > 0.0 else 0.0
                i += 1


@njit(cache=True, nogil=True)
def _fine_restrict(wh, wv, up, down, b, x, agg, bc):  # pragma: no cover - numba
    """``bc = P^T (b - A x)``."""
    bc[:] = 0.0
    for i in range(x.size):
        a = agg[i]
        if a >= 0:
            s, d = _fine_row(wh, wv, up, down, x, i)
            bc[a] += b[i] - (d * x[i] - s)


@njit(cache=True, nogil=True, inline="always")
def _fine_diag(wh, wv, up, i):  # pragma: no cover - numba
    d = float(wh[i])
    if i > 0:
        d += float(wh[i - 1])
    j = up[i]
    if j >= 0:
        d += float(wv[j])
    return d + float(wv[i])  # wv is 0 where there is no pixel below


@njit(cache=True, nogil=True, inline="always")
def find_root(parent, i):  # pragma: no cover - numba
    """The root of ``i``'s piece in the union-find forest ``parent``."""
    while parent[i] != i:
        i = parent[i]
    return i


@njit(cache=True, nogil=True, inline="always")
def join_pieces(parent, a, b):  # pragma: no cover - numba
    """Join the pieces of ``a`` and ``b``: the lower root becomes the root of both (so a piece's root
    is its first member)."""
    ra = find_root(parent, a)
    rb = find_root(parent, b)
    parent[max(ra, rb)] = min(ra, rb)


@njit(cache=True, nogil=True)
def _fine_aggregate(dom, wh, wv, up, theta, agg, rows, cols, fill):  # pragma: no cover - numba
    """Aggregates of 2 x 2 blocks: the pieces of each block under strong edges, numbered block by block
    in raster order of the blocks, into ``agg`` per pixel (-1 for a pixel without an edge). With
    ``fill``, also each aggregate's block row and column. Returns the number of aggregates."""
    H, W = dom.shape
    nc = 0
    start = 0  # raster index of the first pixel of row r
    slot = np.empty(4, dtype=np.int64)
    root = np.empty(4, dtype=np.int64)
    for r in range(0, H, 2):
        n0 = 0
        for c in range(W):
            n0 += dom[r, c]
        n1 = 0
        if r + 1 < H:
            for c in range(W):
                n1 += dom[r + 1, c]
        i0 = start  # running indices in rows r and r + 1
        i1 = start + n0
        for c in range(0, W, 2):
            # the block's pixels: (r, c), (r, c+1), (r+1, c), (r+1, c+1)
            for q in range(4):
                slot[q] = -1
                root[q] = q
            if dom[r, c]:
                slot[0] = i0
                i0 += 1
            if c + 1 < W and dom[r, c + 1]:
                slot[1] = i0
                i0 += 1
            if r + 1 < H:
                if dom[r + 1, c]:
                    slot[2] = i1
                    i1 += 1
                if c + 1 < W and dom[r + 1, c + 1]:
                    slot[3] = i1
                    i1 += 1
            if slot[0] < 0 and slot[1] < 0 and slot[2] < 0 and slot[3] < 0:
                continue
            # strong edges inside the block: 0-1, 2-3 (horizontal), 0-2, 1-3 (vertical)
            for e in range(4):
                p = 0 if e == 0 or e == 2 else (2 if e == 1 else 1)
                q = 1 if e == 0 else (3 if e == 1 or e == 3 else 2)
                ia, ib = slot[p], slot[q]
                if ia < 0 or ib < 0:
                    continue
                w = float(wh[ia]) if e < 2 else float(wv[ia])
                da = _fine_diag(wh, wv, up, ia)
                db = _fine_diag(wh, wv, up, ib)
                if w > 0.0 and w >= theta * np.sqrt(da * db):
                    join_pieces(root, p, q)
            for q in range(4):  # roots first (a root is the lowest slot of its piece)
                ia = slot[q]
                if ia < 0:
                    continue
                if _fine_diag(wh, wv, up, ia) == 0.0:
                    agg[ia] = -1
                    continue
                rq = find_root(root, q)
                if rq == q:
                    if fill:
                        rows[nc] = r // 2
                        cols[nc] = c // 2
                    agg[ia] = nc
                    nc += 1
                else:
                    agg[ia] = agg[slot[rq]]
        start += n0 + n1
    return nc


@njit(cache=True, nogil=True)
def _members(agg, ptr, order):  # pragma: no cover - numba
    """The nodes of each aggregate into ``(ptr, order)`` as in CSR (``ptr`` zeros on entry)."""
    nc = ptr.size - 1
    for i in range(agg.size):
        if agg[i] >= 0:
            ptr[agg[i] + 1] += 1
    for a in range(nc):
        ptr[a + 1] += ptr[a]
    for i in range(agg.size):
        a = agg[i]
        if a >= 0:
            order[ptr[a]] = i
            ptr[a] += 1
    for a in range(nc, 0, -1):
        ptr[a] = ptr[a - 1]
    ptr[0] = 0


@njit(cache=True, nogil=True, inline="always")
def _add(nb, wt, cnt, b, w):  # pragma: no cover - numba
    """Adds weight ``w`` to neighbour ``b`` in the list ``nb[:cnt]``; returns the (new) list and count."""
    for t in range(cnt):
        if nb[t] == b:
            wt[t] += w
            return nb, wt, cnt
    if cnt == nb.size:
        nb2 = np.empty(2 * cnt, dtype=nb.dtype)
        wt2 = np.empty(2 * cnt, dtype=wt.dtype)
        nb2[:cnt] = nb
        wt2[:cnt] = wt
        nb, wt = nb2, wt2
    nb[cnt] = b
    wt[cnt] = w
    return nb, wt, cnt + 1


@njit(cache=True, nogil=True)
def _coarse_from_fine(wh, wv, up, down, agg, ptr, order, indptr, idx, val, fill):  # pragma: no cover
    """The Galerkin coarse operator of the stencil under ``agg`` as an adjacency list: without ``fill``
    each coarse node's count of neighbours into ``indptr[1:]``, with it (``indptr`` summed) the lists."""
    nb = np.empty(16, dtype=np.int32)
    wt = np.empty(16, dtype=np.float64)
    for a in range(ptr.size - 1):
        cnt = 0
        for m in range(ptr[a], ptr[a + 1]):
            i = order[m]
            for e in range(4):
                if e == 0:
                    j = i + 1 if wh[i] != 0.0 else -1
                    w = float(wh[i]) if j >= 0 else 0.0
                elif e == 1:
                    j = i - 1 if i > 0 and wh[i - 1] != 0.0 else -1
                    w = float(wh[i - 1]) if j >= 0 else 0.0
                elif e == 2:
                    j = down[i]
                    w = float(wv[i]) if j >= 0 else 0.0
                else:
                    j = up[i]
                    w = float(wv[j]) if j >= 0 else 0.0
                if j < 0:
                    continue
                b = agg[j]
                if b >= 0 and b != a:
                    nb, wt, cnt = _add(nb, wt, cnt, b, w)
        if not fill:
            indptr[a + 1] = cnt
        else:
            s = indptr[a]
            for t in range(cnt):
                idx[s + t] = nb[t]
                val[s + t] = wt[t]


# -- coarse levels: adjacency lists ---------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _diag(indptr, val, d):  # pragma: no cover - numba
    for i in range(d.size):
        for t in range(indptr[i], indptr[i + 1]):
            d[i] += val[t]


@njit(cache=True, nogil=True)
def _coarse_apply_residual(indptr, idx, val, diag, b, x, agg, bc):  # pragma: no cover - numba
    bc[:] = 0.0
    for i in range(x.size):
        a = agg[i]
        if a >= 0:
            s = 0.0
            for t in range(indptr[i], indptr[i + 1]):
                s += val[t] * x[idx[t]]
            bc[a] += b[i] - (diag[i] * x[i] - s)


@njit(cache=True, nogil=True)
def _coarse_gs(indptr, idx, val, diag, b, x, backward):  # pragma: no cover - numba
    n = x.size
    for k in range(n):
        i = n - 1 - k if backward else k
        d = diag[i]
        if d > 0.0:
            s = b[i]
            for t in range(indptr[i], indptr[i + 1]):
                s += val[t] * x[idx[t]]
            x[i] = s / d
        else:
            x[i] = 0.0


@njit(cache=True, nogil=True)
def _coarse_pieces(indptr, idx, val, diag, rows, cols, theta, parent, key):  # pragma: no cover - numba
    """Like :func:`_fine_aggregate` one level up: nodes sit in blocks ``(rows, cols)`` and are grouped by
    ``(rows // 2, cols // 2)`` into the pieces each group makes under strong edges. Writes each node's
    key (its parent block in raster order, then its piece's first node)."""
    n = diag.size
    for i in range(n):
        parent[i] = i
    for i in range(n):
        pr, pc = rows[i] // 2, cols[i] // 2
        for t in range(indptr[i], indptr[i + 1]):
            j = idx[t]
            if j <= i or rows[j] // 2 != pr or cols[j] // 2 != pc:
                continue
            if val[t] >= theta * np.sqrt(diag[i] * diag[j]):
                join_pieces(parent, i, j)
    wmax = 0
    for i in range(n):
        wmax = max(wmax, cols[i] // 2 + 1)
    for i in range(n):
        r = find_root(parent, i)
        parent[i] = r
        key[i] = ((rows[i] // 2) * wmax + cols[i] // 2) * n + r


@njit(cache=True, nogil=True)
def _number(perm, key, diag, rows, cols, agg, crow, ccol):  # pragma: no cover - numba
    """Aggregates numbered in the order of their keys (nodes without an edge: -1); returns how many."""
    nc = 0
    last = -1
    for m in range(perm.size):
        i = perm[m]
        if diag[i] == 0.0:
            agg[i] = -1
            continue
        if key[i] != last:
            last = key[i]
            crow[nc] = rows[i] // 2
            ccol[nc] = cols[i] // 2
            nc += 1
        agg[i] = nc - 1
    return nc


def _coarse_aggregate(lev: _Level, rows, cols, theta: float):
    n = lev.diag.size
    parent = np.empty(n, dtype=np.int64)
    key = np.empty(n, dtype=np.int64)
    _coarse_pieces(lev.indptr, lev.idx, lev.val, lev.diag, rows, cols, theta, parent, key)
    del parent
    perm = np.argsort(key, kind="stable")
    agg = np.empty(n, dtype=np.int32)
    crow = np.empty(n, dtype=np.int32)
    ccol = np.empty(n, dtype=np.int32)
    nc = _number(perm, key, lev.diag, rows, cols, agg, crow, ccol)
    return agg, crow[:nc].copy(), ccol[:nc].copy(), nc


@njit(cache=True, nogil=True)
def _coarse_from_coarse(indptr, idx, val, agg, ptr, order, cptr, cidx, cval, fill):  # pragma: no cover
    nb = np.empty(16, dtype=np.int32)
    wt = np.empty(16, dtype=np.float64)
    for a in range(ptr.size - 1):
        cnt = 0
        for m in range(ptr[a], ptr[a + 1]):
            i = order[m]
            for t in range(indptr[i], indptr[i + 1]):
                b = agg[idx[t]]
                if b >= 0 and b != a:
                    nb, wt, cnt = _add(nb, wt, cnt, b, val[t])
        if not fill:
            cptr[a + 1] = cnt
        else:
            s = cptr[a]
            for t in range(cnt):
                cidx[s + t] = nb[t]
                cval[s + t] = wt[t]


def _galerkin(kernel, args: tuple, agg: NDArray, nc: int) -> tuple[NDArray, NDArray, NDArray]:
    """The coarse adjacency lists under ``agg`` by ``kernel`` (count, then fill)."""
    ptr = np.zeros(nc + 1, dtype=np.int64)
    order = np.empty(agg.size, dtype=np.int32)
    _members(agg, ptr, order)
    indptr = np.zeros(nc + 1, dtype=np.int64)
    idx = np.empty(0, dtype=np.int32)
    val = np.empty(0, dtype=np.float64)
    kernel(*args, agg, ptr, order, indptr, idx, val, False)
    np.cumsum(indptr, out=indptr)
    idx = np.empty(int(indptr[-1]), dtype=np.int32)
    val = np.empty(int(indptr[-1]), dtype=np.float64)
    kernel(*args, agg, ptr, order, indptr, idx, val, True)
    return indptr, idx, val


@njit(cache=True, nogil=True)
def _prolong(x, agg, xc, scale):  # pragma: no cover - numba
    for i in range(x.size):
        a = agg[i]
        if a >= 0:
            x[i] += scale * xc[a]


# -- CG's fused steps -----------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _step(x, r, p, q, alpha):  # pragma: no cover - numba
    """``x += alpha p``, ``r -= alpha q``; returns ``|r|^2``."""
    rr = 0.0
    for i in range(x.size):
        x[i] += alpha * p[i]
        v = r[i] - alpha * q[i]
        r[i] = v
        rr += v * v
    return rr


@njit(cache=True, nogil=True)
def _dot(a, b):  # pragma: no cover - numba
    s = 0.0
    for i in range(a.size):
        s += float(a[i]) * float(b[i])
    return s


@njit(cache=True, nogil=True)
def _direction(p, z, beta):  # pragma: no cover - numba
    for i in range(p.size):
        p[i] = z[i] + beta * p[i]


# -- the hierarchy --------------------------------------------------------------------------------------
@dataclass
class _Level:
    indptr: NDArray
    idx: NDArray
    val: NDArray
    diag: NDArray
    agg: NDArray | None = None  # to the next level
    x: NDArray | None = None
    b: NDArray | None = None


class Multigrid:
    """The preconditioner of the stencil ``(wh, wv, up, down)`` on the domain ``dom``."""

    def __init__(self, dom: NDArray[np.bool_], wh, wv, up, down, theta: float = THETA) -> None:
        self.dom, self.wh, self.wv, self.up, self.down = dom, wh, wv, up, down
        self.agg = np.empty(wh.size, dtype=np.int32)
        none = np.empty(0, dtype=np.int32)
        nc = _fine_aggregate(dom, wh, wv, up, theta, self.agg, none, none, False)
        rows = np.empty(nc, dtype=np.int32)
        cols = np.empty(nc, dtype=np.int32)
        _fine_aggregate(dom, wh, wv, up, theta, self.agg, rows, cols, True)
        self.levels: list[_Level] = []
        self.coarsest = None
        if nc == 0:
            return
        indptr, idx, val = _galerkin(_coarse_from_fine, (wh, wv, up, down), self.agg, nc)
        while True:
            lev = _Level(indptr, idx, val, np.zeros(nc))
            _diag(indptr, val, lev.diag)
            lev.x, lev.b = np.zeros(nc), np.zeros(nc)
            self.levels.append(lev)
            if nc <= COARSEST:
                break
            agg, crows, ccols, cnc = _coarse_aggregate(lev, rows, cols, theta)
            # nodes that could not join (their group's edges are weak) are tried again in larger
            # groups; once a group spans the image, nothing is left to join
            while cnc > 0.9 * nc and (crows.max(initial=0) > 0 or ccols.max(initial=0) > 0):
                rows, cols = rows // 2, cols // 2
                agg, crows, ccols, cnc = _coarse_aggregate(lev, rows, cols, theta)
            if cnc == 0 or cnc >= nc:
                break
            cindptr, cidx, cval = _galerkin(_coarse_from_coarse, (indptr, idx, val), agg, cnc)
            if cindptr[-1] == 0:
                break  # each aggregate is a whole piece: nothing to correct, so this level is the coarsest
            lev.agg = agg
            indptr, idx, val = cindptr, cidx, cval
            rows, cols, nc = crows, ccols, cnc
        self.coarsest = _factor(self.levels[-1])

    def __call__(self, r: NDArray[np.float64], z: NDArray[np.float32]) -> None:
        """``z = B r`` (one V-cycle from zero)."""
        z[:] = 0.0
        args = (self.wh, self.wv, self.up, self.down)
        # red-black: red then black before the coarse correction, black then red after (symmetric)
        for _ in range(SWEEPS):
            _fine_gs(self.dom, *args, r, z, 0)
            _fine_gs(self.dom, *args, r, z, 1)
        if self.levels:
            top = self.levels[0]
            _fine_restrict(*args, r, z, self.agg, top.b)
            self._cycle(0)
            _prolong(z, self.agg, top.x, OVERCORRECT)
        for _ in range(SWEEPS):
            _fine_gs(self.dom, *args, r, z, 1)
            _fine_gs(self.dom, *args, r, z, 0)

    def _cycle(self, k: int) -> None:
        lev = self.levels[k]
        if k == len(self.levels) - 1:
            lev.x[:] = self.coarsest(lev.b)
            return
        lev.x[:] = 0.0
        m = (lev.indptr, lev.idx, lev.val, lev.diag)
        for _ in range(SWEEPS):
            _coarse_gs(*m, lev.b, lev.x, False)
        nxt = self.levels[k + 1]
        _coarse_apply_residual(*m, lev.b, lev.x, lev.agg, nxt.b)
        self._cycle(k + 1)
        _prolong(lev.x, lev.agg, nxt.x, OVERCORRECT)
        for _ in range(SWEEPS):
            _coarse_gs(*m, lev.b, lev.x, True)


#: Coarsest levels of at most this many nodes are factored densely by numpy (an inverse: 1.3 MB at 400
#: nodes), larger ones (coarsening that stalled) by scipy's sparse LU; both solve the same system.
DENSE_COARSEST = 1000


def _factor(lev: _Level):
    """A direct solve of the coarsest level, one node of each connected piece held at 0."""
    n = lev.diag.size
    rows = np.repeat(np.arange(n), np.diff(lev.indptr))
    if n > DENSE_COARSEST:
        return _sparse_factor(lev, rows)
    # connected pieces by the stored edges (as scipy.sparse.csgraph's connected_components): label
    # propagation to the smallest label of each piece, whose node is the one held
    lab = np.arange(n)
    while True:
        low = lab.copy()
        np.minimum.at(low, rows, lab[lev.idx])
        np.minimum.at(low, lev.idx, lab[rows])
        low = low[low]  # pointer jumping: a path of n nodes settles in about log2(n) rounds
        if np.array_equal(low, lab):
            break
        lab = low
    hold = lab == np.arange(n)
    hold |= lev.diag == 0.0
    A = np.zeros((n, n))
    np.add.at(A, (rows, lev.idx), lev.val)
    M = np.diag(lev.diag) - A
    M[hold, :] = 0.0
    M[:, hold] = 0.0
    M[hold, hold] = 1.0
    inv = np.linalg.inv(M)

    def direct(b: NDArray) -> NDArray:
        return inv @ np.where(hold, 0.0, b)

    return direct


def _sparse_factor(lev: _Level, rows: NDArray):
    """:func:`_factor` for a large coarsest level, by scipy's sparse LU."""
    import scipy.sparse
    import scipy.sparse.csgraph
    import scipy.sparse.linalg

    n = lev.diag.size
    A = scipy.sparse.csr_matrix((lev.val, lev.idx, lev.indptr), shape=(n, n))
    _, lab = scipy.sparse.csgraph.connected_components(A, directed=False)
    first = np.unique(lab, return_index=True)[1]
    hold = np.zeros(n, dtype=bool)
    hold[first] = True
    hold |= lev.diag == 0.0
    keep = scipy.sparse.diags((~hold).astype(np.float64))
    L = keep @ (scipy.sparse.diags(lev.diag) - A) @ keep + scipy.sparse.diags(hold.astype(np.float64))
    lu = scipy.sparse.linalg.splu(L.tocsc())

    def direct(b: NDArray) -> NDArray:
        return lu.solve(np.where(hold, 0.0, b))

    return direct


def solve(
    dom: NDArray[np.bool_],
    wh: NDArray[np.float32],
    wv: NDArray[np.float32],
    up: NDArray[np.int32],
    down: NDArray[np.int32],
    b: NDArray[np.float64],
    x: NDArray[np.float64],
    tol: float,
    maxiter: int = 500,
) -> int:
    """Solves ``A x = b`` for the stencil ``(wh, wv, up, down)`` on the domain ``dom`` by CG preconditioned
    with :class:`Multigrid`, from the start ``x`` (updated in place) to a relative residual ``tol``.
    ``b`` must be consistent (sum to 0 on each connected piece); it is overwritten (it becomes the
    residual). Returns the number of iterations."""
    n = b.size
    stencil = (wh, wv, up, down)
    bnorm = float(np.sqrt(_dot(b, b)))
    r = b
    q = np.empty(n)
    if _dot(x, x) > 0.0:
        _residual(wh, wv, up, down, x, r)
    if bnorm == 0.0 or np.sqrt(_dot(r, r)) <= tol * bnorm:
        return 0
    mg = Multigrid(dom, *stencil)
    z = np.empty(n, dtype=np.float32)
    mg(r, z)
    p = z.astype(np.float64)
    rz = _dot(r, p)
    its = 0
    while its < maxiter:
        its += 1
        pq = fine_apply(*stencil, p, q)
        # p can be all but a null vector of this singular matrix (a constant per piece): pq is then
        # rounding noise, and the step along p harmless
        if pq == 0.0:
            break
        alpha = rz / pq
        if np.sqrt(_step(x, r, p, q, alpha)) <= tol * bnorm:
            break
        mg(r, z)
        rz, rz_old = _dot(r, z), rz
        if rz_old == 0.0:
            break
        _direction(p, z, rz / rz_old)
    return its
