"""The storm's soft contacts: the capacitance of the current contact set (rebuilt when
the set changes) and one contact step of its stones.

Functions of a :class:`hailstorm.runtime.storm.Storm`'s state (``st``), called by
``Storm._substep``. :func:`contact_set` forms W = Bᵀ D B, K = W⁻¹ and the
force and displacement blocks of the set (:class:`ContactSet`); :func:`advance`
moves the stones in contact by one sub-step through
:func:`hailstorm.runtime.hail.contact_step` with unilateral release, in numpy or, on the
numba backend, with the per-contact work in kernels (:func:`advance_compiled`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hailstorm.runtime import contact_capacitance as _policy
from hailstorm.runtime import patches
from hailstorm.runtime.compiled import (
    capacitance_blocks,
    contact_post,
    contact_prep,
    exact_step,
    explicit_modes,
    inv_spd,
    modal_stiffness,
    rigid_contacts,
    substep_contacts,
    substep_damping,
)
from hailstorm.runtime.hail import _X_GRID, _Z_GRID, GRAVITY, ContactStep, contact_modes, contact_step

if TYPE_CHECKING:  # pragma: no cover
    from hailstorm.runtime.storm import Storm

__all__ = ["ContactSet", "advance", "advance_compiled", "contact_matrices", "contact_set", "exact_damping"]


@dataclass
class ContactSet:
    """The capacitance of the storm's current set of soft contacts (:func:`contact_set`),
    kept while the set (stones, triangles, patch radii) is unchanged."""

    key: tuple
    W: np.ndarray
    K: np.ndarray
    G: np.ndarray  # (c, m) forces at the loaded (non-clamped) dofs of V per unit multiplier
    cols: np.ndarray  # (c,) their columns of D
    DVV: np.ndarray  # (3|V|, m) displacement of V per unit multiplier
    stones: np.ndarray
    tris: np.ndarray
    bary: np.ndarray
    normals: np.ndarray
    X: np.ndarray  # undeformed contact points (s, 3) (the patch centres)
    rest: np.ndarray  # (s,) distance along the normal from the reference point to the stone's centre at contact
    patch_radius: np.ndarray  # (s,) patch radius [m] (0: point contact)
    verts: np.ndarray  # (s, P) vertices carrying each contact's force
    weights: np.ndarray  # (s, P) their weights (B: block (verts[k, p], k) = weights[k, p] I3)
    Kdiag: np.ndarray  # diag(K), a contiguous writable copy (what the compiled kernels take)
    C: np.ndarray | None = None  # exact-integrator dashpot (cached)
    modes: tuple | None = None  # (omega^2, Phi, sqrt(m)) of M^-1/2 K M^-1/2 (cached, contact_modes)


def contact_set(st: Storm, stones: np.ndarray, tris: np.ndarray, bary: np.ndarray, key: tuple,
                radius: np.ndarray | None = None) -> ContactSet:
    """The capacitance of the soft contacts ``stones`` (point contacts, or patches of ``radius``)."""
    gf, mode = st.gf, st.scene.mode
    normals = st.index.normals[tris]
    s = stones.size
    if radius is None:
        verts, w = np.asarray(gf.triangles)[tris], bary
        radius = np.zeros(s)
    else:
        verts, w = patches.cached_weights(st, stones, tris, bary, radius, normals)
    verts = verts.astype(np.int64, copy=False)
    if rigid_contacts(verts, w, st._fixed):
        raise RuntimeError("rigid contacts must be filtered before the capacitance")  # pragma: no cover
    V, W, G, cols, DG = capacitance_blocks(verts, w, normals, mode == "sticky", st._D, st._col_of)
    K = inv_spd(W, float(_policy.COND_LIMIT), float(_policy.PINV_RCOND))  # spd_inverse's policy
    # reference point: the contact point (the patch centre). A patch contact prescribes the
    # pressure-weighted mean normal displacement of the surface under the disc, measured from
    # the tangent plane at the contact point (the plane of the disc): the stone's lowest point
    # follows it. (Measuring from the weighted mean undeformed surface point sum_p w_p X_p
    # instead, which lies below the tangent plane on the convex seat, opens every contact with
    # a small gap: measured restitution 0.488 instead of 0.499 for the single drop.)
    X = np.einsum("kj,kjd->kd", bary, st.X[gf.triangles[tris]])
    st.stats["capacitance_rebuilds"] += 1
    return ContactSet(key=key, W=W, K=K, G=G, cols=cols, DVV=DG, stones=stones, tris=tris, bary=bary,
                      normals=normals, X=X, rest=st.radius[stones].copy(),
                      patch_radius=np.asarray(radius, dtype=np.float64).copy(), verts=verts, weights=w,
                      Kdiag=np.diag(K).copy())


def advance(st: Storm, near: np.ndarray, soft: np.ndarray, was_open: np.ndarray, h: float) -> None:
    """Advance the stones in soft contact by ``h`` through the capacitance of their
    contact set (rebuilt when the set of (stone, triangle[, patch radius]) changes),
    with unilateral release; update the seat's forces and the statistics."""
    tris = st.ctri[soft]
    key: tuple[tuple[Any, ...], ...]
    if st._patch:
        rad = patches.radii(st, soft, tris)
        key = tuple(zip(soft.tolist(), tris.tolist(), rad.tolist()))
    else:
        rad = None
        key = tuple(zip(soft.tolist(), tris.tolist()))
    if st.cache is None or st.cache.key != key:
        st.cache = contact_set(st, soft, tris, st.cbary[soft].copy(), key, rad)
    advance_compiled(st, near, soft, was_open, h, st.cache)


def advance_compiled(st: Storm, near: np.ndarray, soft: np.ndarray, was_open: np.ndarray, h: float,
                     cc: ContactSet) -> None:
    """:func:`advance` after the contact set is known, with the per-contact
    work in compiled kernels (:func:`hailstorm.runtime.compiled.contact_prep`,
    :func:`hailstorm.runtime.compiled.contact_post`) around the same :func:`contact_step`."""
    sc = st.scene
    exact = sc.integrator == "exact"
    sticky = sc.mode == "sticky"
    s = soft.size
    nk = cc.normals
    q, a, vq, gq, mq, always, acc = contact_prep(
        soft, st.pos, st.vel, st.radius, st.mass, GRAVITY, st.wind, st._drag_coef, nk, cc.X, cc.rest,
        cc.Kdiag, sticky, exact, float(sc.rest_speed))
    group, wts = (np.repeat(np.arange(s), 3), nk.ravel()) if sticky else (None, None)
    if group is None:
        group, wts = np.arange(s), np.ones(s)
    res = None
    lim, rcond = float(_policy.COND_LIMIT), float(_policy.PINV_RCOND)
    K, W = cc.K, cc.W
    if exact:
        C = exact_damping(st, cc, mq)
        qn, vn, act, force, seat, peak, pub, ok = exact_step(q, vq, a, mq, gq, h, cc.K, cc.W, C,
                                                              bool(sc.unilateral), group, wts, always, lim,
                                                              rcond)
        if ok:
            res = ContactStep(q=qn, v=vn, active=act, force=force, seat_force=seat, peak_seat_force=peak,
                              peak_ubar=pub)
    else:
        implicit = sc.integrator == "implicit"
        K, W, C = contact_matrices(st, cc, mq, h)
        qn, vn, act, force, seat = substep_contacts(q, vq, a, mq, gq, h, K, W, C, implicit,
                                                    bool(sc.unilateral), group, wts, lim, rcond)
        res = ContactStep(q=qn, v=vn, active=act, force=force, seat_force=seat, peak_seat_force=seat,
                          peak_ubar=qn - a)
    if res is None:
        res = contact_step(q, vq, a, mq, gq, h, K=K, W=W, damping=C, integrator=sc.integrator,
                           unilateral=sc.unilateral, group=group, normal_of=wts,
                           always_damped=always if exact else None)
    impacts, fmax, indent, n_active = contact_post(
        soft, st.pos, st.vel, st.ctri, st.hit, was_open[np.searchsorted(near, soft)], nk, acc, q, a, vq,
        gq, res.q, res.v, res.active, res.seat_force, res.peak_seat_force, res.peak_ubar, sticky, exact, h,
        float(sc.rest_speed))
    stats = st.stats
    stats["impacts"] += int(impacts)
    st.lam = res.seat_force
    st._set_forces(cc, res.seat_force, res.peak_seat_force)
    stats["max_contact_force"] = max(stats["max_contact_force"], float(fmax))
    if n_active:
        stats["max_indentation_m"] = max(stats["max_indentation_m"], float(indent))
    stats["max_simultaneous_contacts"] = max(stats["max_simultaneous_contacts"], int(n_active))


def _modes(cc: ContactSet, mq: np.ndarray) -> tuple:
    """The contact set's normal modes (cached with the set)."""
    if cc.modes is None or cc.modes[2].shape != mq.shape:
        cc.modes = contact_modes(cc.K, mq)
    return cc.modes


def exact_damping(st: Storm, cc: ContactSet, mq: np.ndarray) -> np.ndarray:
    """Exact-integrator dashpot of a contact set, per mode (:func:`hailstorm.runtime.hail.modal_damping`;
    cached with the set)."""
    if cc.C is None or cc.C.shape != (mq.size, mq.size):
        om2, Phi, sqm = _modes(cc, mq)
        cc.C = substep_damping(om2, Phi, sqm, float(st.scene.restitution), 0.0, False, _X_GRID, _Z_GRID)
    return cc.C


def contact_matrices(st: Storm, cc: ContactSet, mq: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(K, W, C)`` of a sub-step ``h`` of the implicit or symplectic integrator.

    ``C`` is the dashpot per mode (:func:`hailstorm.runtime.hail.modal_damping`: backward
    Euler's numerical damping compensated). For the symplectic (explicit) step, ``K``
    and ``W`` carry the modes it can resolve (:func:`hailstorm.runtime.hail._explicit_modes`:
    unchanged at ``omega h`` <~ 0.3, at most ``1 / h^2``); the implicit step takes the
    set's own.
    """
    om2, Phi, sqm = _modes(cc, mq)
    sc = st.scene
    K, W = cc.K, cc.W
    if sc.integrator == "symplectic":
        om2 = explicit_modes(om2, float(h))
        K, W = modal_stiffness(om2, Phi, sqm)
    C = substep_damping(om2, Phi, sqm, float(sc.restitution), float(h), sc.integrator == "implicit", _X_GRID,
                        _Z_GRID)
    return K, W, C
