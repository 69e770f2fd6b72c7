"""Collision of the stones with the seat: the surface's index and the broad and narrow phase.

Every triangle is covered by sample points (centroids of a regular subdivision, so
every point of a triangle lies within ``sample_radius`` of one of its samples), held
in a uniform grid (:class:`hailstorm.runtime.compiled.SampleGrid`) that the compiled
broad and narrow phase query (:mod:`hailstorm.runtime.compiled.flight`,
:mod:`hailstorm.runtime.compiled.narrow`): nearest sample, then exact point-triangle
distances on the (locally deformed) candidate triangles. Built once per storm.

The tests hold those kernels to a brute-force closest point over all triangles
(``tests/reference/collide_ref.py``).

:class:`Collision` runs them on a storm's :class:`~hailstorm.runtime.storm.stones.Stones`
against the :class:`~hailstorm.runtime.storm.seat.SeatState`: the broad phase
(conservative advancement, :meth:`Collision.near_set`), free flight, the free part
of a sub-step (closest points, time of impact, contacts that open, hard walls:
:meth:`Collision.free_phase`), the penetration statistics and retirement.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING


import numpy as np

from hailstorm.runtime.compiled import SampleGrid, flight, free_phase, near_set, penetration, retired
from hailstorm.runtime.compiled.grid import surface_arrays
from hailstorm.runtime.contact import policy
from hailstorm.runtime.storm.hail import GRAVITY
from hailstorm.runtime.contact.normals import CREASE_ANGLE, corner_normals
from hailstorm.runtime.storm.recording import StormStats

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.hail import Air
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.seat import SeatState
    from hailstorm.runtime.storm.stones import Stones
    from hailstorm.runtime.bundle.compliance import ComplianceSource

__all__ = ["Collision", "SurfaceIndex", "sharp_features"]



def sharp_features(vertices: np.ndarray, triangles: np.ndarray,
                   crease: float = CREASE_ANGLE) -> tuple[np.ndarray, np.ndarray]:
    """The surface's sharp edges and corners: where the smooth reading (:func:`corner_normals`)
    stops, and a sphere over the edge touches it as an edge.

    Parameters
    ----------
    vertices : (n, 3) ndarray
    triangles : (m, 3) int ndarray
    crease : float
        [rad].

    Returns
    -------
    sharp_edge : (m, 3) bool ndarray
        Edge ``k`` of triangle ``t`` (from its corner ``k`` to corner ``k + 1``) meets its
        neighbour's at more than ``crease`` between their normals, or has no neighbour.
    sharp_vertex : (n,) bool ndarray
        The vertex ends a sharp edge.
    """
    X = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.intp)
    m = T.shape[0]
    n_vertices = len(X)
    face_normals = np.cross(X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]])
    ln = np.linalg.norm(face_normals, axis=1, keepdims=True)
    face_normals /= np.where(ln > 0, ln, 1.0)
    a, b = T.ravel(), T[:, [1, 2, 0]].ravel()  # edge k of t: row 3 t + k
    key = np.minimum(a, b) * np.int64(n_vertices) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    sharp = np.ones(3 * m, dtype=bool)
    pair = np.flatnonzero(ks[1:] == ks[:-1])  # two triangles on one edge (sorted neighbours)
    e1, e2 = order[pair], order[pair + 1]
    cos = np.einsum("kd,kd->k", face_normals[e1 // 3], face_normals[e2 // 3])
    # (an edge of more than two triangles stays sharp)
    single = np.ones(pair.size, dtype=bool)
    if pair.size > 1:
        run = (pair[1:] == pair[:-1] + 1)
        single[1:] &= ~run
        single[:-1] &= ~run
    smooth = single & (cos >= math.cos(crease))
    sharp[e1[smooth]] = False
    sharp[e2[smooth]] = False
    sharp_vertex = np.zeros(n_vertices, dtype=bool)
    sharp_vertex[a[sharp]] = True
    sharp_vertex[b[sharp]] = True
    return sharp.reshape(m, 3), sharp_vertex


class SurfaceIndex:
    """The surface's samples, their grid, the triangle and corner normals and the bounding box.

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
        #: the surface's normals at the triangles' corners (m, 3, 3) (:func:`corner_normals`)
        self.corner_normals = corner_normals(self.vertices, self.triangles, CREASE_ANGLE)
        #: the sharp edges (m, 3) and corners (n,) (:func:`sharp_features`)
        self.sharp_edges, self.sharp_vertices = sharp_features(self.vertices, self.triangles, CREASE_ANGLE)
        self.bbox = (self.vertices.min(axis=0), self.vertices.max(axis=0))



class Collision:
    """Broad and narrow phase of a storm's stones against the (deformed) seat.

    Parameters
    ----------
    gf : ComplianceSource
        The bundle's surface (vertices, triangles, ``contactable``, ``fixed``).
    scene : Scene
        ``time.adaptive`` (time of impact), ``time.min_substep``
        (the shortest sub-step), ``contact.restitution`` (hard walls),
        ``storm.margin`` (retirement).
    air : Air
    """

    #: the gap within which a contact opens [radii]
    TOI_TOL = 0.01

    def __init__(self, gf: ComplianceSource, scene: Scene, air: Air) -> None:
        self.index = SurfaceIndex(gf.vertices, gf.triangles)
        tri = np.asarray(gf.triangles)
        fixed = np.asarray(gf.fixed)
        has_col = np.asarray(gf.contactable) | fixed
        #: triangles that deform under a contact (others are a hard wall)
        self.soft = has_col[tri].all(axis=1) & ~fixed[tri].all(axis=1)
        #: clamped vertices, as the kernels take them
        self.fixed = np.ascontiguousarray(gf.fixed, dtype=bool)
        #: a triangle corner or edge carrying at most this weight on free vertices is a hard wall
        self.rigid_weight = float(policy.RIGID_WEIGHT)
        self.lo, self.hi = self.index.bbox
        self.air = air
        self.toi = bool(scene.time.adaptive)
        self.hmin = scene.time.min_substep
        self.restitution = float(scene.contact.restitution)
        self.margin = float(scene.storm.margin)
        #: the surface as the compiled kernels take it
        self.surface = surface_arrays(self.index.grid, self.index.sample_radius, self.index.vertices,
                                      self.index.triangles)

    def near_set(self, stones: Stones, live: np.ndarray, dt: float, umax: float) -> tuple[np.ndarray, np.ndarray]:
        """The live stones that may touch the seat within ``dt`` and the others
        (conservative advancement, :func:`hailstorm.runtime.compiled.near_set`;
        ``umax``: the bound of the seat's displacement)."""
        ix = self.index
        m = near_set(ix.grid, ix.sample_radius, ix.bbox, live, stones.pos, stones.vel, stones.radius, stones.ctri,
                     stones.budget, stones.bud_u, 1.5 * umax, dt, GRAVITY)
        return live[m], live[~m]

    def fly(self, stones: Stones, idx: np.ndarray, h: float) -> None:
        """Free flight of stones ``idx`` over ``h`` (gravity and drag)."""
        flight(idx, stones.pos, stones.vel, stones.radius, h, GRAVITY, self.air.wind, self.air.drag_coef)

    def free_phase(self, stones: Stones, near: np.ndarray, h: float, seat: SeatState, stats: StormStats) -> float:
        """Closest points, time of impact, contacts that open, hard walls
        (:func:`hailstorm.runtime.compiled.free_phase`), on each stone's contact surface
        (:meth:`Stones.contact_radius`). Returns the sub-step taken."""
        use_u, cols, forces = seat.kernel_load()
        h, walls = free_phase(
            near, h, self.toi, self.TOI_TOL, self.hmin, stones.pos, stones.vel, stones.radius, stones.offset,
            stones.shift, stones.ctri, stones.cbary, stones.cnormal, stones.gap, stones.near_tri, self.surface,
            self.index.normals, self.index.corner_normals, self.index.sharp_edges, self.index.sharp_vertices,
            self.soft, self.fixed, self.rigid_weight, seat.umax, use_u, seat.D, cols, forces, GRAVITY, self.air.wind,
            self.air.drag_coef, self.restitution)
        stats.wall_contacts += int(walls)
        return float(h)

    def penetration(self, stones: Stones, near: np.ndarray, dt: float, seat: SeatState, stats: StormStats) -> None:
        """The near stones' overlap with the deformed surface, into the statistics (their
        contact surfaces', :meth:`Stones.contact_radius`: a patch contact's sphere reaches
        its offset deeper than the mean of the dent under it, by the model)."""
        use_u, cols, forces = seat.kernel_load()
        mp, mpc, mrc, spc, npc, mpf = penetration(
            near, float(dt), stones.pos, stones.vel, stones.contact_radius(), stones.ctri, self.surface, seat.umax, use_u,
            seat.D, cols, forces)
        stats.max_penetration_m = max(stats.max_penetration_m, mp)
        stats.max_penetration_contact_m = max(stats.max_penetration_contact_m, mpc)
        stats.max_penetration_contact_rel = max(stats.max_penetration_contact_rel, mrc)
        stats.max_penetration_free_m = max(stats.max_penetration_free_m, mpf)
        stats.pen_contact_sum += spc
        stats.pen_contact_n += int(npc)

    def retired(self, stones: Stones, live: np.ndarray) -> np.ndarray:
        """The live stones that left the seat's region."""
        return live[retired(live, stones.pos, stones.radius, self.lo, self.hi, self.margin)]

    def fell_through(self, stones: Stones, ids: np.ndarray) -> int:
        """How many of the stones ``ids`` never touched the seat yet are below it, inside its
        footprint: they passed through it (a step or a speed too large)."""
        p = stones.pos[ids]
        lo, hi = self.lo, self.hi
        below = (p[:, 2] < lo[2]) & ((p[:, :2] >= lo[:2]) & (p[:, :2] <= hi[:2])).all(axis=1)
        return int((below & ~stones.hit[ids]).sum())

    def warm_up(self, stones: Stones, seat: SeatState, dt: float) -> None:
        """Load (or compile) the kernels with the storm loop's argument types."""
        self.warm_up_flight(stones, dt)
        self.warm_up_narrow(stones, seat, dt)

    def warm_up_flight(self, stones: Stones, dt: float) -> None:
        """Load (or compile) free flight, retirement and the broad phase (the loop's argument types)."""
        none = np.zeros(0, dtype=np.intp)
        self.fly(stones, none, 0.0)
        self.retired(stones, none)
        self.near_set(stones, none, dt, 0.0)

    def warm_up_narrow(self, stones: Stones, seat: SeatState, dt: float) -> None:
        """Load (or compile) the narrow phase and the penetration statistics (the loop's argument types)."""
        none = np.zeros(0, dtype=np.intp)
        stats = StormStats()
        self.free_phase(stones, none, dt, seat, stats)
        self.penetration(stones, none, dt, seat, stats)
