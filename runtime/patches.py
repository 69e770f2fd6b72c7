"""Patch contacts in the storm: the radius of each contact's pressure disc, the per-stone
cache of its weights, and the normal stiffness of a patch or of a triangle.

Functions of a :class:`hailstorm.runtime.storm.Storm`'s state (``st``); the rules are in
the module notes of :mod:`hailstorm.runtime.storm` ("Patch contacts"). The weights
themselves are :func:`hailstorm.runtime.weights.patch_weights`; on the numba backend
:func:`radii` runs as one kernel (:func:`hailstorm.runtime.compiled.patch_radii`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

import numpy as np

from hailstorm.runtime.compiled import patch_compliance, patch_one, patch_radii
from hailstorm.runtime.hail import GRAVITY
from hailstorm.runtime.weights import PATCH_DROP, PATCH_FACING

if TYPE_CHECKING:  # pragma: no cover
    from hailstorm.runtime.storm import Storm

__all__ = ["all_triangle_stiffness", "cached_weights", "radii", "stiffness", "triangle_stiffness"]


def radii(st: Storm, stones: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Patch radius of each soft contact ``stones`` (updated in ``st.crad``).

    The radius is the Hertz radius of the contact's *peak* force, estimated
    from its current state as a linear oscillator about its static
    equilibrium: ``F_peak = F_eq + sqrt((F - F_eq)^2 + k m v_n^2)``
    (``F``: the previous sub-step's force on that contact, ``F_eq``: the
    stone's weight along the normal, ``k``: its stiffness, the diagonal of
    the current capacitance, or the point stiffness of the triangle for a
    contact that just opened, whose ``F = 0``: the impact's expected
    peak). The estimate is (nearly) constant over one impact and tends to
    the resting force afterwards, so the patch is sized for the deepest
    dent of the impact and is not re-weighted while the force rises and
    falls. A contact keeps its radius until the target leaves the band
    ``[a / (1 + tol), a (1 + tol)]`` (``tol = patch_tolerance``).
    """
    return radii_compiled(st, stones, tris)


def radii_compiled(st: Storm, stones: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """:func:`radii` in one kernel (:func:`hailstorm.runtime.compiled.patch_radii`); the
    new contacts' weights at their first radius go to the weights cache."""
    sc = st.scene
    cc = st.cache
    if cc is not None and cc.stones.size and st.lam.size:
        cs, kd, lam = cc.stones, cc.Kdiag, st.lam
    else:
        cs, kd, lam = st._no_cols, st._no_forces, st._no_forces
    if st._k_tri_all is None:
        st._k_tri_all = all_triangle_stiffness(st)
    e_star = float(st.gf.young) / (1.0 - float(st.gf.poisson) ** 2)
    a, resizes, a0, off, wv, ww = patch_radii(
        stones, tris, st.mass, st.radius, st.vel, st.cbary, st.crad, st.index.normals, GRAVITY,
        st.wind, st._drag_coef, cs, kd, lam, sc.mode == "sticky", st._k_tri_all, e_star,
        float(sc.patch_min_radius), float(sc.patch_tolerance), float(sc.rest_speed), *st._disc, PATCH_FACING,
        PATCH_DROP, st._pidx, st.X, st._D, st._col_of)
    stats = st.stats
    stats["patch_resizes"] += int(resizes)
    for i in np.flatnonzero(a0 > 0.0).tolist():
        j = int(stones[i])
        st._wcache[j] = (int(tris[i]), st.cbary[j].tobytes(), float(a0[i]), wv[off[i]:off[i + 1]],
                         ww[off[i]:off[i + 1]])
        stats["patch_weights_computed"] += 1
    if a.size:
        stats["max_patch_radius_m"] = max(stats["max_patch_radius_m"], float(a.max()))
    return a


def stiffness(st: Storm, stones: np.ndarray, tris: np.ndarray, radius: np.ndarray,
              normals: np.ndarray) -> np.ndarray:
    """Normal stiffness ``1 / (g^T D g)`` of each patch contact alone, (s,) [N/m]."""
    verts, w = cached_weights(st, stones, tris, st.cbary[stones], radius, normals)
    k = np.zeros(stones.size)
    for i in range(stones.size):
        c = patch_compliance(verts[i].astype(np.int64, copy=False), w[i], normals[i], st._D, st._col_of)
        k[i] = 1.0 / c if c > 0 else 0.0
    return k


def cached_weights(st: Storm, stones: np.ndarray, tris: np.ndarray, bary: np.ndarray, radius: np.ndarray,
                   normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Padded (s, P) vertex lists and weights of patch contacts, cached per stone.

    A contact keeps its ``(triangle, beta)`` while its stone stays over the
    triangle and its radius while the force stays within the tolerance, so
    the weights are reused until one of them changes.
    """
    out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * stones.size
    todo = []
    for i, (j, t, a) in enumerate(zip(stones.tolist(), tris.tolist(), radius.tolist())):
        c = st._wcache.get(j)
        if c is not None and c[0] == t and c[2] == a and c[1] == bary[i].tobytes():
            out[i] = (c[3], c[4])
        else:
            todo.append(i)
    st.stats["patch_weights_reused"] += stones.size - len(todo)
    if todo:
        st.stats["patch_weights_computed"] += len(todo)
        for i in todo:
            v, w_ = patch_one(int(tris[i]), bary[i], float(radius[i]), normals[i], 3.0, *st._disc,
                              PATCH_FACING, PATCH_DROP, st._pidx, st.X)
            st._wcache[int(stones[i])] = (int(tris[i]), bary[i].tobytes(), float(radius[i]), v, w_)
            out[i] = (v, w_)
    done = cast(list[tuple[np.ndarray, np.ndarray]], out)  # every slot is filled above
    P = max(3, max(o[0].size for o in done))
    verts = np.empty((stones.size, P), dtype=np.intp)
    w = np.zeros((stones.size, P))
    for i, (v, wi) in enumerate(done):  # padding: weight-0 copies of the first vertex (weights._pad)
        verts[i, :v.size] = v
        verts[i, v.size:] = v[0]
        w[i, :v.size] = wi
    return verts, w


def triangle_stiffness(st: Storm, tris: np.ndarray) -> np.ndarray:
    """Normal contact stiffness at the centroid of triangles, [N/m].

    Used to size the sub-step *before* a contact opens (so the first
    impact step is already resolved). Hard triangles give 0. Computed for
    every soft triangle at once on first use (batched 9 x 9 blocks of D:
    one gather instead of one per triangle), then looked up.
    """
    if st._k_tri_all is None:
        st._k_tri_all = all_triangle_stiffness(st)
    tris = np.asarray(tris, dtype=np.intp)
    return np.where(tris >= 0, st._k_tri_all[tris], 0.0)


def all_triangle_stiffness(st: Storm, chunk: int = 4096) -> np.ndarray:
    """``1 / (b^T D_tt b)`` per soft triangle, ``b = (1/3, 1/3, 1/3) kron n`` (0 elsewhere)."""
    tri = np.asarray(st.gf.triangles, dtype=np.intp)
    out = np.zeros(tri.shape[0])
    soft = np.flatnonzero(st.soft)
    col_of = st._col_of
    third = np.full(3, 1.0 / 3.0)
    for s0 in range(0, soft.size, chunk):
        t = soft[s0:s0 + chunk]
        V = tri[t]
        cb = col_of[V]
        rows = (3 * V[:, :, None] + np.arange(3)).reshape(-1, 9)
        cols = (3 * np.maximum(cb, 0)[:, :, None] + np.arange(3)).reshape(-1, 9)
        # (T, 9, 9) blocks, each column-major like gf.compliance's (same gemv sums)
        blk = np.ascontiguousarray(st._D[rows[:, None, :], cols[:, :, None]])  # (T, col, row)
        blk[np.repeat(cb < 0, 3, axis=1)] = 0.0  # clamped columns
        blk = blk.transpose(0, 2, 1)
        Bn = (third[None, :, None] * st.index.normals[t][:, None, :]).reshape(-1, 9)  # kron(1/3, n)
        w = np.matmul(np.matmul(Bn[:, None, :], blk), Bn[:, :, None])[:, 0, 0]
        out[t] = np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), 0.0)
    return out
