"""The seat's surface as the storm's collision kernels see it: sample points in a grid.

Every triangle is covered by sample points (centroids of a regular subdivision, so
every point of a triangle lies within ``sample_radius`` of one of its samples), held
in a uniform grid (:class:`hailstorm.runtime.compiled.SampleGrid`) that the compiled
broad and narrow phase query (:mod:`hailstorm.runtime.compiled.flight`,
:mod:`hailstorm.runtime.compiled.narrow`): nearest sample, then exact point-triangle
distances on the (locally deformed) candidate triangles. Built once per storm.

The tests hold those kernels to a brute-force closest point over all triangles
(``tests/reference/collide_ref.py``).
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.compiled import SampleGrid

__all__ = ["SurfaceIndex"]


class SurfaceIndex:
    """The surface's samples, their grid, the triangle normals and the bounding box.

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
        #: the triangle of each sample
        self.sample_tri = np.concatenate(owners) if owners else np.zeros(0, np.intp)
        #: every point of a triangle lies within this of one of its samples
        self.sample_radius = float(srad.max()) if len(p) else 0.0
        #: the sample points (m, 3)
        self.samples = np.concatenate(samples) if samples else np.zeros((0, 3))
        #: the samples in a uniform grid, for the compiled kernels (:mod:`hailstorm.runtime.compiled`)
        self.grid = SampleGrid.build(self.samples, self.sample_tri, max(2.0 * self.sample_radius, 1e-6))
        fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        ln = np.linalg.norm(fn, axis=1, keepdims=True)
        #: outward unit normals of the undeformed triangles
        self.normals = fn / np.where(ln > 0, ln, 1.0)
        self.bbox = (self.vertices.min(axis=0), self.vertices.max(axis=0))
