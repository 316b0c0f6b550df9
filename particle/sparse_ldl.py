"""Sparse ``L D L^T`` factorisation of the symmetric tangent stiffness, in numba.

(Longer than the project's 450-line guideline: the symbolic analysis and the
numeric kernels index the same precomputed supernode arrays and are read
together; split in two, neither half explains itself.)

The Newton solver and the adjoint pass factorise tangents of one fixed sparsity
pattern (:class:`particle.statics.TangentPattern`) thousands of times. SuperLU
(``splu`` with a symmetric minimum-degree ordering and ``diag_pivot_thresh=0``)
does an unpivoted LU of the symmetric matrix, that is ``L D L^T``, but redoes
the ordering and the symbolic analysis on every call. Here they are done once
per pattern (:func:`analyse` -> :class:`Symbolic`), and a call only runs the
numeric part (:func:`factorize` -> :class:`Factor`):

* ordering: the permutation SuperLU's ``MMD_AT_PLUS_A`` (multiple minimum degree
  on ``A + A^T``, postordered) picks for the pattern, read off one SuperLU
  factorisation of a diagonally dominant matrix on it (scipy exposes no
  ordering on its own);
* elimination tree and column counts of ``L`` (Liu's algorithm, as in Davis' LDL
  package), the row patterns of ``L``, and its *supernodes*: runs of consecutive
  columns with the same pattern below the diagonal (a particle's three dofs at
  least; the last separator is dense), each stored as one dense column-major
  block, with everything the numeric part indexes precomputed;
* numeric: left-looking supernodal ``L D L^T``: each supernode gathers the
  updates of the supernodes below it in the elimination tree as small dense
  products, then factorises its own block (Davis, *Direct methods for sparse
  linear systems*, 2006, ch. 4 and 9). Dense inner loops over contiguous
  memory are what makes it faster than a column-by-column ``L D L^T``;
* solves: the forward, diagonal and backward sweeps supernode by supernode,
  for one right-hand side (n,) or many (n, r) at once.

On the liver punch's tangent (687 dofs, 21,357 entries, 31,485 in ``L``): 0.54 ms
per factorisation against SuperLU's 2.2 ms, 0.54 ms against 1.27 ms per solve
with 31 right-hand sides, 0.06 ms against 0.09 ms with one; the analysis takes
8 ms once.

**No pivoting** is done, as with SuperLU's ``diag_pivot_thresh=0`` before: the
pivots ``D`` follow the fill-reducing order whatever their size. That is exact
for a positive definite tangent and fine for an indefinite one without a zero
pivot on the way (a softening spring); an exactly zero (or non-finite) pivot
raises :class:`RuntimeError`, as SuperLU does on an exactly singular matrix, so
callers can shift the diagonal and retry. Only the lower triangle of the
permuted matrix is read: the tangent is symmetric up to the round-off of its
assembly (~1e-16 relative). The pattern is structural: explicitly stored zeros
(a prescribed particle's decoupled rows) count as entries (SuperLU drops them,
so its ``L`` has some 5 % fewer entries on a constrained tangent).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse.linalg import splu

from particle.kernels import JIT
from particle.lanes import LANES, vadd, vload, vmul, vsplat, vstore, vsub


@dataclass(frozen=True, eq=False)
class Symbolic:
    """Everything about ``P A P^T = L D L^T`` that depends only on the pattern of ``A``.

    ``n`` unknowns (index ``k`` of the permuted matrix is ``perm[k]`` of ``A``), ``m``
    entries in the lower triangle of ``P A P^T``, ``S`` supernodes. Supernode ``s`` holds
    columns ``sup_ptr[s]`` to ``sup_ptr[s + 1] - 1`` of ``L``; its ``nr`` rows
    ``rows[row_ptr[s]:row_ptr[s + 1]]`` (ascending: its own columns, then the rows
    below) and ``nc`` columns are a dense column-major block at ``x_ptr[s]`` of the
    factor's values, the unit diagonal of ``L`` stored, its upper triangle unused.
    Supernode ``s`` is updated by supernodes ``upd_sup[u]`` (for ``u`` in
    ``upd_ptr[s]:upd_ptr[s + 1]``), whose block rows ``upd_q1[u]:upd_q2[u]`` fall
    in ``s``'s columns.

    Attributes:
        perm: (n,) int64, new -> old.
        a_src: (m,) int64, index in the caller's CSC ``data`` of each lower entry.
        a_dst: (m,) int64, its index in the factor's values.
        sup_ptr: (S + 1,) int64.
        row_ptr: (S + 1,) int64.
        rows: (row_ptr[-1],) int64.
        x_ptr: (S + 1,) int64, x_ptr[-1] values in all.
        upd_ptr: (S + 1,) int64.
        upd_sup, upd_q1, upd_q2: (U,) int64.
    """
    perm: np.ndarray
    a_src: np.ndarray
    a_dst: np.ndarray
    sup_ptr: np.ndarray
    row_ptr: np.ndarray
    rows: np.ndarray
    x_ptr: np.ndarray
    upd_ptr: np.ndarray
    upd_sup: np.ndarray
    upd_q1: np.ndarray
    upd_q2: np.ndarray

    @property
    def n(self) -> int:
        return len(self.perm)

    @property
    def nnz(self) -> int:
        """Entries of ``L`` strictly below the diagonal (SuperLU's ``L.nnz`` is this + n)."""
        nc, nr = np.diff(self.sup_ptr), np.diff(self.row_ptr)
        return int(np.sum(nc * nr - nc * (nc + 1) // 2))


def minimum_degree_order(indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(n,) int64 fill-reducing symmetric order (new -> old) of the CSC pattern ``indptr``,
    ``indices`` (structurally symmetric, every diagonal entry present).

    SuperLU's ``MMD_AT_PLUS_A`` ordering, taken from a factorisation of a
    diagonally dominant matrix on the pattern (so that no pivot can vanish).
    """
    n = len(indptr) - 1
    cols = np.repeat(np.arange(n), np.diff(indptr))
    data = np.where(indices == cols, float(np.diff(indptr).max() + 1), -1.0)
    lu = superlu(indptr, indices, data)
    return np.argsort(lu.perm_c).astype(np.int64)  # perm_c is old -> new


def superlu(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray):
    """SuperLU's factorisation of the symmetric CSC matrix (``indptr``, ``indices``, ``data``):
    ``MMD_AT_PLUS_A`` ordering, no row pivoting (fill ~25 % below COLAMD's). The source
    of :func:`minimum_degree_order` and the reference this module is tested against (it
    orders and analyses the pattern at every call)."""
    n = len(indptr) - 1
    matrix = sp.csc_matrix((data, indices, indptr), shape=(n, n))
    return splu(matrix, permc_spec="MMD_AT_PLUS_A", options=dict(SymmetricMode=True),
                diag_pivot_thresh=0.0)


def analyse(indptr: np.ndarray, indices: np.ndarray,
            perm: np.ndarray | None = None) -> Symbolic:
    """Symbolic analysis of the symmetric CSC pattern ``indptr`` (n + 1,), ``indices`` (nnz,).

    ``perm`` (n,) new -> old, default :func:`minimum_degree_order`. The pattern
    must be structurally symmetric with its diagonal present (a tangent's is).
    """
    indptr = np.asarray(indptr, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    n = len(indptr) - 1
    perm = minimum_degree_order(indptr, indices) if perm is None else perm
    perm = np.asarray(perm, dtype=np.int64)
    inv = np.empty(n, dtype=np.int64)
    inv[perm] = np.arange(n)
    rows = inv[indices]
    cols = inv[np.repeat(np.arange(n), np.diff(indptr))]
    src = np.flatnonzero(rows >= cols)  # the lower triangle of P A P^T
    src = src[np.lexsort((cols[src], rows[src]))]  # by row: the upper triangle by column
    up_ptr = np.searchsorted(rows[src], np.arange(n + 1)).astype(np.int64)
    parent, counts = _etree_and_counts(up_ptr, cols[src])
    l_ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    l_row = _column_patterns(up_ptr, cols[src], parent, l_ptr)
    sup_ptr = _supernodes(parent, counts)
    row_ptr, s_rows, x_ptr = _supernode_rows(sup_ptr, l_ptr, l_row)
    a_dst = _value_index(sup_ptr, row_ptr, s_rows, x_ptr, rows[src], cols[src])
    order = np.argsort(a_dst)  # scatter the values in storage order
    upd = _updates(sup_ptr, row_ptr, s_rows)
    return Symbolic(perm, src[order].astype(np.int64), a_dst[order], sup_ptr, row_ptr, s_rows,
                    x_ptr, *upd)


@njit(**JIT)
def _etree_and_counts(up_ptr, up_row):
    """(parent (n,), counts (n,)) of ``L``: elimination tree (-1 at a root) and the number of
    entries below the diagonal per column, from the upper triangle of ``P A P^T`` by
    column (``up_ptr``, ``up_row``, rows <= the column).

    Row ``k`` of ``L`` is the set of nodes met walking up the (partial) tree from
    each ``i < k`` in column ``k``, until a node already marked for ``k`` (Liu;
    Davis' ``ldl_symbolic``).
    """
    n = len(up_ptr) - 1
    parent = np.full(n, -1, dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    flag = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        flag[k] = k
        for p in range(up_ptr[k], up_ptr[k + 1]):
            i = up_row[p]
            while flag[i] != k:  # i < k: stops at k at the latest
                if parent[i] == -1:
                    parent[i] = k
                counts[i] += 1
                flag[i] = k
                i = parent[i]
    return parent, counts


@njit(**JIT)
def _column_patterns(up_ptr, up_row, parent, l_ptr):
    """(nnz,) row indices of ``L`` below the diagonal by column (CSC with ``l_ptr``),
    ascending: the tree walk of :func:`_etree_and_counts` again, recording what it
    meets; rows ``k`` come in increasing order."""
    n = len(up_ptr) - 1
    l_row = np.empty(l_ptr[n], dtype=np.int64)
    fill = l_ptr[:-1].copy()  # next free position of each column
    flag = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        flag[k] = k
        for p in range(up_ptr[k], up_ptr[k + 1]):
            i = up_row[p]
            while flag[i] != k:
                l_row[fill[i]] = k
                fill[i] += 1
                flag[i] = k
                i = parent[i]
    return l_row


def _supernodes(parent: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(S + 1,) first column of each supernode: column j joins j - 1's when it is j - 1's
    parent and has one entry less below the diagonal (then both have the same rows
    below j: a column's pattern is contained in its parent's, plus the parent)."""
    n = len(parent)
    j = np.arange(1, n)
    joins = (parent[:-1] == j) & (counts[:-1] == counts[1:] + 1)
    return np.concatenate([[0], j[~joins], [n]]).astype(np.int64)


def _supernode_rows(sup_ptr: np.ndarray, l_ptr: np.ndarray, l_row: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row_ptr, rows, x_ptr) of :class:`Symbolic`: a supernode's rows are its own
    columns followed by the rows below the diagonal of its last column."""
    first, last = sup_ptr[:-1], sup_ptr[1:] - 1
    blocks = [np.concatenate([np.arange(f, e + 1), l_row[l_ptr[e]:l_ptr[e + 1]]])
              for f, e in zip(first, last)]
    nr = np.array([len(b) for b in blocks], dtype=np.int64)
    row_ptr = np.concatenate([[0], np.cumsum(nr)]).astype(np.int64)
    x_ptr = np.concatenate([[0], np.cumsum(nr * np.diff(sup_ptr))]).astype(np.int64)
    return row_ptr, np.concatenate(blocks).astype(np.int64), x_ptr


def _value_index(sup_ptr: np.ndarray, row_ptr: np.ndarray, rows: np.ndarray,
                 x_ptr: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(m,) index in the factor's values of the lower entries (``r`` (m,) >= ``c`` (m,)) of
    ``P A P^T``: supernode ``s`` of column ``c``, position of row ``r`` in its rows."""
    n = sup_ptr[-1]
    sup_of = np.repeat(np.arange(len(sup_ptr) - 1), np.diff(sup_ptr))
    s = sup_of[c]
    owner = np.repeat(np.arange(len(row_ptr) - 1), np.diff(row_ptr))
    t = np.searchsorted(owner * n + rows, s * n + r) - row_ptr[s]  # rows ascending per s
    return x_ptr[s] + (c - sup_ptr[s]) * np.diff(row_ptr)[s] + t


def _updates(sup_ptr: np.ndarray, row_ptr: np.ndarray, rows: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(upd_ptr, upd_sup, upd_q1, upd_q2) of :class:`Symbolic`: each supernode's rows
    below its own columns, cut into runs that fall in one later supernode."""
    sup_of = np.repeat(np.arange(len(sup_ptr) - 1), np.diff(sup_ptr))
    target, source, q1, q2 = [], [], [], []
    for d in range(len(sup_ptr) - 1):
        nc = sup_ptr[d + 1] - sup_ptr[d]
        below = sup_of[rows[row_ptr[d] + nc:row_ptr[d + 1]]]
        cuts = np.flatnonzero(np.diff(below)) + 1
        starts, ends = np.concatenate([[0], cuts]), np.concatenate([cuts, [len(below)]])
        keep = ends > starts
        target.append(below[starts[keep]])
        source.append(np.full(keep.sum(), d))
        q1.append(nc + starts[keep])
        q2.append(nc + ends[keep])
    target, source, q1, q2 = (np.concatenate(a).astype(np.int64)
                              for a in (target, source, q1, q2))
    order = np.argsort(target, kind="stable")  # sources ascending within a target
    upd_ptr = np.searchsorted(target[order], np.arange(len(sup_ptr))).astype(np.int64)
    return upd_ptr, source[order], q1[order], q2[order]


@njit(inline="always", **JIT)
def _axpy_lanes(y, yo, v, vo, m, a):
    """``y[yo:yo + m] -= a v[vo:vo + m]`` (``y`` and ``v`` may be one array, the ranges
    apart) in explicit lanes (:mod:`particle.lanes`), the last ``m`` mod ``LANES``
    elements scalar: each element gets the scalar expression's operations, so the result
    is bitwise the scalar loop's. Inlined into the sweeps: LLVM vectorises such a loop
    only in a function of its own (it cannot tell the ranges apart), and a call per
    update cost more than its work on the short vectors here."""
    va = vsplat(a)
    vector = m - m % LANES
    for t in range(0, vector, LANES):
        vstore(y, yo + t, vsub(vload(y, yo + t), vmul(va, vload(v, vo + t))))
    for t in range(vector, m):
        y[yo + t] -= a * v[vo + t]


@njit(inline="always", **JIT)
def _axpy3_lanes(y, yo, v, o0, o1, o2, m, a0, a1, a2):
    """``y[yo:yo + m] -= a0 v[o0:o0 + m] + a1 v[o1:o1 + m] + a2 v[o2:o2 + m]``, as
    :func:`_axpy_lanes`: three updates of one vector in one pass (a particle's three dofs
    are three columns), a third of the loads and stores of ``y``."""
    c0, c1, c2 = vsplat(a0), vsplat(a1), vsplat(a2)
    vector = m - m % LANES
    for t in range(0, vector, LANES):
        sum3 = vadd(vadd(vmul(c0, vload(v, o0 + t)), vmul(c1, vload(v, o1 + t))),
                    vmul(c2, vload(v, o2 + t)))
        vstore(y, yo + t, vsub(vload(y, yo + t), sum3))
    for t in range(vector, m):
        y[yo + t] -= a0 * v[o0 + t] + a1 * v[o1 + t] + a2 * v[o2 + t]


@njit(**JIT)
def _numeric(sup_ptr, row_ptr, rows, x_ptr, upd_ptr, upd_sup, upd_q1, upd_q2, a_src, a_dst,
             data, x, d):
    """Fill ``x`` (x_ptr[-1],) with ``L`` and ``d`` (n,) with ``D`` of the matrix with CSC
    ``data``; returns -1, or the first (permuted) column whose pivot is zero or not finite.

    Supernode ``s``, left-looking: subtract ``L_d D_d L_d^T`` of each supernode ``d``
    updating it (:func:`_update`), then ``L D L^T`` of its dense block, column by
    column (each column minus the columns left of it, then divided by its pivot).
    """
    n = len(d)
    x[:] = 0.0
    for p in range(len(a_src)):
        x[a_dst[p]] = data[a_src[p]]
    relpos = np.empty(n, dtype=np.int64)
    work = np.empty(n)
    for s in range(len(sup_ptr) - 1):
        f, nc = sup_ptr[s], sup_ptr[s + 1] - sup_ptr[s]
        r0, nr, xs = row_ptr[s], row_ptr[s + 1] - row_ptr[s], x_ptr[s]
        for t in range(nr):
            relpos[rows[r0 + t]] = t
        for u in range(upd_ptr[s], upd_ptr[s + 1]):
            _update(sup_ptr, row_ptr, rows, x_ptr, upd_sup[u], upd_q1[u], upd_q2[u], f, nr,
                    xs, relpos, x, d, work)
        for c in range(nc):
            diag = xs + c * nr + c  # entry (c, c); rows c + 1.. of column c follow it
            for k in range(0, c - 2, 3):  # entries (c, k..k + 2) at lk, lk + nr, lk + 2 nr
                lk = xs + k * nr + c
                _axpy3_lanes(x, diag, x, lk, lk + nr, lk + 2 * nr, nr - c, x[lk] * d[f + k],
                             x[lk + nr] * d[f + k + 1], x[lk + 2 * nr] * d[f + k + 2])
            for k in range(c - c % 3, c):
                lk = xs + k * nr + c  # entry (c, k)
                _axpy_lanes(x, diag, x, lk, nr - c, x[lk] * d[f + k])
            pivot = x[diag]
            if pivot == 0.0 or not np.isfinite(pivot):
                return f + c
            d[f + c] = pivot
            x[diag] = 1.0
            for t in range(diag + 1, xs + (c + 1) * nr):
                x[t] /= pivot
    return -1


@njit(**JIT)
def _update(sup_ptr, row_ptr, rows, x_ptr, src, q1, q2, f, nr, xs, relpos, x, d, work):
    """Subtract supernode ``src``'s ``L D L^T`` from the columns ``rows[q1:q2]`` (of ``src``'s
    block rows) of the target supernode at ``xs`` (first column ``f``, ``nr`` rows mapped
    by ``relpos``): per target column, ``src``'s columns summed densely in ``work`` (three
    at a time), then scattered."""
    fd, ncd = sup_ptr[src], sup_ptr[src + 1] - sup_ptr[src]
    rd0, nrd, xd = row_ptr[src], row_ptr[src + 1] - row_ptr[src], x_ptr[src]
    for q in range(q1, q2):
        m = nrd - q  # rows of src at and below the target column's
        work[:m] = 0.0
        for k in range(0, ncd - 2, 3):  # work -= -sum_k L_k (L_qk d_k)
            lk = xd + k * nrd + q  # entry (q, k) of src
            _axpy3_lanes(work, 0, x, lk, lk + nrd, lk + 2 * nrd, m, -x[lk] * d[fd + k],
                         -x[lk + nrd] * d[fd + k + 1], -x[lk + 2 * nrd] * d[fd + k + 2])
        for k in range(ncd - ncd % 3, ncd):
            lk = xd + k * nrd + q
            _axpy_lanes(work, 0, x, lk, m, -x[lk] * d[fd + k])
        col = xs + (rows[rd0 + q] - f) * nr
        for t in range(m):
            x[col + relpos[rows[rd0 + q + t]]] -= work[t]


@njit(fastmath={"reassoc", "contract"}, **JIT)
def _solve_one(sup_ptr, row_ptr, rows, x_ptr, x, d, perm, b, out):
    """``out`` (n,) = ``A^{-1} b`` for ``b`` (n,): forward, diagonal and backward sweeps on the
    permuted vector, supernode by supernode.

    The rows of a supernode below its own columns are gathered once into ``below``.
    The forward sweep accumulates their updates there and scatters them once; the
    backward sweep takes each column's contribution from them as a dot product.
    Both go three columns per pass over ``below`` (:func:`_below_update`,
    :func:`_below_dots`): the passes are short (tens of rows), so fewer of them,
    each doing more per row loaded, is what makes the sweep fast (58 against 81
    us per solve on the liver's tangent, 687 dofs; ``fastmath`` reassociates the
    dot products so they vectorise).
    """
    n = len(d)
    w = np.empty(n)
    for k in range(n):
        w[k] = b[perm[k]]
    buffer = np.empty(n)  # a supernode's rows below its columns (fewer than n)
    for s in range(len(sup_ptr) - 1):  # L w' = w
        f, nc = sup_ptr[s], sup_ptr[s + 1] - sup_ptr[s]
        r0, nr, xs = row_ptr[s], row_ptr[s + 1] - row_ptr[s], x_ptr[s]
        own = w[f:f + nc]
        for c in range(nc):  # the block's own (dense, unit lower) triangle
            wc, col = own[c], x[xs + c * nr:xs + c * nr + nc]
            for t in range(c + 1, nc):
                own[t] -= col[t] * wc
        if nr > nc:
            below = buffer[:nr - nc]
            _below_update(x, xs, nr, nc, own, below)
            targets = rows[r0 + nc:r0 + nr]
            for t in range(nr - nc):
                w[targets[t]] -= below[t]
    for k in range(n):  # D w'' = w'
        w[k] /= d[k]
    for s in range(len(sup_ptr) - 2, -1, -1):  # L^T w''' = w''
        f, nc = sup_ptr[s], sup_ptr[s + 1] - sup_ptr[s]
        r0, nr, xs = row_ptr[s], row_ptr[s + 1] - row_ptr[s], x_ptr[s]
        own = w[f:f + nc]
        if nr > nc:  # the rows below are final: their part of every column first
            below = buffer[:nr - nc]
            sources = rows[r0 + nc:r0 + nr]
            for t in range(nr - nc):
                below[t] = w[sources[t]]
            _below_dots(x, xs, nr, nc, below, own)
        for c in range(nc - 1, -1, -1):  # then the triangle, last column first
            col = x[xs + c * nr:xs + c * nr + nc]
            acc = 0.0
            for t in range(c + 1, nc):
                acc += col[t] * own[t]
            own[c] -= acc
    for k in range(n):
        out[perm[k]] = w[k]


@njit(**JIT)
def _solve_restricted(sup_ptr, row_ptr, rows, x_ptr, x, d, perm, dofs, values, out):
    """``out`` (k,) = ``(A^{-1} b)[dofs]`` for ``b`` (n,) zero but at ``dofs`` (k,), where it
    is ``values`` (k,): :func:`_solve_one` with the scatter and the gather in the same call.
    Returns False (``out`` untouched) if a dof is outside ``0..n-1``."""
    n = len(d)
    for t in range(len(dofs)):
        if not 0 <= dofs[t] < n:
            return False
    b = np.zeros(n)
    for t in range(len(dofs)):
        b[dofs[t]] = values[t]
    full = np.empty(n)
    _solve_one(sup_ptr, row_ptr, rows, x_ptr, x, d, perm, b, full)
    for t in range(len(dofs)):
        out[t] = full[dofs[t]]
    return True


@njit(fastmath={"reassoc", "contract"}, **JIT)
def _below_update(x, xs, nr, nc, own, below):
    """``below = sum_c L[nc:, c] own[c]`` over the ``nc`` columns of the supernode block at
    ``x[xs:]`` (``nr`` rows, column-major), three columns per pass."""
    m = nr - nc
    below[:] = 0.0
    c = 0
    while c + 3 <= nc:
        w0, w1, w2 = own[c], own[c + 1], own[c + 2]
        c0 = x[xs + c * nr + nc:xs + (c + 1) * nr]
        c1 = x[xs + (c + 1) * nr + nc:xs + (c + 2) * nr]
        c2 = x[xs + (c + 2) * nr + nc:xs + (c + 3) * nr]
        for t in range(m):
            below[t] += c0[t] * w0 + c1[t] * w1 + c2[t] * w2
        c += 3
    while c < nc:
        wc, col = own[c], x[xs + c * nr + nc:xs + (c + 1) * nr]
        for t in range(m):
            below[t] += col[t] * wc
        c += 1


@njit(fastmath={"reassoc", "contract"}, **JIT)
def _below_dots(x, xs, nr, nc, below, own):
    """``own[c] -= L[nc:, c] . below`` for the ``nc`` columns of the supernode block at
    ``x[xs:]``, three columns per pass over ``below``."""
    m = nr - nc
    c = 0
    while c + 3 <= nc:
        c0 = x[xs + c * nr + nc:xs + (c + 1) * nr]
        c1 = x[xs + (c + 1) * nr + nc:xs + (c + 2) * nr]
        c2 = x[xs + (c + 2) * nr + nc:xs + (c + 3) * nr]
        a0, a1, a2 = 0.0, 0.0, 0.0
        for t in range(m):
            v = below[t]
            a0 += c0[t] * v
            a1 += c1[t] * v
            a2 += c2[t] * v
        own[c] -= a0
        own[c + 1] -= a1
        own[c + 2] -= a2
        c += 3
    while c < nc:
        col = x[xs + c * nr + nc:xs + (c + 1) * nr]
        acc = 0.0
        for t in range(m):
            acc += col[t] * below[t]
        own[c] -= acc
        c += 1


@njit(**JIT)
def _sub_rows(w, yo, first, count, width, x, lo, stride):
    """Row ``w[yo:yo + width]`` minus ``sum_c x[lo + c stride] w[(first + c) width:][:width]``
    over ``c < count``, three rows per pass (:func:`_axpy3_lanes`)."""
    for c in range(0, count - 2, 3):
        k = lo + c * stride
        o = (first + c) * width
        _axpy3_lanes(w, yo, w, o, o + width, o + 2 * width, width, x[k], x[k + stride],
                     x[k + 2 * stride])
    for c in range(count - count % 3, count):
        _axpy_lanes(w, yo, w, (first + c) * width, width, x[lo + c * stride])


@njit(**JIT)
def _sub_gathered(w, yo, rows, start, count, width, x, lo):
    """Row ``w[yo:yo + width]`` minus ``sum_t x[lo + t] w[rows[start + t] width:][:width]``
    over ``t < count``, three rows per pass (:func:`_axpy3_lanes`)."""
    for t in range(0, count - 2, 3):
        i = start + t
        _axpy3_lanes(w, yo, w, rows[i] * width, rows[i + 1] * width, rows[i + 2] * width,
                     width, x[lo + t], x[lo + t + 1], x[lo + t + 2])
    for t in range(count - count % 3, count):
        _axpy_lanes(w, yo, w, rows[start + t] * width, width, x[lo + t])


@njit(**JIT)
def _solve_many(sup_ptr, row_ptr, rows, x_ptr, x, d, perm, b, out, width):
    """``out`` (n, r) = ``A^{-1} b`` for ``b`` (n, r), any memory order.

    The sweeps run on a permuted copy ``w``, row ``k`` at ``w[k * width:][:r]``, so
    that the innermost loop runs over the right-hand sides (contiguous, in explicit
    lanes) and each entry of ``L`` is read once for all of them; ``width`` (>= r, a
    multiple of :data:`~particle.lanes.LANES`) leaves the lanes no scalar remainder (the
    padding stays 0). Row-oriented: a row of ``w`` takes all its updates from one
    supernode at once. Measured on the liver punch's tangent (687 dofs, 40,257 entries in
    ``L``) against a call per update (an LLVM-vectorised loop of its own, width a
    multiple of 16): 3 right-hand sides 384 -> 100 us, 16: 408 -> 169 us, 120: 1,088 ->
    845 us, bitwise the same solutions.
    """
    n, r = b.shape
    w = np.zeros(n * width)
    for k in range(n):
        for c in range(r):
            w[k * width + c] = b[perm[k], c]
    for s in range(len(sup_ptr) - 1):  # L w' = w: row t minus L[t, c] w'[c], c < t
        f, nc = sup_ptr[s], sup_ptr[s + 1] - sup_ptr[s]
        r0, nr, xs = row_ptr[s], row_ptr[s + 1] - row_ptr[s], x_ptr[s]
        for t in range(1, nr):
            _sub_rows(w, rows[r0 + t] * width, f, min(t, nc), width, x, xs + t, nr)
    for k in range(n):  # D w'' = w'
        inv = 1.0 / d[k]
        for c in range(r):
            w[k * width + c] *= inv
    for s in range(len(sup_ptr) - 2, -1, -1):  # L^T w''' = w'': row c minus L[t, c] w'''[t]
        f, nc = sup_ptr[s], sup_ptr[s + 1] - sup_ptr[s]
        r0, nr, xs = row_ptr[s], row_ptr[s + 1] - row_ptr[s], x_ptr[s]
        for c in range(nc - 1, -1, -1):
            _sub_gathered(w, (f + c) * width, rows, r0 + c + 1, nr - c - 1, width, x,
                          xs + c * nr + c + 1)
    for k in range(n):
        for c in range(r):
            out[perm[k], c] = w[k * width + c]


class Factor:
    """``A = P^T L D L^T P`` of a symmetric matrix (:func:`factorize`); solves like SuperLU.

    Attributes:
        symbolic: the pattern's :class:`Symbolic`.
        x: (symbolic.x_ptr[-1],) the supernodes' blocks of ``L``.
        d: (n,) the pivots ``D``, in the permuted order.
    """

    def __init__(self, symbolic: Symbolic, x: np.ndarray, d: np.ndarray) -> None:
        self.symbolic, self.x, self.d = symbolic, x, d
        # the solve kernels' leading arguments, gathered once: a Newton iteration solves
        # with one factor many times, each solve a few microseconds of compiled work
        self._arrays = (symbolic.sup_ptr, symbolic.row_ptr, symbolic.rows, symbolic.x_ptr,
                        x, d, symbolic.perm)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.symbolic.n, self.symbolic.n)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^{-1} rhs`` for ``rhs`` (n,) or (n, r) of any memory order.

        Like SuperLU's ``solve``: a new array of ``rhs``' shape, Fortran-ordered if
        2-D (a column per right-hand side), so that ``solve(b.T).T`` of a C-ordered
        ``b`` (r, n) is C-ordered again without a copy.
        """
        n = len(self.d)
        b = np.asarray(rhs, dtype=np.float64)
        if b.ndim not in (1, 2) or b.shape[0] != n:
            raise ValueError(f"right-hand side of shape {b.shape} for a {n} x {n} matrix")
        args = self._arrays
        if b.ndim == 1:
            out = np.empty(n)
            _solve_one(*args, b, out)
        elif b.shape[1] == 1:
            # one column, (n, 1): both C- and F-contiguous, which numba types as C, the
            # usual (n, r) transposes as F: a second specialisation of _solve_many to compile
            out = np.empty(b.shape, order="F")
            _solve_one(*args, np.ascontiguousarray(b[:, 0]), out[:, 0])
        else:
            out = np.empty(b.shape, order="F")
            _solve_many(*args, b, out, -(-b.shape[1] // LANES) * LANES)
        return out

    def solve_restricted(self, dofs: np.ndarray, values: np.ndarray) -> np.ndarray:
        """(k,) ``(A^{-1} b)[dofs]`` for the right-hand side ``b`` (n,) that is ``values``
        (k,) float64 at the distinct ``dofs`` (k,) int64 and zero elsewhere: :meth:`solve`
        on a problem whose other unknowns are decoupled (a Newton step on the free dofs of
        a tangent with identity rows at the constraints), in one compiled call."""
        if not (dofs.dtype == np.int64 and values.dtype == np.float64
                and dofs.shape == values.shape == (len(dofs),)):
            raise ValueError(f"dofs {dofs.dtype} {dofs.shape} and values {values.dtype} "
                             f"{values.shape}: int64 and float64 of one length")
        out = np.empty(len(dofs))
        if not _solve_restricted(*self._arrays, dofs, values, out):
            raise ValueError(f"dofs outside 0..{len(self.d) - 1}")
        return out


def factorize(symbolic: Symbolic, data: np.ndarray) -> Factor:
    """``L D L^T`` of the symmetric matrix with CSC ``data`` (nnz(A),) on ``symbolic``'s pattern.

    No pivoting (module docstring): :class:`RuntimeError` on a zero or non-finite
    pivot, e.g. of an exactly singular matrix, or of NaN in ``data``.
    """
    s = symbolic
    x, d = np.empty(s.x_ptr[-1]), np.empty(s.n)
    bad = _numeric(s.sup_ptr, s.row_ptr, s.rows, s.x_ptr, s.upd_ptr, s.upd_sup, s.upd_q1,
                   s.upd_q2, s.a_src, s.a_dst, np.asarray(data, dtype=np.float64), x, d)
    if bad >= 0:
        raise RuntimeError(f"Factor is exactly singular: zero or non-finite pivot at dof "
                           f"{s.perm[bad]} (L D L^T without pivoting)")
    return Factor(s, x, d)
