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
from typing import Callable

import numpy as np

__all__ = ["HAVE_NUMBA", "SampleGrid", "closest_points", "near_set", "resolve_backend"]

try:  # pragma: no cover - exercised by whichever of the two environments runs the tests
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    numba = None
    HAVE_NUMBA = False


def _njit(f: Callable) -> Callable:
    """``numba.njit(cache=True)`` when numba is installed, else the plain function."""
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
def _closest_points(pts, reach, md, use_u, lo, h, dims, start, items, spts, owner, sr,
                    X, T, D, fcols, fv):  # pragma: no cover (compiled)
    k = pts.shape[0]
    out_tri = np.full(k, -1, np.int64)
    out_bary = np.zeros((k, 3))
    out_pt = np.full((k, 3), np.nan)
    out_d = np.full(k, np.inf)
    nv = X.shape[0]
    stamp = np.full(nv, -1, np.int64)  # vertex -> query row whose deformed position is in Y
    Y = np.empty((nv, 3))
    corner = np.empty((3, 3))
    bc = np.empty(3)
    best_bc = np.empty(3)
    ncol = fcols.shape[0]
    for i in range(k):
        p = pts[i]
        r = reach[i]
        d0 = _nearest_sample(p, lo, h, dims, start, items, spts)
        if d0 - sr - md > r:
            continue
        lim = min(r, d0 + md) + md + sr
        lim2 = lim * lim
        best = np.inf
        best_sd = np.inf
        best_t = -1
        ilo = np.empty(3, np.int64)
        ihi = np.empty(3, np.int64)
        empty = False
        for d in range(3):
            a = int(math.floor((p[d] - lim - lo[d]) / h))
            b = int(math.floor((p[d] + lim - lo[d]) / h))
            if b < 0 or a >= dims[d]:
                empty = True
            ilo[d] = max(a, 0)
            ihi[d] = min(b, dims[d] - 1)
        if empty:
            continue
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
                            if use_u and stamp[v] != i:
                                # the vertex's displacement under the current forces
                                for e in range(3):
                                    row = 3 * v + e
                                    acc = 0.0
                                    for j in range(ncol):
                                        acc += D[row, fcols[j]] * fv[j]
                                    Y[v, e] = X[v, e] + acc
                                stamp[v] = i
                            for e in range(3):
                                corner[m, e] = Y[v, e] if use_u else X[v, e]
                        _closest_on_triangle(p, corner[0], corner[1], corner[2], bc)
                        d2 = 0.0
                        for e in range(3):
                            x = bc[0] * corner[0, e] + bc[1] * corner[1, e] + bc[2] * corner[2, e]
                            d2 += (p[e] - x) * (p[e] - x)
                        dd = math.sqrt(d2)
                        # ties (a shared edge or vertex): the triangle of the nearer sample, as
                        # the reference's k-d order
                        if dd < best or (dd == best and sd < best_sd):
                            best = dd
                            best_sd = sd
                            best_t = t
                            for e in range(3):
                                best_bc[e] = bc[e]
                                out_pt[i, e] = bc[0] * corner[0, e] + bc[1] * corner[1, e] + bc[2] * corner[2, e]
        if best_t >= 0 and best <= r:
            out_tri[i] = best_t
            out_d[i] = best
            for e in range(3):
                out_bary[i, e] = best_bc[e]
        else:
            for e in range(3):
                out_pt[i, e] = np.nan
    return out_tri, out_bary, out_pt, out_d


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
        D, cols, forces = np.zeros((1, 1), order="F"), np.zeros(0, np.int64), np.zeros(0)
    assert D is not None and cols is not None and forces is not None
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return _closest_points(
        pts, np.ascontiguousarray(np.broadcast_to(np.asarray(reach, dtype=np.float64), (pts.shape[0],))),
        float(max_displacement) if use_u else 0.0, use_u,
        grid.lo, grid.h, grid.dims, grid.start, grid.items, grid.points, grid.owner, float(sample_radius),
        vertices, triangles, D, np.asarray(cols, dtype=np.int64), np.asarray(forces, dtype=np.float64))


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
def _one_patch(x, n, a, h, qx, qy, qw, facing, drop, glo, gh, gdims, gstart, gitems, cent, radii, tnorm,
               p0, e1, e2, reach, tris, T, nv):  # pragma: no cover (compiled)
    """Compiled ``runtime.weights._one_patch``: (vertices, weights) of one patch, both
    empty if the disc hits no usable triangle."""
    tol = 1e-12 * max(a, 1.0)
    lim = a + reach + tol
    # candidate triangles: centroid within a + reach (grid), then within a + own radius, facing n
    nc = 0
    cand = np.empty(cent.shape[0], np.int64)
    ilo = np.empty(3, np.int64)
    ihi = np.empty(3, np.int64)
    for d in range(3):
        ilo[d] = max(int(math.floor((x[d] - lim - glo[d]) / gh)), 0)
        ihi[d] = min(int(math.floor((x[d] + lim - glo[d]) / gh)), gdims[d] - 1)
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
