"""D's own error at the scale of one hat load, measured on the bundle itself.

Part of the near field (:mod:`hailstorm.runtime.contact.near_field`). Its
model, ``W = w^T D w - w^T H w + c(a)``, counts on ``D - H`` (the body's
response minus the half-space's) being smooth at the contact. Read off a
bundle, it is, pair by pair, except on its diagonal: the finite elements
under one hat load give its own vertex too small a displacement (the load is
concentrated on one element's scale, where the elements cannot follow the
displacement's kink). Measured on the default seat (6 mm, P2): ``D_ii - H_ii``
lies 0.6-1.2e-5 m/N (15-20 % of ``D_ii``) below the smooth value the vertex's
neighbours give it, and by more at a few vertices of a 3 mm seat. A stone
that lands on a vertex then meets a mesh stiffer than one that lands on an
edge: +2.8 % against -2.9 % at the seat's nose (a 2.5 mm stone at the peak
of its impact).

:func:`hat_defect` measures that defect per contactable vertex ``i``:

* ``g_ij = (D_ij + D_ji) / 2 - H_ij`` (normal components along the vertex
  normal; the tangential ones averaged over the tangent plane) for the
  contactable vertices ``j`` within 2.2 mean edge lengths of ``i`` (the
  half-space kernel ``H`` on hat loads as :func:`hailstorm.runtime.compiled.near_field.hat_compliance`
  integrates it);
* the smooth value at ``i``: the fit ``g(r) = g_0 + b r^2`` over those pairs
  (``D - H`` is even in ``r`` at a point of a smooth surface);
* ``Delta_i = g_0 - (D_ii - H_ii)``: what the vertex lacks (0 where fewer
  than :data:`MIN_NEIGHBOURS` neighbours are contactable).

:func:`patch_defect` adds it to a patch with its load's part the mesh cannot
spread (``w_i - wbar_i``, ``wbar_i`` the mean of ``w`` over the vertex's edge
neighbours): ``e(w) = sum_i Delta_i w_i (w_i - wbar_i)``. A load on one
vertex (``w = e_i``) gets all of ``Delta_i``; a load spread smoothly over
many vertices gets next to nothing, as the finite elements converge for it.
(Measured: the diagonal alone, ``sum_i Delta_i w_i^2``, also corrects wide
patches, and put a 12.5 mm stone 10.6 mm deep into the 6 mm seat at -6.2 %
of the 3 mm seat's force, against -3.9 % with the share above and -3.2 %
without any.)
"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from hailstorm.runtime.bundle.read import vertex_normals
from hailstorm.runtime.compiled.near_field import hat_compliance

__all__ = ["MIN_NEIGHBOURS", "NEIGHBOUR_REACH", "HatDefect", "hat_defect", "patch_defect", "vertex_neighbours"]

#: the neighbours a vertex's smooth value is fitted over: within this many of its mean edge lengths
NEIGHBOUR_REACH = 2.2
#: fewer contactable neighbours than this: no defect is measured (the vertex keeps D as it is)
MIN_NEIGHBOURS = 6


class HatDefect:
    """A bundle's hat-scale defect for one near-field material (module notes).

    Attributes
    ----------
    normal, tangential : (n,) ndarray
        ``Delta_i`` per surface vertex [m/N] (0 off the contactable surface).
    neighbours : (ptr, nbr) int64 ndarrays
        The surface's edge neighbours (CSR: ``nbr[ptr[v]:ptr[v + 1]]``, sorted).
    edges : (2 e,) int64 ndarray
        The same as sorted keys ``v * n + u`` (both directions), for lookups in bulk.
    degree : (n,) int64 ndarray
        Each vertex's number of edge neighbours.
    """

    def __init__(self, normal: np.ndarray, tangential: np.ndarray, neighbours: tuple[np.ndarray, np.ndarray]):
        self.normal = normal
        self.tangential = tangential
        self.neighbours = neighbours
        ptr, nbr = neighbours
        self.edges = np.repeat(np.arange(ptr.size - 1, dtype=np.int64), np.diff(ptr)) * (ptr.size - 1) + nbr
        self.degree = np.diff(ptr)


def vertex_neighbours(triangles: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The edge neighbours of each vertex of a triangle surface, CSR ``(ptr, nbr)`` (sorted per vertex)."""
    T = np.asarray(triangles, dtype=np.int64)
    e = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    e = np.unique(e[:, 0] * n + e[:, 1])
    src, dst = e // n, e % n
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(ptr, src + 1, 1)
    return np.cumsum(ptr), dst.astype(np.int64)


def _pair_blocks(gf: Any, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The 3 x 3 blocks ``D[rows[k], cols[k]]`` (surface vertex rows, contactable vertex columns), (k, 3, 3)."""
    D = gf.D
    r = 3 * rows[:, None, None] + np.arange(3)[None, :, None]
    c = 3 * np.asarray(gf.column_of)[cols][:, None, None] + np.arange(3)[None, None, :]
    return np.asarray(D[r, c], dtype=np.float64)


def _normal_tangential(B: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``n^T B n`` and the mean of ``B`` over the tangent plane, per 3 x 3 block, (k,) each."""
    bn = np.einsum("ki,kij,kj->k", n, B, n)
    return bn, 0.5 * (np.einsum("kii->k", B) - bn)


def _measure(gf: Any, young: float, poisson: float, surface: tuple[np.ndarray, ...]) -> HatDefect:
    from scipy.spatial import cKDTree

    X, T, areas, ptr, tri = surface
    nv = X.shape[0]
    nptr, nbr = vertex_neighbours(T, nv)
    normal, tangential = np.zeros(nv), np.zeros(nv)
    out = HatDefect(normal, tangential, (nptr, nbr))
    C = np.flatnonzero(np.asarray(gf.contactable))
    if C.size == 0:
        return out
    N = vertex_normals(X, T)
    owner = np.repeat(np.arange(nv), np.diff(nptr))
    edge = np.bincount(owner, weights=np.linalg.norm(X[owner] - X[nbr], axis=1), minlength=nv)
    edge = edge / np.maximum(np.diff(nptr), 1)
    tree = cKDTree(X[C])
    near = tree.query_ball_point(X[C], NEIGHBOUR_REACH * edge[C])
    I = np.repeat(C, [len(j) for j in near])
    J = C[np.concatenate([np.asarray(j, dtype=np.int64) for j in near])] if I.size else np.zeros(0, np.int64)
    keep = I != J
    I, J = I[keep], J[keep]

    # D: the vertex's own block and the pairs' symmetric part, along the vertex's normal and tangent plane
    dn_ii, dt_ii = _normal_tangential(_pair_blocks(gf, C, C), N[C])
    sym = 0.5 * (_pair_blocks(gf, I, J) + np.swapaxes(_pair_blocks(gf, J, I), 1, 2))
    dn_ij, dt_ij = _normal_tangential(sym, N[I])

    # H on the same hat loads, on the tangent plane at the vertex (the pair's symmetric part)
    def whw(verts: np.ndarray, at: np.ndarray) -> np.ndarray:
        verts = np.ascontiguousarray(verts, dtype=np.int64)
        w = np.ones(verts.shape, dtype=np.float64)
        return hat_compliance(verts, w, np.ascontiguousarray(X[at]), np.ascontiguousarray(N[at]), X, T, areas, ptr, tri)

    k_n = (1.0 - poisson**2) / (np.pi * young)
    k_t = k_n * (2.0 - poisson) / (2.0 * (1.0 - poisson))
    h_ii = whw(C[:, None], C)
    h_ij = 0.5 * (whw(np.column_stack([I, J]), I) - whw(I[:, None], I) - whw(J[:, None], I))

    # the smooth value at each vertex: g(r) = g0 + b r^2 fitted over its pairs (weighted sums per vertex)
    r2 = np.sum((X[I] - X[J]) ** 2, axis=1)
    slot = np.searchsorted(C, I)
    count = np.bincount(slot, minlength=C.size).astype(np.float64)
    s1, s2 = np.bincount(slot, r2, C.size), np.bincount(slot, r2 * r2, C.size)
    det = count * s2 - s1 * s1
    ok = (count >= MIN_NEIGHBOURS) & (det > 1e-12 * np.maximum(count * s2, np.finfo(float).tiny))
    for d_ii, d_ij, k, dest in ((dn_ii, dn_ij, k_n, normal), (dt_ii, dt_ij, k_t, tangential)):
        g = d_ij - k * h_ij
        sg, sgr = np.bincount(slot, g, C.size), np.bincount(slot, g * r2, C.size)
        g0 = np.where(ok, (s2 * sg - s1 * sgr) / np.where(ok, det, 1.0), 0.0)
        dest[C] = np.where(ok, g0 - (d_ii - k * h_ii), 0.0)
    return out


_DEFECTS: "weakref.WeakKeyDictionary[Any, dict[tuple[float, float], HatDefect]]" = weakref.WeakKeyDictionary()


def hat_defect(gf: Any, young: float, poisson: float, surface: tuple[np.ndarray, ...]) -> HatDefect:
    """The bundle's hat-scale defect against the half-space of ``young``, ``poisson`` (module notes).

    Measured once per bundle and material (a few hundred milliseconds for the
    default seat), then cached with the bundle.

    Parameters
    ----------
    gf : GreensFunctions
        A loaded bundle whose columns answer hat loads.
    young, poisson : float
        The near field's material [Pa], [-].
    surface : tuple of ndarrays
        The bundle's surface as the kernel reads it
        (:func:`hailstorm.runtime.contact.near_field.kernel_surface`).

    Returns
    -------
    HatDefect
    """
    key = (float(young), float(poisson))
    try:
        cached = _DEFECTS[gf]
    except (KeyError, TypeError):
        cached = {}
        try:
            _DEFECTS[gf] = cached
        except TypeError:  # pragma: no cover - not weak-referenceable
            pass
    if key not in cached:
        cached[key] = _measure(gf, *key, surface)
    return cached[key]


def patch_defect(defect: HatDefect, verts: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``e(w) = sum_i Delta_i w_i (w_i - wbar_i)`` of each patch, normal and tangential [m/N], (s,) each.

    Parameters
    ----------
    defect : HatDefect
        From :func:`hat_defect`.
    verts, weights : (s, P) ndarrays
        Each patch's vertices and hat-load weights (weight 0: padding).
    """
    v = np.asarray(verts, dtype=np.int64)
    w = np.where(np.asarray(weights, dtype=np.float64) > 0.0, weights, 0.0)
    if v.size == 0:
        return np.zeros(v.shape[0]), np.zeros(v.shape[0])
    vv = np.where(w > 0.0, v, 0)
    n = defect.normal.size
    # adjacent[k, p, q]: verts[k, q] is an edge neighbour of verts[k, p] (one lookup in the sorted keys)
    keys = vv[:, :, None] * n + vv[:, None, :]
    pos = np.minimum(np.searchsorted(defect.edges, keys), defect.edges.size - 1)
    adjacent = defect.edges[pos] == keys
    wbar = np.einsum("kpq,kq->kp", adjacent, w) / np.maximum(defect.degree[vv], 1)
    share = w * (w - wbar)
    return (np.einsum("kp,kp->k", defect.normal[vv], share),
            np.einsum("kp,kp->k", defect.tangential[vv], share))
