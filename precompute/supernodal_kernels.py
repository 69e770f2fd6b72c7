"""Compiled core of the supernodal solve (:mod:`hailstorm.precompute.supernodal`).

The factor is ``P K Pᵀ = L Lᵀ`` split into supernodes: consecutive columns
``start[s]:start[s+1]`` of L stored with one row pattern below their diagonal
block (relaxed supernodes: the entries a column lacks are stored as zeros).
Supernode ``s`` stores

* ``dinv[doff[s]:]``: the inverse of its (nc, nc) lower-triangular diagonal
  block, column-major (the triangular solves become matrix products);
* ``below[boff[s]:]``: its (mb, nc) block under the diagonal, column-major;
* ``rows[roff[s]:roff[s + 1]]``: the mb rows of that block (positions in L).

A block of w right-hand sides ``X`` is stored dof by dof (``X[r * w + q]`` is
dof r of right-hand side q): a supernode's rows are then contiguous, and each
row one BLAS column of the (w, n) column-major view. Products of more than
:data:`GEMM_FROM` multiply-adds go to BLAS ``dgemm``; smaller ones run as loops.
"""

from __future__ import annotations

from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.lapack import gemm

#: multiply-adds (w * nc * max(nc, mb)) from which a supernode's products go to BLAS (2048 to
#: 65536 measured within the noise of each other on the default seat, P1 and P2, at 3 mm; loops
#: for every supernode are 1.3-1.5x slower)
GEMM_FROM = 8192


@kernel
def pattern_is_closed(indptr, indices, mark):  # pragma: no cover (compiled)
    """Whether the (sorted, lower-triangular) pattern of L is a Cholesky factor's: below its first
    off-diagonal row a (its parent), every column's rows are rows of column a. Exact cancellation
    can leave an entry out of a computed L; then the parent pointers no longer lead to every row a
    sparse solve reaches. ``mark`` is (n,) work space, all -1."""
    n = indptr.size - 1
    for j in range(n):
        b = indptr[j]
        e = indptr[j + 1]
        if e - b <= 2:
            continue
        a = indices[b + 1]
        for t in range(indptr[a], indptr[a + 1]):
            mark[indices[t]] = j
        for t in range(b + 2, e):
            if mark[indices[t]] != j:
                return False
    return True


@kernel
def gather_panels(indptr, indices, data, scale, start, rows, roff, boff, doff, below, diag,
                  where):  # pragma: no cover (compiled)
    """Scatter the CSC lower triangle ``indptr, indices, data`` of a unit-diagonal L into
    every supernode's ``below`` block and its (not yet inverted) diagonal block in
    ``diag``, scaling column j by ``scale[j]``; both start zeroed (a relaxed supernode's
    panel holds explicit zeros). ``where`` is (n,) work space, all -1.

    Raises
    ------
    ValueError
        An entry of L lies outside its supernode's pattern.
    """
    ns = start.size - 1
    for s in range(ns):
        c0 = start[s]
        nc = start[s + 1] - c0
        r0 = roff[s]
        mb = roff[s + 1] - r0
        for i in range(mb):
            where[rows[r0 + i]] = i
        for k in range(nc):
            j = c0 + k
            sc = scale[j]
            for t in range(indptr[j], indptr[j + 1]):
                r = indices[t]
                if r < c0 + nc:
                    diag[doff[s] + k * nc + r - c0] = data[t] * sc
                elif where[r] >= 0:
                    below[boff[s] + k * mb + where[r]] = data[t] * sc
                else:
                    raise ValueError("an entry of L lies outside its supernode's pattern")
        for i in range(mb):
            where[rows[r0 + i]] = -1


@kernel
def _copy(src, i, dst, j, n):  # pragma: no cover (compiled)
    for k in range(n):
        dst[j + k] = src[i + k]


@kernel
def _extent(s, start, roff, boff, doff):  # pragma: no cover (compiled)
    """Supernode s: first column, columns, first row below, rows below, panel and diagonal offsets."""
    return start[s], start[s + 1] - start[s], roff[s], roff[s + 1] - roff[s], boff[s], doff[s]


@kernel
def _forward(s, start, rows, roff, boff, doff, below, dinv, X, w, tmp, W):  # pragma: no cover (compiled)
    """Supernode s of the forward solve L y = b on the w right-hand sides in ``X``."""
    c0, nc, r0, mb, bo, do = _extent(s, start, roff, boff, doff)
    if w * nc * max(nc, mb) >= GEMM_FROM:
        gemm(False, True, w, nc, nc, 1.0, X[c0 * w:], w, dinv[do:], nc, 0.0, tmp, w)
        _copy(tmp, 0, X, c0 * w, nc * w)
        if mb > 0:
            gemm(False, True, w, mb, nc, 1.0, tmp, w, below[bo:], mb, 0.0, W, w)
            for i in range(mb):
                r = rows[r0 + i] * w
                for q in range(w):
                    X[r + q] -= W[i * w + q]
        return
    for k in range(nc):
        for q in range(w):
            acc = 0.0
            for l in range(k + 1):
                acc += dinv[do + l * nc + k] * X[(c0 + l) * w + q]
            tmp[k * w + q] = acc
    _copy(tmp, 0, X, c0 * w, nc * w)
    for i in range(mb):
        r = rows[r0 + i] * w
        for k in range(nc):
            a = below[bo + k * mb + i]
            t = k * w
            for q in range(w):
                X[r + q] -= a * tmp[t + q]


@kernel
def _backward(s, start, rows, roff, boff, doff, below, dinv, X, w, tmp, W):  # pragma: no cover (compiled)
    """Supernode s of the backward solve Lᵀ x = y on the w right-hand sides in ``X``."""
    c0, nc, r0, mb, bo, do = _extent(s, start, roff, boff, doff)
    _copy(X, c0 * w, tmp, 0, nc * w)
    if w * nc * max(nc, mb) >= GEMM_FROM:
        if mb > 0:
            for i in range(mb):
                r = rows[r0 + i] * w
                _copy(X, r, W, i * w, w)
            gemm(False, False, w, nc, mb, -1.0, W, w, below[bo:], mb, 1.0, tmp, w)
        gemm(False, False, w, nc, nc, 1.0, tmp, w, dinv[do:], nc, 0.0, X[c0 * w:], w)
        return
    for i in range(mb):
        r = rows[r0 + i] * w
        for k in range(nc):
            a = below[bo + k * mb + i]
            t = k * w
            for q in range(w):
                tmp[t + q] -= a * X[r + q]
    for k in range(nc):
        for q in range(w):
            acc = 0.0
            for l in range(k, nc):
                acc += dinv[do + k * nc + l] * tmp[l * w + q]
            X[(c0 + k) * w + q] = acc


@kernel
def solve_columns(start, parent, rows, roff, boff, doff, below, dinv, col_sn, back, ptr, idx, val, read, out,
                  X, tmp, W, mark):  # pragma: no cover (compiled)
    """``out[:, k] = (L Lᵀ)⁻¹ b_k`` read at the positions ``read`` (-1: zero), for the
    w = ``ptr.size - 1`` sparse right-hand sides ``b_k`` (entries ``val[ptr[k]:ptr[k + 1]]`` at
    the positions ``idx[ptr[k]:ptr[k + 1]]`` of L).

    Pruned: the forward solve visits only the supernodes of the loaded
    positions and their ancestors (the paths to the root), the backward solve
    only ``back`` (ascending: the supernodes holding a read position and their
    ancestors). ``X``, ``tmp``, ``W`` and ``mark`` are work space (n * w,
    w * max nc, w * max mb, number of supernodes). Returns the floating-point
    operations done per right-hand side.
    """
    w = ptr.size - 1
    ns = start.size - 1
    mark[:] = False
    for t in range(ptr[w]):  # the forward set: the loads' supernodes and their ancestors
        s = col_sn[idx[t]]
        while s >= 0 and not mark[s]:
            mark[s] = True
            s = parent[s]
    for i in range(back.size):
        s = back[i]
        for j in range(start[s] * w, start[s + 1] * w):
            X[j] = 0.0
    for s in range(ns):
        if mark[s]:
            for j in range(start[s] * w, start[s + 1] * w):
                X[j] = 0.0
    for k in range(w):
        for t in range(ptr[k], ptr[k + 1]):
            X[idx[t] * w + k] += val[t]
    flops = 0
    for s in range(ns):
        if mark[s]:
            _forward(s, start, rows, roff, boff, doff, below, dinv, X, w, tmp, W)
            flops += _flops(s, start, roff)
    for i in range(back.size - 1, -1, -1):
        _backward(back[i], start, rows, roff, boff, doff, below, dinv, X, w, tmp, W)
        flops += _flops(back[i], start, roff)
    for i in range(read.size):
        r = read[i]
        for k in range(w):
            out[i, k] = X[r * w + k] if r >= 0 else 0.0
    return flops


@kernel
def _flops(s, start, roff):  # pragma: no cover (compiled)
    """Floating-point operations of one right-hand side's sweep through supernode s
    (the triangular solve with its diagonal block and the product below it)."""
    nc = start[s + 1] - start[s]
    return nc * nc + 2 * nc * (roff[s + 1] - roff[s])
