"""Closest points on a (deformed) triangle surface, with a spatial index.

The index is a :class:`scipy.spatial.cKDTree` over sample points of the
*undeformed* triangles (centroids of a regular subdivision, so every point of
a triangle is within ``sample_radius`` of one of its samples), built once. A
query at a stone centre gathers the triangles with a sample within
``min(reach, d0 + displacement_max) + displacement_max + sample_radius`` (``d0`` the nearest
sample: so no triangle within ``reach`` of the point on the *deformed* surface
is missed),
then computes exact point-triangle distances on the deformed triangles,
vectorised over all (point, candidate) pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from hailstorm.runtime.compiled import SampleGrid
from hailstorm.runtime.gather import _unique_inverse

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

    ``KNN``: samples fetched per query point in one dense k-d tree call
    (a ball query is the fallback when more lie within reach).

    Parameters
    ----------
    vertices : (n, 3) ndarray
        Undeformed vertex positions.
    triangles : (m, 3) int ndarray
    """

    KNN = 48

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.intp)
        p = self.vertices[self.triangles]
        self.centroids = p.mean(axis=1)
        #: largest centroid-to-corner distance over all triangles
        self.circumradius = float(np.linalg.norm(p - self.centroids[:, None, :], axis=2).max()) if len(p) else 0.0
        # the k-d tree holds sample points of every triangle (centroids of a regular
        # subdivision) so that every point of a triangle lies within `sample_radius` of one
        # of its samples: large triangles (underside) no longer widen every query
        cr = np.linalg.norm(p - self.centroids[:, None, :], axis=2).max(axis=1) if len(p) else np.zeros(0)
        rho = float(np.median(cr)) if len(p) else 0.0
        level = np.maximum(1, np.ceil(cr / max(rho, 1e-300))).astype(np.intp) if len(p) else np.zeros(0, np.intp)
        samples, owners, srad = [], [], np.zeros(len(p))
        for L in np.unique(level):
            ts = np.flatnonzero(level == L)
            # barycentric centroids of the L^2 sub-triangles
            bc_list: list[tuple[float, float]] = []
            for i in range(L):
                for j in range(L - i):
                    bc_list.append(((i + 1 / 3) / L, (j + 1 / 3) / L))  # upward sub-triangles
                    if i + j < L - 1:
                        bc_list.append(((i + 2 / 3) / L, (j + 2 / 3) / L))  # downward ones
            bc = np.array(bc_list)
            w = np.column_stack([1 - bc.sum(axis=1), bc])  # (L^2, 3)
            pts = np.einsum("sk,tkd->tsd", w, p[ts]).reshape(-1, 3)
            samples.append(pts)
            owners.append(np.repeat(ts, w.shape[0]))
            srad[ts] = cr[ts] / L
        self._sample_tri = np.concatenate(owners) if owners else np.zeros(0, np.intp)
        #: every point of a triangle lies within this of one of its samples
        self.sample_radius = float(srad.max()) if len(p) else 0.0
        spts = np.concatenate(samples) if samples else np.zeros((0, 3))
        self.tree = cKDTree(spts)
        #: the same samples in a uniform grid, for the compiled kernels (:mod:`hailstorm.runtime.compiled`)
        self.grid = SampleGrid.build(spts, self._sample_tri, max(2.0 * self.sample_radius, 1e-6))
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
        displacement: "Callable[[np.ndarray], np.ndarray] | None" = None,
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
        displacement : callable, optional
            ``displacement(vertices) -> (k, 3)``: the displacement of the
            given vertices. Evaluated only at the candidate triangles'
            vertices (the surface is never deformed as a whole).
        max_displacement : float
            Upper bound of ``|u|`` over the surface (widens the candidate
            search so that moved triangles are not missed).

        Returns
        -------
        Closest
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        k = pts.shape[0]
        reach = np.asarray(reach, dtype=np.float64)
        if reach.shape != (k,):
            reach = np.broadcast_to(reach, (k,))
        out = Closest(
            triangle=np.full(k, -1, dtype=np.intp),
            bary=np.zeros((k, 3)),
            point=np.full((k, 3), np.nan),
            distance=np.full(k, np.inf),
        )
        if k == 0:
            return out
        # the closest surface point is no farther than the nearest centroid (d0): triangles
        # that can hold it have their centroid within min(reach, d0) + circumradius (+ |u|)
        # d0 (distance to the nearest sample, a point of the undeformed surface) bounds the
        # distance to the closest point: candidates lie within min(reach, d0) + sample radius
        md = float(max_displacement)
        # one k-d tree call: the KNN nearest samples within the widest bound; the first is
        # d0 (when none is within the bound, nothing is within reach)
        kk = max(2, min(self.KNN, self.tree.n))
        bound = float(reach.max()) + 2.0 * md + self.sample_radius
        dd, ii = self.tree.query(pts, k=kk, distance_upper_bound=bound)
        d0 = dd[:, 0]
        lim = np.minimum(reach, d0 + md) + md + self.sample_radius
        inside = dd <= lim[:, None]
        inside[d0 - self.sample_radius - md > reach] = False
        # rows whose KNN-th sample is still within lim may miss some: ball query for those
        full = inside[:, -1].copy()
        inside[full] = False
        owner, col = np.nonzero(inside)
        smp = ii[owner, col]
        if full.any():
            sel = np.flatnonzero(full)
            lists = self.tree.query_ball_point(pts[sel], lim[sel])
            counts = np.fromiter((len(x) for x in lists), dtype=np.intp, count=sel.size)
            owner = np.concatenate([owner, np.repeat(sel, counts)])
            smp = np.concatenate([smp, np.fromiter((t for x in lists for t in x), dtype=np.intp,
                                                   count=int(counts.sum()))])
            order = np.argsort(owner, kind="stable")
            owner, smp = owner[order], smp[order]
        if smp.size == 0:
            return out
        # (owner, triangle) pairs sorted by owner; a triangle seen through several of its
        # samples is tested several times (harmless: cheaper than de-duplicating)
        tri = self._sample_tri[smp]
        corners = self.triangles[tri]
        if displacement is not None:
            verts, corners = _unique_inverse(corners, self.vertices.shape[0])
            Xl = self.vertices[verts] + displacement(verts)
        else:
            Xl = self.vertices if deformed is None else np.asarray(deformed, dtype=np.float64)
        po = pts[owner]
        T = Xl[corners]  # (pairs, 3, 3): one gather for the three corners
        cp, bary = closest_point_on_triangles(po, T[:, 0], T[:, 1], T[:, 2])
        dv = po - cp
        d = np.sqrt(np.einsum("ij,ij->i", dv, dv))
        # the minimum per owner (the first pair among equal distances: stable sort)
        order = np.lexsort((d, owner))
        so = owner[order]
        head = np.empty(so.size, dtype=bool)
        head[0] = True
        np.not_equal(so[1:], so[:-1], out=head[1:])
        first = order[head]
        o = so[head]
        ok = d[first] <= reach[o]
        first, o = first[ok], o[ok]
        out.triangle[o] = tri[first]
        out.bary[o] = bary[first]
        out.point[o] = cp[first]
        out.distance[o] = d[first]
        return out
