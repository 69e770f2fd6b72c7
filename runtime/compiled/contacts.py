"""The compiled SPD policy and the stones' constrained coordinates around a contact step.

* :func:`inv_spd` -- the contact core's SPD inverse
  (:func:`hailstorm.runtime.contact.policy.spd_inverse`) inside the compiled steps,
  for the contacts still active after a release;
* :func:`contact_prep`, :func:`contact_post` -- the two halves of a storm's
  contact step around the integrator.

A storm contact set's blocks of D are the contact API's
(:func:`hailstorm.runtime.contact.capacitance_build.from_weights`).
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.wmatrix import symmetrise
from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.lapack import cholesky, eigh, gram, inverse

__all__ = ["contact_post", "contact_prep", "inv_spd", "submatrix"]


@kernel
def inv_spd(W, cond_limit, rcond):  # pragma: no cover (compiled)
    """Inverse of a small symmetric positive (semi-)definite matrix under the contact
    API's policy (:func:`hailstorm.runtime.contact.policy.spd_inverse`; pass its
    ``COND_LIMIT`` and ``PINV_RCOND``): Cholesky if the condition estimate from the
    factor's diagonal is below ``cond_limit``, else the pseudo-inverse (eigenvalues
    below ``rcond`` times the largest dropped)."""
    n = W.shape[0]
    if n == 0:
        return np.zeros((0, 0))
    Ws = np.empty((n, n))
    finite = True
    for i in range(n):
        for j in range(n):
            Ws[i, j] = 0.5 * (W[i, j] + W[j, i])
            finite = finite and math.isfinite(Ws[i, j])
    if finite:
        L, ok = cholesky(Ws)
        if ok:
            dmin = np.inf
            dmax = 0.0
            for i in range(n):
                d = abs(L[i, i])
                dmin = min(dmin, d)
                dmax = max(dmax, d)
            if dmin > 0.0 and (dmax / dmin) ** 2 < cond_limit:
                Li = inverse(L)
                K = gram(Li)
                symmetrise(K)
                return K
    if not finite:
        raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    lam, Q = eigh(Ws)
    top = 0.0
    for j in range(n):
        top = max(top, lam[j])
    K = np.zeros((n, n))
    for j in range(n):
        if lam[j] > rcond * top:
            for r in range(n):
                for c in range(n):
                    K[r, c] += Q[r, j] * Q[c, j] / lam[j]
    symmetrise(K)
    return K


@kernel
def contact_prep(soft, pos, vel, radius, mass, g, wind, drag_coef, nk, Xc, rest, Kdiag, sticky, exact,
                 rest_speed):  # pragma: no cover (compiled)
    """The constrained coordinates of a contact set for :func:`hailstorm.runtime.storm.hail.contact_step`
    (the first half of :meth:`hailstorm.runtime.storm.soft_contacts.SoftContacts.advance`): ``(q, anchor, v, accel, mass,
    always_damped, acc)``, per contact (frictionless, normal components) or
    per component (sticky); ``acc`` (s, 3) is the stones' gravity + drag. (The
    dashpot is the contact set's, per mode: ``ContactIntegrator.exact_damping`` and
    ``contact_matrices``.)"""
    s = soft.size
    nq = 3 * s if sticky else s
    q = np.empty(nq); a = np.empty(nq); vq = np.empty(nq); gq = np.empty(nq); mq = np.empty(nq)
    always = np.zeros(nq, np.bool_)
    acc = np.empty((s, 3))
    for i in range(s):
        j = soft[i]
        acc[i, 0] = 0.0; acc[i, 1] = 0.0; acc[i, 2] = -g
        if drag_coef > 0.0:
            w0 = vel[j, 0] - wind[0]; w1 = vel[j, 1] - wind[1]; w2 = vel[j, 2] - wind[2]
            c = drag_coef / radius[j] * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            acc[i, 0] -= c * w0; acc[i, 1] -= c * w1; acc[i, 2] -= c * w2
        pn = 0.0; xn = 0.0; vn = 0.0; an = 0.0
        for d in range(3):
            pn += nk[i, d] * pos[j, d]
            xn += nk[i, d] * Xc[i, d]
            vn += nk[i, d] * vel[j, d]
            an += nk[i, d] * acc[i, d]
        if sticky:
            for d in range(3):
                q[3 * i + d] = pos[j, d]
                a[3 * i + d] = Xc[i, d] + rest[i] * nk[i, d]
                vq[3 * i + d] = vel[j, d]
                gq[3 * i + d] = acc[i, d]
                mq[3 * i + d] = mass[j]
        else:
            q[i] = pn; a[i] = xn + rest[i]; vq[i] = vn; gq[i] = an; mq[i] = mass[j]
        if exact:
            # resting (oscillation amplitude about equilibrium below rest_speed): the
            # dashpot acts both ways, no switching events
            if sticky:
                kd = max(max(max(Kdiag[3 * i], 0.0), max(Kdiag[3 * i + 1], 0.0)), max(Kdiag[3 * i + 2], 0.0))
            else:
                kd = max(Kdiag[i], 0.0)
            om = math.sqrt(kd / mass[j])
            ubar = pn - xn - rest[i]
            u_eq = an * mass[j] / max(kd, 1e-300)
            r = math.hypot(vn, om * (ubar - u_eq)) < rest_speed
            if sticky:
                for d in range(3):
                    always[3 * i + d] = r
            else:
                always[i] = r
    return q, a, vq, gq, mq, always, acc


@kernel
def contact_post(soft, pos, vel, ctri, hit, was_open, nk, acc, q, a, vq, gq, rq, rv, ractive, rseat, rpeak,
                 rpubar, sticky, exact, h, rest_speed):  # pragma: no cover (compiled)
    """Apply a contact step to the stones, in place (compiled second half of
    :meth:`hailstorm.runtime.storm.soft_contacts.SoftContacts.advance`): new positions and velocities (frictionless: free
    tangential motion), released contacts closed, impacts marked. ``rpeak``, ``rpubar``:
    the step's ``peak_seat_force`` and ``peak_ubar`` (:class:`hailstorm.runtime.storm.hail.ContactStep`);
    a contact that carried force at some instant of the step counts as touched.

    Returns
    -------
    impacts : int
        Contacts that opened in this sub-step, pushed, and came in faster than ``rest_speed``.
    max_force : float
        Largest contact force magnitude within the sub-step [N].
    max_indentation : float
        Largest normal contact displacement of a touched contact within the sub-step (-inf if none) [m].
    n_touched : int
        Contacts that carried force within the sub-step.
    """
    s = soft.size
    impacts = 0
    fmax = 0.0
    indent = -np.inf
    n_active = 0
    for i in range(s):
        j = soft[i]
        if sticky:
            act = ractive[3 * i] and ractive[3 * i + 1] and ractive[3 * i + 2]
            f2 = rseat[3 * i] ** 2 + rseat[3 * i + 1] ** 2 + rseat[3 * i + 2] ** 2
            p2 = rpeak[3 * i] ** 2 + rpeak[3 * i + 1] ** 2 + rpeak[3 * i + 2] ** 2
            ubn = 0.0
            for d in range(3):
                ubn += rpubar[3 * i + d] * nk[i, d]
        else:
            act = ractive[i]
            f2 = rseat[i] ** 2
            p2 = rpeak[i] ** 2
            ubn = rpubar[i]
        fmax = max(fmax, math.sqrt(f2), math.sqrt(p2))
        if act or p2 > 0.0:
            n_active += 1
            indent = max(indent, -ubn)
            if not was_open[i]:
                vin = vel[j, 0] * nk[i, 0] + vel[j, 1] * nk[i, 1] + vel[j, 2] * nk[i, 2]
                if vin < -rest_speed:
                    impacts += 1
                hit[j] = True
        for d in range(3):
            if sticky:
                vnew = rv[3 * i + d]
                pnew = rq[3 * i + d]
            else:
                vt0 = vel[j, d] - vq[i] * nk[i, d]
                at = acc[i, d] - gq[i] * nk[i, d]
                vnew = vt0 + h * at + rv[i] * nk[i, d]
                pnew = pos[j, d] - q[i] * nk[i, d] + h * vt0 + 0.5 * h * h * at + rq[i] * nk[i, d]
            if not exact:
                pnew = pos[j, d] + h * vnew  # (semi-)implicit position update
            vel[j, d] = vnew
            pos[j, d] = pnew
        if not act:
            ctri[j] = -1
    return impacts, fmax, indent, n_active


@kernel
def submatrix(M, idx):  # pragma: no cover (compiled)
    """``M[idx][:, idx]`` as a new C-contiguous (k, k) array (the integrators' active subsets)."""
    out = np.empty((idx.size, idx.size))
    for r in range(idx.size):
        for c in range(idx.size):
            out[r, c] = M[idx[r], idx[c]]
    return out
