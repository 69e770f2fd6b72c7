"""D's own error at the scale of its hat loads, measured on the bundle itself.

Part of the near field (:mod:`hailstorm.runtime.contact.near_field`). Its
model, ``W = w^T D w - w^T K w + c(a)`` (``K`` the near-field kernel on hat
loads: the half-space's, or the layer's), counts on ``D - K`` being smooth at
the contact. Read off a bundle it is, pair by pair, except at the shortest
range: the finite elements under one hat load give its own vertex too small a
displacement and its edge neighbours too large a one (the load sits on one
element's scale, where the elements cannot follow the displacement's kink).
Measured on a 15 mm pad of the default foam on its rigid base at the default
seat's settings (6 mm, P2), against the exact layer on the same hat loads
(:mod:`hailstorm.runtime.contact.layer_kernel`): ``D_ii`` is 5 % low, the first
ring 4-6 % high, and beyond it ``D`` is the layer's to within about 1e-7 m/N.
Left in, a stone's force depends on where on the mesh it lands, and a wide one
is off by the first ring's excess.

:func:`hat_defect` measures the defect per contactable vertex ``i``:

* ``g_ij = (D_ij + D_ji) / 2 - K_ij`` (normal components along the vertex
  normal; the tangential ones averaged over the tangent plane, against the
  half-space's tangential kernel) for the contactable vertices ``j`` within
  :data:`NEIGHBOUR_REACH` mean edge lengths of ``i``, and ``g_ii``;
* the smooth part at ``i``: the fit ``s_i(r) = c_0 + c_2 r^2`` over the pairs
  beyond the first ring (``D - K`` is even in ``r`` at a point of a smooth
  surface; two rings of lever arm; the body's curvature and whatever else the
  kernel does not explain are in it);
* the defect on the *near pairs*, the vertex itself and its edge neighbours:
  ``delta_ij = g_ij - s_i(r_ij)`` (none where fewer than :data:`MIN_NEIGHBOURS`
  pairs lie beyond the first ring).

:func:`patch_defect` takes it off a patch: ``e(w) = -sum_{near ij} w_i w_j delta_ij``,
so that within one ring ``D`` counts with the kernel plus its smooth part, and
beyond, as it is. A load on one vertex (``w = e_i``) gets ``-delta_ii``; a stone
smaller than an element gets the same compliance wherever it lands (measured
on the default seat: within 0.7 % over vertex, edge and centroid, against
1.8 % with the earlier form below).

(Before: ``sum_i Delta_i w_i (w_i - wbar_i)`` with ``Delta_i = -delta_ii`` fitted
over all pairs within 2.2 edge lengths, first ring included. It left the
first ring's excess in a wide patch and fitted through it; on the flat 15 mm pad
it gave -1.0 .. -2.7 % against the converged contact where this form gives
-0.2 .. +1.2 % for contact radii up to 7 mm.)
"""

from __future__ import annotations

import hashlib
import json
import logging
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.runtime.bundle.compliance import pair_blocks
from hailstorm.runtime.bundle.read import vertex_normals
from hailstorm.runtime.compiled.near_field import hat_compliance, layer_sum
from hailstorm.runtime.contact.layer_kernel import layer_kernel, layer_surface

__all__ = ["MIN_NEIGHBOURS", "NEIGHBOUR_REACH", "HatDefect", "hat_defect", "patch_defect", "vertex_neighbours"]

#: the pairs a vertex's smooth part is fitted over: within this many of its mean edge lengths,
#: beyond its first ring (two rings of a regular mesh, r from about 1.7 to 3 edge lengths)
NEIGHBOUR_REACH = 3.0
#: fewer pairs than this beyond the first ring: no defect is measured (the vertex keeps D as it is)
MIN_NEIGHBOURS = 6
#: the measurement's version in its cache file's key: raise it when :func:`hat_defect`'s
#: measurement changes (its constants above are in the key already)
CACHE_VERSION = 1

_log = logging.getLogger(__name__)


class HatDefect:
    """A bundle's hat-scale defect for one near-field kernel (module notes).

    Attributes
    ----------
    normal, tangential : (n,) ndarray
        ``Delta_i = -delta_ii`` per surface vertex [m/N]: what a load on the vertex alone
        lacks (0 off the contactable surface or where none was measured).
    keys : (k,) int64 ndarray
        The near pairs ``(i, j)`` (``j`` = ``i`` or an edge neighbour of ``i``) as sorted keys
        ``i n + j``, ``n`` the surface's vertex count.
    near_normal, near_tangential : (k,) ndarray
        ``delta_ij`` of each near pair [m/N].
    """

    def __init__(self, n: int, keys: np.ndarray, near_normal: np.ndarray, near_tangential: np.ndarray):
        self.keys = keys
        self.near_normal = near_normal
        self.near_tangential = near_tangential
        self.normal = np.zeros(n)
        self.tangential = np.zeros(n)
        diag = keys // n == keys % n
        self.normal[keys[diag] % n] = -near_normal[diag]
        self.tangential[keys[diag] % n] = -near_tangential[diag]


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


def _normal_tangential(B: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``n^T B n`` and the mean of ``B`` over the tangent plane, per 3 x 3 block, (k,) each."""
    bn = np.einsum("ki,kij,kj->k", n, B, n)
    return bn, 0.5 * (np.einsum("kii->k", B) - bn)


def _layer_pairs(gf: Any, young: float, poisson: float, C: np.ndarray, I: np.ndarray,
                 J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The layer kernel's regular part on hat loads (:mod:`hailstorm.runtime.contact.layer_kernel`), at the
    thickness under the first vertex: ``R_ii`` of each of ``C`` and the symmetric ``R_ij`` of each pair (m/N)."""
    kern, surf = layer_kernel(poisson), layer_surface(gf)
    h = surf.thick[C]
    inv = np.where(np.isfinite(h) & (h > 0), 1.0 / np.where(h > 0, h, 1.0), 0.0)
    scale = inv / young

    def quad(verts: np.ndarray, inv_h: np.ndarray) -> np.ndarray:
        verts = np.ascontiguousarray(verts, dtype=np.int64)
        return layer_sum(verts, np.ones(verts.shape), surf.X, surf.hat_ptr, surf.hat_pts, surf.hat_w,
                         np.ascontiguousarray(inv_h), kern.table, kern.step)

    slot = np.searchsorted(C, I)
    r_ii = quad(C[:, None], inv) * scale
    same = quad(J[:, None], inv[slot]) * scale[slot]
    r_ij = 0.5 * (quad(np.column_stack([I, J]), inv[slot]) * scale[slot] - r_ii[slot] - same)
    return r_ii, r_ij


def _measure(gf: Any, young: float, poisson: float, surface: tuple[np.ndarray, ...], layer: bool) -> HatDefect:
    from scipy.spatial import cKDTree

    X, T, areas, ptr, tri = surface
    nv = X.shape[0]
    none = HatDefect(nv, np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    C = np.flatnonzero(np.asarray(gf.contactable))
    if C.size == 0:
        return none
    nptr, nbr = vertex_neighbours(T, nv)
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
    ring = np.isin(I * nv + J, owner * nv + nbr)  # the first ring: edge neighbours

    # D: the vertex's own block and the pairs' symmetric part, along the vertex's normal and tangent plane
    dn_ii, dt_ii = _normal_tangential(pair_blocks(gf, C, C), N[C])
    sym = 0.5 * (pair_blocks(gf, I, J) + np.swapaxes(pair_blocks(gf, J, I), 1, 2))
    dn_ij, dt_ij = _normal_tangential(sym, N[I])

    # the kernel on the same hat loads: H on the tangent plane at the vertex (the pair's symmetric part)
    def whw(verts: np.ndarray, at: np.ndarray) -> np.ndarray:
        verts = np.ascontiguousarray(verts, dtype=np.int64)
        w = np.ones(verts.shape, dtype=np.float64)
        return hat_compliance(verts, w, np.ascontiguousarray(X[at]), np.ascontiguousarray(N[at]), X, T, areas, ptr, tri)

    k_n = (1.0 - poisson**2) / (np.pi * young)
    k_t = k_n * (2.0 - poisson) / (2.0 * (1.0 - poisson))
    h_ii = whw(C[:, None], C)
    h_ij = 0.5 * (whw(np.column_stack([I, J]), I) - whw(I[:, None], I) - whw(J[:, None], I))
    gn_ii, gn_ij = dn_ii - k_n * h_ii, dn_ij - k_n * h_ij
    if layer:  # and the layer's regular part, normal only
        r_ii, r_ij = _layer_pairs(gf, young, poisson, C, I, J)
        gn_ii, gn_ij = gn_ii - r_ii, gn_ij - r_ij
    gt_ii, gt_ij = dt_ii - k_t * h_ii, dt_ij - k_t * h_ij

    # the smooth part at each vertex: s(r) = c0 + c2 r^2 fitted over its pairs beyond the first ring
    r2 = np.sum((X[I] - X[J]) ** 2, axis=1)
    slot = np.searchsorted(C, I)
    far = ~ring
    count = np.bincount(slot[far], minlength=C.size).astype(np.float64)
    s1, s2 = np.bincount(slot[far], r2[far], C.size), np.bincount(slot[far], r2[far] ** 2, C.size)
    det = count * s2 - s1 * s1
    ok = (count >= MIN_NEIGHBOURS) & (det > 1e-12 * np.maximum(count * s2, np.finfo(float).tiny))
    safe = np.where(ok, det, 1.0)
    nears = []
    for g_ii, g_ij in ((gn_ii, gn_ij), (gt_ii, gt_ij)):
        sg, sgr = np.bincount(slot[far], g_ij[far], C.size), np.bincount(slot[far], g_ij[far] * r2[far], C.size)
        c0 = (s2 * sg - s1 * sgr) / safe
        c2 = (count * sgr - s1 * sg) / safe
        nears.append(np.concatenate([(g_ii - c0)[ok], (g_ij - c0[slot] - c2[slot] * r2)[ring & ok[slot]]]))
    keys = np.concatenate([C[ok] * nv + C[ok], (I * nv + J)[ring & ok[slot]]])
    order = np.argsort(keys)
    return HatDefect(nv, keys[order], nears[0][order], nears[1][order])


_DEFECTS: "weakref.WeakKeyDictionary[Any, dict[tuple[float, float, bool], HatDefect]]" = weakref.WeakKeyDictionary()


def hat_defect(gf: Any, young: float, poisson: float, surface: tuple[np.ndarray, ...], layer: bool = False) -> HatDefect:
    """The bundle's hat-scale defect against the half-space of ``young``, ``poisson`` (module notes),
    or against the layer kernel's (``layer``).

    Measured once per bundle and material (about a second for the default seat),
    then cached with the bundle in memory and in hailstorm's cache directory
    (``hat_defect/``, keyed by the bundle's content and the material, written
    atomically; a file that cannot be read or written is passed by).

    Parameters
    ----------
    gf : GreensFunctions
        A loaded bundle whose columns answer hat loads.
    young, poisson : float
        The near field's material [Pa], [-].
    surface : tuple of ndarrays
        The bundle's surface as the kernel reads it
        (:func:`hailstorm.runtime.contact.near_field.kernel_surface`).
    layer : bool
        Take the layer kernel's regular part off too (module notes; the ``"layer"`` near field's).

    Returns
    -------
    HatDefect
    """
    key = (float(young), float(poisson), bool(layer))
    try:
        cached = _DEFECTS[gf]
    except (KeyError, TypeError):
        cached = {}
        try:
            _DEFECTS[gf] = cached
        except TypeError:  # pragma: no cover - not weak-referenceable
            pass
    if key not in cached:
        path = _cache_path(gf, *key)
        found = None if path is None else _read_cached(path, surface[0].shape[0])
        if found is None:
            found = _measure(gf, key[0], key[1], surface, key[2])
            if path is not None:
                _write_cached(path, found)
        cached[key] = found
    return cached[key]


def _cache_path(gf: Any, young: float, poisson: float, layer: bool) -> Path | None:
    """The defect's file in hailstorm's cache directory (``hat_defect/<key>.npz``), keyed by the
    bundle's content (its manifest's hash, which covers every array's) and the material; None
    for a bundle without one (built in memory)."""
    from hailstorm.runtime.bundle.stamps import default_cache_dir

    manifest = getattr(gf, "manifest", None) or {}
    content = manifest.get("manifest_sha256")
    if not content:
        return None
    key = hashlib.sha256(json.dumps({"bundle": content, "young": repr(young), "poisson": repr(poisson),
                                     "layer": layer, "reach": NEIGHBOUR_REACH, "min": MIN_NEIGHBOURS,
                                     "version": CACHE_VERSION}, sort_keys=True).encode()).hexdigest()
    return default_cache_dir() / "hat_defect" / f"{key[:24]}.npz"


def _read_cached(path: Path, n: int) -> HatDefect | None:
    """A cached defect, or None when the file is missing, unreadable or not of this surface."""
    try:
        with np.load(path) as f:
            keys, dn, dt, nv = (np.array(f["keys"], dtype=np.int64), np.array(f["near_normal"], dtype=np.float64),
                                np.array(f["near_tangential"], dtype=np.float64), int(f["n"]))
    except (OSError, KeyError, ValueError):
        return None
    if nv != n or keys.ndim != 1 or dn.shape != keys.shape or dt.shape != keys.shape \
            or not (np.all(np.isfinite(dn)) and np.all(np.isfinite(dt))):
        return None
    return HatDefect(nv, keys, dn, dt)


def _write_cached(path: Path, defect: HatDefect) -> None:
    """Write the defect atomically; a cache that cannot be written is passed by."""
    try:
        from hailstorm.runtime.bundle.atomic import replacing

        path.parent.mkdir(parents=True, exist_ok=True)
        with replacing(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, keys=defect.keys, near_normal=defect.near_normal,
                         near_tangential=defect.near_tangential, n=np.int64(defect.normal.size))
    except OSError as exc:
        _log.debug("could not cache the hat defect (%s)", exc)


def patch_defect(defect: HatDefect, verts: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``e(w) = -sum_{near ij} w_i w_j delta_ij`` of each patch, normal and tangential [m/N], (s,) each.

    Parameters
    ----------
    defect : HatDefect
        From :func:`hat_defect`.
    verts, weights : (s, P) ndarrays
        Each patch's vertices and hat-load weights (weight 0: padding).
    """
    v = np.asarray(verts, dtype=np.int64)
    w = np.where(np.asarray(weights, dtype=np.float64) > 0.0, weights, 0.0)
    if v.size == 0 or defect.keys.size == 0:
        return np.zeros(v.shape[0]), np.zeros(v.shape[0])
    vv = np.where(w > 0.0, v, 0)
    n = defect.normal.size
    # each ordered pair of the patch looked up in the sorted near-pair keys at once
    keys = vv[:, :, None] * n + vv[:, None, :]
    pos = np.minimum(np.searchsorted(defect.keys, keys), defect.keys.size - 1)
    hit = defect.keys[pos] == keys
    dn = np.where(hit, defect.near_normal[pos], 0.0)
    dt = np.where(hit, defect.near_tangential[pos], 0.0)
    return -np.einsum("kp,kpq,kq->k", w, dn, w), -np.einsum("kp,kpq,kq->k", w, dt, w)
