"""Stones that meet: the broad phase of stone pairs, their time of impact within a step,
and the normal impact of two elastic spheres integrated through its contact.

The storm's orchestration is :mod:`hailstorm.runtime.storm.stone_collisions`; the closed
forms the tests hold these kernels to are :func:`hailstorm.runtime.storm.stone_collisions.hertz_impact`.

The contact law (one pair, along the line of centres; ``delta`` the overlap)
----------------------------------------------------------------------------
* compression (``delta' > 0``): Hertz, ``F = k delta^(3/2)``, ``k = 4/3 E* sqrt(R*)``;
* restitution (``delta' <= 0``): ``F = (k / e^3) (delta - delta_p)^(3/2)`` with
  ``delta_p = (1 - e^2) delta_max``: the unloading curve through the peak that returns
  the share ``e^2`` of the stored energy, so the pair separates at ``e`` times its
  approach speed (Thornton's elastic-plastic unloading in its Hertzian form);
  ``e = 0``: the pair stops at the peak and separates with no speed.

The contact lasts tens of microseconds for hailstones (much less than a storm step):
:func:`hertz_impact` integrates it to its end with RK4 in a fixed number of steps per
phase, the maximum compression and the release located inside their steps.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["candidate_pairs", "collide_pairs", "hertz_impact"]


@kernel
def _force(delta, k, delta_p):  # pragma: no cover (compiled)
    """The pair's contact force ``k (delta - delta_p)^(3/2)`` at overlap ``delta`` (compression:
    Hertz's ``k``, ``delta_p = 0``; restitution: the unloading law's)."""
    d = delta - delta_p
    return k * d ** 1.5 if d > 0.0 else 0.0


@kernel
def _rk4(delta, w, h, m, k, delta_p):  # pragma: no cover (compiled)
    """One RK4 step of ``delta' = w``, ``m w' = -F(delta)``."""
    a1 = -_force(delta, k, delta_p) / m
    d2, w2 = delta + 0.5 * h * w, w + 0.5 * h * a1
    a2 = -_force(d2, k, delta_p) / m
    d3, w3 = delta + 0.5 * h * w2, w + 0.5 * h * a2
    a3 = -_force(d3, k, delta_p) / m
    d4, w4 = delta + h * w3, w + h * a3
    a4 = -_force(d4, k, delta_p) / m
    return (delta + h / 6.0 * (w + 2.0 * w2 + 2.0 * w3 + w4),
            w + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4))


@kernel
def hertz_impact(m_eff, r_eff, e_star, speed, restitution, steps):  # pragma: no cover (compiled)
    """The normal impact of two elastic spheres, integrated through the contact.

    Parameters
    ----------
    m_eff, r_eff : float
        The pair's effective mass ``m1 m2 / (m1 + m2)`` [kg] and radius ``R1 R2 / (R1 + R2)`` [m].
    e_star : float
        The contact modulus ``E*`` [Pa] (``1/E* = (1 - nu1^2)/E1 + (1 - nu2^2)/E2``).
    speed : float
        The approach speed along the line of centres [m/s] (> 0).
    restitution : float
        The coefficient of restitution ``e`` in [0, 1] (the module's unloading law).
    steps : int
        RK4 steps per phase (the step is the phase's duration over ``steps``, from the
        Hertz time scale ``delta_max / speed``).

    Returns
    -------
    speed_out : float
        The separation speed [m/s].
    duration : float
        The contact time [s].
    peak_force : float
        The largest contact force [N].
    delta_max : float
        The largest overlap [m].
    """
    k = 4.0 / 3.0 * e_star * math.sqrt(r_eff)
    # the time scale of the compression (only sizes the steps): Hertz's overlap over the speed
    scale = (1.25 * m_eff * speed * speed / k) ** 0.4 / speed
    h = 1.5 * scale / steps
    delta, w, t = 0.0, speed, 0.0
    zero = 0.0
    # compression: to the instant the approach stops (w = 0), located by Newton on the step
    for _ in range(100 * steps):
        d1, w1 = _rk4(delta, w, h, m_eff, k, zero)
        if w1 <= 0.0:
            hs, ds = h, d1
            for _it in range(40):  # the sub-step that ends at w = 0 (w is smooth there)
                ds, ws = _rk4(delta, w, hs, m_eff, k, zero)
                if abs(ws) <= 1e-14 * speed:
                    break
                a = -_force(ds, k, zero) / m_eff
                hs = hs - ws / a
            delta, w, t = ds, 0.0, t + hs
            break
        delta, w, t = d1, w1, t + h
    delta_max = delta
    peak = k * delta_max ** 1.5
    e = restitution
    if e <= 0.0:
        return 0.0, t, peak, delta_max
    delta_p = (1.0 - e * e) * delta_max
    k_u = k / (e * e * e)
    h = 1.5 * e * scale / steps  # (the restitution lasts e times the compression)
    for _ in range(100 * steps):
        d1, w1 = _rk4(delta, w, h, m_eff, k_u, delta_p)
        if d1 <= delta_p:
            # released within the step: the force vanishes there, so the speed is constant to
            # second order and the release time is the linear crossing
            frac = (delta - delta_p) / (delta - d1) if delta > d1 else 1.0
            return -w1, t + frac * h, peak, delta_max
        delta, w, t = d1, w1, t + h
    return -w, t, peak, delta_max  # (not reached: the release comes within ~steps steps)


@kernel
def candidate_pairs(live, pos0, pos, radius, margin):  # pragma: no cover (compiled)
    """Pairs of the ``live`` stones whose swept boxes (from ``pos0`` to ``pos``, grown by
    the radius and ``margin`` radii) overlap: sort and sweep along x, (p, 2) ids."""
    n = live.size
    lo = np.empty((n, 3))
    hi = np.empty((n, 3))
    for q in range(n):
        i = live[q]
        g = radius[i] * (1.0 + margin)
        for d in range(3):
            lo[q, d] = min(pos0[i, d], pos[i, d]) - g
            hi[q, d] = max(pos0[i, d], pos[i, d]) + g
    order = np.argsort(lo[:, 0])
    out = np.empty((max(4 * n, 16), 2), np.int64)
    c = 0
    for a in range(n):
        qa = order[a]
        for b in range(a + 1, n):
            qb = order[b]
            if lo[qb, 0] > hi[qa, 0]:
                break
            if lo[qb, 1] > hi[qa, 1] or lo[qa, 1] > hi[qb, 1] or lo[qb, 2] > hi[qa, 2] or lo[qa, 2] > hi[qb, 2]:
                continue
            if c == out.shape[0]:
                bigger = np.empty((2 * c, 2), np.int64)
                bigger[:c] = out[:c]
                out = bigger
            i, j = live[qa], live[qb]
            out[c, 0] = min(i, j)
            out[c, 1] = max(i, j)
            c += 1
    return out[:c]


@kernel
def _at(i, t, t0, p0, pos, dt, out):  # pragma: no cover (compiled)
    """Stone ``i``'s centre at ``t`` in the step: straight from ``p0[i]`` (at ``t0[i]``) to ``pos[i]`` (at ``dt``)."""
    span = dt - t0[i]
    f = (t - t0[i]) / span if span > 0.0 else 1.0
    for d in range(3):
        out[d] = p0[i, d] + (pos[i, d] - p0[i, d]) * f


@kernel
def _toi(i, j, t0, p0, pos, vel, radius, dt):  # pragma: no cover (compiled)
    """The first instant in the step at which stones ``i`` and ``j`` touch while approaching
    (their centres on straight paths; -1: none)."""
    ts = max(t0[i], t0[j])
    a = np.empty(3)
    b = np.empty(3)
    _at(i, ts, t0, p0, pos, dt, a)
    _at(j, ts, t0, p0, pos, dt, b)
    d0 = b - a
    d1 = (pos[j] - pos[i]) - d0  # the change of the separation over [ts, dt]
    reach = radius[i] + radius[j]
    A = d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]
    B = 2.0 * (d0[0] * d1[0] + d0[1] * d1[1] + d0[2] * d1[2])
    C = d0[0] * d0[0] + d0[1] * d0[1] + d0[2] * d0[2] - reach * reach
    if C <= 0.0:
        f = 0.0  # touching already at ts
    else:
        disc = B * B - 4.0 * A * C
        if A <= 0.0 or disc < 0.0 or B >= 0.0:
            return -1.0
        f = (-B - math.sqrt(disc)) / (2.0 * A)
        if f > 1.0:
            return -1.0
    tc = ts + f * (dt - ts)
    # approaching at that instant (the end-of-step velocities: gravity is common to both)
    dx = d0 + f * d1
    if (vel[i, 0] - vel[j, 0]) * dx[0] + (vel[i, 1] - vel[j, 1]) * dx[1] + (vel[i, 2] - vel[j, 2]) * dx[2] <= 0.0:
        return -1.0
    return tc


@kernel
def collide_pairs(pairs, pos0, pos, vel, radius, mass, dt, e_star, restitution, steps,
                  max_rounds):  # pragma: no cover (compiled)
    """Resolve the stone collisions of one step, in time order, in place.

    Each stone moves straight from ``pos0`` (the step's start) to ``pos`` (its end); a pair of
    ``pairs`` that touches while approaching is resolved at its time of impact ``tau`` as an
    isolated normal impact (:func:`hertz_impact`, frictionless): both velocities change by the
    impulse along the line of centres, and each end position by its velocity change times
    ``dt - tau`` (the rest of the step); the stone's path then starts again at ``tau``. The
    earliest impact first, until no pair meets (at most ``max_rounds``).

    Returns
    -------
    records : (c, 8) ndarray
        Per impact: stone i, stone j, tau [s into the step], approach speed [m/s],
        separation speed [m/s], contact time [s], peak force [N], impulse [N s].
    """
    nmax = pos.shape[0]
    t0 = np.zeros(nmax)
    p0 = pos0.copy()
    records = np.empty((max_rounds, 8))
    c = 0
    a = np.empty(3)
    b = np.empty(3)
    for _ in range(max_rounds):
        best, tbest = -1, dt + 1.0
        for q in range(pairs.shape[0]):
            tc = _toi(pairs[q, 0], pairs[q, 1], t0, p0, pos, vel, radius, dt)
            if tc >= 0.0 and tc < tbest:
                best, tbest = q, tc
        if best < 0:
            break
        i, j = pairs[best, 0], pairs[best, 1]
        _at(i, tbest, t0, p0, pos, dt, a)
        _at(j, tbest, t0, p0, pos, dt, b)
        n = b - a
        ln = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        if ln <= 0.0:
            break  # (coincident centres: no line of centres)
        n /= ln
        vn = (vel[i, 0] - vel[j, 0]) * n[0] + (vel[i, 1] - vel[j, 1]) * n[1] + (vel[i, 2] - vel[j, 2]) * n[2]
        mi, mj = mass[i], mass[j]
        m_eff = mi * mj / (mi + mj)
        r_eff = radius[i] * radius[j] / (radius[i] + radius[j])
        out, duration, peak, _dmax = hertz_impact(m_eff, r_eff, e_star, vn, restitution, steps)
        J = m_eff * (vn + out)
        rest = dt - tbest
        for d in range(3):
            dvi = -J / mi * n[d]
            dvj = J / mj * n[d]
            vel[i, d] += dvi
            vel[j, d] += dvj
            pos[i, d] += dvi * rest
            pos[j, d] += dvj * rest
            p0[i, d] = a[d]
            p0[j, d] = b[d]
        t0[i] = tbest
        t0[j] = tbest
        records[c, 0] = i
        records[c, 1] = j
        records[c, 2] = tbest
        records[c, 3] = vn
        records[c, 4] = out
        records[c, 5] = duration
        records[c, 6] = peak
        records[c, 7] = J
        c += 1
    return records[:c]
