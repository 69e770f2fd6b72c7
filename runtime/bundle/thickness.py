"""The local thickness of a bundle's body under its surface vertices: rays cast inwards.

Part of the bundle layer (:mod:`hailstorm.runtime.bundle`): the distance from a
surface vertex along its inward normal to the first boundary face of the body
it meets (the clamped underside, the rigid shell, or the opposite surface).
The storm's validity limits read it (``delta / h``,
:mod:`hailstorm.runtime.storm.limits`), and so does the near field of a pad on
its rigid base (:mod:`hailstorm.runtime.contact.layer_kernel`).
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from hailstorm.runtime.bundle.read import vertex_normals

__all__ = ["PAIRS_PER_PASS", "PadThickness", "RayCaster", "ray_thickness", "surface_thickness"]

#: (ray, triangle) pairs tested at a time (about 500 bytes of temporaries each): bounds the
#: caster's memory whatever the number of rays (the ray chunks adapt to the pairs per ray)
PAIRS_PER_PASS = 1 << 18


class RayCaster:
    """Rays against a fixed set of triangles: the distance to the first one each ray hits.

    The triangles are searched in growing balls around each origin: a triangle
    that a ray hits at distance ``t <= r`` meets the ball of radius ``r``, so its
    centroid lies within ``r`` plus the largest centroid-to-corner distance; the
    closest hit among those triangles is the closest of all when it is at most
    ``r`` away. Rays not settled so are searched again with ``r`` doubled, the last
    pass over every triangle. Each (ray, triangle) pair is Moeller-Trumbore's test;
    a ray through an edge or a corner hits (tolerance 1e-9 on the barycentric
    coordinates).

    Parameters
    ----------
    points : (N, 3) ndarray
    faces : (k, 3) int ndarray
        Triangles on ``points`` (any orientation).
    """

    def __init__(self, points: np.ndarray, faces: np.ndarray) -> None:
        P = np.asarray(points, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        self.corners = P[self.faces]  # (k, 3, 3)
        self._tree: Any = None
        if self.faces.shape[0]:
            self.centre = self.corners.mean(axis=1)
            self.reach = float(np.linalg.norm(self.corners - self.centre[:, None], axis=2).max())
            used = self.corners.reshape(-1, 3)
            self.diag = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
            self.size = float(np.median(np.linalg.norm(self.corners[:, 1] - self.corners[:, 0], axis=1)))

    def cast(self, origins: np.ndarray, directions: np.ndarray, *, skip: np.ndarray | None = None,
             start_radius: float | None = None) -> np.ndarray:
        """Distance from each origin along its direction to the first triangle it hits.

        Parameters
        ----------
        origins : (r, 3) ndarray
        directions : (r, 3) ndarray
            Unit directions (e.g. inward normals).
        skip : (r,) int ndarray, optional
            Per ray, a node whose triangles the ray ignores (the node the ray
            starts from; -1: none).
        start_radius : float, optional
            The first ball's radius [m] (default: 4 median edge lengths; ``inf``:
            one pass over every triangle, brute force).

        Returns
        -------
        (r,) ndarray
            The distance [m] (``inf`` where the ray meets no triangle). Hits closer
            than ``1e-9`` of the triangles' bounding-box diagonal are ignored (the
            ray's own start).
        """
        O = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        Dn = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        sk = np.full(O.shape[0], -1, dtype=np.int64) if skip is None else np.asarray(skip, dtype=np.int64).reshape(-1)
        out = np.full(O.shape[0], np.inf)
        k = self.faces.shape[0]
        if k == 0 or O.size == 0:
            return out
        r = 4.0 * self.size if start_radius is None else float(start_radius)
        todo = np.arange(O.shape[0])
        best = np.full(O.shape[0], np.inf)
        step = 256
        while todo.size:
            last = r >= self.diag
            best[todo] = np.inf
            # rays per chunk: from the last chunk's pairs per ray, a ball of twice the radius holding ~4x
            step = max(1, PAIRS_PER_PASS // k) if last else max(1, step // 4)
            i = 0
            while i < todo.size:  # rays in chunks: at most about PAIRS_PER_PASS (ray, face) pairs at a time
                rays = todo[i:i + step]
                i += rays.size
                if last:
                    ray, face = np.repeat(rays, k), np.tile(np.arange(k), rays.size)
                else:
                    if self._tree is None:
                        from scipy.spatial import cKDTree

                        self._tree = cKDTree(self.centre)
                    near = self._tree.query_ball_point(O[rays], r + self.reach)
                    ray = np.repeat(rays, [len(c) for c in near])
                    face = np.fromiter(itertools.chain.from_iterable(near), dtype=np.int64, count=ray.size)
                    step = int(np.clip(PAIRS_PER_PASS * rays.size // max(ray.size, 1), 1, 1 << 14))
                np.minimum.at(best, ray, self._hits(O, Dn, sk, ray, face))
            done = last | (best[todo] <= r)
            out[todo[done]] = best[todo[done]]
            todo = todo[~done]
            r *= 2.0
        return out

    def _hits(self, O: np.ndarray, Dn: np.ndarray, skip: np.ndarray, ray: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Hit distance of each (ray, face) pair (inf: no hit)."""
        c = self.corners[face]
        v0 = c[:, 0]
        e1, e2 = c[:, 1] - v0, c[:, 2] - v0
        d = Dn[ray]
        p = np.cross(d, e2)
        det = np.einsum("kd,kd->k", p, e1)
        ok = np.abs(det) > 1e-300
        inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
        tv = O[ray] - v0
        u = np.einsum("kd,kd->k", tv, p) * inv
        qv = np.cross(tv, e1)
        v = np.einsum("kd,kd->k", d, qv) * inv
        t = np.einsum("kd,kd->k", qv, e2) * inv
        tol = 1e-9
        hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1.0 + tol) & (t > 1e-9 * self.diag)
        F, sk = self.faces[face], skip[ray]
        hit &= ~((F[:, 0] == sk) | (F[:, 1] == sk) | (F[:, 2] == sk))
        return np.where(hit, t, np.inf)


def ray_thickness(points: np.ndarray, faces: np.ndarray, origins: np.ndarray, directions: np.ndarray, *,
                  skip: np.ndarray | None = None, start_radius: float | None = None) -> np.ndarray:
    """Distance from each origin along its direction to the first of ``faces`` it hits
    (:meth:`RayCaster.cast`; ``inf``: none)."""
    return RayCaster(points, faces).cast(origins, directions, skip=skip, start_radius=start_radius)


class PadThickness:
    """The local pad thickness under the surface vertices of a bundle, cast on first request.

    The thickness under a vertex is the distance from it along its inward normal
    (:func:`hailstorm.runtime.bundle.read.vertex_normals` of the outward surface triangles, reversed) to the
    first boundary face of the body it meets: the clamped underside (the rigid
    shell) or the opposite surface. The boundary is the bundle's surface, which
    is the boundary of its volume mesh (the contract: the surface and the volume
    mesh it came from, :func:`boundary_faces` of ``volume_tets`` through
    ``surface_nodes``; checked in the tests), so no volume data is read. ``inf``
    where the ray meets nothing (an open surface, e.g. a synthetic plate). Each
    vertex is cast once, when first asked for (a storm asks for the vertices of
    the triangles it impacts); building this costs the vertex normals only.

    Parameters
    ----------
    gf : ElasticSource
        ``vertices`` and ``triangles`` (outward).
    """

    def __init__(self, gf: Any) -> None:
        self.X = np.asarray(gf.vertices, dtype=np.float64)
        self.inward = -vertex_normals(self.X, gf.triangles)
        self.caster = RayCaster(self.X, np.asarray(gf.triangles))
        self.values = np.full(self.X.shape[0], np.nan)

    def _cast(self, vertices: np.ndarray) -> np.ndarray:
        return self.caster.cast(self.X[vertices], self.inward[vertices], skip=vertices)

    def __call__(self, vertices: np.ndarray) -> np.ndarray:
        """The thickness under ``vertices`` (surface vertex indices, any shape) [m]."""
        v = np.asarray(vertices, dtype=np.int64)
        new = np.unique(v[np.isnan(self.values[v])])
        if new.size:
            self.values[new] = self._cast(new)
        return self.values[v]


def surface_thickness(gf: Any, vertices: np.ndarray | None = None) -> np.ndarray:
    """The local pad thickness under surface vertices [m] (:class:`PadThickness`).

    Parameters
    ----------
    gf : ElasticSource
        ``vertices``, ``triangles`` (outward).
    vertices : int ndarray, optional
        Surface vertex indices (default: every vertex).
    """
    pad = PadThickness(gf)
    return pad(np.arange(pad.X.shape[0]) if vertices is None else vertices)
