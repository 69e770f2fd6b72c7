"""The contact integrators' steps: the sub-stepped backward Euler / symplectic Euler with their
step sizing and dashpot; the exact one (closed form, modal with events) is
:mod:`hailstorm.runtime.compiled.exact`.

They are the one implementation of :func:`hailstorm.runtime.storm.hail.contact_step` (a thin
wrapper over :func:`~hailstorm.runtime.compiled.exact.exact_step` and :func:`substep_contacts`)
and of the storm's contact step. The tests hold them to the numpy statement of the same algorithms
(``tests/reference/contact_step_ref.py``), to :func:`scipy.linalg.expm` of the state
matrix and to the analytic bounce of one contact; the step sizing's rules are in
:mod:`hailstorm.runtime.storm.driver`.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.contacts import inv_spd, submatrix
from hailstorm.runtime.compiled.lapack import solve
from hailstorm.runtime.compiled.modal import explicit_modes_py, modal_damping_py, modal_stiffness_py

__all__ = ["explicit_modes", "modal_stiffness", "substep_contacts", "substep_damping", "substep_size"]


@kernel
def substep_size(near, h_left, hmin, vel, radius, mass, pos, gap, near_tri, ctri, k_tri, approach_fraction,
                 rest_speed, omega_dt, symplectic, cc_stones, Kdiag, sticky, cc_normals, cc_X, cc_rest,
                 g):  # pragma: no cover (compiled)
    """The sub-step of the adaptive implicit and symplectic integrators
    (:meth:`hailstorm.runtime.storm.integrators.ContactIntegrator.substep_size`): approaching stones travel at most ``approach_fraction``
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


#: the contact set's modal dashpot (the one definition in :mod:`hailstorm.runtime.compiled.modal`, compiled):
#: ``substep_damping(om2, Phi, sqm, restitution, dt, implicit, x_grid, z_grid)`` -> (n, n)
#: (``x_grid``, ``z_grid``: the restitution table of :func:`hailstorm.runtime.storm.hail.damping_ratio_for_restitution`)
substep_damping = kernel(modal_damping_py)
#: the modal frequencies an explicit step carries (hailstorm.runtime.storm.hail's, compiled)
explicit_modes = kernel(explicit_modes_py)
#: K and its pseudo-inverse W from modes (hailstorm.runtime.storm.hail's, compiled)
modal_stiffness = kernel(modal_stiffness_py)


@kernel
def _indices(mask):  # pragma: no cover (compiled)
    """``np.flatnonzero(mask)`` of a bool array (int64), as a loop."""
    k = 0
    for i in range(mask.size):
        if mask[i]:
            k += 1
    out = np.empty(k, np.int64)
    k = 0
    for i in range(mask.size):
        if mask[i]:
            out[k] = i
            k += 1
    return out


@kernel
def substep_contacts(q, v, a, m, g, dt, K, W, C, implicit, unilateral, group, wts, cond_limit,
                     rcond):  # pragma: no cover
    """Compiled implicit (backward Euler) and symplectic Euler contact step of
    :func:`hailstorm.runtime.storm.hail.contact_step` (see there): the (n, n) dashpot ``C`` in compression
    only, unilateral release by active-set iteration (``cond_limit``, ``rcond``: the
    policy of :func:`inv_spd`). Returns ``(q, v, active, force, seat_force)``.

    (Element-wise work is written as loops and the solve is :func:`~hailstorm.runtime.compiled.lapack.solve`:
    the same arithmetic as the array expressions and ``np.linalg.solve`` they replace, bit for
    bit, at about half the first run's compile.)"""
    n = q.size
    ng = np.int64(0)  # (not the literal 0: a literal argument is a second specialisation of _gsum, _track)
    for i in range(n):
        ng = max(ng, group[i] + 1)
    vn_g = np.zeros(ng)
    for i in range(n):
        vn_g[group[i]] += wts[i] * v[i]
    on = np.empty(n, np.bool_)
    for i in range(n):
        on[i] = vn_g[group[i]] < 0.0
    active = np.ones(n, np.bool_)
    ubar = np.empty(n)
    for i in range(n):
        ubar[i] = q[i] - a[i]
    v_new = np.empty(n)
    force = np.zeros(n)
    while True:
        idx = _indices(active)
        Ka = inv_spd(submatrix(W, idx), cond_limit, rcond) if idx.size < n else K
        for i in range(n):
            v_new[i] = v[i] + dt * g[i]
        na = idx.size
        if na:
            ca = submatrix(C, idx)
            for r in range(na):
                for cc in range(na):
                    if not (on[idx[r]] and on[idx[cc]]):
                        ca[r, cc] = 0.0
            ua = np.empty(na)
            for r in range(na):
                ua[r] = ubar[idx[r]]
            if implicit:
                dt2 = dt * dt
                A = np.empty((na, na))
                for r in range(na):
                    for cc in range(na):
                        A[r, cc] = dt2 * Ka[r, cc] + dt * ca[r, cc]
                rhs = np.empty(na)
                ku = Ka @ ua
                for r in range(na):
                    i = idx[r]
                    A[r, r] += m[i]
                    rhs[r] = m[i] * v[i] + dt * (m[i] * g[i] - ku[r])
                vs = solve(A, rhs)
                for r in range(na):
                    v_new[idx[r]] = vs[r]
            else:
                va = np.empty(na)
                for r in range(na):
                    va[r] = v[idx[r]]
                ku = Ka @ ua
                kc = ca @ va
                for r in range(na):
                    i = idx[r]
                    v_new[i] = v[i] + dt * (g[i] - (ku[r] + kc[r]) / m[i])
        force = np.zeros(n)
        for r in range(na):
            i = idx[r]
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
    q_new = np.empty(n)
    for i in range(n):
        q_new[i] = q[i] + dt * v_new[i]
    seat = np.zeros(n)
    idx = _indices(active)
    if idx.size:
        Ka = inv_spd(submatrix(W, idx), cond_limit, rcond) if idx.size < n else K
        da = np.empty(idx.size)
        for r in range(idx.size):
            da[r] = q_new[idx[r]] - a[idx[r]]
        sa = Ka @ da
        for r in range(idx.size):
            seat[idx[r]] = sa[r]
    for i in range(n):
        if not active[i]:
            force[i] = 0.0
    return q_new, v_new, active, force, seat
