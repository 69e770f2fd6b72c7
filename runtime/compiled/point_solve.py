"""The one-call solve of bilateral point contacts, compiled: :func:`point_contacts`.

The contact API's fast path (:func:`hailstorm.runtime.contact.solve_contacts` for the common
case): validation, the contacts' vertices, ``W = G^T D_VV G`` straight from D's columns, its
Cholesky factorisation under the general path's condition test and the products, fused in one
call. Anything out of the ordinary hands the solve back to the general path with a code. The
tests hold it to the general path (random sets, both modes, every code).
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.blocks import columns_times
from hailstorm.runtime.compiled.jit import kernel

__all__ = ["point_contacts"]


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
def _valid_points(nt, tri, bary, ubar, bary_sum_tol, bary_neg_tol):  # pragma: no cover (compiled)
    """Whether every contact is on a triangle of ``0..nt-1`` with finite ``bary`` and ``ubar`` and
    barycentric coordinates within the general path's tolerances (:func:`point_contacts`'s code 1)."""
    for k in range(tri.size):
        if tri[k] < 0 or tri[k] >= nt:
            return False
        sm = 0.0
        for a in range(3):
            if not (math.isfinite(bary[k, a]) and math.isfinite(ubar[k, a])) or bary[k, a] < -bary_neg_tol:
                return False
            sm += bary[k, a]
        if not abs(sm - 1.0) <= bary_sum_tol:
            return False
    return True


@kernel
def _facet_normals(vertices, triangles, tri, nrm):  # pragma: no cover (compiled)
    """The contacted triangles' unit normals into ``nrm`` (s, 3), as
    :func:`hailstorm.runtime.contact.normals.triangle_normals`; False at a degenerate triangle
    (:func:`point_contacts`'s code 2)."""
    for k in range(tri.size):
        p0 = vertices[triangles[tri[k], 0]]
        p1 = vertices[triangles[tri[k], 1]]
        p2 = vertices[triangles[tri[k], 2]]
        a0 = p1[0] - p0[0]; a1 = p1[1] - p0[1]; a2 = p1[2] - p0[2]
        b0 = p2[0] - p0[0]; b1 = p2[1] - p0[1]; b2 = p2[2] - p0[2]
        c0 = a1 * b2 - a2 * b1; c1 = a2 * b0 - a0 * b2; c2 = a0 * b1 - a1 * b0
        ln = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if not ln > 0.0:
            return False
        nrm[k, 0] = c0 / ln; nrm[k, 1] = c1 / ln; nrm[k, 2] = c2 / ln
    return True


@kernel
def _point_compliance(Dt, column_of, triangles, tri, bary):  # pragma: no cover (compiled)
    """The (3s, 3s) contact compliance ``W3 = B^T D_VV B`` of point contacts, symmetrised, from
    whole columns of D (the rows of ``Dt``), without ``D_VV``."""
    s = tri.size
    # X[3l+e, 3k+d] = sum_ab w_ka w_lb D[3 v_ka + d, 3 c(v_lb) + e]: W3 transposed
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
    return 0.5 * (X + X.T)


@kernel
def _point_forces(W3, nrm, ubar, sticky, cond_limit, f):  # pragma: no cover (compiled)
    """The contact forces into ``f`` (s, 3) that realise ``ubar``: ``W3^-1 ubar`` (sticky) or the
    normal forces of ``W_n = N^T W3 N`` (frictionless, unit normals ``nrm``), by
    :func:`_cholesky_solve`; False if the factorisation fails its test (:func:`point_contacts`'s
    code 4)."""
    s = f.shape[0]
    if sticky:
        lam = _cholesky_solve(W3, ubar.ravel().copy(), cond_limit)
        if lam is None:
            return False
        f[:, :] = lam.reshape(s, 3)
        return True
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
        return False
    for k in range(s):
        for d in range(3):
            f[k, d] = lam[k] * nrm[k, d]
    return True


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
    if not _valid_points(nt, tri, bary, ubar, bary_sum_tol, bary_neg_tol):
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
    nrm = np.zeros((s, 3))
    if not sticky and not _facet_normals(vertices, triangles, tri, nrm):
        return (2,) + fail
    W3 = _point_compliance(Dt, column_of, triangles, tri, bary)
    f = np.empty((s, 3))
    if not _point_forces(W3, nrm, ubar, sticky, cond_limit, f):
        return (4,) + fail
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
