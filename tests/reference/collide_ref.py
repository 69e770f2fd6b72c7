"""Closest points on a triangle surface, the plain way: test oracles for the compiled
narrow phase (:mod:`hailstorm.runtime.compiled.grid`).

:func:`closest_point_on_triangles` is Ericson's Voronoi-region test, vectorised;
:func:`closest_brute` applies it to *every* triangle of the surface (no index, no
bound, no candidate search), so it is independent of the grid and sample logic the
kernels use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def closest_point_on_triangles(
    p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on triangles ``(a, b, c)`` to points ``p`` (row-wise).

    Vectorised Voronoi-region test (Ericson, *Real-Time Collision Detection*,
    5.1.5).

    Parameters
    ----------
    p, a, b, c : (k, 3) ndarray

    Returns
    -------
    point : (k, 3) ndarray
        Closest points.
    bary : (k, 3) ndarray
        Their barycentric coordinates (non-negative, summing to one).
    """
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (p, a, b, c))
    # (written for few numpy calls: the arrays are short, the cost is per call)
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = np.einsum("ki,ki->k", ab, ap)
    d2 = np.einsum("ki,ki->k", ac, ap)
    gaa = np.einsum("ki,ki->k", ab, ab)
    gab = np.einsum("ki,ki->k", ab, ac)
    gbb = np.einsum("ki,ki->k", ac, ac)
    d3 = d1 - gaa; d4 = d2 - gab
    d5 = d1 - gab; d6 = d2 - gbb
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    e1 = d4 - d3; e2 = d5 - d6
    k = d1.size
    num = np.empty((5, k)); den = np.empty((5, k))
    num[0] = d1; num[1] = d2; num[2] = e1; num[3] = vb; num[4] = vc
    den[0] = d1 - d3; den[1] = d2 - d6; den[2] = e1 + e2
    np.add(va + vb, vc, out=den[3]); den[4] = den[3]
    den[den == 0] = 1.0
    t = num / den
    # Voronoi regions in Ericson's order, applied last to first (the first true one wins)
    m = (va <= 0) & (e1 >= 0) & (e2 >= 0)  # edge BC
    v = np.where(m, 1.0 - t[2], t[3]); w = np.where(m, t[2], t[4])
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)  # edge AC
    v = np.where(m, 0.0, v); w = np.where(m, t[1], w)
    m = (d6 >= 0) & (d5 <= d6)  # vertex C
    v = np.where(m, 0.0, v); w = np.where(m, 1.0, w)
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)  # edge AB
    v = np.where(m, t[0], v); w = np.where(m, 0.0, w)
    m = (d3 >= 0) & (d4 <= d3)  # vertex B
    v = np.where(m, 1.0, v); w = np.where(m, 0.0, w)
    m = (d1 <= 0) & (d2 <= 0)  # vertex A
    v = np.where(m, 0.0, v); w = np.where(m, 0.0, w)
    bary = np.empty((k, 3))
    bary[:, 1] = v
    bary[:, 2] = w
    bary[:, 0] = 1.0 - v - w
    np.minimum(np.maximum(bary, 0.0, out=bary), 1.0, out=bary)  # np.clip, without its overhead
    bary /= np.add.reduce(bary, axis=1, keepdims=True)
    point = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return point, bary


@dataclass
class Closest:
    """Result of :func:`closest_brute` (one row per query point).

    ``triangle`` is -1 (and ``distance`` inf) where no triangle lies within
    the reach.
    """

    triangle: np.ndarray  # (k,) int
    bary: np.ndarray  # (k, 3)
    point: np.ndarray  # (k, 3) on the (deformed) surface
    distance: np.ndarray  # (k,)



def closest_brute(points: np.ndarray, X: np.ndarray, triangles: np.ndarray, reach: np.ndarray | float = np.inf,
                  u: np.ndarray | None = None) -> Closest:
    """Closest point on the (deformed, ``X + u``) surface to each point, over all triangles."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    Xd = np.asarray(X, dtype=np.float64) + (0.0 if u is None else np.asarray(u, dtype=np.float64))
    T = np.asarray(triangles)
    k, m = pts.shape[0], T.shape[0]
    reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), (k,))
    out = Closest(triangle=np.full(k, -1, dtype=np.intp), bary=np.zeros((k, 3)), point=np.full((k, 3), np.nan),
                  distance=np.full(k, np.inf))
    for i in range(k):
        p = np.repeat(pts[i:i + 1], m, axis=0)
        cp, bc = closest_point_on_triangles(p, Xd[T[:, 0]], Xd[T[:, 1]], Xd[T[:, 2]])
        d = np.linalg.norm(p - cp, axis=1)
        j = int(np.argmin(d))
        if d[j] <= reach[i]:
            out.triangle[i], out.bary[i], out.point[i], out.distance[i] = j, bc[j], cp[j], d[j]
    return out


def contact_normal_ref(p: np.ndarray, t: int, bary: np.ndarray, X: np.ndarray, triangles: np.ndarray,
                       tri_normals: np.ndarray, corner: np.ndarray, sharp_edge: np.ndarray,
                       sharp_vertex: np.ndarray) -> np.ndarray:
    """The contact normal of a sphere centred at ``p`` in contact at ``bary`` on triangle ``t``, the
    plain way (the oracle of :func:`hailstorm.runtime.compiled.narrow.contact_normal`): the corner
    normals interpolated at ``bary``; where ``p``'s closest point on ``t`` lies on a sharp edge or
    corner of it, the direction from that point to ``p``; the triangle's normal where either
    does not face its side."""
    T = np.asarray(triangles)
    n_t = np.asarray(tri_normals[t], dtype=np.float64)
    m = np.asarray(bary, dtype=np.float64) @ np.asarray(corner[t], dtype=np.float64)
    n = m / np.linalg.norm(m) if m @ n_t > 0 else n_t
    P = np.asarray(X, dtype=np.float64)[T[t]]
    q, bc = closest_point_on_triangles(p[None], P[0][None], P[1][None], P[2][None])
    zero = bc[0] <= 1e-12
    if not zero.any():
        return n
    if zero.sum() == 1:  # on the edge opposite the zero corner: from corner k0 + 1 to k0 + 2
        sharp = bool(sharp_edge[t, (int(np.flatnonzero(zero)[0]) + 1) % 3])
    else:
        sharp = bool(sharp_vertex[T[t, int(np.flatnonzero(~zero)[0])]])
    f = p - q[0]
    if sharp and np.linalg.norm(f) > 0 and f @ n_t > 1e-9 * np.linalg.norm(f):
        return f / np.linalg.norm(f)
    return n
