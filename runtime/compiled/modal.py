"""Plain-Python statements of the modal contact algebra that numba compiles
(:mod:`hailstorm.runtime.compiled.integrators`) and that :func:`hailstorm.runtime.storm.hail.modal_damping`
(the dashpot) and the tests' numpy contact step (``tests/reference/contact_step_ref.py``)
call as they are: one definition of each.

* :func:`modal_damping_py` -- the dashpot per normal mode (target restitution);
* :func:`explicit_modes_py`, :func:`modal_stiffness_py` -- the modes an explicit step carries;
* :func:`scalar_exact_py` -- the exact integrator's closed-form single contact;
* :func:`interp_py` / :data:`interp1` -- ``np.interp`` for one value, numpy's rule (compiled).
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["explicit_modes_py", "interp1", "interp_py", "modal_damping_py", "modal_stiffness_py", "scalar_exact_py"]


def interp_py(x, xp, fp):
    """``np.interp(x, xp, fp)`` for one float and increasing ``xp``, by numpy's rule (the
    largest ``j`` with ``xp[j] <= x``; the same slope formula and NaN fallback), so that
    the result is numpy's bit for bit: compiled, numba's ``np.interp`` costs ~6 s of a
    first run's compile for this one call."""
    n = xp.size
    if x != x:
        return x
    if x > xp[n - 1]:
        return fp[n - 1]
    if x < xp[0]:
        return fp[0]
    lo = 0
    hi = n
    while lo < hi:
        mid = (lo + hi) >> 1
        if x >= xp[mid]:
            lo = mid + 1
        else:
            hi = mid
    j = lo - 1
    if j == n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    r = slope * (x - xp[j]) + fp[j]
    if r != r:
        r = slope * (x - xp[j + 1]) + fp[j + 1]
        if r != r and fp[j] == fp[j + 1]:
            r = fp[j]
    return r


interp1 = kernel(interp_py)


def modal_damping_py(om2, Phi, sqm, restitution, dt, implicit, x_grid, z_grid):
    """The dashpot matrix ``M^1/2 Phi diag(2 zeta_j omega_j) Phi^T M^1/2`` (plain numpy that
    this package also compiles): every mode ``j`` gets the damping ratio of
    the target restitution (implicit: less backward Euler's numerical ``omega_j dt / 2``),
    zero modes none."""
    n = om2.size
    c = np.zeros(n)
    for j in range(n):
        om = math.sqrt(max(om2[j], 0.0))
        if om <= 0.0:
            continue
        e = restitution
        zn = 0.0
        if implicit:
            zn = 0.5 * om * dt
            # the restitution phase loses exp(-zn pi/2); beyond the target no dashpot
            x = -math.log(min(max(e, 1e-300), 1.0)) - zn * math.pi / 2.0
            if x <= 0.0:
                continue
        else:
            x = -math.log(min(max(e, 1e-300), 1.0))
        z = interp1(x, x_grid, z_grid)
        c[j] = 2.0 * max(z - zn, 0.0) * om
    # (loops, not broadcasts: the same products, bit for bit, ~1 s less of a first run's compile)
    r, k = Phi.shape
    P = np.empty((r, k))
    Pc = np.empty((r, k))
    PT = np.empty((k, r))
    for i in range(r):
        for j in range(k):
            P[i, j] = Phi[i, j] * sqm[i]
            Pc[i, j] = P[i, j] * c[j]
            PT[j, i] = P[i, j]
    C = Pc @ PT
    out = np.empty((r, r))
    for i in range(r):
        for j in range(r):
            out[i, j] = 0.5 * (C[i, j] + C[j, i])
    return out


def explicit_modes_py(om2, dt):
    """Squared modal frequencies an explicit step of ``dt`` can carry:
    ``omega^2 / sqrt(1 + (omega dt)^4)`` (unchanged to 1e-3 at ``omega dt = 0.2``;
    at most ``1 / dt^2``, inside symplectic Euler's stability limit ``omega dt < 2``).
    Stiff modes (contacts closer than the mesh resolves, whose relative motion the
    stones do not excite) would otherwise need sub-steps no storm can afford."""
    out = np.empty(om2.size)
    for j in range(om2.size):
        x = om2[j] * dt * dt
        out[j] = om2[j] / math.sqrt(1.0 + x * x)
    return out


def modal_stiffness_py(om2, Phi, sqm):
    """``K = M^1/2 Phi diag(om2) Phi^T M^1/2`` and its (pseudo-)inverse ``W`` (zero modes dropped)."""
    P = np.ascontiguousarray(Phi * sqm.reshape(-1, 1))
    Q = np.ascontiguousarray(Phi / sqm.reshape(-1, 1))
    inv = np.zeros(om2.size)
    top = 0.0
    for j in range(om2.size):
        top = max(top, om2[j])
    for j in range(om2.size):
        if om2[j] > 1e-10 * top:
            inv[j] = 1.0 / om2[j]
    K = np.ascontiguousarray(P * om2.reshape(1, -1)) @ np.ascontiguousarray(P.T)
    W = np.ascontiguousarray(Q * inv.reshape(1, -1)) @ np.ascontiguousarray(Q.T)
    return 0.5 * (K + K.T), 0.5 * (W + W.T)


def scalar_exact_py(q: float, v: float, a: float, m: float, g: float, dt: float, k: float, c: float,
                  unilateral: bool, always: bool) -> tuple[float, float, bool, bool, float, float]:
    """One frictionless contact, closed form (plain floats; :mod:`hailstorm.runtime.compiled`
    compiles this same function for its exact step). Returns ``(q, v, active, ok, umin, umax)``;
    ``ok`` is False when the case is not covered (overdamped, or release from an
    always-damped state): the general path then takes the step. ``umin``, ``umax``
    are the smallest and largest ``q - a`` (the deepest compression; the largest
    stretch of a bilateral contact) while the contact is closed during the step,
    located analytically: the closed form's extrema in each segment lie at its ends or
    at the zeros of ``v``, and a damped oscillation's first minimum (maximum) is its
    deepest (highest), so the ends and the first two zeros of ``v`` in the segment
    suffice."""
    t = 0.0
    umin = umax = q - a
    damp = always or v < 0.0
    if unilateral and not damp and -k * (q - a) < 0.0 and v >= 0.0:
        return q, v, True, False, umin, umax  # pulls at the start: let the general path release it
    w2 = k / m
    if w2 <= 0.0:
        return q, v, True, False, umin, umax
    off = a + g / w2  # equilibrium q_eq
    finished = False
    for _ in range(6):
        h = dt - t
        if h <= 0.0:
            finished = True
            break
        ce = c if damp else 0.0
        sig = 0.5 * ce / m
        wd2 = w2 - sig * sig
        if wd2 <= 1e-6 * w2:
            return q, v, True, False, umin, umax
        wd = math.sqrt(wd2)
        y0 = q - off
        A, B = y0, (v + sig * y0) / wd
        P, Q = v, A * wd + sig * B  # v(t) = e^{-sig t} (P cos wd t - Q sin wd t)
        te = h
        kind = 0
        # first zero of v (wd t = atan2(P, Q) mod pi); the next one is pi / wd later
        tv0 = (math.atan2(P, Q) % math.pi) / wd
        if c > 0.0 and not always:
            # v(t) = 0: wd t = atan2(P, Q) mod pi (first positive root)
            th = math.atan2(P, Q) % math.pi
            if th <= 1e-12:
                th += math.pi
            tv = th / wd
            if tv < te:
                te, kind = tv, 1
        if unilateral and ce == 0.0:
            # release: q = a while moving out (undamped: y = R cos(wd t - phi))
            R = math.hypot(A, B)
            ystar = a - off
            if R > abs(ystar) and R > 0.0:
                phi = math.atan2(B, A)
                al = math.acos(max(-1.0, min(1.0, ystar / R)))
                # y = ystar with v >= 0 (y increasing): wd t - phi = -al (mod 2 pi)
                tr = ((-al + phi) % (2.0 * math.pi)) / wd
                if tr <= 1e-15 * dt:
                    tr += 2.0 * math.pi / wd
                if tr < te:
                    te, kind = tr, 2
        # deepest compression inside the segment (its ends are covered below and above)
        for j in range(2):
            tz = tv0 + j * math.pi / wd
            if 0.0 < tz < te:
                qz = off + math.exp(-sig * tz) * (A * math.cos(wd * tz) + B * math.sin(wd * tz))
                umin = min(umin, qz - a)
                umax = max(umax, qz - a)
        e = math.exp(-sig * te)
        cs, sn = math.cos(wd * te), math.sin(wd * te)
        q = off + e * (A * cs + B * sn)
        v = e * (P * cs - Q * sn)
        t += te
        umin = min(umin, q - a)
        umax = max(umax, q - a)
        if kind == 1:
            damp = False
        elif kind == 2:
            # released: free flight for the rest of the step
            h = dt - t
            q += h * v + 0.5 * h * h * g
            v += h * g
            return q, v, False, True, umin, umax
        else:
            finished = True
            break
    if not finished:
        return q, v, True, False, umin, umax
    if unilateral and always and -k * (q - a) - c * v < 0.0 and v >= 0.0:
        return q, v, True, False, umin, umax
    return q, v, True, True, umin, umax
