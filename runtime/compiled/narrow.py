"""The storm's narrow phase: the free part of a sub-step (closest points, time of impact,
contacts that open, hard walls) and the penetration statistics.

The rules are in the module notes of :mod:`hailstorm.runtime.storm.driver`; the tests hold the
closest points to brute force over every triangle (``tests/reference/collide_ref.py``)
and the whole to analytic bounces.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.flight import drag_dot
from hailstorm.runtime.compiled.grid import closest_one, triangle_distance

__all__ = ["contact_normal", "free_phase", "penetration"]


@kernel
def _unit(x, out):  # pragma: no cover (compiled)
    ln = max(math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]), 1e-300)
    for e in range(3):
        out[e] = x[e] / ln
    return ln


#: a stone in a patch's dead zone moves at most this many radii per sub-step (its contact
#: surface is within the dead zone of the seat: a tangent plane predicts the time of impact
#: only over a short way on a curved seat)
DEAD_ZONE_REACH = 0.1


#: how far (beyond its offset, in contact-surface radii) a stone receding in its engagement may lie
#: inside its contact surface and be put back on it instead of opening a contact (:func:`free_phase`)
RELEASE_OVERLAP = 0.1


@kernel
def _opening(toi_tol, radius, offset):  # pragma: no cover (compiled)
    """The gap within which a stone's contact opens: ``toi_tol`` of its contact radius, or of
    its offset when it flies through a patch's dead zone (so that it engages where it should)."""
    if offset > 0.0:
        return toi_tol * min(radius - offset, offset)
    return toi_tol * radius


@kernel
def _over_triangle(p, t, X, T, tri_normals):  # pragma: no cover (compiled)
    """Does ``p`` project onto triangle ``t`` (undeformed; 1e-3 of its edges' slack)?"""
    n0 = tri_normals[t, 0]; n1 = tri_normals[t, 1]; n2 = tri_normals[t, 2]
    a = T[t, 0]; b = T[t, 1]; c = T[t, 2]
    v00 = X[b, 0] - X[a, 0]; v01 = X[b, 1] - X[a, 1]; v02 = X[b, 2] - X[a, 2]
    v10 = X[c, 0] - X[a, 0]; v11 = X[c, 1] - X[a, 1]; v12 = X[c, 2] - X[a, 2]
    w0 = p[0] - X[a, 0]; w1 = p[1] - X[a, 1]; w2 = p[2] - X[a, 2]
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
    return b1 >= -1e-3 and b2 >= -1e-3 and b1 + b2 <= 1.0 + 1e-3


@kernel
def _plane_distance(i, t, pos, cbary, cnormal, X, T):  # pragma: no cover (compiled)
    """The distance of stone ``i``'s centre from its contact's plane: through the point
    ``cbary[i]`` of triangle ``t``, at right angles to the contact's normal ``cnormal[i]``."""
    dn = 0.0
    for e in range(3):
        xe = 0.0
        for c in range(3):
            xe += cbary[i, c] * X[T[t, c], e]
        dn += cnormal[i, e] * (pos[i, e] - xe)
    return dn


#: a barycentric weight at most this counts as 0 (the closest point on that side's edge or corner)
_ON_BOUNDARY = 1e-12


@kernel
def contact_normal(p, t, bary, X, T, tri_normals, corner, sharp_edge, sharp_vertex, bt,
                   out):  # pragma: no cover (compiled)
    """The unit normal of a contact at ``bary`` on triangle ``t`` (undeformed) of the sphere
    centred at ``p``, into ``out`` (``bt``: scratch).

    The faceted surface read as a smooth one: the normals at the triangle's corners
    interpolated at ``bary`` (``corner``, (m, 3, 3), :func:`hailstorm.runtime.contact.weights.corner_normals`),
    continuous across an edge. But where ``p`` lies over a sharp edge or corner of ``t``
    (``sharp_edge`` (m, 3): edge ``k`` from corner ``k`` to ``k + 1``; ``sharp_vertex`` (n,):
    :func:`hailstorm.runtime.storm.collide.sharp_features`), the closest point of ``t`` on it,
    the direction from that point to ``p``: the sphere on the edge, turning from one side's
    normal to the other's. The triangle's normal where either does not face its side."""
    dn = 0.0
    ln = 0.0
    for e in range(3):
        out[e] = bary[0] * corner[t, 0, e] + bary[1] * corner[t, 1, e] + bary[2] * corner[t, 2, e]
        dn += out[e] * tri_normals[t, e]
        ln += out[e] * out[e]
    ln = math.sqrt(ln)
    if dn > 0.0 and ln > 0.0:
        for e in range(3):
            out[e] /= ln
    else:
        for e in range(3):
            out[e] = tri_normals[t, e]
    a = T[t, 0]; b = T[t, 1]; c = T[t, 2]
    triangle_distance(p, X[a], X[b], X[c], bt)
    zeros = 0
    k0 = -1
    kv = -1
    for k in range(3):
        if bt[k] <= _ON_BOUNDARY:
            zeros += 1
            k0 = k
        else:
            kv = k
    if zeros == 0:
        return
    sharp = sharp_edge[t, (k0 + 1) % 3] if zeros == 1 else sharp_vertex[T[t, kv]]
    if not sharp:
        return
    f0 = p[0] - (bt[0] * X[a, 0] + bt[1] * X[b, 0] + bt[2] * X[c, 0])
    f1 = p[1] - (bt[0] * X[a, 1] + bt[1] * X[b, 1] + bt[2] * X[c, 1])
    f2 = p[2] - (bt[0] * X[a, 2] + bt[1] * X[b, 2] + bt[2] * X[c, 2])
    fn = f0 * tri_normals[t, 0] + f1 * tri_normals[t, 1] + f2 * tri_normals[t, 2]
    fl = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    if fl > 0.0 and fn > 1e-9 * fl:
        out[0] = f0 / fl
        out[1] = f1 / fl
        out[2] = f2 / fl


@kernel
def free_phase(near, h, toi, toi_tol, hmin, pos, vel, radius, offset, shift, ctri, cbary, cnormal, gap, near_tri, surf,
               tri_normals, corner, sharp_edge, sharp_vertex, soft, fixed, rigid_weight, umax, use_u, D, fcols, fv, g, wind, drag_coef,
               restitution):  # pragma: no cover
    """The first phases of one storm sub-step for the near stones, in place: closest
    points, time of impact, contacts that open, hard walls.

    A stone's contact surface is the sphere of radius ``radius - offset``
    (:meth:`hailstorm.runtime.storm.stones.Stones.contact_radius`; the queries reach its
    whole sphere). Stones without a contact query the deformed surface; an open contact
    keeps its ``(t, beta)`` while the closest point of the undeformed surface lies on that
    triangle (inside it or on its boundary), else moves to it; its anchor lies ``shift`` out
    along its normal ``cnormal`` (:func:`contact_normal` of the corners' normals ``corner`` and
    the sharp edges and corners ``sharp_edge``, ``sharp_vertex``, set where the contact opens or
    moves;
    :attr:`hailstorm.runtime.storm.stones.Stones.shift`; the module
    notes of :mod:`hailstorm.runtime.storm.driver`, "Facets"). With ``toi`` the sub-step ends when the
    first approaching stone reaches the tangent plane at its closest point (one
    approaching in a patch's dead zone moves at most ``DEAD_ZONE_REACH`` radii); contacts
    open within ``toi_tol`` radii (approaching or overlapping; ``toi_tol`` of the offset in
    a patch's dead zone), the stone put on the surface along the contact's normal (its
    contact surface at the closest point; the anchor out by the normal's tilt from the
    direction to that point). A free stone whose sphere is
    clear of the surface ends its engagement (``offset`` set to 0, in place). Contacts on
    hard triangles (or on the clamped edge or corner of a soft one: at most
    ``rigid_weight`` of the closest point's barycentric weight on free vertices,
    :data:`hailstorm.runtime.contact.policy.RIGID_WEIGHT`) bounce at once.

    Returns
    -------
    h : float
        The sub-step actually taken.
    walls : int
        Impacts on hard triangles.

    Notes
    -----
    One kernel over two hundred lines, on purpose: split into its four phases (closest
    points, time of impact, contacts that open, hard walls) as separate kernels it compiled in
    7.6 s of CPU instead of 6.0 s on a first run (``tests/benchmarks/compile_time.py``,
    2026-12-06, load 0.8), the same arithmetic; the first run's compile is what issue #44 asks
    to shorten. The phases are marked by comments.
    """
    X = surf[8]
    T = surf[9]
    k = near.size
    nv = X.shape[0]
    done = np.zeros(nv if use_u else 0, np.bool_)
    Y = np.empty((nv if use_u else 0, 3))
    done0 = np.zeros(0, np.bool_)
    Y0 = np.empty((0, 3))
    # a bool variable, not the literal False: a literal argument compiles a second
    # specialisation of closest_one (~4 s of a first run)
    undeformed = use_u and not use_u
    in_contact = np.zeros(k, np.bool_)
    # (filled by a loop, not np.full: its three specialisations cost ~0.7 s of a first run)
    dist = np.empty(k)
    tri = np.empty(k, np.int64)
    bary = np.zeros((k, 3))
    point = np.empty((k, 3))
    for j in range(k):
        dist[j] = np.inf
        tri[j] = -1
        for e in range(3):
            point[j, e] = np.nan
    gp = np.zeros(k)
    bt = np.empty(3)
    nrm = np.empty(3)
    dvec = np.empty(3)
    queried = False
    for j in range(k):
        i = near[j]
        if ctri[i] >= 0:
            in_contact[j] = True
            # the closest point of the undeformed surface: the contact keeps its (t, beta) while
            # that point lies on t (inside it or on its boundary), else moves there (module notes);
            # asked only once the centre no longer projects onto t (a nearer plane inside t's prism,
            # past a concave edge's bisector, is taken up by the shift when the contact moves)
            t = ctri[i]
            if _over_triangle(pos[i], t, X, T, tri_normals):
                gap[i] = 0.0
                continue
            tt, dd = closest_one(pos[i], 2.0 * radius[i] + umax + 1e-3, 0.0, undeformed, surf, D, fcols, fv,
                                  done0, Y0, bary[j], point[j])
            moved = False
            if tt < 0:  # (nothing within reach: the contact is gone)
                ctri[i] = -1
                shift[i] = 0.0
                tri[j] = tt
                dist[j] = dd
            elif tt != t:
                a = T[t, 0]; b = T[t, 1]; c = T[t, 2]
                moved = triangle_distance(pos[i], X[a], X[b], X[c], bt) > dd + 1e-9 * radius[i]
            if moved:  # to the closest point; the spring's length carried over if it would shorten
                before = _plane_distance(i, t, pos, cbary, cnormal, X, T) + shift[i]
                ctri[i] = tt
                for e in range(3):
                    cbary[i, e] = bary[j, e]
                contact_normal(pos[i], tt, cbary[i], X, T, tri_normals, corner, sharp_edge, sharp_vertex, bt, nrm)
                for e in range(3):
                    cnormal[i, e] = nrm[e]
                tri[j] = tt
                dist[j] = dd
                shift[i] = max(before - _plane_distance(i, tt, pos, cbary, cnormal, X, T), 0.0)
        else:
            queried = True
            sp = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
            tt, dd = closest_one(pos[i], radius[i] + sp * h + 1e-3, umax if use_u else 0.0, use_u, surf, D,
                                  fcols, fv, done, Y, bary[j], point[j])
            tri[j] = tt
            dist[j] = dd
            near_tri[i] = tt
            gp[j] = dd - (radius[i] - offset[i])
            if offset[i] > 0.0 and gp[j] > offset[i]:  # its sphere is clear: the engagement is over
                gp[j] -= offset[i]
                offset[i] = 0.0
        gap[i] = gp[j]
    timing = toi and queried
    # time of impact: the first approaching stone to reach its tangent plane
    if timing:
        tmin = np.inf
        for j in range(k):
            i = near[j]
            if in_contact[j] or not np.isfinite(gp[j]) or not gp[j] > _opening(toi_tol, radius[i], offset[i]):
                continue
            for e in range(3):
                dvec[e] = pos[i, e] - point[j, e]
            _unit(dvec, nrm)
            w = -(vel[i, 0] * nrm[0] + vel[i, 1] * nrm[1] + vel[i, 2] * nrm[2])
            an = -drag_dot(i, vel, radius, nrm, g, wind, drag_coef)
            if w > 0.0 and gp[j] < w * h + 0.5 * abs(an) * h * h:
                disc = math.sqrt(max(w * w + 2.0 * an * gp[j], 0.0))
                tmin = min(tmin, 2.0 * gp[j] / max(w + disc, 1e-12))
            if offset[i] > 0.0 and w > 0.0:  # approaching in a patch's dead zone: the tangent plane holds only so far
                tmin = min(tmin, DEAD_ZONE_REACH * radius[i] / max(math.sqrt(
                    vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2), 1e-12))
        if tmin < np.inf:
            h = min(h, max(tmin, hmin))
    # contacts that open, at their closest points
    for j in range(k):
        i = near[j]
        if in_contact[j] or tri[j] < 0:
            continue
        eps = _opening(toi_tol, radius[i], offset[i])
        if timing:
            if not gp[j] < eps:
                continue
            for e in range(3):
                dvec[e] = pos[i, e] - point[j, e]
            _unit(dvec, nrm)
            vn = vel[i, 0] * nrm[0] + vel[i, 1] * nrm[1] + vel[i, 2] * nrm[2]
            if not (vn < 0.0 or gp[j] < -eps):
                continue
            if vn >= 0.0 and offset[i] > 0.0 and gp[j] >= -(offset[i] + RELEASE_OVERLAP * (radius[i] - offset[i])):
                # receding in its engagement, inside its contact surface by little: a contact released
                # on the tangent plane it kept while the stone slid (a frictionless contact keeps its
                # point and normal) meets the surface's own curvature, or a ridge, under the slide.
                # The stone is leaving: it is put back on its contact surface, its velocity kept.
                # Opening a contact here cost it the dashpot's damping for one sub-step at a fine dt
                # and nothing at a coarse one (measured: 1 % of the rebound speed across a ridge at
                # dt 0.02 ms, not at 0.5 ms)
                for e in range(3):
                    pos[i, e] -= gp[j] * nrm[e]
                gap[i] = 0.0
                continue
        elif not dist[j] < radius[i] - offset[i]:
            continue
        t = tri[j]
        ctri[i] = t
        for e in range(3):
            cbary[i, e] = bary[j, e]
        # put on the surface along the contact's normal, its contact surface at the (deformed)
        # closest point: out by the overlap (in by a gap within the tolerance); where the normal
        # is not the direction from that point to the centre (the smooth surface's normal, tilted
        # from the facet's, or an edge's side), the anchor lies out by the difference, so that
        # the spring starts at its rest length (or compressed by the overlap of a stone that is
        # not approaching, without the time of impact)
        contact_normal(pos[i], t, cbary[i], X, T, tri_normals, corner, sharp_edge, sharp_vertex, bt, nrm)
        dn = 0.0
        for e in range(3):
            cnormal[i, e] = nrm[e]
            dn += nrm[e] * (pos[i, e] - point[j, e])
        push = (radius[i] - offset[i]) - dist[j]
        if not timing:
            vn = vel[i, 0] * nrm[0] + vel[i, 1] * nrm[1] + vel[i, 2] * nrm[2]
            push = max(push, 0.0) if vn < 0.0 else 0.0
        for e in range(3):
            pos[i, e] += push * nrm[e]
        shift[i] = max(dist[j] - dn, 0.0)
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
            if free_w > rigid_weight:
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


@kernel
def penetration(near, dt, pos, vel, radius, ctri, surf, umax, use_u, D, fcols, fv):  # pragma: no cover
    """Overlap of the near stones with the deformed surface, for the statistics
    (:meth:`hailstorm.runtime.storm.collide.Collision.penetration`): free stones within this step's reach, stones in
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
        t, d = closest_one(pos[i], reach, umax if use_u else 0.0, use_u, surf, D, fcols, fv, done, Y, bary, point)
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
