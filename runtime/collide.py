"""Closest points on a (deformed) triangle surface, with a spatial index.

The index is a :class:`scipy.spatial.cKDTree` over the *undeformed* triangle
centroids, built once. A query at a stone centre gathers the triangles whose
centroid lies within ``reach + circumradius_max + displacement_max`` (so no
triangle within ``reach`` of the point on the *deformed* surface is missed),
then computes exact point-triangle distances on the deformed triangles,
vectorised over all (point, candidate) pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Closest", "SurfaceIndex", "closest_point_on_triangles"]


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
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    k = p.shape[0]
    bary = np.empty((k, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        # interior (lowest priority; overwritten by the region tests below)
        den = va + vb + vc
        den = np.where(den != 0, den, 1.0)
        v = vb / den
        w = vc / den
        bary[:] = np.stack([1 - v - w, v, w], axis=1)
        # edge BC
        e1 = d4 - d3
        e2 = d5 - d6
        m = (va <= 0) & (e1 >= 0) & (e2 >= 0)
        t = np.where(m, e1 / np.where(e1 + e2 != 0, e1 + e2, 1.0), 0.0)
        bary[m] = np.stack([np.zeros(m.sum()), 1 - t[m], t[m]], axis=1)
        # edge AC
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        t = np.where(m, d2 / np.where(d2 - d6 != 0, d2 - d6, 1.0), 0.0)
        bary[m] = np.stack([1 - t[m], np.zeros(m.sum()), t[m]], axis=1)
        # vertex C
        m = (d6 >= 0) & (d5 <= d6)
        bary[m] = (0.0, 0.0, 1.0)
        # edge AB
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        t = np.where(m, d1 / np.where(d1 - d3 != 0, d1 - d3, 1.0), 0.0)
        bary[m] = np.stack([1 - t[m], t[m], np.zeros(m.sum())], axis=1)
        # vertex B
        m = (d3 >= 0) & (d4 <= d3)
        bary[m] = (0.0, 1.0, 0.0)
        # vertex A
        m = (d1 <= 0) & (d2 <= 0)
        bary[m] = (1.0, 0.0, 0.0)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    point = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return point, bary


@dataclass
class Closest:
    """Result of :meth:`SurfaceIndex.query` (one row per query point).

    ``triangle`` is -1 (and ``distance`` inf) where no triangle lies within
    the reach.
    """

    triangle: np.ndarray  # (k,) int
    bary: np.ndarray  # (k, 3)
    point: np.ndarray  # (k, 3) on the (deformed) surface
    distance: np.ndarray  # (k,)


class SurfaceIndex:
    """Spatial index over a triangle surface for closest-point queries.

    Parameters
    ----------
    vertices : (n, 3) ndarray
        Undeformed vertex positions.
    triangles : (m, 3) int ndarray
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.intp)
        p = self.vertices[self.triangles]
        self.centroids = p.mean(axis=1)
        #: largest centroid-to-corner distance over all triangles
        self.circumradius = float(np.linalg.norm(p - self.centroids[:, None, :], axis=2).max()) if len(p) else 0.0
        self.tree = cKDTree(self.centroids)
        fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        ln = np.linalg.norm(fn, axis=1, keepdims=True)
        #: outward unit normals of the undeformed triangles
        self.normals = fn / np.where(ln > 0, ln, 1.0)
        self.bbox = (self.vertices.min(axis=0), self.vertices.max(axis=0))

    def query(
        self,
        points: np.ndarray,
        reach: np.ndarray | float,
        *,
        deformed: np.ndarray | None = None,
        max_displacement: float = 0.0,
    ) -> Closest:
        """Closest point on the (deformed) surface to each point, within ``reach``.

        Parameters
        ----------
        points : (k, 3) ndarray
        reach : float or (k,) ndarray
            Search radius per point [m]; farther surfaces are not reported.
        deformed : (n, 3) ndarray, optional
            Deformed vertex positions ``X + u``; default the undeformed ones.
        max_displacement : float
            Upper bound of ``|u|`` over the surface (widens the candidate
            search so that moved triangles are not missed).

        Returns
        -------
        Closest
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        k = pts.shape[0]
        reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), (k,))
        out = Closest(
            triangle=np.full(k, -1, dtype=np.intp),
            bary=np.zeros((k, 3)),
            point=np.full((k, 3), np.nan),
            distance=np.full(k, np.inf),
        )
        if k == 0:
            return out
        X = self.vertices if deformed is None else np.asarray(deformed, dtype=np.float64)
        lists = self.tree.query_ball_point(pts, reach + self.circumradius + max_displacement)
        counts = np.fromiter((len(x) for x in lists), dtype=np.intp, count=k)
        if counts.sum() == 0:
            return out
        owner = np.repeat(np.arange(k), counts)
        tri = np.fromiter((t for x in lists for t in x), dtype=np.intp, count=int(counts.sum()))
        corners = self.triangles[tri]
        cp, bary = closest_point_on_triangles(pts[owner], X[corners[:, 0]], X[corners[:, 1]], X[corners[:, 2]])
        d = np.linalg.norm(pts[owner] - cp, axis=1)
        # the minimum per owner: sort by (owner, d), take the first of each owner
        order = np.lexsort((d, owner))
        first = order[np.r_[True, owner[order][1:] != owner[order][:-1]]]
        o = owner[first]
        ok = d[first] <= reach[o]
        first, o = first[ok], o[ok]
        out.triangle[o] = tri[first]
        out.bary[o] = bary[first]
        out.point[o] = cp[first]
        out.distance[o] = d[first]
        return out
