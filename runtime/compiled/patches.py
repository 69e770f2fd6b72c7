"""Patch contacts: the weights of a Hertz pressure disc, a patch's normal compliance and
the storm's patch sizing.

The contact API's :func:`hailstorm.runtime.contact.weights.patch_weights` is the weights' numpy
statement; the sizing rule's is ``tests/reference/patches_ref.py``.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.hblocks import d_entry
from hailstorm.runtime.compiled.flight import drag_dot
from hailstorm.runtime.compiled.grid import cell_range, sorted_ints
from hailstorm.runtime.compiled.sphere import impact_radius_of

#: A resting contact (oscillation amplitude below ``rest_speed``) is re-sized to the patch
#: radius of its force once it is this far off (relative): the static dent follows the weight,
#: not the impact that brought the stone (the ``patch_tolerance`` band alone left resting
#: patches up to 20 % too large, hence too stiff).
REST_TOLERANCE = 0.01

__all__ = ["disc_patch", "patch_compliance", "patch_one", "patch_radii"]


@kernel
def disc_patch(x, n, a, h, qx, qy, qw, facing, drop, pidx):  # pragma: no cover (compiled)
    """Compiled ``hailstorm.runtime.contact.weights._one_patch`` for one disc: (vertices, weights) of one patch, both
    empty if the disc hits no usable triangle. ``pidx``: :func:`hailstorm.runtime.contact.weights._patch_index_arrays`."""
    glo, gh, gdims, gstart, gitems, cent, radii, tnorm, p0, e1, e2, reach, tris, T, nv = pidx
    tol = 1e-12 * max(a, 1.0)
    lim = a + reach + tol
    # candidate triangles: centroid within a + reach (grid), then within a + own radius, facing n
    nc = 0
    cand = np.empty(cent.shape[0], np.int64)
    ilo, ihi = cell_range(x, lim, glo, gh, gdims)
    for ci in range(ilo[0], ihi[0] + 1):
        for cj in range(ilo[1], ihi[1] + 1):
            for ck in range(ilo[2], ihi[2] + 1):
                c = (ci * gdims[1] + cj) * gdims[2] + ck
                for q in range(gstart[c], gstart[c + 1]):
                    s = gitems[q]
                    dx = cent[s, 0] - x[0]; dy = cent[s, 1] - x[1]; dz = cent[s, 2] - x[2]
                    dd = math.sqrt(dx * dx + dy * dy + dz * dz)
                    if dd <= lim and dd <= a + radii[s] + tol and (
                            tnorm[s, 0] * n[0] + tnorm[s, 1] * n[1] + tnorm[s, 2] * n[2]) > facing:
                        cand[nc] = s
                        nc += 1
    if nc == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    cand = sorted_ints(cand[:nc])
    # inverse of [e1 e2 -n] per candidate (projection along n onto its plane)
    Minv = np.empty((nc, 3, 3))
    for m in range(nc):
        s = cand[m]
        A = np.empty((3, 3))
        for r in range(3):
            A[r, 0] = e1[s, r]; A[r, 1] = e2[s, r]; A[r, 2] = -n[r]
        det = (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
               - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
               + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))
        for r in range(3):
            for c in range(3):
                r1 = (c + 1) % 3; r2 = (c + 2) % 3
                c1 = (r + 1) % 3; c2 = (r + 2) % 3
                Minv[m, r, c] = (A[r1, c1] * A[r2, c2] - A[r1, c2] * A[r2, c1]) / det
    # tangents of the disc, as hailstorm.runtime.contact.weights._tangents
    if abs(n[0]) < 0.9:
        ax, ay, az = 1.0, 0.0, 0.0
    else:
        ax, ay, az = 0.0, 1.0, 0.0
    t1x = n[1] * az - n[2] * ay; t1y = n[2] * ax - n[0] * az; t1z = n[0] * ay - n[1] * ax
    ln = math.sqrt(t1x * t1x + t1y * t1y + t1z * t1z)
    t1x /= ln; t1y /= ln; t1z /= ln
    t2x = n[1] * t1z - n[2] * t1y; t2y = n[2] * t1x - n[0] * t1z; t2z = n[0] * t1y - n[1] * t1x
    wv = np.zeros(nv)
    touched = np.zeros(nv, np.bool_)
    ntouch = 0
    tlist = np.empty(3 * qx.size, np.int64)
    eps = 1e-10
    Y = np.empty(3)
    for q in range(qx.size):
        Y[0] = x[0] + a * (qx[q] * t1x + qy[q] * t2x)
        Y[1] = x[1] + a * (qx[q] * t1y + qy[q] * t2y)
        Y[2] = x[2] + a * (qx[q] * t1z + qy[q] * t2z)
        best = np.inf
        bm = -1
        bl1 = 0.0; bl2 = 0.0
        for m in range(nc):
            s = cand[m]
            d0 = Y[0] - p0[s, 0]; d1 = Y[1] - p0[s, 1]; d2 = Y[2] - p0[s, 2]
            l1 = Minv[m, 0, 0] * d0 + Minv[m, 0, 1] * d1 + Minv[m, 0, 2] * d2
            l2 = Minv[m, 1, 0] * d0 + Minv[m, 1, 1] * d1 + Minv[m, 1, 2] * d2
            tt = Minv[m, 2, 0] * d0 + Minv[m, 2, 1] * d1 + Minv[m, 2, 2] * d2
            if l1 >= -eps and l2 >= -eps and l1 + l2 <= 1.0 + eps and abs(tt) <= a + h:
                if abs(tt) < best:
                    best = abs(tt); bm = m; bl1 = l1; bl2 = l2
        if bm < 0:
            continue
        lam0 = max(1.0 - bl1 - bl2, 0.0); lam1 = max(bl1, 0.0); lam2 = max(bl2, 0.0)
        sm = lam0 + lam1 + lam2
        t = tris[cand[bm]]
        for k, lk in ((0, lam0), (1, lam1), (2, lam2)):
            v = T[t, k]
            if not touched[v]:
                touched[v] = True
                tlist[ntouch] = v
                ntouch += 1
            wv[v] += (lk / sm) * qw[q]
    if ntouch == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    V = sorted_ints(tlist[:ntouch])
    # (loops, not w.max(), boolean masks and w / w.sum(): the same arithmetic, in the same
    # order, at ~1.5 s less of a first run's compile)
    wmax = 0.0
    for iw in range(ntouch):
        wmax = max(wmax, wv[V[iw]])
    nk = 0
    for iw in range(ntouch):
        if wv[V[iw]] > drop * wmax:
            nk += 1
    Vk = np.empty(nk, np.int64)
    wk = np.empty(nk)
    nk = 0
    wsum = 0.0
    for iw in range(ntouch):
        wi = wv[V[iw]]
        if wi > drop * wmax:
            Vk[nk] = V[iw]
            wk[nk] = wi
            wsum += wi
            nk += 1
    for iw in range(nk):
        wk[iw] = wk[iw] / wsum
    return Vk, wk


@kernel
def _positive(V, w):  # pragma: no cover (compiled)
    """The entries of ``(V, w)`` with ``w > 0`` (``V[w > 0], w[w > 0]``, as loops)."""
    k = 0
    for i in range(w.size):
        if w[i] > 0.0:
            k += 1
    Vk = np.empty(k, np.int64)
    wk = np.empty(k)
    k = 0
    for i in range(w.size):
        if w[i] > 0.0:
            Vk[k] = V[i]
            wk[k] = w[i]
            k += 1
    return Vk, wk


@kernel
def _append(wv, ww, V, w):  # pragma: no cover (compiled)
    """``np.concatenate((wv, V)), np.concatenate((ww, w))`` (int64, float64), as loops
    (one kernel for both: one type specialisation)."""
    ov = np.empty(wv.size + V.size, np.int64)
    ow = np.empty(ww.size + w.size)
    for i in range(wv.size):
        ov[i] = wv[i]
        ow[i] = ww[i]
    for i in range(V.size):
        ov[wv.size + i] = V[i]
        ow[ww.size + i] = w[i]
    return ov, ow


@kernel
def patch_one(t, bary, a, n, resolution, rule_off, rule_x, rule_y, rule_w, facing, drop,
              pidx, X):  # pragma: no cover (compiled)
    """Weights of one patch contact on triangle ``t`` at ``bary`` with radius ``a`` and
    normal ``n`` (``hailstorm.runtime.contact.weights.patch_weights`` for one contact, positive weights
    only): (vertices, weights). ``rule_*``: the disc rules of ``n_r`` = 0..40 points per
    radius, concatenated (rule ``n_r`` is ``rule_off[n_r]:rule_off[n_r + 1]``)."""
    T = pidx[13]
    if a > 0.0:
        x = np.zeros(3)
        for m in range(3):
            for e in range(3):
                x[e] += bary[m] * X[T[t, m], e]
        h = 0.0
        for m in range(3):
            a_ = T[t, m]
            b_ = T[t, (m + 2) % 3]
            h += math.sqrt((X[a_, 0] - X[b_, 0]) ** 2 + (X[a_, 1] - X[b_, 1]) ** 2 + (X[a_, 2] - X[b_, 2]) ** 2)
        h /= 3.0
        n_r = int(min(max(math.ceil(resolution * a / max(h, 1e-300)) + 4, 4), 40))
        o0 = rule_off[n_r]
        o1 = rule_off[n_r + 1]
        V, w = disc_patch(x, n, a, h, rule_x[o0:o1], rule_y[o0:o1], rule_w[o0:o1], facing, drop, pidx)
        if V.size:
            return _positive(V, w)
    V = np.empty(3, np.int64)
    w = np.empty(3)
    k = 0
    for m in range(3):
        if bary[m] > 0.0:
            V[k] = T[t, m]
            w[k] = bary[m]
            k += 1
    return V[:k], w[:k]


@kernel
def patch_compliance(verts, w, normal, D, column_of):  # pragma: no cover (compiled)
    """Normal compliance ``g^T D_vv g`` of one contact alone, ``g = w kron normal``."""
    c = 0.0
    nv = verts.size
    for j in range(nv):
        if w[j] == 0.0:
            continue
        cb = column_of[verts[j]]
        if cb < 0:
            continue
        for e in range(3):
            col = 3 * cb + e
            gj = w[j] * normal[e]
            acc = 0.0
            for i in range(nv):
                if w[i] == 0.0:
                    continue
                r = 3 * verts[i]
                acc += w[i] * (d_entry(D, r, col) * normal[0] + d_entry(D, r + 1, col) * normal[1]
                               + d_entry(D, r + 2, col) * normal[2])
            c += gj * acc
    return c


@kernel
def _sphere_target(kk, f, f_eq, m, vn, R, e_star, a_min):  # pragma: no cover (compiled)
    """Patch radius for the expected peak force ``f_eq + sqrt((f - f_eq)^2 + k m vn^2)``:
    the sphere's impact patch (:func:`hailstorm.runtime.compiled.sphere.impact_radius_of`),
    clipped to ``[a_min, R]``, then at least ``a_min``."""
    kk = max(kk, 0.0)
    fp = f_eq + math.sqrt((f - f_eq) ** 2 + kk * m * vn * vn)
    a = impact_radius_of(fp, R, e_star)
    a = min(max(a, a_min), R)
    return max(a, a_min)


@kernel
def patch_radii(stones, tris, mass, radius, vel, cbary, crad, cnormal, g, wind, drag_coef, cc_stones, Kdiag,
                lam, sticky, k_tri, e_star, a_min, tol, rest_speed, rule_off, rule_x, rule_y, rule_w, facing,
                drop, pidx, X, D, column_of):  # pragma: no cover (compiled)
    """The storm's patch sizing (:meth:`hailstorm.runtime.storm.patches.Patches.radii`, the rule): the patch radius of
    each soft contact, written to ``crad``; ``cnormal``: the stones' contact normals.

    ``cc_stones``, ``Kdiag``, ``lam``: the previous contact set's stones, the diagonal
    of its capacitance and its multipliers (a stone found there is a *known*
    contact). A new contact is sized with the triangle's point stiffness ``k_tri``,
    then once more with the stiffness of that patch alone; its weights at the first
    radius are returned for the weights cache.

    Returns
    -------
    a : (s,) ndarray
        The radii.
    resizes : int
        Known contacts whose radius changed.
    a0 : (s,) ndarray
        New contacts: the first radius (0 for known ones).
    off, wv, ww : ndarrays
        New contact ``i``'s weights at ``a0[i]``: vertices ``wv[off[i]:off[i + 1]]``,
        weights ``ww[...]`` (empty for known ones).
    """
    s = stones.size
    out = np.empty(s)
    a0s = np.zeros(s)
    off = np.zeros(s + 1, np.int64)
    wv = np.empty(0, np.int64)
    ww = np.empty(0)
    resizes = 0
    t1 = 1.0 + tol
    for i in range(s):
        j = stones[i]
        t = tris[i]
        n = cnormal[j]
        m = mass[j]
        R = radius[j]
        vn = vel[j, 0] * n[0] + vel[j, 1] * n[1] + vel[j, 2] * n[2]
        gn = drag_dot(j, vel, radius, n, g, wind, drag_coef)
        f_eq = m * max(-gn, 0.0)
        ik = -1
        for c in range(cc_stones.size):
            if cc_stones[c] == j:
                ik = c
                break
        k = 0.0
        f = 0.0
        if ik >= 0:
            if sticky:
                fn = 0.0
                for d in range(3):
                    k += Kdiag[3 * ik + d] * n[d] * n[d]
                    fn += lam[3 * ik + d] * n[d]
                f = abs(fn)
            else:
                k = Kdiag[ik]
                f = abs(lam[ik])
            target = _sphere_target(k, f, f_eq, m, vn, R, e_star, a_min)
            off[i + 1] = off[i]
        else:
            a0 = _sphere_target(k_tri[t], 0.0, f_eq, m, vn, R, e_star, a_min)
            V, w = patch_one(t, cbary[j], a0, n, 3.0, rule_off, rule_x, rule_y, rule_w, facing, drop, pidx, X)
            c = patch_compliance(V, w, n, D, column_of)
            a1 = _sphere_target(1.0 / c if c > 0.0 else 0.0, 0.0, f_eq, m, vn, R, e_star, a_min)
            target = a1 if (a1 > a0 * t1 or a1 * t1 < a0) else a0
            a0s[i] = a0
            wv, ww = _append(wv, ww, V, w)
            off[i + 1] = off[i] + V.size
        cur = crad[j] if ik >= 0 else 0.0
        amp = math.sqrt((f - f_eq) ** 2 / max(max(k, 0.0) * m, 1e-300) + vn * vn)
        resting = ik >= 0 and amp < rest_speed
        if cur <= 0.0 or target > cur * t1 or (resting and abs(target - cur) > REST_TOLERANCE * cur):
            if cur > 0.0:
                resizes += 1
            cur = target
        crad[j] = cur
        out[i] = cur
    return out, resizes, a0s, off, wv, ww
