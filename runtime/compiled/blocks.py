"""The contact API's reads of a dense D: its blocks and its products with columns, compiled.

The one implementation of these blocks: used by the contact core
(:mod:`hailstorm.runtime.contact`: :func:`~hailstorm.runtime.contact.solve_contacts`,
:func:`~hailstorm.runtime.contact.capacitance`), whose capacitance the storm's contact
set is (:meth:`hailstorm.runtime.storm.contact_set.ContactSets.build`). The tests hold them
to dense algebra on D (fancy-indexed blocks, a dense B).

* :func:`vertex_block` -- ``D_VV`` (transposed), gathered row by row;
* :func:`weighted_rows` -- ``G^T M``: ``D_VV G`` or the full-surface response;
* :func:`constraint_rows` -- ``(D_VV G)^T`` straight from D (no ``D_VV``);
* :func:`columns_times` -- ``D[:, cols] g``.

The contact compliance ``W`` formed from these rows is
:func:`hailstorm.runtime.compiled.wmatrix.contact_compliance`; the one-call solve of
bilateral point contacts, :func:`hailstorm.runtime.compiled.point_solve.point_contacts`.

D (``Dt``, ``M``) is read in its storage type, float64 or float32 (numba compiles
one specialisation per type, cached like the rest): every product and sum is
formed in float64 (each float32 entry is widened as it is read, the outputs are
float64 arrays), so a float32 D costs only its own rounding, never a float64
copy of D.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["columns_times", "constraint_rows", "vertex_block", "weighted_rows"]


@kernel
def vertex_block(V, Dt, column_of):  # pragma: no cover (compiled)
    """The compliance block ``D_VV`` of the vertices ``V``, transposed.

    Parameters
    ----------
    V : (|V|,) int ndarray
        Surface vertices.
    Dt : (c, 3n) ndarray
        ``D.T``; C-contiguous for a column-major D (each row one column of D,
        so every read below is within one contiguous column).
    column_of : (n,) int ndarray
        D's column block of each vertex (-1 clamped).

    Returns
    -------
    (3|V|, 3|V|) C-contiguous ndarray ``M`` with ``M[3j + e, 3i + d] =
    D[3 V[i] + d, 3 column_of[V[j]] + e]``: ``M.T`` is ``D_VV`` (F-ordered),
    with zero columns at clamped vertices. Written row by row: the scattered
    reads are the cost (about 2-3 ms at |V| = 265 on the reference machine,
    against 5 ms for numpy's gather).
    """
    nV = V.size
    out = np.zeros((3 * nV, 3 * nV))
    rows = 3 * V
    for j in range(nV):
        cb = column_of[V[j]]
        if cb < 0:
            continue
        s0 = Dt[3 * cb]
        s1 = Dt[3 * cb + 1]
        s2 = Dt[3 * cb + 2]
        d0 = out[3 * j]
        d1 = out[3 * j + 1]
        d2 = out[3 * j + 2]
        for i in range(nV):  # the three columns of a vertex at once: more reads in flight
            r = rows[i]
            d0[3 * i] = s0[r]
            d0[3 * i + 1] = s0[r + 1]
            d0[3 * i + 2] = s0[r + 2]
            d1[3 * i] = s1[r]
            d1[3 * i + 1] = s1[r + 1]
            d1[3 * i + 2] = s1[r + 2]
            d2[3 * i] = s2[r]
            d2[3 * i + 1] = s2[r + 1]
            d2[3 * i + 2] = s2[r + 2]
    return out


@kernel
def weighted_rows(M, blocks, loc, w, normals, sticky):  # pragma: no cover (compiled)
    """``Y = G^T M``: the rows of ``M`` combined with the weights of the contact constraints.

    ``G`` (``3|V| x m``) is the constraint matrix of :mod:`hailstorm.runtime.contact` (``B``
    for sticky contacts, ``B N`` for frictionless ones); its row ``3i + d`` is
    read from row ``3 blocks[i] + d`` of ``M`` (skipped where ``blocks[i] < 0``).

    * ``M = vertex_block(...)`` (``D_VV^T``) and ``blocks = arange(|V|)``:
      ``Y = G^T D_VV^T = (D_VV G)^T``, the displacement of V per unit multiplier;
    * ``M = D.T`` and ``blocks = column_of[V]``: ``Y = (D[:, V] G)^T``, the
      full-surface response per unit multiplier.

    Every row of ``Y`` is a sum of whole contiguous rows of ``M`` (the work is
    ``m x P x 3`` vector updates, not a dense product with ``G``).

    Parameters
    ----------
    M : (r, q) ndarray, C-contiguous
    blocks : (|V|,) int ndarray
    loc, w : (s, P) int / float ndarrays
        Position in V and weight of each contact's vertices (weight 0: padding).
    normals : (s, 3) ndarray
        Unit normals (read only when not ``sticky``).
    sticky : bool
        ``m = 3s`` (G = B) or ``m = s`` (G = B N).

    Returns
    -------
    (m, q) ndarray
    """
    s, P = loc.shape
    q = M.shape[1]
    m = 3 * s if sticky else s
    Y = np.zeros((m, q))
    for k in range(s):
        for p in range(P):
            wp = w[k, p]
            b = blocks[loc[k, p]]
            if wp == 0.0 or b < 0:
                continue
            for d in range(3):
                if sticky:
                    dst = Y[3 * k + d]
                    c = wp
                else:
                    dst = Y[k]
                    c = wp * normals[k, d]
                src = M[3 * b + d]
                for j in range(q):
                    dst[j] += c * src[j]
    return Y


#: How many vertices of V ahead :func:`constraint_rows` asks for the rows it will read
#: (measured on the default seat at s = 100: none 1.01 ms, 4 ahead 0.88, 8 ahead 0.72, 16 0.82).
PREFETCH_AHEAD = 8

if numba.config.DISABLE_JIT:  # the kernels run as Python: nothing to ask the memory for

    def prefetch(arr, i):  # pragma: no cover
        """No-op (``NUMBA_DISABLE_JIT=1``)."""

else:

    @intrinsic
    def prefetch(typingctx, arr, i):  # pragma: no cover (compiled)
        """Hint the CPU to fetch ``arr[i]`` into the caches (LLVM's ``prefetch``: read, keep,
        data); no effect on results, no fault on any address. The scattered reads of
        :func:`constraint_rows` wait on memory one after another; issuing them a few
        vertices ahead keeps more of them in flight."""
        sig = types.void(arr, i)

        def codegen(context, builder, signature, args):
            aryty = signature.args[0]
            ary = context.make_array(aryty)(context, builder, args[0])
            ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
            i8p = ir.IntType(8).as_pointer()
            i32 = ir.IntType(32)
            fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
            fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
            builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3),
                              ir.Constant(i32, 1)])
            return context.get_dummy_value()

        return sig, codegen


@kernel
def _add_sticky(d0, d1, d2, rows, wa, a0, a1, a2):  # pragma: no cover (compiled)
    """``d_e += wa a_e`` at the rows of V: one vertex's three columns ``a0``, ``a1``, ``a2`` (three
    rows of ``D.T``), the rows a few vertices ahead asked for first (see :data:`PREFETCH_AHEAD`)."""
    n = rows.size
    for i in range(n):
        if i + PREFETCH_AHEAD < n:
            ahead = rows[i + PREFETCH_AHEAD]
            prefetch(a0, ahead)
            prefetch(a1, ahead)
            prefetch(a2, ahead)
        r = rows[i]
        j = 3 * i
        for o in range(3):
            d0[j + o] += wa * a0[r + o]
            d1[j + o] += wa * a1[r + o]
            d2[j + o] += wa * a2[r + o]


@kernel
def _add_normal(dst, rows, c0, c1, c2, a0, a1, a2):  # pragma: no cover (compiled)
    """``dst += c0 a0 + c1 a1 + c2 a2`` at the rows of V, each term added in that order
    (frictionless: the weight times the normal's components), prefetching as :func:`_add_sticky`."""
    n = rows.size
    for i in range(n):
        if i + PREFETCH_AHEAD < n:
            ahead = rows[i + PREFETCH_AHEAD]
            prefetch(a0, ahead)
            prefetch(a1, ahead)
            prefetch(a2, ahead)
        r = rows[i]
        for o in range(3):
            j = 3 * i + o
            x = dst[j]
            x += c0 * a0[r + o]
            x += c1 * a1[r + o]
            x += c2 * a2[r + o]
            dst[j] = x


@kernel
def constraint_rows(Dt, column_of, V, loc, w, normals, sticky):  # pragma: no cover (compiled)
    """``Y = (D_VV G)^T`` straight from the columns of D: :func:`weighted_rows` of
    :func:`vertex_block`, fused (the same sums in the same order, bit for bit), without
    forming ``D_VV``.

    Row ``(k, d)`` of ``Y`` is the weighted sum over contact ``k``'s vertices of column
    ``(v, d)`` of D read at the rows of V: ``3 s P`` scattered row reads of ``|V|``
    chunks of three doubles, instead of writing and re-reading the ``(3|V|)^2`` block.
    The reads are latency-bound: one vertex (three columns of D) per pass over the rows
    of V, the rows a few vertices ahead asked for first (:data:`PREFETCH_AHEAD`), each
    entry summed vertex by vertex in the order of ``loc``.

    Parameters
    ----------
    Dt : (3c, 3n) C-contiguous ndarray
        ``D.T`` (each row a column of D).
    column_of : (n,) int ndarray
    V : (|V|,) int ndarray
        The contacts' vertices (``loc`` indexes into it).
    loc, w, normals, sticky
        As in :func:`weighted_rows`.

    Returns
    -------
    (m, 3|V|) ndarray
    """
    s, P = loc.shape
    nV = V.size
    m = 3 * s if sticky else s
    Y = np.zeros((m, 3 * nV))
    rows = 3 * V
    for k in range(s):
        for p in range(P):
            wa = w[k, p]
            cb = column_of[V[loc[k, p]]]
            if wa == 0.0 or cb < 0:
                continue
            ca = 3 * cb
            if sticky:
                _add_sticky(Y[3 * k], Y[3 * k + 1], Y[3 * k + 2], rows, wa, Dt[ca], Dt[ca + 1], Dt[ca + 2])
            else:
                _add_normal(Y[k], rows, wa * normals[k, 0], wa * normals[k, 1], wa * normals[k, 2], Dt[ca],
                            Dt[ca + 1], Dt[ca + 2])
    return Y


@kernel
def columns_times(Dt, cols, g):  # pragma: no cover (compiled)
    """``D[:, cols] @ g`` for a column-major D (``Dt = D.T`` C-contiguous); ``cols < 0`` skipped.

    Eight columns per pass over the output (summed as two groups of four, the
    grouping of the sums unchanged since four per pass): each column of D is read
    once, in order, and the output is read and written an eighth as often as by
    one column at a time (memory-bound: 0.75 ms for 795 columns of 4428 rows on
    the default seat, 0.86 ms four per pass, 1.2 ms for a single-threaded BLAS
    product over a contiguous block of D of the same size).
    """
    n = Dt.shape[1]
    u = np.zeros(n)
    live = np.empty(cols.size, np.int64)
    gl = np.empty(cols.size)
    nl = 0
    for j in range(cols.size):
        if cols[j] >= 0:
            live[nl] = cols[j]
            gl[nl] = g[j]
            nl += 1
    j = 0
    while j + 8 <= nl:  # two groups of four per pass: u is read and written half as often
        c0 = Dt[live[j]]
        c1 = Dt[live[j + 1]]
        c2 = Dt[live[j + 2]]
        c3 = Dt[live[j + 3]]
        c4 = Dt[live[j + 4]]
        c5 = Dt[live[j + 5]]
        c6 = Dt[live[j + 6]]
        c7 = Dt[live[j + 7]]
        g0 = gl[j]
        g1 = gl[j + 1]
        g2 = gl[j + 2]
        g3 = gl[j + 3]
        g4 = gl[j + 4]
        g5 = gl[j + 5]
        g6 = gl[j + 6]
        g7 = gl[j + 7]
        for i in range(n):  # the sums of two passes of four, in the same order
            u[i] = ((u[i] + (g0 * c0[i] + g1 * c1[i] + g2 * c2[i] + g3 * c3[i]))
                    + (g4 * c4[i] + g5 * c5[i] + g6 * c6[i] + g7 * c7[i]))
        j += 8
    while j + 4 <= nl:
        c0 = Dt[live[j]]
        c1 = Dt[live[j + 1]]
        c2 = Dt[live[j + 2]]
        c3 = Dt[live[j + 3]]
        g0 = gl[j]
        g1 = gl[j + 1]
        g2 = gl[j + 2]
        g3 = gl[j + 3]
        for i in range(n):
            u[i] += g0 * c0[i] + g1 * c1[i] + g2 * c2[i] + g3 * c3[i]
        j += 4
    while j < nl:
        c0 = Dt[live[j]]
        g0 = gl[j]
        for i in range(n):
            u[i] += g0 * c0[i]
        j += 1
    return u
