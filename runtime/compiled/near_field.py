"""The near field of sub-mesh contacts: the half-space's ``1/r`` kernel on hat loads, compiled.

:func:`hat_compliance` is ``w^T H w`` of each patch contact, where ``H[i, j]``
is the ``1/r`` potential at patch vertex ``i`` of the hat traction of vertex
``j`` (``phi_j / a_j``) on the contact's tangent plane
(:mod:`hailstorm.runtime.contact.near_field`, which states the model; the numpy
statement the tests hold this kernel to is ``tests/reference/near_field_ref.py``).
Per contact: project its weighted vertices and their triangles on the plane,
keep the triangles that face along the normal, and sum the closed-form
potential (:func:`edge_term`) over the triangles' edges.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["edge_term", "hat_compliance", "hat_pair_sum", "hat_potential", "layer_sum", "layer_term"]


@kernel
def _hats(y0, y1, p0, p1, e10, e11, e20, e21, det):  # pragma: no cover (compiled)
    """The three hat functions of the plane triangle (p, p + e1, p + e2) at (y0, y1)."""
    d0, d1 = y0 - p0, y1 - p1
    l1 = (d0 * e21 - d1 * e20) / det
    l2 = (e10 * d1 - e11 * d0) / det
    return 1.0 - l1 - l2, l1, l2


@kernel
def edge_term(x0, x1, P, out):  # pragma: no cover (compiled)
    """Add ``int_T phi_c / |x - y| dy`` (c = 0, 1, 2) of the plane triangle ``P`` (3, 2) at ``x`` to ``out`` (3,).

    ``T`` split into the triangles ``(x, p, q)`` over its edges (signed); along
    each ray from ``x`` the kernel cancels the Jacobian and the linear ``phi``
    integrates exactly, leaving ``(h L / 2) int_0^1 (phi(x) + phi(y(s))) / |y(s) - x| ds``
    over the edge: ``asinh`` and a square root. (Scalar arithmetic only: it runs
    for every vertex and triangle of every patch, and allocates nothing.)
    """
    P00, P01 = P[0, 0], P[0, 1]
    e10, e11 = P[1, 0] - P00, P[1, 1] - P01
    e20, e21 = P[2, 0] - P00, P[2, 1] - P01
    det = e10 * e21 - e11 * e20
    if det == 0.0:
        return
    px0, px1, px2 = _hats(x0, x1, P00, P01, e10, e11, e20, e21, det)
    for a in range(3):
        b = (a + 1) % 3
        p0, p1 = P[a, 0], P[a, 1]
        q0, q1 = P[b, 0], P[b, 1]
        pq0, pq1 = q0 - p0, q1 - p1
        L2 = pq0 * pq0 + pq1 * pq1
        L = math.sqrt(L2)
        r0x, r0y = p0 - x0, p1 - x1
        cross = r0x * pq1 - r0y * pq0
        h = abs(cross) / L
        if h <= 1e-12 * L:
            continue
        s0 = -(r0x * pq0 + r0y * pq1) / L2
        r0 = math.sqrt(r0x * r0x + r0y * r0y)
        r1 = math.sqrt((q0 - x0) ** 2 + (q1 - x1) ** 2)
        ash = math.asinh(L * (1.0 - s0) / h) - math.asinh(-L * s0 / h)
        a0, a1, a2 = _hats(p0, p1, P00, P01, e10, e11, e20, e21, det)
        b0, b1, b2 = _hats(q0, q1, P00, P01, e10, e11, e20, e21, det)
        sign = (1.0 if cross > 0 else -1.0) * (1.0 if det > 0 else -1.0)
        f = sign * h * L / 2.0
        out[0] += f * ((px0 + a0 + (b0 - a0) * s0) / L * ash + (b0 - a0) / L2 * (r1 - r0))
        out[1] += f * ((px1 + a1 + (b1 - a1) * s0) / L * ash + (b1 - a1) / L2 * (r1 - r0))
        out[2] += f * ((px2 + a2 + (b2 - a2) * s0) / L * ash + (b2 - a2) / L2 * (r1 - r0))


@kernel
def hat_potential(points, corners):  # pragma: no cover (compiled)
    """``I[i, t, c] = int_T phi_c(y) / |x_i - y| dy``: points (k, 2), plane triangles (m, 3, 2) -> (k, m, 3)."""
    out = np.zeros((points.shape[0], corners.shape[0], 3))
    for i in range(points.shape[0]):
        for t in range(corners.shape[0]):
            edge_term(points[i, 0], points[i, 1], corners[t], out[i, t])
    return out


@kernel
def hat_compliance(verts, weights, centres, normals, X, T, areas, fan_ptr, fan_tri):  # pragma: no cover (compiled)
    """``w^T H w`` of each contact [1/m] (times ``(1 - nu^2) / (pi E)``: the normal compliance), (s,).

    Parameters: padded (s, P) vertex lists and weights (weight 0: padding),
    contact points and unit normals (s, 3), the surface's vertices (n, 3),
    triangles (m, 3) and lumped areas (n,), and the vertex -> triangles map
    (CSR: ``fan_tri[fan_ptr[v]:fan_ptr[v + 1]]``).
    """
    s, P = verts.shape
    out = np.zeros(s)
    mark = np.full(T.shape[0], -1, np.int64)
    wpos = np.zeros(X.shape[0])  # the current patch's weight of each vertex (0: not in it)
    tri = np.empty(T.shape[0], np.int64)
    acc = np.zeros(3)
    for k in range(s):
        ln = math.sqrt(normals[k, 0] ** 2 + normals[k, 1] ** 2 + normals[k, 2] ** 2)
        n0, n1, n2 = normals[k, 0] / ln, normals[k, 1] / ln, normals[k, 2] / ln
        # the tangent plane's axes t1 = n x ref, t2 = n x t1 (ref: x, or y when n is near x)
        if abs(n0) < 0.9:
            a0, a1, a2 = 0.0, n2, -n1
        else:
            a0, a1, a2 = -n2, 0.0, n0
        la = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        a0, a1, a2 = a0 / la, a1 / la, a2 / la
        b0, b1, b2 = n1 * a2 - n2 * a1, n2 * a0 - n0 * a2, n0 * a1 - n1 * a0
        # the patch's vertices (weight > 0) and the facing triangles of their fans
        nt = 0
        for p in range(P):
            if weights[k, p] > 0.0:
                wpos[verts[k, p]] = weights[k, p]
        for p in range(P):
            if weights[k, p] <= 0.0:
                continue
            v = verts[k, p]
            for f in range(fan_ptr[v], fan_ptr[v + 1]):
                t = fan_tri[f]
                if mark[t] == k:
                    continue
                mark[t] = k
                i0, i1, i2 = T[t, 0], T[t, 1], T[t, 2]
                u0, u1, u2 = X[i1, 0] - X[i0, 0], X[i1, 1] - X[i0, 1], X[i1, 2] - X[i0, 2]
                w0, w1, w2 = X[i2, 0] - X[i0, 0], X[i2, 1] - X[i0, 1], X[i2, 2] - X[i0, 2]
                c0, c1, c2 = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
                if c0 * n0 + c1 * n1 + c2 * n2 >= 0.5 * math.sqrt(c0 * c0 + c1 * c1 + c2 * c2):
                    tri[nt] = t
                    nt += 1
        # their corners on the plane, once per patch
        x0c, x1c, x2c = centres[k, 0], centres[k, 1], centres[k, 2]
        Q = np.empty((nt, 3, 2))
        for it in range(nt):
            for c in range(3):
                j = T[tri[it], c]
                e0, e1, e2 = X[j, 0] - x0c, X[j, 1] - x1c, X[j, 2] - x2c
                Q[it, c, 0] = e0 * a0 + e1 * a1 + e2 * a2
                Q[it, c, 1] = e0 * b0 + e1 * b1 + e2 * b2
        total = 0.0
        for p in range(P):
            wi = weights[k, p]
            if wi <= 0.0:
                continue
            v = verts[k, p]
            e0, e1, e2 = X[v, 0] - x0c, X[v, 1] - x1c, X[v, 2] - x2c
            y0, y1 = e0 * a0 + e1 * a1 + e2 * a2, e0 * b0 + e1 * b1 + e2 * b2
            for it in range(nt):
                acc[0] = 0.0
                acc[1] = 0.0
                acc[2] = 0.0
                edge_term(y0, y1, Q[it], acc)
                t = tri[it]
                for c in range(3):  # column j = corner c of t, if j carries weight in this patch
                    j = T[t, c]
                    if wpos[j] > 0.0:
                        total += wi * wpos[j] * acc[c] / areas[j]
        out[k] = total
        for p in range(P):
            wpos[verts[k, p]] = 0.0
    return out


@kernel
def hat_pair_sum(verts, weights, k, X, hat_ptr, hat_pts, hat_w, inv_h, table, step):  # pragma: no cover (compiled)
    """``sum_ij w_i w_j int phi_j/a_j g(|x_i - y| inv_h)`` of patch ``k`` (:func:`layer_sum`'s body)."""
    P = verts.shape[1]
    n = table.shape[0]
    end = (n - 1) * step
    acc = 0.0
    for a in range(P):
        wa = weights[k, a]
        if wa <= 0.0:
            continue
        i = verts[k, a]
        for b in range(P):
            wb = weights[k, b]
            if wb <= 0.0:
                continue
            j = verts[k, b]
            part = 0.0
            for q in range(hat_ptr[j], hat_ptr[j + 1]):
                d0 = X[i, 0] - hat_pts[q, 0]
                d1 = X[i, 1] - hat_pts[q, 1]
                d2 = X[i, 2] - hat_pts[q, 2]
                rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) * inv_h
                if rho >= end:
                    g = table[n - 1] * end / rho
                else:
                    x = rho / step
                    m = min(int(x), n - 2)
                    f = x - m
                    g = table[m] * (1.0 - f) + table[m + 1] * f
                part += hat_w[q] * g
            acc += wa * wb * part
    return acc


@kernel
def layer_sum(verts, weights, X, hat_ptr, hat_pts, hat_w, inv_h, table, step):  # pragma: no cover (compiled)
    """``sum_ij w_i w_j int phi_j/a_j g(|x_i - y| / h)`` of each patch contact, (s,).

    The smooth part ``g`` of a kernel (:mod:`hailstorm.runtime.contact.layer_kernel`)
    on the hat loads of each patch, as D's columns answer them: at patch vertex
    ``i``, the hat traction of vertex ``j`` (quadrature points ``hat_pts`` and
    weights ``hat_w`` of vertex ``j``'s fan, CSR by ``hat_ptr``). ``g`` is tabulated
    on ``rho = k step`` (``table``), linear between, and decays as ``1/rho`` past its end.
    Padded (s, P) vertex lists and weights (weight 0: padding), ``inv_h`` (s,) the
    contacts' ``1/h``.
    """
    s = verts.shape[0]
    out = np.zeros(s)
    for k in range(s):
        out[k] = hat_pair_sum(verts, weights, k, X, hat_ptr, hat_pts, hat_w, inv_h[k], table, step)
    return out


@kernel
def layer_term(verts, weights, radius, thick, X, hat_ptr, hat_pts, hat_w, table, step, disc_table, disc_step,
               young):  # pragma: no cover (compiled)
    """The layer's term ``T(w)`` of each patch contact [m/N], (s,)
    (:func:`hailstorm.runtime.contact.layer_kernel.layer_correction`, which states it).

    ``h`` the weights' mean of ``thick`` (the thickness under each surface vertex); 0 where it
    is not finite and positive; NaN where ``radius / h`` lies past the disc's table
    (``disc_table`` on ``alpha = k disc_step``), for the caller to integrate.
    """
    s = verts.shape[0]
    out = np.zeros(s)
    nd = disc_table.shape[0]
    for k in range(s):
        wsum = 0.0
        hsum = 0.0
        for p in range(verts.shape[1]):
            w = weights[k, p]
            if w > 0.0:
                wsum += w
                hsum += w * thick[verts[k, p]]
        if not wsum > 0.0:
            continue
        h = hsum / wsum
        if not (h > 0.0 and h < np.inf):
            continue
        x = radius[k] / h / disc_step
        if x > nd - 1:
            out[k] = np.nan
            continue
        m = min(int(x), nd - 2)
        f = x - m
        phi = disc_table[m] * (1.0 - f) + disc_table[m + 1] * f
        S = hat_pair_sum(verts, weights, k, X, hat_ptr, hat_pts, hat_w, 1.0 / h, table, step)
        out[k] = (phi * wsum * wsum - S) / (young * h)
    return out
