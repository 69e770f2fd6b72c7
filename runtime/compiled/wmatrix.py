"""The contact compliance ``W = G^T D_VV G`` from the rows ``(D_VV G)^T``, compiled.

Part of the contact API's kernels: :func:`contact_compliance` takes the rows that
:func:`hailstorm.runtime.compiled.blocks.weighted_rows` or
:func:`hailstorm.runtime.compiled.blocks.constraint_rows` read from D and forms ``W``
(symmetrised by :func:`symmetrise`), row by row and four rows at a time. Used by the contact
core (:mod:`hailstorm.runtime.contact.contact_capacitance`) and, through it, by the storm's
contact set; the tests hold it to the dense product ``G^T D_VV G``.

``Y`` is read in its storage type (float64, or float32 from a float32 D); every sum is formed
in float64 and ``W`` is a float64 array.
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["contact_compliance", "symmetrise"]


@kernel
def contact_compliance(Y, loc, w, normals, sticky):  # pragma: no cover (compiled)
    """The contact compliance ``W = G^T D_VV G`` from ``Y = (D_VV G)^T``, symmetrised.

    ``Y`` is :func:`weighted_rows` of :func:`vertex_block`. ``Y G`` is
    ``G^T D_VV^T G = W^T``; the symmetrised result is W.
    Arguments as in :func:`weighted_rows`; returns the (m, m) W.

    Row by row: row ``k`` of ``Y G`` reads only row ``k`` of ``Y`` (in L1) and writes
    only row ``k`` of the result (a column-by-column sweep strides through both
    arrays: 2.4x slower at s = 100). Each entry is summed in a register over its
    contact's weighted vertices, in the order of ``loc``, from zero (the sums, bit for
    bit, of accumulating into the zeroed row, without its stores and re-loads), four
    rows at a time (each vertex's position and weight loaded once for the four: 0.26 ->
    0.18 ms at s = 100 point contacts, 0.76 -> 0.46 ms patches, on the default seat).
    """
    s, P = loc.shape
    m = Y.shape[0]
    # the weighted vertices of G, grouped by contact in (contact, vertex) order:
    # row offset in Y and weight; contact l owns entries start[l]:start[l + 1]
    nz = 0
    start = np.empty(s + 1, np.int64)
    gr = np.empty(s * P, np.int64)
    gw = np.empty(s * P)
    for l in range(s):
        start[l] = nz
        for p in range(P):
            if w[l, p] != 0.0:
                gr[nz] = 3 * loc[l, p]
                gw[nz] = w[l, p]
                nz += 1
    start[s] = nz
    W = np.empty((m, m))
    k = 0
    while k + 4 <= m:
        if sticky:
            _sticky_rows4(Y[k], Y[k + 1], Y[k + 2], Y[k + 3], W[k], W[k + 1], W[k + 2], W[k + 3], start, gr, gw)
        else:
            _normal_rows4(Y[k], Y[k + 1], Y[k + 2], Y[k + 3], W[k], W[k + 1], W[k + 2], W[k + 3], start, gr, gw,
                          normals)
        k += 4
    while k < m:
        if sticky:
            _sticky_row(Y[k], W[k], start, gr, gw)
        else:
            _normal_row(Y[k], W[k], start, gr, gw, normals)
        k += 1
    symmetrise(W)
    return W


@kernel
def _sticky_row(y, dst, start, gr, gw):  # pragma: no cover (compiled)
    """One row of ``Y G`` for sticky contacts (see :func:`contact_compliance`): ``dst`` from ``y``."""
    for l in range(start.size - 1):
        x0 = 0.0
        x1 = 0.0
        x2 = 0.0
        for q in range(start[l], start[l + 1]):
            r = gr[q]
            wp = gw[q]
            x0 += wp * y[r]
            x1 += wp * y[r + 1]
            x2 += wp * y[r + 2]
        dst[3 * l] = x0
        dst[3 * l + 1] = x1
        dst[3 * l + 2] = x2


@kernel
def _sticky_rows4(ya, yb, yc, yd, da, db, dc, dd, start, gr, gw):  # pragma: no cover (compiled)
    """Four rows of ``Y G`` at once: :func:`_sticky_row` of each, the same sums."""
    for l in range(start.size - 1):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        b0 = 0.0
        b1 = 0.0
        b2 = 0.0
        c0 = 0.0
        c1 = 0.0
        c2 = 0.0
        e0 = 0.0
        e1 = 0.0
        e2 = 0.0
        for q in range(start[l], start[l + 1]):
            r = gr[q]
            wp = gw[q]
            a0 += wp * ya[r]
            a1 += wp * ya[r + 1]
            a2 += wp * ya[r + 2]
            b0 += wp * yb[r]
            b1 += wp * yb[r + 1]
            b2 += wp * yb[r + 2]
            c0 += wp * yc[r]
            c1 += wp * yc[r + 1]
            c2 += wp * yc[r + 2]
            e0 += wp * yd[r]
            e1 += wp * yd[r + 1]
            e2 += wp * yd[r + 2]
        da[3 * l] = a0
        da[3 * l + 1] = a1
        da[3 * l + 2] = a2
        db[3 * l] = b0
        db[3 * l + 1] = b1
        db[3 * l + 2] = b2
        dc[3 * l] = c0
        dc[3 * l + 1] = c1
        dc[3 * l + 2] = c2
        dd[3 * l] = e0
        dd[3 * l + 1] = e1
        dd[3 * l + 2] = e2


@kernel
def _normal_row(y, dst, start, gr, gw, normals):  # pragma: no cover (compiled)
    """One row of ``Y G`` for frictionless contacts (``G = B N``): ``dst`` from ``y``."""
    for l in range(start.size - 1):
        n0 = normals[l, 0]
        n1 = normals[l, 1]
        n2 = normals[l, 2]
        x = 0.0
        for q in range(start[l], start[l + 1]):
            r = gr[q]
            wp = gw[q]
            x += (wp * n0) * y[r]
            x += (wp * n1) * y[r + 1]
            x += (wp * n2) * y[r + 2]
        dst[l] = x


@kernel
def _normal_rows4(ya, yb, yc, yd, da, db, dc, dd, start, gr, gw, normals):  # pragma: no cover (compiled)
    """Four rows of ``Y G`` at once: :func:`_normal_row` of each, the same sums."""
    for l in range(start.size - 1):
        n0 = normals[l, 0]
        n1 = normals[l, 1]
        n2 = normals[l, 2]
        xa = 0.0
        xb = 0.0
        xc = 0.0
        xd = 0.0
        for q in range(start[l], start[l + 1]):
            r = gr[q]
            wp = gw[q]
            c0 = wp * n0
            c1 = wp * n1
            c2 = wp * n2
            xa += c0 * ya[r]
            xa += c1 * ya[r + 1]
            xa += c2 * ya[r + 2]
            xb += c0 * yb[r]
            xb += c1 * yb[r + 1]
            xb += c2 * yb[r + 2]
            xc += c0 * yc[r]
            xc += c1 * yc[r + 1]
            xc += c2 * yc[r + 2]
            xd += c0 * yd[r]
            xd += c1 * yd[r + 1]
            xd += c2 * yd[r + 2]
        da[l] = xa
        db[l] = xb
        dc[l] = xc
        dd[l] = xd


@kernel
def symmetrise(W):  # pragma: no cover (compiled)
    """``W <- (W + W^T) / 2`` in place, as ``0.5 * (W[a, b] + W[b, a])`` for ``a < b``."""
    m = W.shape[0]
    for a in range(m):
        for b in range(a + 1, m):
            x = 0.5 * (W[a, b] + W[b, a])
            W[a, b] = x
            W[b, a] = x
