"""Kernels of the stored H-matrix (:class:`hailstorm.runtime.bundle.hmatrix.HMatrix`): its product
with a vector and its entries, block by block over its block table.

The plain numpy forms are :meth:`~hailstorm.runtime.bundle.hmatrix.HMatrix.matvec_ref` and
:meth:`~hailstorm.runtime.bundle.hmatrix.HMatrix.entries_ref`, which the tests hold these to.
Both work in the tree order of the rows and columns (positions), on the block table
``r0, r1, c0, c1, rank, offset`` and the data (a dense block column-major; a far block's
``U`` (``m x rank``) then ``V`` (``n x rank``), column-major).

* :func:`hmatrix_matvec` -- ``y = H x`` (tree order);
* :func:`hmatrix_entries` -- ``H[rows, cols]`` for sorted row and column positions;
* :func:`d_entry` -- one entry ``D[r, c]`` of a dense D or of an H-matrix's kernel arrays
  (:attr:`~hailstorm.runtime.bundle.hmatrix.HMatrix.kernel_arrays`): what the storm's kernels
  read D through, compiled once per kind of D;
* :func:`hmatrix_entry` -- that entry of an H-matrix.
"""

from __future__ import annotations

import numpy as np
from numba.core import types
from numba.extending import overload

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["d_entry", "hmatrix_entries", "hmatrix_entry", "hmatrix_matvec"]


@kernel
def hmatrix_entry(rpos, rcell, cpos, ccell, grid, blocks, data, r, c):  # pragma: no cover (compiled)
    """``H[r, c]`` (original row and column): the block of the grid cell of ``(r, c)``, then its
    entry (a far block's: a row of ``U`` times a row of ``V``)."""
    b = grid[rcell[r], ccell[c]]
    r0, r1, c0, c1, k, off = blocks[b, 0], blocks[b, 1], blocks[b, 2], blocks[b, 3], blocks[b, 4], blocks[b, 5]
    rl, cl, m = rpos[r] - r0, cpos[c] - c0, r1 - r0
    if k < 0:
        return data[off + cl * m + rl]
    n = c1 - c0
    v = 0.0
    vb = off + m * k + cl
    for q in range(k):
        v += data[off + q * m + rl] * data[vb + q * n]
    return v


def d_entry(D, r, c):
    """``D[r, c]``: ``D`` a dense (column-major) array, or the 7-tuple of an H-matrix's
    :attr:`~hailstorm.runtime.bundle.hmatrix.HMatrix.kernel_arrays` (:func:`hmatrix_entry`).
    The compiled kernels get one specialisation per kind (an overload); this is its plain form."""
    if isinstance(D, tuple):
        return hmatrix_entry(D[0], D[1], D[2], D[3], D[4], D[5], D[6], r, c)
    return D[r, c]


@overload(d_entry, jit_options={"cache": True})
def _d_entry_compiled(D, r, c):  # pragma: no cover (compile-time dispatch)
    if isinstance(D, types.Array):
        return lambda D, r, c: D[r, c]
    if isinstance(D, types.BaseTuple):
        return lambda D, r, c: hmatrix_entry(D[0], D[1], D[2], D[3], D[4], D[5], D[6], r, c)
    return None


@kernel
def hmatrix_matvec(blocks, data, xp, n_rows):  # pragma: no cover (compiled)
    """``yp = H xp`` in tree order: (n_rows,) float64; a far block as ``U (V^T x)``."""
    yp = np.zeros(n_rows)
    for b in range(blocks.shape[0]):
        r0, r1, c0, c1, k, off = blocks[b, 0], blocks[b, 1], blocks[b, 2], blocks[b, 3], blocks[b, 4], blocks[b, 5]
        m, n = r1 - r0, c1 - c0
        if k < 0:
            for j in range(n):
                xj = xp[c0 + j]
                if xj != 0.0:
                    base = off + j * m
                    for i in range(m):
                        yp[r0 + i] += data[base + i] * xj
        else:
            vb = off + m * k
            for q in range(k):
                s = 0.0
                for j in range(n):
                    s += data[vb + q * n + j] * xp[c0 + j]
                if s != 0.0:
                    ub = off + q * m
                    for i in range(m):
                        yp[r0 + i] += data[ub + i] * s
    return yp


@kernel
def hmatrix_entries(blocks, data, rs, ro, cs, co, out):  # pragma: no cover (compiled)
    """``out[ro[i], co[j]] = H[rs[i], cs[j]]`` for sorted row and column positions ``rs``, ``cs``
    (``ro``, ``co`` where each goes in ``out``): each block reads the rows and columns within it
    (found by bisection); a far block's entry is the dot product of a row of ``U`` and one of ``V``."""
    for b in range(blocks.shape[0]):
        r0, r1, c0, c1, k, off = blocks[b, 0], blocks[b, 1], blocks[b, 2], blocks[b, 3], blocks[b, 4], blocks[b, 5]
        jlo, jhi = np.searchsorted(cs, c0), np.searchsorted(cs, c1)
        if jlo == jhi:
            continue
        ilo, ihi = np.searchsorted(rs, r0), np.searchsorted(rs, r1)
        if ilo == ihi:
            continue
        m, n = r1 - r0, c1 - c0
        for jj in range(jlo, jhi):
            cl = cs[jj] - c0
            oc = co[jj]
            for ii in range(ilo, ihi):
                rl = rs[ii] - r0
                if k < 0:
                    out[ro[ii], oc] = data[off + cl * m + rl]
                else:
                    v = 0.0
                    vb = off + m * k + cl
                    for q in range(k):
                        v += data[off + q * m + rl] * data[vb + q * n]
                    out[ro[ii], oc] = v
