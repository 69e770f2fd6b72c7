"""The numpy narrow phase of a storm sub-step: closest points, time of impact, contacts
that open, hard walls.

Functions of a :class:`hailstorm.runtime.storm.Storm`'s state (``st``), called by
``Storm._substep`` on the numpy backend; :func:`hailstorm.runtime.compiled.free_phase` is
their compiled counterpart (it queries every free near stone: the query reuse
and the gap prediction here only save numpy calls). See the module notes of
:mod:`hailstorm.runtime.storm` for the rules.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hailstorm.runtime.hail import GRAVITY

if TYPE_CHECKING:  # pragma: no cover
    from hailstorm.runtime.storm import Storm

__all__ = ["Proximity", "contacts_to_open", "hard_walls", "open_contacts", "predict_gaps", "proximity",
           "reproject", "time_of_impact"]


@dataclass
class Proximity:
    """The near stones' closest points of one sub-step (see :func:`proximity`)."""

    near: np.ndarray  # (k,) the near stones
    in_contact: np.ndarray  # (k,) open contact at the sub-step's start
    qi: np.ndarray  # positions (in near) of the stones without a contact
    dist: np.ndarray  # (k,) distance centre - closest point (inf: nothing within reach)
    tri: np.ndarray  # (k,) closest triangle (-1: none)
    bary: np.ndarray  # (k, 3) its barycentric coordinates
    point: np.ndarray  # (k, 3) the closest point (nan: none or predicted)
    qreach: np.ndarray  # (k,) the query's reach (nan: no query)
    gap: np.ndarray  # (k,) dist - radius (0 in contact)
    eps: np.ndarray  # (k,) gap below which a contact opens


def reproject(st: Storm, stones: np.ndarray) -> np.ndarray:
    """True for open contacts whose stone is still over its triangle."""
    t = st.ctri[stones]
    P = st.X[st.gf.triangles[t]]
    n = st.index.normals[t]
    c = st.pos[stones]
    # barycentric coordinates of the centre projected on the triangle plane
    v0, v1 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    w = c - P[:, 0]
    w = w - np.einsum("ij,ij->i", w, n)[:, None] * n
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", w, v0)
    d21 = np.einsum("ij,ij->i", w, v1)
    den = d00 * d11 - d01 * d01
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    tol = 1e-3
    return (b1 >= -tol) & (b2 >= -tol) & (b1 + b2 <= 1 + tol)


def proximity(st: Storm, near: np.ndarray, in_contact: np.ndarray, h: float) -> Proximity:
    """Closest points of the deformed surface to the near stones without a kept contact
    (reused from the step's query or predicted where possible) and their gaps; an open
    contact keeps ``(t, beta)`` while its stone stays over the triangle, and one whose
    stone slid off moves to the closest point of the undeformed surface."""
    k = near.size
    keep = np.zeros(k, dtype=bool)
    if in_contact.any():
        keep[in_contact] = reproject(st, near[in_contact])
    dist = np.full(k, np.inf)
    tri = np.full(k, -1, dtype=np.intp)
    bary = np.zeros((k, 3))
    point = np.full((k, 3), np.nan)
    qreach = np.full(k, np.nan)
    qi = np.flatnonzero(~in_contact)
    if qi.size:
        j = near[qi]
        pad = np.sqrt(np.einsum("ij,ij->i", st.vel[j], st.vel[j])) * h
        reach = st.radius[j] + pad + 1e-3
        qreach[qi] = reach
        # reuse the end-of-step query where nothing moved since (same stamp, enough reach)
        lq = st._last_query
        fresh = np.zeros(j.size, bool)
        if lq is not None and lq[0] == st.stats["substeps"]:
            pos_in = np.searchsorted(lq[1], j)
            pos_in = np.minimum(pos_in, max(lq[1].size - 1, 0))
            if lq[1].size:
                fresh = (lq[1][pos_in] == j) & (lq[2][pos_in] >= reach)
        if fresh.any():
            assert lq is not None  # fresh is all False without a last query
            hq0 = lq[3]
            f_i = pos_in[fresh]
            dist[qi[fresh]], tri[qi[fresh]] = hq0.distance[f_i], hq0.triangle[f_i]
            bary[qi[fresh]], point[qi[fresh]] = hq0.bary[f_i], hq0.point[f_i]
            st.stats["queries_reused"] += int(fresh.sum())
        # stones whose gap was predicted by the previous sub-step of this step (they
        # could not touch in it): no query, the prediction is a lower bound
        # (only stones that cannot touch within the rest of the step; the bound shrinks
        # by the change of the seat's peak displacement since)
        pg = st._pgap[j] - abs(st.umax - st._pred_umax)
        sp = np.sqrt(np.einsum("ij,ij->i", st.vel[j], st.vel[j]))
        pred = ~fresh & (st._pstamp[j] == st.stats["substeps"]) & (pg > sp * h + GRAVITY * h * h + 1e-4)
        if pred.any():
            pj = j[pred]
            dist[qi[pred]] = pg[pred] + st.radius[pj]
            st.stats["queries_predicted"] += int(pred.sum())
        if not (fresh | pred).all():
            sub = ~(fresh | pred)
            hq = st._query(j[sub], reach[sub])
            dist[qi[sub]], tri[qi[sub]], bary[qi[sub]], point[qi[sub]] = hq.distance, hq.triangle, hq.bary, hq.point
        st.near_tri[j] = tri[qi]
    gap = np.where(in_contact, 0.0, dist - st.radius[near])
    st.gap[near] = gap
    # a contact whose stone slid off its triangle moves to the closest point of the
    # undeformed surface (the contact stays open: no spurious release and spring-back)
    moved = np.flatnonzero(in_contact & ~keep)
    if moved.size:
        j = near[moved]
        hm = st._query(j, 2.0 * st.radius[j] + st.umax + 1e-3, deformed=False)
        ok = hm.triangle >= 0
        st.ctri[j] = np.where(ok, hm.triangle, -1)
        st.cbary[j[ok]] = hm.bary[ok]
        tri[moved], bary[moved], point[moved] = hm.triangle, hm.bary, hm.point
        dist[moved] = hm.distance
    return Proximity(near=near, in_contact=in_contact, qi=qi, dist=dist, tri=tri, bary=bary,
                      point=point, qreach=qreach, gap=gap, eps=st._toi_tol * st.radius[near])


def time_of_impact(st: Storm, px: Proximity, h: float) -> float:
    """End the sub-step when the first approaching stone touches the tangent plane at
    its closest point (exact on a plane, conservative on convex parts; a concave
    overshoot is put back onto the surface when the contact opens)."""
    near, gap, point, eps = px.near, px.gap, px.point, px.eps
    fin = np.isfinite(gap) & ~px.in_contact & (gap > eps)
    if fin.any():
        fi = np.flatnonzero(fin)
        j = near[fi]
        dvec = st.pos[j] - point[fi]
        nrm = dvec / np.maximum(np.sqrt(np.einsum("ij,ij->i", dvec, dvec)), 1e-300)[:, None]
        w = -np.einsum("ij,ij->i", st.vel[j], nrm)  # approach speed
        an = -np.einsum("ij,ij->i", st._accel(j), nrm)
        hits = (w > 0) & (gap[fi] < w * h + 0.5 * np.abs(an) * h * h)
        if hits.any():
            wh, gh, ah = w[hits], gap[fi][hits], an[hits]
            # gap = w t + a t^2 / 2 (smallest positive root)
            disc = np.sqrt(np.maximum(wh * wh + 2.0 * ah * gh, 0.0))
            t_hit = 2.0 * gh / np.maximum(wh + disc, 1e-12)
            h = float(min(h, max(t_hit.min(), st._hmin)))
    return h


def contacts_to_open(st: Storm, px: Proximity) -> np.ndarray:
    """Mask of the near stones whose contact opens in this sub-step: within the opening
    gap and approaching (or overlapping) with time of impact, else overlapping."""
    near, gap, point, eps, tri = px.near, px.gap, px.point, px.eps, px.tri
    if not (st._toi and px.qi.size):
        return ~px.in_contact & (px.dist < st.radius[near]) & (tri >= 0)
    new = ~px.in_contact & (tri >= 0) & (gap < eps)
    if new.any():
        # open only stones that approach the (local) surface or overlap it
        nn = np.flatnonzero(new)
        dvec = st.pos[near[nn]] - point[nn]
        nrm = dvec / np.maximum(np.linalg.norm(dvec, axis=1, keepdims=True), 1e-300)
        vn = np.einsum("ij,ij->i", st.vel[near[nn]], nrm)
        new[nn] = (vn < 0) | (gap[nn] < -eps[nn])
    return new


def predict_gaps(st: Storm, px: Proximity, new: np.ndarray, h: float) -> None:
    """Gap lower bounds for the next sub-step of this step (free stones that stay free;
    nothing within the query's reach: the gap is at least reach - r)."""
    near, gap, point = px.near, px.gap, px.point
    gap_lb = np.where(np.isfinite(gap), gap, px.qreach - st.radius[near])
    keepf = ~px.in_contact & ~new & np.isfinite(gap_lb)
    fi = np.flatnonzero(keepf)
    if fi.size:
        j = near[fi]
        okp = np.isfinite(point[fi]).all(axis=1)
        dvec = st.pos[j] - np.where(okp[:, None], point[fi], st.pos[j])
        nrm = dvec / np.maximum(np.sqrt(np.einsum("ij,ij->i", dvec, dvec)), 1e-300)[:, None]
        w = np.maximum(-np.einsum("ij,ij->i", st.vel[j], nrm), 0.0)
        sp = np.sqrt(np.einsum("ij,ij->i", st.vel[j], st.vel[j]))
        w = np.where(okp, w, sp)  # predicted stones: no closest point, use |v|
        st._pgap[j] = gap_lb[fi] - w * h - GRAVITY * h * h
        st._pstamp[j] = st.stats["substeps"] + 1
        st._pred_umax = st.umax


def open_contacts(st: Storm, px: Proximity, new: np.ndarray) -> None:
    """Open the contacts ``new`` at their closest points; the stone is put on the surface."""
    near, gap, tri, bary = px.near, px.gap, px.tri, px.bary
    st.ctri[near[new]] = tri[new]
    st.cbary[near[new]] = bary[new]
    if new.any():
        j = near[new]
        nrm = st.index.normals[st.ctri[j]]
        if st._toi:
            # put the stone on the deformed surface (it is within eps of it)
            st.pos[j] -= gap[new][:, None] * nrm
        else:
            # a stone that opens a contact while approaching is put back onto the deformed
            # surface (it overshot by at most one sub-step's travel)
            approaching = np.einsum("ij,ij->i", st.vel[j], nrm) < 0
            depth = np.clip(-gap[new], 0.0, None) * approaching
            st.pos[j] += depth[:, None] * nrm


def hard_walls(st: Storm, near: np.ndarray, point: np.ndarray) -> None:
    """Contacts on triangles that cannot deform: projection out of the wall and a
    restitution bounce; the contact closes at once."""
    sc = st.scene
    opened = near[(st.ctri[near] >= 0)]
    t = st.ctri[opened]
    # (a contact point on the clamped edge or corner of a soft triangle cannot move either)
    pinned = (st.cbary[opened] * ~st._fixed[st.gf.triangles[t]]).sum(axis=1) <= 1e-12
    wall = opened[~st.soft[t] | pinned]
    if wall.size:
        j = np.searchsorted(near, wall)
        dvec = st.pos[wall] - point[j]
        dw = np.linalg.norm(dvec, axis=1, keepdims=True)
        nrm = np.where(dw > 1e-12, dvec / np.maximum(dw, 1e-300), st.index.normals[st.ctri[wall]])
        st.pos[wall] += np.clip(st.radius[wall][:, None] - dw, 0.0, None) * nrm
        vn = np.einsum("ij,ij->i", st.vel[wall], nrm)
        imp = vn < 0
        st.vel[wall] -= ((1.0 + sc.restitution) * np.minimum(vn, 0.0))[:, None] * nrm
        st.stats["wall_contacts"] += int(imp.sum())
        st.ctri[wall] = -1
