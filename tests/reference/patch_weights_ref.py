"""Reference (numpy) patch weights: the consistent nodal load of a pressure disc.

The library computes them in the compiled kernel
:func:`hailstorm.runtime.compiled.patches.disc_patch` (through
:func:`hailstorm.runtime.contact.weights.patch_weights`); this is the same
algorithm in vectorised numpy, written for reading, with its own candidate
search (a k-d tree over the triangle centroids instead of the kernel's grid).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.weights import (
    PATCH_DROP,
    PATCH_FACING,
    contact_points,
    disc_rule,
    radial_points,
    triangle_index,
)


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.sqrt(e1 @ e1)
    return e1, np.cross(n, e1)


def one_patch_ref(gf, x: np.ndarray, n: np.ndarray, a: float, h: float, profile: str = "hertz",
                  resolution: float = 3.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices and weights of one patch of radius ``a`` at ``x`` with normal ``n``; None if the
    disc hits no usable triangle (every quadrature point projected along ``n`` onto the
    nearest facing usable triangle, its barycentric weights accumulated on the vertices)."""
    idx = triangle_index(gf)
    if idx.tris.size == 0:
        return None
    tree = cKDTree(idx.centroids)
    cand = np.asarray(tree.query_ball_point(x, a + idx.reach + 1e-12 * max(a, 1.0)), dtype=np.intp)
    if cand.size == 0:
        return None
    dc = idx.centroids[cand] - x
    near = np.sqrt(np.add.reduce(dc * dc, axis=1)) <= a + idx.radii[cand] + 1e-12 * max(a, 1.0)
    cand = cand[near & (idx.normals[cand] @ n > PATCH_FACING)]
    if cand.size == 0:
        return None
    n_r = radial_points(a, h, resolution)
    qx, qy, qw = disc_rule(n_r, 4 * n_r, profile)
    e1, e2 = _tangents(n)
    Y = x + a * (qx[:, None] * e1 + qy[:, None] * e2)  # (Q, 3)
    # project Y along n onto each candidate plane: [e1 e2 -n] [l1 l2 t]^T = Y - p0
    M = np.empty((cand.size, 3, 3))
    M[:, :, 0] = idx.e1[cand]
    M[:, :, 1] = idx.e2[cand]
    M[:, :, 2] = -n
    sol = np.matmul(Y[None, :, :] - idx.p0[cand][:, None, :], np.linalg.inv(M).transpose(0, 2, 1))
    l1, l2, tt = sol[..., 0].T, sol[..., 1].T, sol[..., 2].T  # (Q, T)
    eps = 1e-10
    inside = (l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1.0 + eps) & (np.abs(tt) <= a + h)
    cost = np.where(inside, np.abs(tt), np.inf)
    j = np.argmin(cost, axis=1)
    hit = np.isfinite(cost[np.arange(j.size), j])
    if not hit.any():
        return None
    q = np.flatnonzero(hit)
    jt = j[q]
    lam = np.stack([1.0 - l1[q, jt] - l2[q, jt], l1[q, jt], l2[q, jt]], axis=1)
    np.clip(lam, 0.0, None, out=lam)
    lam /= lam.sum(axis=1, keepdims=True)
    verts = np.asarray(gf.triangles)[idx.tris[cand[jt]]]  # (q, 3)
    V, inv = np.unique(verts, return_inverse=True)
    w = np.bincount(inv.ravel(), weights=(lam * qw[q, None]).ravel(), minlength=V.size)
    keep = w > PATCH_DROP * w.max()
    V, w = V[keep], w[keep]
    return V, w / w.sum()


def patch_weights_ref(gf, tri, bary, radius, normals=None, profile: str = "hertz",
                      resolution: float = 3.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per contact (vertices, weights) as :func:`hailstorm.runtime.contact.weights.patch_weights`
    (unpadded; the barycentric weights where the radius is 0 or the disc misses)."""
    T = np.asarray(gf.triangles)
    t = np.asarray(tri, dtype=np.intp).reshape(-1)
    b = np.asarray(bary, dtype=np.float64).reshape(t.size, 3)
    a = np.broadcast_to(np.asarray(radius, dtype=np.float64), (t.size,))
    n = triangle_normals(gf.vertices, T[t]) if normals is None else np.asarray(normals, dtype=np.float64)
    X = contact_points(gf.vertices, T, t, b)
    P = np.asarray(gf.vertices, dtype=np.float64)[T[t]]
    h = np.linalg.norm(P - np.roll(P, 1, axis=1), axis=2).mean(axis=1)
    out = []
    for k in range(t.size):
        res = one_patch_ref(gf, X[k], n[k], float(a[k]), float(h[k]), profile, resolution) if a[k] > 0 else None
        out.append(res if res is not None else (T[t[k]], b[k]))
    return out
