"""The contact API's kernels: blocks of D, the contact compliance, one-call point-contact solves.

The one implementation of these blocks: used by the contact core
(:mod:`hailstorm.runtime.contact`: :func:`~hailstorm.runtime.contact.solve_contacts`,
:func:`~hailstorm.runtime.contact.capacitance`), whose capacitance the storm's contact
set is (:meth:`hailstorm.runtime.storm.contact_set.ContactSets.build`). The tests hold them
to dense algebra on D (fancy-indexed blocks, a dense B).

* :func:`vertex_block` -- ``D_VV`` (transposed), gathered row by row;
* :func:`weighted_rows` -- ``G^T M``: ``D_VV G`` or the full-surface response;
* :func:`constraint_rows` -- ``(D_VV G)^T`` straight from D (no ``D_VV``);
* :func:`contact_compliance` -- ``W = G^T D_VV G`` from it;
* :func:`columns_times` -- ``D[:, cols] g``;
* :func:`point_contacts` -- a fresh solve of bilateral point contacts in one call.

D (``Dt``, ``M``) is read in its storage type, float64 or float32 (numba compiles
one specialisation per type, cached like the rest): every product and sum is
formed in float64 (each float32 entry is widened as it is read, the outputs are
float64 arrays), so a float32 D costs only its own rounding, never a float64
copy of D.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["columns_times", "constraint_rows", "contact_compliance", "point_contacts", "symmetrise", "vertex_block",
           "weighted_rows"]


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


@kernel
def _cholesky_solve(A, rhs, cond_limit):  # pragma: no cover (compiled)
    """``A^-1 rhs`` by Cholesky (LAPACK) for a symmetric A, or None if A is not positive
    definite or its condition estimate ``(max L_ii / min L_ii)^2`` reaches ``cond_limit``
    (the test of :class:`hailstorm.runtime.contact.policy.SPDFactor`)."""
    m = A.shape[0]
    if m == 0:
        return np.zeros(0)
    for i in range(m):
        for j in range(m):
            if not math.isfinite(A[i, j]):
                return None
    try:
        L = np.linalg.cholesky(A)
    except Exception:
        return None
    dmin = np.inf
    dmax = 0.0
    for i in range(m):
        dmin = min(dmin, L[i, i])
        dmax = max(dmax, L[i, i])
    if not (dmin > 0.0 and (dmax / dmin) ** 2 < cond_limit):
        return None
    z = rhs.copy()
    for i in range(m):  # L z = rhs
        y = z[i]
        for p in range(i):
            y -= L[i, p] * z[p]
        z[i] = y / L[i, i]
    for i in range(m - 1, -1, -1):  # L^T x = z
        y = z[i]
        for p in range(i + 1, m):
            y -= L[p, i] * z[p]
        z[i] = y / L[i, i]
    return z


@kernel
def point_contacts(Dt, column_of, contactable, fixed, triangles, vertices, tri, bary, ubar, sticky, want_u,
                   bary_sum_tol, bary_neg_tol, cond_limit, rigid_weight):  # pragma: no cover (compiled)
    """One fresh solve of bilateral point contacts, whole: :func:`hailstorm.runtime.contact.solve_contacts`
    for the common case, its validation, blocks, factorisation policy and products fused in one call.

    Validates, finds V, forms ``W = G^T D_VV G`` straight from D's columns (no
    D_VV), factorises it, and returns the forces, the contact displacements
    ``B^T D_VV B f``, the vertex forces and, if ``want_u``, the full-surface
    displacement. Anything out of the ordinary returns a non-zero ``code`` and
    the caller takes the general path, which raises the proper error or handles
    the case: invalid input (1), a contact on a vertex without a column of D or a
    degenerate triangle (2), a rigid contact (3), ``W`` not safely positive
    definite (4: coincident contacts, the pseudo-inverse).

    Parameters
    ----------
    Dt : (c, 3n) ndarray
        ``D.T`` of a column-major D.
    column_of : (n,) int ndarray
    contactable, fixed : (n,) bool ndarrays
        A contact's vertices must be one or the other; its weight on clamped
        vertices carries no force.
    triangles : (T, 3) int ndarray
    vertices : (n, 3) ndarray
    tri : (s,) int ndarray
    bary, ubar : (s, 3) ndarrays
    sticky, want_u : bool
    bary_sum_tol, bary_neg_tol, cond_limit, rigid_weight : float
        The general path's tolerances (:mod:`hailstorm.runtime.contact.policy`).

    Returns
    -------
    code : int
    forces, contact_displacement : (s, 3) ndarrays
    V : (|V|,) int64 ndarray
    vertex_forces : (|V|, 3) ndarray
    u : (3n,) ndarray (empty unless ``want_u``)
    """
    s = tri.size
    nt = triangles.shape[0]
    n = column_of.size
    empty = np.zeros((0, 3))
    fail = (np.zeros((s, 3)), np.zeros((s, 3)), np.zeros(0, np.int64), empty, np.zeros(0))
    for k in range(s):
        if tri[k] < 0 or tri[k] >= nt:
            return (1,) + fail
        sm = 0.0
        for a in range(3):
            if not (math.isfinite(bary[k, a]) and math.isfinite(ubar[k, a])) or bary[k, a] < -bary_neg_tol:
                return (1,) + fail
            sm += bary[k, a]
        if not abs(sm - 1.0) <= bary_sum_tol:
            return (1,) + fail
    # V, the position of each contact's vertices in it, rigid contacts
    pos = np.full(n, -1, np.int64)
    lst = np.empty(3 * s, np.int64)
    nV = 0
    for k in range(s):
        free_w = 0.0
        for a in range(3):
            v = triangles[tri[k], a]
            if not (contactable[v] or fixed[v]):
                return (2,) + fail
            if not fixed[v]:
                free_w += abs(bary[k, a])
            if pos[v] < 0:
                pos[v] = 0
                lst[nV] = v
                nV += 1
        if free_w <= rigid_weight:
            return (3,) + fail
    V = np.sort(lst[:nV])
    for i in range(nV):
        pos[V[i]] = i
    # normals (frictionless), from the triangles as hailstorm.runtime.contact.normals.triangle_normals
    nrm = np.zeros((s, 3))
    if not sticky:
        for k in range(s):
            p0 = vertices[triangles[tri[k], 0]]
            p1 = vertices[triangles[tri[k], 1]]
            p2 = vertices[triangles[tri[k], 2]]
            a0 = p1[0] - p0[0]; a1 = p1[1] - p0[1]; a2 = p1[2] - p0[2]
            b0 = p2[0] - p0[0]; b1 = p2[1] - p0[1]; b2 = p2[2] - p0[2]
            c0 = a1 * b2 - a2 * b1; c1 = a2 * b0 - a0 * b2; c2 = a0 * b1 - a1 * b0
            ln = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            if not ln > 0.0:
                return (2,) + fail
            nrm[k, 0] = c0 / ln; nrm[k, 1] = c1 / ln; nrm[k, 2] = c2 / ln
    # X[3l+e, 3k+d] = sum_ab w_ka w_lb D[3 v_ka + d, 3 c(v_lb) + e]: W3 transposed, from whole
    # columns of D (the rows of Dt); symmetrised below
    m3 = 3 * s
    X = np.zeros((m3, m3))
    for l in range(s):
        for b in range(3):
            cb = column_of[triangles[tri[l], b]]
            wb = bary[l, b]
            if cb < 0 or wb == 0.0:
                continue
            for e in range(3):
                col = Dt[3 * cb + e]
                dst = X[3 * l + e]
                for k in range(s):
                    for a in range(3):
                        c = bary[k, a] * wb
                        r = 3 * triangles[tri[k], a]
                        dst[3 * k] += c * col[r]
                        dst[3 * k + 1] += c * col[r + 1]
                        dst[3 * k + 2] += c * col[r + 2]
    W3 = 0.5 * (X + X.T)
    if sticky:
        lam = _cholesky_solve(W3, ubar.ravel().copy(), cond_limit)
        if lam is None:
            return (4,) + fail
        f = lam.reshape(s, 3).copy()
    else:
        Wn = np.zeros((s, s))
        for k in range(s):
            for l in range(s):
                acc = 0.0
                for d in range(3):
                    for e in range(3):
                        acc += nrm[k, d] * W3[3 * k + d, 3 * l + e] * nrm[l, e]
                Wn[k, l] = acc
        c = np.empty(s)
        for k in range(s):
            c[k] = ubar[k, 0] * nrm[k, 0] + ubar[k, 1] * nrm[k, 1] + ubar[k, 2] * nrm[k, 2]
        lam = _cholesky_solve(0.5 * (Wn + Wn.T), c, cond_limit)
        if lam is None:
            return (4,) + fail
        f = np.empty((s, 3))
        for k in range(s):
            for d in range(3):
                f[k, d] = lam[k] * nrm[k, d]
    cd = (W3 @ f.ravel()).reshape(s, 3)
    g = np.zeros((nV, 3))
    for k in range(s):
        for a in range(3):
            i = pos[triangles[tri[k], a]]
            for d in range(3):
                g[i, d] += bary[k, a] * f[k, d]
    if want_u:
        cols = np.empty(3 * nV, np.int64)
        for i in range(nV):
            cb = column_of[V[i]]
            for d in range(3):
                cols[3 * i + d] = 3 * cb + d if cb >= 0 else -1
        u = columns_times(Dt, cols, g.ravel())
    else:
        u = np.zeros(0)
    return 0, f, cd, V, g, u
