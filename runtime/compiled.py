"""Optional compiled kernels (numba) for the storm's per-step geometry.

The storm's narrow phase runs hundreds of tiny numpy calls per step; their
per-call overhead, not arithmetic, is what a step costs. The kernels here do
the same work in compiled loops, when `numba <https://numba.pydata.org>`_ is
installed (``pip install "hailstorm[fast]"``). Without numba nothing here is
used and the runtime stays numpy/scipy only; the numpy code paths
(:meth:`runtime.collide.SurfaceIndex.query`, ``Storm._near_set``) are the
reference the tests hold these kernels to.

* :class:`SampleGrid` — a uniform grid over the surface's sample points (the
  same samples as :class:`runtime.collide.SurfaceIndex`'s k-d tree), for
  queries that run inside compiled code;
* :func:`closest_points` — closest points of the (deformed) surface within a
  reach, as ``SurfaceIndex.query``;
* :func:`near_set` — the storm's conservative-advancement broad phase.

The kernels are compiled on first use and cached on disk (``cache=True``,
beside this file's bytecode), so only the first run after an install pays
the compilation (a few seconds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from runtime.hail import _scalar_exact as _hail_scalar_exact

__all__ = ["HAVE_NUMBA", "SampleGrid", "closest_points", "near_set", "resolve_backend"]

try:  # pragma: no cover - exercised by whichever of the two environments runs the tests
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False


def _njit(f: Callable) -> Any:
    """``numba.njit(cache=True)`` when numba is installed, else the plain function
    (never called then: the storm takes the numpy path)."""
    return numba.njit(cache=True, nogil=True)(f) if HAVE_NUMBA else f


def resolve_backend(backend: str) -> str:
    """The backend a storm runs on: ``"numba"`` or ``"numpy"``.

    Parameters
    ----------
    backend : {"auto", "numba", "numpy"}
        ``"auto"`` takes numba when it is installed.

    Raises
    ------
    ValueError
        ``"numba"`` asked for but numba is not installed, or an unknown name.
    """
    if backend == "auto":
        return "numba" if HAVE_NUMBA else "numpy"
    if backend == "numba" and not HAVE_NUMBA:
        raise ValueError('backend "numba" needs numba: pip install "hailstorm[fast]" (or use backend "auto")')
    if backend not in ("numba", "numpy"):
        raise ValueError(f'backend must be "auto", "numba" or "numpy", not {backend!r}')
    return backend


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


# -- kernels ------------------------------------------------------------------------
@_njit
def _closest_on_triangle(p, a, b, c, out_bary):  # pragma: no cover (compiled)
    """Closest point of triangle (a, b, c) to p (Ericson 5.1.5, as the numpy reference):
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


@_njit
def _cell_range(p, lim, lo, h, dims):  # pragma: no cover (compiled)
    """First and last cell index per axis of the box ``p +- lim`` (clipped to the grid;
    an axis with ``ilo > ihi`` means the box misses the grid)."""
    ilo = np.empty(3, np.int64)
    ihi = np.empty(3, np.int64)
    for d in range(3):
        ilo[d] = max(int(math.floor((p[d] - lim - lo[d]) / h)), 0)
        ihi[d] = min(int(math.floor((p[d] + lim - lo[d]) / h)), dims[d] - 1)
    return ilo, ihi


@_njit
def _nearest_sample(p, lo, h, dims, start, items, spts):  # pragma: no cover (compiled)
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


@_njit
def _closest_one(p, r, md, use_u, surf, D, fcols, fv, done, Y, bary_out, point_out):  # pragma: no cover
    """Closest point of the (deformed) surface to ``p`` within ``r``: (triangle, distance),
    (-1, inf) if none; writes ``bary_out`` and ``point_out``. ``done``/``Y`` cache the
    deformed positions of the vertices met so far (the forces are those of the call)."""
    lo, h, dims, start, items, spts, owner, sr, X, T = surf
    d0 = _nearest_sample(p, lo, h, dims, start, items, spts)
    if d0 - sr - md > r:
        return -1, np.inf
    lim = min(r, d0 + md) + md + sr
    lim2 = lim * lim
    ilo, ihi = _cell_range(p, lim, lo, h, dims)
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
                                    u0 += D[3 * v, col] * fv[j]
                                    u1 += D[3 * v + 1, col] * fv[j]
                                    u2 += D[3 * v + 2, col] * fv[j]
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


@_njit
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
        t, d = _closest_one(pts[i], reach[i], md, use_u, surf, D, fcols, fv, done, Y, out_bary[i], out_pt[i])
        out_tri[i] = t
        out_d[i] = d
    return out_tri, out_bary, out_pt, out_d


def _surface(grid: SampleGrid, sample_radius: float, vertices: np.ndarray, triangles: np.ndarray) -> tuple:
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

    The compiled counterpart of :meth:`runtime.collide.SurfaceIndex.query`:
    the same candidate bound and the same exact point-triangle distances.
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
    D : (3n, c) ndarray, optional
        Compliance columns (vertex-major rows) and ``cols``, ``forces``: the
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
        float(max_displacement) if use_u else 0.0, use_u, _surface(grid, sample_radius, vertices, triangles),
        D, np.asarray(cols, dtype=np.int64), np.asarray(forces, dtype=np.float64))


@_njit
def _near_set(live, pos, vel, radius, ctri, budget, bud_u, U, dt, g, lo, hi, sr,
              glo, h, dims, start, items, spts):  # pragma: no cover (compiled)
    n = live.size
    near = np.zeros(n, np.bool_)
    for q in range(n):
        i = live[q]
        sp = math.sqrt(vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1] + vel[i, 2] * vel[i, 2])
        travel = sp * dt + g * dt * dt + 1e-4
        inc = U - bud_u[i]
        if inc > 0.0:
            budget[i] -= inc
            bud_u[i] = U
        if ctri[i] >= 0:
            budget[i] = -np.inf
            near[q] = True
            continue
        if budget[i] <= travel:
            o2 = 0.0
            for d in range(3):
                o = max(max(lo[d] - pos[i, d], pos[i, d] - hi[d]), 0.0)
                o2 += o * o
            lb = math.sqrt(o2) - sr - radius[i] - U - 1e-4
            if lb <= travel:
                d0 = _nearest_sample(pos[i], glo, h, dims, start, items, spts)
                lb = d0 - sr - radius[i] - U - 1e-4
            budget[i] = lb
            bud_u[i] = U
        if budget[i] <= travel:
            near[q] = True
        else:
            budget[i] -= travel
    return near


def near_set(grid: SampleGrid, sample_radius: float, bbox: tuple[np.ndarray, np.ndarray], live: np.ndarray,
             pos: np.ndarray, vel: np.ndarray, radius: np.ndarray, ctri: np.ndarray, budget: np.ndarray,
             bud_u: np.ndarray, U: float, dt: float, gravity: float) -> np.ndarray:
    """The storm's broad phase (compiled ``Storm._near_set``): mask of the ``live``
    stones that may touch the seat within ``dt``. Updates ``budget`` and ``bud_u``
    in place (see ``Storm._near_set`` for the budget rule)."""
    return _near_set(live, pos, vel, radius, ctri, budget, bud_u, float(U), float(dt), float(gravity),
                     bbox[0], bbox[1], float(sample_radius), grid.lo, grid.h, grid.dims, grid.start,
                     grid.items, grid.points)



# -- patch weights ------------------------------------------------------------------
@_njit
def _one_patch(x, n, a, h, qx, qy, qw, facing, drop, pidx):  # pragma: no cover (compiled)
    """Compiled ``runtime.weights._one_patch``: (vertices, weights) of one patch, both
    empty if the disc hits no usable triangle. ``pidx``: :func:`runtime.weights._patch_index_arrays`."""
    glo, gh, gdims, gstart, gitems, cent, radii, tnorm, p0, e1, e2, reach, tris, T, nv = pidx
    tol = 1e-12 * max(a, 1.0)
    lim = a + reach + tol
    # candidate triangles: centroid within a + reach (grid), then within a + own radius, facing n
    nc = 0
    cand = np.empty(cent.shape[0], np.int64)
    ilo, ihi = _cell_range(x, lim, glo, gh, gdims)
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
    cand = np.sort(cand[:nc])
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
    # tangents of the disc, as runtime.weights._tangents
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
    V = np.sort(tlist[:ntouch])
    w = wv[V]
    keep = w > drop * w.max()
    V = V[keep]
    w = w[keep]
    return V, w / w.sum()


# -- flight and contact blocks --------------------------------------------------------
@_njit
def flight(idx, pos, vel, radius, h, g, wind, drag_coef):  # pragma: no cover (compiled)
    """Free flight of stones ``idx`` over ``h``, in place: gravity ``g`` [m/s^2] plus,
    if ``drag_coef > 0``, quadratic drag ``-(drag_coef / r) |v - wind| (v - wind)``
    (``drag_coef = 3 C_d rho_air / (8 rho_ice)``), taken constant over the step as
    :func:`runtime.hail.free_flight` does."""
    a = np.empty(3)
    for q in range(idx.size):
        i = idx[q]
        a[0] = 0.0; a[1] = 0.0; a[2] = -g
        if drag_coef > 0.0:
            w0 = vel[i, 0] - wind[0]; w1 = vel[i, 1] - wind[1]; w2 = vel[i, 2] - wind[2]
            c = drag_coef / radius[i] * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            a[0] -= c * w0; a[1] -= c * w1; a[2] -= c * w2
        for d in range(3):
            pos[i, d] += h * vel[i, d] + 0.5 * h * h * a[d]
            vel[i, d] += h * a[d]


@_njit
def _dvv(V, D, column_of):  # pragma: no cover (compiled)
    """D_VV (3|V|, 3|V|), zero columns at clamped vertices."""
    nV = V.size
    out = np.zeros((3 * nV, 3 * nV))
    for j in range(nV):
        cb = column_of[V[j]]
        if cb < 0:
            continue
        for e in range(3):
            col = 3 * cb + e
            for i in range(nV):
                for d in range(3):
                    out[3 * i + d, 3 * j + e] = D[3 * V[i] + d, col]
    return out


@_njit
def rigid_contacts(verts, w, fixed):  # pragma: no cover (compiled)
    """True if some contact's weight lies entirely on clamped vertices
    (``runtime.contact_capacitance._rigid``, any)."""
    for k in range(verts.shape[0]):
        free_w = 0.0
        for p in range(verts.shape[1]):
            if not fixed[verts[k, p]]:
                free_w += abs(w[k, p])
        if free_w <= 1e-12:
            return True
    return False


@_njit
def retired(live, pos, radius, lo, hi, margin):  # pragma: no cover (compiled)
    """Mask of the ``live`` stones that left the seat's region (compiled rule of
    ``Storm.step``): below the seat by ``margin``, or beyond its footprint grown by
    ``2 margin + r`` while below its top."""
    out = np.zeros(live.size, np.bool_)
    for q in range(live.size):
        i = live[q]
        r = radius[i]
        outside = False
        for d in range(2):
            if pos[i, d] < lo[d] - 2.0 * margin - r or pos[i, d] > hi[d] + 2.0 * margin + r:
                outside = True
        out[q] = pos[i, 2] < lo[2] - margin or (outside and pos[i, 2] < hi[2])
    return out


@_njit
def capacitance_blocks(verts, w, normals, sticky, D, column_of):  # pragma: no cover (compiled)
    """The dense blocks of a contact set (the storm's ``_build_cache``) in one pass.

    Parameters
    ----------
    verts, w : (s, P) int / float ndarrays
        Vertices carrying each contact's force and their weights (padding: weight 0).
    normals : (s, 3) ndarray
    sticky : bool
        Three multipliers per contact (``G = B``) or one normal multiplier (``G = B N``).
    D : (3n, c) ndarray
        The compliance; ``column_of`` (n,): D's column block of each vertex (-1 clamped).

    Returns
    -------
    V : (|V|,) int64 ndarray
        The sorted union of ``verts``.
    W : (m, m) ndarray
        ``G^T D_VV G``, symmetrised (m = 3s sticky, s frictionless).
    G : (c, m) ndarray
        Vertex forces per unit multiplier at the ``c`` loaded dofs of V (vertices
        with a column of D, vertex-major).
    cols : (c,) int64 ndarray
        Their columns of D.
    DG : (3|V|, m) ndarray
        ``D_VV G``: displacement of V per unit multiplier.
    """
    s, P = verts.shape
    nv_all = column_of.size
    pos = np.full(nv_all, -1, np.int64)
    lst = np.empty(s * P, np.int64)
    nV = 0
    for k in range(s):
        for p in range(P):
            v = verts[k, p]
            if pos[v] < 0:
                pos[v] = 0
                lst[nV] = v
                nV += 1
    V = np.sort(lst[:nV])
    for i in range(nV):
        pos[V[i]] = i
    m = 3 * s if sticky else s
    G = np.zeros((3 * nV, m))
    for k in range(s):
        for p in range(P):
            i = pos[verts[k, p]]
            if sticky:
                for d in range(3):
                    G[3 * i + d, 3 * k + d] += w[k, p]
            else:
                for d in range(3):
                    G[3 * i + d, k] += w[k, p] * normals[k, d]
    DG = _dvv(V, D, column_of) @ G
    W = G.T @ DG
    W = 0.5 * (W + W.T)
    # the loaded dofs (vertices with a column of D) and their columns
    nl = 0
    for i in range(nV):
        if column_of[V[i]] >= 0:
            nl += 1
    cols = np.empty(3 * nl, np.int64)
    Gl = np.empty((3 * nl, m))
    r = 0
    for i in range(nV):
        cb = column_of[V[i]]
        if cb < 0:
            continue
        for d in range(3):
            cols[r] = 3 * cb + d
            Gl[r] = G[3 * i + d]
            r += 1
    return V, W, Gl, cols, DG


@_njit
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
                acc += w[i] * (D[r, col] * normal[0] + D[r + 1, col] * normal[1] + D[r + 2, col] * normal[2])
            c += gj * acc
    return c


# -- the storm's sub-step, free part ------------------------------------------------------
@_njit
def _drag_dot(i, vel, radius, nrm, g, wind, drag_coef):  # pragma: no cover (compiled)
    """``accel . nrm`` of stone i in flight (gravity + drag)."""
    a0 = 0.0; a1 = 0.0; a2 = -g
    if drag_coef > 0.0:
        w0 = vel[i, 0] - wind[0]; w1 = vel[i, 1] - wind[1]; w2 = vel[i, 2] - wind[2]
        c = drag_coef / radius[i] * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        a0 -= c * w0; a1 -= c * w1; a2 -= c * w2
    return a0 * nrm[0] + a1 * nrm[1] + a2 * nrm[2]


@_njit
def _unit(x, out):  # pragma: no cover (compiled)
    ln = max(math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]), 1e-300)
    for e in range(3):
        out[e] = x[e] / ln
    return ln


@_njit
def free_phase(near, h, toi, toi_tol, hmin, pos, vel, radius, ctri, cbary, gap, near_tri, surf, tri_normals,
               soft, fixed, umax, use_u, D, fcols, fv, g, wind, drag_coef, restitution):  # pragma: no cover
    """The first phases of one storm sub-step for the near stones, in place (compiled
    ``Storm._proximity``, ``_time_of_impact``, ``_contacts_to_open``, ``_open_contacts``
    and ``_hard_walls``; see those for the rules).

    Stones without a contact query the deformed surface; an open contact keeps its
    ``(t, beta)`` while its stone stays over the triangle, else moves to the closest
    point of the undeformed surface. With ``toi`` the sub-step ends when the first
    approaching stone reaches the tangent plane at its closest point; contacts open
    within ``toi_tol`` radii (approaching or overlapping), the stone put on the
    surface; contacts on hard triangles (or on the clamped edge or corner of a soft
    one) bounce at once.

    Returns
    -------
    h : float
        The sub-step actually taken.
    walls : int
        Impacts on hard triangles.
    """
    X = surf[8]
    T = surf[9]
    k = near.size
    nv = X.shape[0]
    done = np.zeros(nv if use_u else 0, np.bool_)
    Y = np.empty((nv if use_u else 0, 3))
    done0 = np.zeros(0, np.bool_)
    Y0 = np.empty((0, 3))
    in_contact = np.zeros(k, np.bool_)
    dist = np.full(k, np.inf)
    tri = np.full(k, -1, np.int64)
    bary = np.zeros((k, 3))
    point = np.full((k, 3), np.nan)
    gp = np.zeros(k)
    nrm = np.empty(3)
    dvec = np.empty(3)
    queried = False
    for j in range(k):
        i = near[j]
        if ctri[i] >= 0:
            in_contact[j] = True
            # does the centre still project onto the contact triangle (undeformed)?
            t = ctri[i]
            n0 = tri_normals[t, 0]; n1 = tri_normals[t, 1]; n2 = tri_normals[t, 2]
            a = T[t, 0]; b = T[t, 1]; c = T[t, 2]
            v00 = X[b, 0] - X[a, 0]; v01 = X[b, 1] - X[a, 1]; v02 = X[b, 2] - X[a, 2]
            v10 = X[c, 0] - X[a, 0]; v11 = X[c, 1] - X[a, 1]; v12 = X[c, 2] - X[a, 2]
            w0 = pos[i, 0] - X[a, 0]; w1 = pos[i, 1] - X[a, 1]; w2 = pos[i, 2] - X[a, 2]
            wn = w0 * n0 + w1 * n1 + w2 * n2
            w0 -= wn * n0; w1 -= wn * n1; w2 -= wn * n2
            d00 = v00 * v00 + v01 * v01 + v02 * v02
            d01 = v00 * v10 + v01 * v11 + v02 * v12
            d11 = v10 * v10 + v11 * v11 + v12 * v12
            d20 = w0 * v00 + w1 * v01 + w2 * v02
            d21 = w0 * v10 + w1 * v11 + w2 * v12
            den = d00 * d11 - d01 * d01
            b1 = (d11 * d20 - d01 * d21) / den
            b2 = (d00 * d21 - d01 * d20) / den
            if not (b1 >= -1e-3 and b2 >= -1e-3 and b1 + b2 <= 1.0 + 1e-3):
                # slid off: the closest point of the undeformed surface (the contact stays open)
                tt, dd = _closest_one(pos[i], 2.0 * radius[i] + umax + 1e-3, 0.0, False, surf, D, fcols, fv,
                                      done0, Y0, bary[j], point[j])
                ctri[i] = tt
                if tt >= 0:
                    for e in range(3):
                        cbary[i, e] = bary[j, e]
                tri[j] = tt
                dist[j] = dd
        else:
            queried = True
            sp = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
            tt, dd = _closest_one(pos[i], radius[i] + sp * h + 1e-3, umax if use_u else 0.0, use_u, surf, D,
                                  fcols, fv, done, Y, bary[j], point[j])
            tri[j] = tt
            dist[j] = dd
            near_tri[i] = tt
            gp[j] = dd - radius[i]
        gap[i] = gp[j]
    timing = toi and queried
    # time of impact: the first approaching stone to reach its tangent plane
    if timing:
        tmin = np.inf
        for j in range(k):
            i = near[j]
            if in_contact[j] or not np.isfinite(gp[j]) or not gp[j] > toi_tol * radius[i]:
                continue
            for e in range(3):
                dvec[e] = pos[i, e] - point[j, e]
            _unit(dvec, nrm)
            w = -(vel[i, 0] * nrm[0] + vel[i, 1] * nrm[1] + vel[i, 2] * nrm[2])
            an = -_drag_dot(i, vel, radius, nrm, g, wind, drag_coef)
            if w > 0.0 and gp[j] < w * h + 0.5 * abs(an) * h * h:
                disc = math.sqrt(max(w * w + 2.0 * an * gp[j], 0.0))
                tmin = min(tmin, 2.0 * gp[j] / max(w + disc, 1e-12))
        if tmin < np.inf:
            h = min(h, max(tmin, hmin))
    # contacts that open, at their closest points
    for j in range(k):
        i = near[j]
        if in_contact[j] or tri[j] < 0:
            continue
        eps = toi_tol * radius[i]
        if timing:
            if not gp[j] < eps:
                continue
            for e in range(3):
                dvec[e] = pos[i, e] - point[j, e]
            _unit(dvec, nrm)
            vn = vel[i, 0] * nrm[0] + vel[i, 1] * nrm[1] + vel[i, 2] * nrm[2]
            if not (vn < 0.0 or gp[j] < -eps):
                continue
        elif not dist[j] < radius[i]:
            continue
        t = tri[j]
        ctri[i] = t
        for e in range(3):
            cbary[i, e] = bary[j, e]
        if timing:
            for e in range(3):
                pos[i, e] -= gp[j] * tri_normals[t, e]
        else:
            vn = vel[i, 0] * tri_normals[t, 0] + vel[i, 1] * tri_normals[t, 1] + vel[i, 2] * tri_normals[t, 2]
            if vn < 0.0:
                depth = max(-gp[j], 0.0)
                for e in range(3):
                    pos[i, e] += depth * tri_normals[t, e]
    # hard walls: out of the wall, restitution bounce, the contact closes
    walls = 0
    for j in range(k):
        i = near[j]
        t = ctri[i]
        if t < 0:
            continue
        if soft[t]:
            free_w = 0.0
            for m in range(3):
                if not fixed[T[t, m]]:
                    free_w += cbary[i, m]
            if free_w > 1e-12:
                continue
        for e in range(3):
            dvec[e] = pos[i, e] - point[j, e]
        dw = math.sqrt(dvec[0] ** 2 + dvec[1] ** 2 + dvec[2] ** 2)
        if dw > 1e-12:
            for e in range(3):
                nrm[e] = dvec[e] / dw
        else:
            for e in range(3):
                nrm[e] = tri_normals[t, e]
        push = max(radius[i] - dw, 0.0)
        vn = vel[i, 0] * nrm[0] + vel[i, 1] * nrm[1] + vel[i, 2] * nrm[2]
        if vn < 0.0:
            walls += 1
        for e in range(3):
            pos[i, e] += push * nrm[e]
            vel[i, e] -= (1.0 + restitution) * min(vn, 0.0) * nrm[e]
        ctri[i] = -1
    return h, walls


@_njit
def patch_one(t, bary, a, n, resolution, rule_off, rule_x, rule_y, rule_w, facing, drop,
              pidx, X):  # pragma: no cover (compiled)
    """Weights of one patch contact on triangle ``t`` at ``bary`` with radius ``a`` and
    normal ``n`` (``runtime.weights.patch_weights`` for one contact, positive weights
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
        V, w = _one_patch(x, n, a, h, rule_x[o0:o1], rule_y[o0:o1], rule_w[o0:o1], facing, drop, pidx)
        if V.size:
            keep = w > 0.0
            return V[keep], w[keep]
    V = np.empty(3, np.int64)
    w = np.empty(3)
    k = 0
    for m in range(3):
        if bary[m] > 0.0:
            V[k] = T[t, m]
            w[k] = bary[m]
            k += 1
    return V[:k], w[:k]


# -- the storm's sub-step, contact part -----------------------------------------------
@_njit
def _hertz_target(kk, f, f_eq, m, vn, R, e_star, a_min):  # pragma: no cover (compiled)
    """Patch radius for the expected peak force ``f_eq + sqrt((f - f_eq)^2 + k m vn^2)``:
    the Hertz radius, clipped to ``[a_min, R]``, then at least ``a_min``."""
    kk = max(kk, 0.0)
    fp = f_eq + math.sqrt((f - f_eq) ** 2 + kk * m * vn * vn)
    a = np.cbrt(3.0 * abs(fp) * R / (4.0 * e_star))
    a = min(max(a, a_min), R)
    return max(a, a_min)


@_njit
def patch_radii(stones, tris, mass, radius, vel, cbary, crad, tnormals, g, wind, drag_coef, cc_stones, Kdiag,
                lam, sticky, k_tri, e_star, a_min, tol, rest_speed, rule_off, rule_x, rule_y, rule_w, facing,
                drop, pidx, X, D, column_of):  # pragma: no cover (compiled)
    """Compiled ``Storm._patch_radii`` (see there for the rule): the patch radius of
    each soft contact, written to ``crad``.

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
        n = tnormals[t]
        m = mass[j]
        R = radius[j]
        vn = vel[j, 0] * n[0] + vel[j, 1] * n[1] + vel[j, 2] * n[2]
        gn = _drag_dot(j, vel, radius, n, g, wind, drag_coef)
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
            target = _hertz_target(k, f, f_eq, m, vn, R, e_star, a_min)
            off[i + 1] = off[i]
        else:
            a0 = _hertz_target(k_tri[t], 0.0, f_eq, m, vn, R, e_star, a_min)
            V, w = patch_one(t, cbary[j], a0, n, 3.0, rule_off, rule_x, rule_y, rule_w, facing, drop, pidx, X)
            c = patch_compliance(V, w, n, D, column_of)
            a1 = _hertz_target(1.0 / c if c > 0.0 else 0.0, 0.0, f_eq, m, vn, R, e_star, a_min)
            target = a1 if (a1 > a0 * t1 or a1 * t1 < a0) else a0
            a0s[i] = a0
            wv = np.concatenate((wv, V))
            ww = np.concatenate((ww, w))
            off[i + 1] = off[i] + V.size
        cur = crad[j] if ik >= 0 else 0.0
        amp = math.sqrt((f - f_eq) ** 2 / max(max(k, 0.0) * m, 1e-300) + vn * vn)
        resting = ik >= 0 and amp < rest_speed
        if cur <= 0.0 or target > cur * t1 or (target * t1 < cur and resting):
            if cur > 0.0:
                resizes += 1
            cur = target
        crad[j] = cur
        out[i] = cur
    return out, resizes, a0s, off, wv, ww


@_njit
def contact_prep(soft, pos, vel, radius, mass, g, wind, drag_coef, nk, Xc, rest, Kdiag, sticky, exact,
                 rest_speed, zeta):  # pragma: no cover (compiled)
    """The constrained coordinates of a contact set for :func:`runtime.hail.contact_step`
    (compiled first half of ``Storm._soft_contacts``): ``(q, anchor, v, accel, mass,
    always_damped, acc, damping)``, per contact (frictionless, normal components) or
    per component (sticky); ``acc`` (s, 3) is the stones' gravity + drag; ``damping``
    the exact integrator's dashpot ``2 zeta sqrt(K_ii m_i)``
    (:func:`runtime.hail.damping_coefficients` with ``zeta`` for the scene's
    restitution)."""
    s = soft.size
    nq = 3 * s if sticky else s
    q = np.empty(nq); a = np.empty(nq); vq = np.empty(nq); gq = np.empty(nq); mq = np.empty(nq)
    always = np.zeros(nq, np.bool_)
    damping = np.zeros(nq)
    for c in range(nq):
        damping[c] = 2.0 * zeta * math.sqrt(max(Kdiag[c], 0.0) * mass[soft[c // 3 if sticky else c]])
    acc = np.empty((s, 3))
    for i in range(s):
        j = soft[i]
        acc[i, 0] = 0.0; acc[i, 1] = 0.0; acc[i, 2] = -g
        if drag_coef > 0.0:
            w0 = vel[j, 0] - wind[0]; w1 = vel[j, 1] - wind[1]; w2 = vel[j, 2] - wind[2]
            c = drag_coef / radius[j] * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            acc[i, 0] -= c * w0; acc[i, 1] -= c * w1; acc[i, 2] -= c * w2
        pn = 0.0; xn = 0.0; vn = 0.0; an = 0.0
        for d in range(3):
            pn += nk[i, d] * pos[j, d]
            xn += nk[i, d] * Xc[i, d]
            vn += nk[i, d] * vel[j, d]
            an += nk[i, d] * acc[i, d]
        if sticky:
            for d in range(3):
                q[3 * i + d] = pos[j, d]
                a[3 * i + d] = Xc[i, d] + rest[i] * nk[i, d]
                vq[3 * i + d] = vel[j, d]
                gq[3 * i + d] = acc[i, d]
                mq[3 * i + d] = mass[j]
        else:
            q[i] = pn; a[i] = xn + rest[i]; vq[i] = vn; gq[i] = an; mq[i] = mass[j]
        if exact:
            # resting (oscillation amplitude about equilibrium below rest_speed): the
            # dashpot acts both ways, no switching events
            if sticky:
                kd = max(max(max(Kdiag[3 * i], 0.0), max(Kdiag[3 * i + 1], 0.0)), max(Kdiag[3 * i + 2], 0.0))
            else:
                kd = max(Kdiag[i], 0.0)
            om = math.sqrt(kd / mass[j])
            ubar = pn - xn - rest[i]
            u_eq = an * mass[j] / max(kd, 1e-300)
            r = math.hypot(vn, om * (ubar - u_eq)) < rest_speed
            if sticky:
                for d in range(3):
                    always[3 * i + d] = r
            else:
                always[i] = r
    return q, a, vq, gq, mq, always, acc, damping


@_njit
def contact_post(soft, pos, vel, ctri, hit, was_open, nk, acc, q, a, vq, gq, rq, rv, ractive, rseat, sticky,
                 exact, h, rest_speed):  # pragma: no cover (compiled)
    """Apply a contact step to the stones, in place (compiled second half of
    ``Storm._soft_contacts``): new positions and velocities (frictionless: free
    tangential motion), released contacts closed, impacts marked.

    Returns
    -------
    impacts : int
        Contacts that opened in this sub-step, push, and came in faster than ``rest_speed``.
    max_force : float
        Largest contact force magnitude [N].
    max_indentation : float
        Largest normal contact displacement of an active contact (-inf if none) [m].
    n_active : int
    """
    s = soft.size
    impacts = 0
    fmax = 0.0
    indent = -np.inf
    n_active = 0
    for i in range(s):
        j = soft[i]
        if sticky:
            act = ractive[3 * i] and ractive[3 * i + 1] and ractive[3 * i + 2]
            f2 = rseat[3 * i] ** 2 + rseat[3 * i + 1] ** 2 + rseat[3 * i + 2] ** 2
            ubn = 0.0
            for d in range(3):
                ubn += (rq[3 * i + d] - a[3 * i + d]) * nk[i, d]
        else:
            act = ractive[i]
            f2 = rseat[i] ** 2
            ubn = rq[i] - a[i]
        fmax = max(fmax, math.sqrt(f2))
        if act:
            n_active += 1
            indent = max(indent, -ubn)
            if not was_open[i]:
                vin = vel[j, 0] * nk[i, 0] + vel[j, 1] * nk[i, 1] + vel[j, 2] * nk[i, 2]
                if vin < -rest_speed:
                    impacts += 1
                hit[j] = True
        for d in range(3):
            if sticky:
                vnew = rv[3 * i + d]
                pnew = rq[3 * i + d]
            else:
                vt0 = vel[j, d] - vq[i] * nk[i, d]
                at = acc[i, d] - gq[i] * nk[i, d]
                vnew = vt0 + h * at + rv[i] * nk[i, d]
                pnew = pos[j, d] - q[i] * nk[i, d] + h * vt0 + 0.5 * h * h * at + rq[i] * nk[i, d]
            if not exact:
                pnew = pos[j, d] + h * vnew  # (semi-)implicit position update
            vel[j, d] = vnew
            pos[j, d] = pnew
        if not act:
            ctri[j] = -1
    return impacts, fmax, indent, n_active


@_njit
def penetration(near, dt, pos, vel, radius, ctri, surf, umax, use_u, D, fcols, fv):  # pragma: no cover
    """Overlap of the near stones with the deformed surface, for the statistics
    (compiled ``Storm._step_query``): free stones within this step's reach, stones in
    contact within their radius.

    Returns
    -------
    max_pen, max_pen_contact, max_rel_contact, sum_contact, n_contact, max_pen_free
        Largest overlap [m] of any near stone, of a stone in contact (also relative to
        its radius, and the sum of the non-negative overlaps over the ``n_contact``
        stones in contact within reach), and of a free stone; ``-inf`` where none.
    """
    X = surf[8]
    nv = X.shape[0]
    done = np.zeros(nv if use_u else 0, np.bool_)
    Y = np.empty((nv if use_u else 0, 3))
    bary = np.empty(3)
    point = np.empty(3)
    mp = -np.inf; mpc = -np.inf; mrc = -np.inf; spc = 0.0; npc = 0; mpf = -np.inf
    for q in range(near.size):
        i = near[q]
        free = ctri[i] < 0
        reach = radius[i]
        if free:
            sp = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
            reach += sp * dt + 1e-3
        t, d = _closest_one(pos[i], reach, umax if use_u else 0.0, use_u, surf, D, fcols, fv, done, Y, bary, point)
        if t < 0:
            continue
        pen = radius[i] - d
        mp = max(mp, pen)
        if free:
            mpf = max(mpf, pen)
        else:
            mpc = max(mpc, pen)
            mrc = max(mrc, pen / radius[i])
            spc += max(pen, 0.0)
            npc += 1
    return mp, mpc, mrc, spc, npc, mpf


# -- the exact (modal) contact integrator -----------------------------------------------
#: the closed-form single contact of the exact integrator: runtime.hail's own function, compiled
_scalar_exact = _njit(_hail_scalar_exact)


@_njit
def inv_spd(W):  # pragma: no cover (compiled)
    """Inverse of a small symmetric positive (semi-)definite matrix (Cholesky, else the
    pseudo-inverse), as ``runtime.hail._inv_spd``."""
    n = W.shape[0]
    if n == 0:
        return np.zeros((0, 0))
    Ws = 0.5 * (W + W.T)
    try:
        L = np.linalg.cholesky(Ws)
        Li = np.linalg.inv(L)
        return np.ascontiguousarray(Li.T @ Li)
    except Exception:
        return np.ascontiguousarray(np.linalg.pinv(Ws, rcond=1e-10))


@_njit
def _gsum(x, group, wts, ng, ident):  # pragma: no cover (compiled)
    """Normal sums per contact group of per-component rows ``x`` (n, T) -> (ng, T)."""
    if ident:
        return x.copy()
    out = np.zeros((ng, x.shape[1]))
    for i in range(x.shape[0]):
        out[group[i]] += wts[i] * x[i]
    return out


@_njit
def _sub(M, idx):  # pragma: no cover (compiled)
    out = np.empty((idx.size, idx.size))
    for r in range(idx.size):
        for c in range(idx.size):
            out[r, c] = M[idx[r], idx[c]]
    return out


@_njit
def _modal(Ka, ma, ce):  # pragma: no cover (compiled)
    """Eigen-decomposition of ``z' = A z`` for ``M y'' + C y' + K y = 0``: (lam, V, Vi, ok);
    ``ok`` False for a (nearly) defective system (the numpy path then uses expm)."""
    n = ma.size
    A = np.zeros((2 * n, 2 * n), np.complex128)
    for i in range(n):
        A[i, n + i] = 1.0
        for j in range(n):
            A[n + i, j] = -Ka[i, j] / ma[i]
        A[n + i, n + i] = -ce[i] / ma[i]
    lam, V = np.linalg.eig(A)
    try:
        Vi = np.linalg.inv(V)
    except Exception:
        return lam, V, V, False
    ok = np.all(np.isfinite(Vi.real)) and np.all(np.isfinite(Vi.imag)) and np.abs(V).max() * np.abs(Vi).max() < 1e7
    return lam, V, Vi, ok


@_njit
def _modal_at(lam, V, Vi, z0, tau):  # pragma: no cover (compiled)
    """States (2n, len(tau)) at times ``tau`` from ``z0``."""
    c = Vi @ z0.astype(np.complex128)
    E = np.empty((lam.size, tau.size), np.complex128)
    for i in range(lam.size):
        for j in range(tau.size):
            E[i, j] = np.exp(lam[i] * tau[j]) * c[i]
    return (V @ E).real


@_njit
def exact_step(q, v, a, m, g, dt, K, W, Cn, unilateral, group, wts, always):  # pragma: no cover (compiled)
    """Compiled ``runtime.hail._exact_step`` (the exact integrator's step; see there).

    Returns ``(q, v, active, force, seat_force, ok)``; ``ok`` is False in the rare
    cases the compiled version does not cover (a nearly defective modal basis, an
    overdamped single contact): the caller then runs the numpy version.
    """
    GRID = 32
    REFINE = 2
    MAX_SEGMENTS = 12
    n = q.size
    ng = 0
    for i in range(n):
        ng = max(ng, group[i] + 1)
    v0 = v.copy()
    q = q.copy()
    v = v.copy()
    active = np.ones(n, np.bool_)
    if n == 1 and group[0] == 0 and wts[0] == 1.0:
        k = K[0, 0]
        qn, vn, act, ok = _scalar_exact(q[0], v[0], a[0], m[0], g[0], dt, k, Cn[0], unilateral, always[0])
        if ok:
            q[0] = qn
            v[0] = vn
            active[0] = act
            force = np.zeros(1)
            seat = np.zeros(1)
            if act:
                force[0] = m[0] * ((vn - v0[0]) / dt - g[0])
                seat[0] = k * (qn - a[0])
            return q, v, active, force, seat, True
    ident = ng == n
    for i in range(n):
        if group[i] != i or wts[i] != 1.0:
            ident = False
    damp_g = _gsum(v.reshape(n, 1), group, wts, ng, ident)[:, 0] < 0.0
    t = 0.0
    Ka = K
    for _seg in range(MAX_SEGMENTS):
        # unilateral: release contacts that pull now and do not approach (active-set iteration)
        while True:
            idx = np.flatnonzero(active)
            Ka = inv_spd(_sub(W, idx)) if idx.size < n else K
            if not unilateral or idx.size == 0:
                break
            f = np.zeros(n)
            fa = -(Ka @ (q[idx] - a[idx]))
            for r in range(idx.size):
                i = idx[r]
                ce = Cn[i] if (damp_g[group[i]] or always[i]) else 0.0
                f[i] = fa[r] - ce * v[i]
            fn = _gsum(f.reshape(n, 1), group, wts, ng, ident)[:, 0]
            vn = _gsum(v.reshape(n, 1), group, wts, ng, ident)[:, 0]
            gact = np.zeros(ng, np.bool_)
            for i in range(n):
                if active[i]:
                    gact[group[i]] = True
            pull = (fn < 0.0) & (vn >= 0.0) & gact
            if not pull.any():
                break
            for i in range(n):
                if pull[group[i]]:
                    active[i] = False
        h = dt - t
        if h <= 1e-12 * dt:
            break
        idx = np.flatnonzero(active)
        free = np.flatnonzero(~active)
        if idx.size == 0:
            for i in free:
                q[i] += h * v[i] + 0.5 * h * h * g[i]
                v[i] += h * g[i]
            t = dt
            break
        na = idx.size
        ma = m[idx]
        ga = g[idx]
        aa = a[idx]
        ce = np.empty(na)
        for r in range(na):
            i = idx[r]
            ce[r] = Cn[i] if (damp_g[group[i]] or always[i]) else 0.0
        q_eq = aa + np.linalg.solve(Ka, ma * ga)
        lam, V, Vi, ok = _modal(Ka, ma, ce)
        if not ok:
            return q, v, active, v0, v0, False
        z0 = np.concatenate((q[idx] - q_eq, v[idx]))
        gi = group[idx]
        wi = wts[idx]
        ident_a = ident and na == n
        sw_on = np.zeros(ng, np.bool_)
        has_sw = np.zeros(ng, np.bool_)
        for r in range(na):
            sw_on[gi[r]] = True
            i = idx[r]
            if Cn[i] > 0.0 and not always[i]:
                has_sw[gi[r]] = True
        switchable = sw_on & has_sw
        off_mask = switchable & damp_g
        on_mask = switchable & ~damp_g
        off_eq = q_eq - aa
        lo = 0.0
        hi = h
        tau = h * np.arange(1, GRID + 1) / GRID
        t_e = h
        ze = np.empty(2 * na)
        evg = np.zeros(ng, np.bool_)
        found = False
        for ref in range(REFINE + 1):
            Z = _modal_at(lam, V, Vi, z0, tau)
            y = Z[:na]
            vv = Z[na:]
            vng = _gsum(vv, gi, wi, ng, ident_a)
            fl = -(Ka @ (y + off_eq.reshape(na, 1)))
            for r in range(na):
                fl[r] -= ce[r] * vv[r]
            fng = _gsum(fl, gi, wi, ng, ident_a)
            j = -1
            for col in range(tau.size):
                for gg in range(ng):
                    e = (off_mask[gg] and vng[gg, col] >= 0.0) or (on_mask[gg] and vng[gg, col] < 0.0) or (
                        unilateral and sw_on[gg] and fng[gg, col] < 0.0 and vng[gg, col] >= 0.0)
                    if e:
                        j = col
                        break
                if j >= 0:
                    break
            if ref == 0 and j < 0:
                ze[:] = Z[:, -1]
                break
            if j < 0:  # (the bracket's right end had an event; rounding aside, it still does)
                j = 0
            found = True
            lo, hi = (tau[j - 1] if j else lo), tau[j]
            ze[:] = Z[:, j]
            for gg in range(ng):
                evg[gg] = (off_mask[gg] and vng[gg, j] >= 0.0) or (on_mask[gg] and vng[gg, j] < 0.0) or (
                    unilateral and sw_on[gg] and fng[gg, j] < 0.0 and vng[gg, j] >= 0.0)
            t_e = hi
            if ref < REFINE:
                tau = lo + (hi - lo) * np.arange(1, GRID + 1) / GRID
        # advance to t_e
        for r in range(na):
            q[idx[r]] = ze[r] + q_eq[r]
            v[idx[r]] = ze[na + r]
        for i in free:
            q[i] += t_e * v[i] + 0.5 * t_e * t_e * g[i]
            v[i] += t_e * g[i]
        t += t_e
        if not found:
            break
        vng1 = _gsum(v.reshape(n, 1), group, wts, ng, ident)[:, 0]
        f = np.zeros(n)
        fa = -(Ka @ (q[idx] - aa))
        for r in range(na):
            f[idx[r]] = fa[r] - ce[r] * v[idx[r]]
        fng1 = _gsum(f.reshape(n, 1), group, wts, ng, ident)[:, 0]
        for gg in range(ng):
            ea = evg[gg] and sw_on[gg]
            rel = unilateral and ea and fng1[gg] < 0.0 and vng1[gg] >= 0.0
            if ea and not rel:
                damp_g[gg] = vng1[gg] < 0.0
            if rel:
                for i in range(n):
                    if group[i] == gg:
                        active[i] = False
    else:
        # too many events in one step: finish it with the pattern frozen (rare)
        h = dt - t
        if h > 0:
            idx = np.flatnonzero(active)
            free = np.flatnonzero(~active)
            if idx.size:
                na = idx.size
                ce = np.empty(na)
                for r in range(na):
                    i = idx[r]
                    ce[r] = Cn[i] if (damp_g[group[i]] or always[i]) else 0.0
                q_eq = a[idx] + np.linalg.solve(Ka, m[idx] * g[idx])
                lam, V, Vi, ok = _modal(Ka, m[idx], ce)
                if not ok:
                    return q, v, active, v0, v0, False
                ze = _modal_at(lam, V, Vi, np.concatenate((q[idx] - q_eq, v[idx])), np.array([h]))[:, 0]
                for r in range(na):
                    q[idx[r]] = ze[r] + q_eq[r]
                    v[idx[r]] = ze[na + r]
            for i in free:
                q[i] += h * v[i] + 0.5 * h * h * g[i]
                v[i] += h * g[i]
    force = np.zeros(n)
    seat = np.zeros(n)
    idx = np.flatnonzero(active)
    for i in idx:
        force[i] = m[i] * ((v[i] - v0[i]) / dt - g[i])
    if idx.size:
        sa = Ka @ (q[idx] - a[idx])
        for r in range(idx.size):
            seat[idx[r]] = sa[r]
    return q, v, active, force, seat, True


# -- the sub-stepped (implicit / symplectic) integrators ---------------------------------------
@_njit
def substep_size(near, h_left, hmin, vel, radius, mass, pos, gap, near_tri, ctri, k_tri, approach_fraction,
                 rest_speed, omega_dt, symplectic, cc_stones, Kdiag, sticky, cc_normals, cc_X, cc_rest,
                 g):  # pragma: no cover (compiled)
    """Compiled ``Storm._substep_size`` for the adaptive implicit and symplectic
    integrators (see there): approaching stones travel at most ``approach_fraction``
    radii, an impact about to start and moving contacts are resolved to ``omega_dt``."""
    h = h_left
    om_close = 0.0
    for q in range(near.size):
        i = near[q]
        sp = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        if gap[i] >= sp * h_left + 1e-3 and np.isfinite(gap[i]):
            continue  # cannot reach the surface within the sub-step
        h = min(h, approach_fraction * radius[i] / max(sp, 1e-9))
        t = near_tri[i]
        k = k_tri[t] if t >= 0 else 0.0
        if (sp > rest_speed or symplectic) and k > 0.0:
            om_close = max(om_close, 1.5 * math.sqrt(k / mass[i]))
    if om_close > 0.0:
        h = min(h, omega_dt / om_close)
    om_move = 0.0
    for c in range(cc_stones.size):
        j = cc_stones[c]
        if ctri[j] < 0:
            continue
        if sticky:
            k = max(max(max(Kdiag[3 * c], 0.0), max(Kdiag[3 * c + 1], 0.0)), max(Kdiag[3 * c + 2], 0.0))
        else:
            k = max(Kdiag[c], 0.0)
        om = math.sqrt(k / mass[j])
        vn = 0.0; ubar = 0.0; gn = 0.0
        for d in range(3):
            vn += vel[j, d] * cc_normals[c, d]
            ubar += (pos[j, d] - cc_X[c, d]) * cc_normals[c, d]
            gn += g[d] * cc_normals[c, d]
        ubar -= cc_rest[c]
        u_eq = gn * mass[j] / max(k, 1e-300)
        amp = math.hypot(vn, om * (ubar - u_eq))
        if amp > rest_speed or symplectic:
            om_move = max(om_move, om)
    if om_move > 0.0:
        h = min(h, omega_dt / om_move)
    return min(max(h, hmin), h_left)


@_njit
def substep_damping(Kdiag, mq, restitution, dt, implicit, x_grid, z_grid):  # pragma: no cover (compiled)
    """Compiled :func:`runtime.hail.damping_coefficients` for the implicit (with ``dt``)
    and symplectic integrators: ``2 zeta sqrt(K_ii m_i)``, backward Euler's numerical
    damping ``omega dt / 2`` compensated. ``x_grid``, ``z_grid``: the restitution
    table of :func:`runtime.hail.damping_ratio_for_restitution`."""
    n = mq.size
    out = np.empty(n)
    for i in range(n):
        k = max(Kdiag[i], 0.0)
        e = restitution
        zn = 0.0
        if implicit:
            zn = 0.5 * math.sqrt(k / mq[i]) * dt
            e = min(e / math.exp(-zn * math.pi / 2.0), 1.0)
        z = np.interp(-math.log(min(max(e, 1e-300), 1.0)), x_grid, z_grid)
        out[i] = 2.0 * max(z - zn, 0.0) * math.sqrt(k * mq[i])
    return out


@_njit
def substep_contacts(q, v, a, m, g, dt, K, W, C, implicit, unilateral, group, wts):  # pragma: no cover
    """Compiled implicit (backward Euler) and symplectic Euler contact step of
    :func:`runtime.hail.contact_step` (see there): the dashpot in compression only,
    unilateral release by active-set iteration. Returns ``(q, v, active, force, seat_force)``."""
    n = q.size
    ng = 0
    for i in range(n):
        ng = max(ng, group[i] + 1)
    vn_g = np.zeros(ng)
    for i in range(n):
        vn_g[group[i]] += wts[i] * v[i]
    c = np.empty(n)
    for i in range(n):
        c[i] = C[i] if vn_g[group[i]] < 0.0 else 0.0
    active = np.ones(n, np.bool_)
    ubar = q - a
    v_new = v + dt * g
    force = np.zeros(n)
    while True:
        idx = np.flatnonzero(active)
        Ka = inv_spd(_sub(W, idx)) if idx.size < n else K
        v_new = v + dt * g
        na = idx.size
        if na:
            if implicit:
                A = dt * dt * Ka
                rhs = np.empty(na)
                ku = Ka @ ubar[idx]
                for r in range(na):
                    i = idx[r]
                    A[r, r] += m[i] + dt * c[i]
                    rhs[r] = m[i] * v[i] + dt * (m[i] * g[i] - ku[r])
                vs = np.linalg.solve(A, rhs)
                for r in range(na):
                    v_new[idx[r]] = vs[r]
            else:
                ku = Ka @ ubar[idx]
                for r in range(na):
                    i = idx[r]
                    v_new[i] = v[i] + dt * (g[i] + (-ku[r] - c[i] * v[i]) / m[i])
        force = np.zeros(n)
        for i in idx:
            force[i] = m[i] * ((v_new[i] - v[i]) / dt - g[i])
        if not unilateral or na == 0:
            break
        fn = np.zeros(ng)
        for i in range(n):
            fn[group[i]] += wts[i] * force[i]
        pulling = False
        for i in range(n):
            if active[i] and fn[group[i]] < 0.0:
                active[i] = False
                pulling = True
        if not pulling:
            break
    q_new = q + dt * v_new
    seat = np.zeros(n)
    idx = np.flatnonzero(active)
    if idx.size:
        Ka = inv_spd(_sub(W, idx)) if idx.size < n else K
        sa = Ka @ (q_new[idx] - a[idx])
        for r in range(idx.size):
            seat[idx[r]] = sa[r]
    for i in range(n):
        if not active[i]:
            force[i] = 0.0
    return q_new, v_new, active, force, seat
