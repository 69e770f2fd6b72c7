"""Spatial queries inside compiled code: the surface's sample points in a uniform grid,
nearest samples and closest points of the (deformed) surface.

The tests hold them to brute force over every triangle (``tests/reference/collide_ref.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.hblocks import d_entry

__all__ = ["SampleGrid", "closest_one", "closest_points", "sorted_ints", "surface_arrays", "triangle_distance"]


@kernel
def sorted_ints(a):  # pragma: no cover (compiled)
    """A sorted copy of an int64 array (heapsort: the same result as ``np.sort`` for
    integers, without compiling numba's quicksort, ~5 s of a first run)."""
    b = a.copy()
    n = b.size
    for start in range(n // 2 - 1, -1, -1):
        _sift(b, start, n)
    root = np.int64(0)  # (not the literal 0: a literal argument is a second specialisation of _sift)
    for end in range(n - 1, 0, -1):
        t = b[0]; b[0] = b[end]; b[end] = t
        _sift(b, root, end)
    return b


@kernel
def _sift(b, root, n):  # pragma: no cover (compiled)
    while True:
        child = 2 * root + 1
        if child >= n:
            return
        if child + 1 < n and b[child] < b[child + 1]:
            child += 1
        if b[root] >= b[child]:
            return
        t = b[root]; b[root] = b[child]; b[child] = t
        root = child


@dataclass(frozen=True)
class SampleGrid:
    """Sample points bucketed in a uniform grid of cubic cells (CSR by cell).

    Attributes
    ----------
    lo : (3,) ndarray
        Corner of cell (0, 0, 0) [m].
    h : float
        Cell edge [m].
    dims : (3,) int64 ndarray
        Cells per axis.
    start : (ncell + 1,) int64 ndarray
        The samples of cell ``c`` are ``items[start[c]:start[c + 1]]``.
    items : (S,) int64 ndarray
        Sample indices, grouped by cell.
    points : (S, 3) ndarray
        Sample positions.
    owner : (S,) int64 ndarray
        Triangle of each sample.
    """

    lo: np.ndarray
    h: float
    dims: np.ndarray
    start: np.ndarray
    items: np.ndarray
    points: np.ndarray
    owner: np.ndarray

    @classmethod
    def build(cls, points: np.ndarray, owner: np.ndarray, h: float) -> "SampleGrid":
        """Bucket ``points`` (S, 3) owned by triangles ``owner`` (S,) in cells of edge ``h``."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        if not h > 0 or not np.isfinite(h):
            raise ValueError(f"cell edge must be positive and finite, got {h!r}")
        lo = points.min(axis=0) if len(points) else np.zeros(3)
        hi = points.max(axis=0) if len(points) else np.zeros(3)
        dims = np.maximum(np.floor((hi - lo) / h).astype(np.int64) + 1, 1)
        cell = _cell_ids(points, lo, h, dims)
        order = np.argsort(cell, kind="stable")
        start = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
        np.add.at(start, cell + 1, 1)
        return cls(lo=lo, h=float(h), dims=dims, start=np.cumsum(start), items=order.astype(np.int64),
                   points=points, owner=np.ascontiguousarray(owner, dtype=np.int64))


def _cell_ids(points: np.ndarray, lo: np.ndarray, h: float, dims: np.ndarray) -> np.ndarray:
    ijk = np.clip(np.floor((points - lo) / h).astype(np.int64), 0, dims - 1)
    return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]


@kernel
def _closest_on_triangle(p, a, b, c, out_bary):  # pragma: no cover (compiled)
    """Closest point of triangle (a, b, c) to p (Ericson 5.1.5, as ``tests/reference/collide_ref.py``):
    writes the clipped, normalised barycentric coordinates to ``out_bary``."""
    ab0 = b[0] - a[0]; ab1 = b[1] - a[1]; ab2 = b[2] - a[2]
    ac0 = c[0] - a[0]; ac1 = c[1] - a[1]; ac2 = c[2] - a[2]
    ap0 = p[0] - a[0]; ap1 = p[1] - a[1]; ap2 = p[2] - a[2]
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    gaa = ab0 * ab0 + ab1 * ab1 + ab2 * ab2
    gab = ab0 * ac0 + ab1 * ac1 + ab2 * ac2
    gbb = ac0 * ac0 + ac1 * ac1 + ac2 * ac2
    d3 = d1 - gaa
    d4 = d2 - gab
    d5 = d1 - gab
    d6 = d2 - gbb
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    e1 = d4 - d3
    e2 = d5 - d6
    if d1 <= 0.0 and d2 <= 0.0:  # vertex A
        v = 0.0; w = 0.0
    elif d3 >= 0.0 and d4 <= d3:  # vertex B
        v = 1.0; w = 0.0
    elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge AB
        den = d1 - d3
        v = d1 / (den if den != 0.0 else 1.0); w = 0.0
    elif d6 >= 0.0 and d5 <= d6:  # vertex C
        v = 0.0; w = 1.0
    elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge AC
        den = d2 - d6
        v = 0.0; w = d2 / (den if den != 0.0 else 1.0)
    elif va <= 0.0 and e1 >= 0.0 and e2 >= 0.0:  # edge BC
        den = e1 + e2
        t = e1 / (den if den != 0.0 else 1.0)
        v = 1.0 - t; w = t
    else:  # interior
        den = va + vb + vc
        if den == 0.0:
            den = 1.0
        v = vb / den; w = vc / den
    b0 = min(max(1.0 - v - w, 0.0), 1.0)
    b1 = min(max(v, 0.0), 1.0)
    b2 = min(max(w, 0.0), 1.0)
    s = b0 + b1 + b2
    out_bary[0] = b0 / s; out_bary[1] = b1 / s; out_bary[2] = b2 / s


@kernel
def triangle_distance(p, a, b, c, out_bary):  # pragma: no cover (compiled)
    """Distance from ``p`` to triangle (a, b, c); writes its closest point's barycentric coordinates
    to ``out_bary``."""
    _closest_on_triangle(p, a, b, c, out_bary)
    d = 0.0
    for e in range(3):
        x = out_bary[0] * a[e] + out_bary[1] * b[e] + out_bary[2] * c[e] - p[e]
        d += x * x
    return math.sqrt(d)


@kernel
def cell_range(p, lim, lo, h, dims):  # pragma: no cover (compiled)
    """First and last cell index per axis of the box ``p +- lim`` (clipped to the grid;
    an axis with ``ilo > ihi`` means the box misses the grid)."""
    ilo = np.empty(3, np.int64)
    ihi = np.empty(3, np.int64)
    for d in range(3):
        ilo[d] = max(int(math.floor((p[d] - lim - lo[d]) / h)), 0)
        ihi[d] = min(int(math.floor((p[d] + lim - lo[d]) / h)), dims[d] - 1)
    return ilo, ihi


@kernel
def nearest_sample(p, lo, h, dims, start, items, spts):  # pragma: no cover (compiled)
    """Distance from ``p`` to its nearest sample (inf without samples): rings of cells
    around p's (clamped) cell until the ring's distance bound passes the best."""
    ci = np.empty(3, np.int64)
    for d in range(3):
        ci[d] = min(max(int(math.floor((p[d] - lo[d]) / h)), 0), dims[d] - 1)
    # distance from p to the grid's box: every cell is at least this far
    box = 0.0
    for d in range(3):
        o = max(lo[d] - p[d], p[d] - (lo[d] + dims[d] * h), 0.0)
        box += o * o
    box = math.sqrt(box)
    best2 = np.inf
    rmax = max(dims[0], max(dims[1], dims[2]))
    for R in range(rmax + 1):
        if R >= 1:
            bound = max((R - 1) * h, box)
            if bound * bound > best2:
                break
        for i in range(ci[0] - R, ci[0] + R + 1):
            if i < 0 or i >= dims[0]:
                continue
            for j in range(ci[1] - R, ci[1] + R + 1):
                if j < 0 or j >= dims[1]:
                    continue
                on_shell_ij = abs(i - ci[0]) == R or abs(j - ci[1]) == R
                for k in range(ci[2] - R, ci[2] + R + 1):
                    if k < 0 or k >= dims[2]:
                        continue
                    if not on_shell_ij and abs(k - ci[2]) != R:
                        continue
                    c = (i * dims[1] + j) * dims[2] + k
                    for q in range(start[c], start[c + 1]):
                        s = items[q]
                        dx = spts[s, 0] - p[0]; dy = spts[s, 1] - p[1]; dz = spts[s, 2] - p[2]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best2:
                            best2 = d2
    return math.sqrt(best2)


@kernel
def closest_one(p, r, md, use_u, surf, D, fcols, fv, done, Y, bary_out, point_out):  # pragma: no cover
    """Closest point of the (deformed) surface to ``p`` within ``r``: (triangle, distance),
    (-1, inf) if none; writes ``bary_out`` and ``point_out``. ``done``/``Y`` cache the
    deformed positions of the vertices met so far (the forces are those of the call)."""
    lo, h, dims, start, items, spts, owner, sr, X, T = surf
    d0 = nearest_sample(p, lo, h, dims, start, items, spts)
    if d0 - sr - md > r:
        return -1, np.inf
    lim = min(r, d0 + md) + md + sr
    lim2 = lim * lim
    ilo, ihi = cell_range(p, lim, lo, h, dims)
    corner = np.empty((3, 3))
    bc = np.empty(3)
    best = np.inf
    best_sd = np.inf
    best_t = -1
    ncol = fcols.shape[0]
    for ci in range(ilo[0], ihi[0] + 1):
        for cj in range(ilo[1], ihi[1] + 1):
            for ck in range(ilo[2], ihi[2] + 1):
                c = (ci * dims[1] + cj) * dims[2] + ck
                for q in range(start[c], start[c + 1]):
                    s = items[q]
                    dx = spts[s, 0] - p[0]; dy = spts[s, 1] - p[1]; dz = spts[s, 2] - p[2]
                    sd = dx * dx + dy * dy + dz * dz
                    if sd > lim2:
                        continue
                    t = owner[s]
                    for m in range(3):
                        v = T[t, m]
                        if use_u:
                            if not done[v]:
                                # the vertex's displacement under the current forces (its
                                # three rows are adjacent in each column of D)
                                u0 = 0.0; u1 = 0.0; u2 = 0.0
                                for j in range(ncol):
                                    col = fcols[j]
                                    u0 += d_entry(D, 3 * v, col) * fv[j]
                                    u1 += d_entry(D, 3 * v + 1, col) * fv[j]
                                    u2 += d_entry(D, 3 * v + 2, col) * fv[j]
                                Y[v, 0] = X[v, 0] + u0; Y[v, 1] = X[v, 1] + u1; Y[v, 2] = X[v, 2] + u2
                                done[v] = True
                            for e in range(3):
                                corner[m, e] = Y[v, e]
                        else:
                            for e in range(3):
                                corner[m, e] = X[v, e]
                    _closest_on_triangle(p, corner[0], corner[1], corner[2], bc)
                    d2 = 0.0
                    for e in range(3):
                        x = bc[0] * corner[0, e] + bc[1] * corner[1, e] + bc[2] * corner[2, e]
                        d2 += (p[e] - x) * (p[e] - x)
                    dd = math.sqrt(d2)
                    # ties (a shared edge or vertex): the triangle of the nearer sample, as the
                    # reference's k-d order
                    if dd < best or (dd == best and sd < best_sd):
                        best = dd
                        best_sd = sd
                        best_t = t
                        for e in range(3):
                            bary_out[e] = bc[e]
                            point_out[e] = bc[0] * corner[0, e] + bc[1] * corner[1, e] + bc[2] * corner[2, e]
    if best_t < 0 or best > r:
        for e in range(3):
            bary_out[e] = 0.0
            point_out[e] = np.nan
        return -1, np.inf
    return best_t, best


@kernel
def _closest_points(pts, reach, md, use_u, surf, D, fcols, fv):  # pragma: no cover (compiled)
    k = pts.shape[0]
    out_tri = np.full(k, -1, np.int64)
    out_bary = np.zeros((k, 3))
    out_pt = np.full((k, 3), np.nan)
    out_d = np.full(k, np.inf)
    nv = surf[8].shape[0]
    done = np.zeros(nv if use_u else 0, np.bool_)
    Y = np.empty((nv if use_u else 0, 3))
    for i in range(k):
        t, d = closest_one(pts[i], reach[i], md, use_u, surf, D, fcols, fv, done, Y, out_bary[i], out_pt[i])
        out_tri[i] = t
        out_d[i] = d
    return out_tri, out_bary, out_pt, out_d


def surface_arrays(grid: SampleGrid, sample_radius: float, vertices: np.ndarray, triangles: np.ndarray) -> tuple:
    """The surface as the kernels take it (a tuple of arrays)."""
    return (grid.lo, grid.h, grid.dims, grid.start, grid.items, grid.points, grid.owner, float(sample_radius),
            np.ascontiguousarray(vertices, dtype=np.float64), np.ascontiguousarray(triangles, dtype=np.int64))


#: a stand-in for D when none is given: (2, 2) so that it is only F-contiguous, as a
#: column-major D (a (1, 1) array is also C-contiguous: another compiled specialisation)
_NO_D = np.zeros((2, 2), order="F")


def closest_points(
    grid: SampleGrid,
    sample_radius: float,
    vertices: np.ndarray,
    triangles: np.ndarray,
    points: np.ndarray,
    reach: np.ndarray,
    *,
    D: np.ndarray | None = None,
    cols: np.ndarray | None = None,
    forces: np.ndarray | None = None,
    max_displacement: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of the (deformed) surface to ``points``, within ``reach``.

    Candidates from the nearest sample's bound, then exact point-triangle distances.
    The surface is deformed by ``u = D[:, cols] @ forces`` (evaluated only at
    candidate vertices) when ``forces`` is given.

    Parameters
    ----------
    grid : SampleGrid
        The surface's samples (``SurfaceIndex.grid``).
    sample_radius : float
        Every point of a triangle lies within this of one of its samples [m].
    vertices : (n, 3) ndarray
        Undeformed surface vertices.
    triangles : (m, 3) int ndarray
    points : (k, 3) ndarray
    reach : (k,) ndarray
        Search radius per point [m].
    D : (3n, c) ndarray or tuple, optional
        Compliance columns (vertex-major rows), or a compressed D's
        :attr:`~hailstorm.runtime.bundle.hmatrix.HMatrix.kernel_arrays` (read through
        :func:`~hailstorm.runtime.compiled.hblocks.d_entry`), and ``cols``, ``forces``: the
        loaded columns and their forces.
    max_displacement : float
        Upper bound of ``|u|`` over the surface [m].

    Returns
    -------
    triangle : (k,) int64 ndarray
        -1 where nothing lies within reach.
    bary : (k, 3) ndarray
    point : (k, 3) ndarray
        NaN where nothing lies within reach.
    distance : (k,) ndarray
        inf where nothing lies within reach.
    """
    use_u = forces is not None and D is not None and cols is not None
    if not use_u:
        # (a D given without forces is passed on unused: the same compiled specialisation)
        D, cols, forces = (_NO_D if D is None else D), np.zeros(0, np.int64), np.zeros(0)
    assert D is not None and cols is not None and forces is not None
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return _closest_points(
        pts, np.ascontiguousarray(np.broadcast_to(np.asarray(reach, dtype=np.float64), (pts.shape[0],))),
        float(max_displacement) if use_u else 0.0, use_u, surface_arrays(grid, sample_radius, vertices, triangles),
        D, np.asarray(cols, dtype=np.int64), np.asarray(forces, dtype=np.float64))
