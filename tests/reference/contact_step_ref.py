"""The contact step, the plain way: the oracle of :func:`hailstorm.runtime.compiled.exact_step`
and :func:`hailstorm.runtime.compiled.substep_contacts` (the one implementation, which
:func:`hailstorm.runtime.storm.hail.contact_step` wraps).

Vectorised numpy over the components of a contact set; the exact integrator's modal
solution with :func:`scipy.linalg.expm` where the eigenbasis is (nearly) defective,
evaluated at every sample time from the segment's start (the kernel takes one
``expm`` per grid and its powers). It shares with the kernels only the plain-Python
statement of the scalar closed form (:mod:`hailstorm.runtime.compiled.modal`) and the
contact core's SPD policy; its static equilibrium solves with the capacitance
(:func:`equilibrium_ref`) where the kernel multiplies by the compliance.
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.compiled.modal import scalar_exact_py
from hailstorm.runtime.contact.policy import spd_inverse
from hailstorm.runtime.storm.hail import INTEGRATORS, ContactStep


def equilibrium_ref(K: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``K x = f`` for the static equilibrium; for a singular ``K`` (coincident contacts:
    the pseudo-inverse capacitance has zero modes) the least-squares, min-norm ``x``
    (the part of ``f`` on the zero modes, which moves coincident stones relative to
    each other, is not carried)."""
    ok = True
    try:
        x = np.linalg.solve(K, f)
    except Exception:
        ok = False
        x = f.copy()
    if ok:
        r = K @ x - f
        ok = np.all(np.isfinite(x)) and np.sqrt(np.sum(r * r)) <= 1e-9 * np.sqrt(np.sum(f * f)) + 1e-300
    if not ok:
        x = np.linalg.lstsq(K, f, rcond=1e-10)[0]
    return x


def contact_step_ref(
    q: np.ndarray,
    v: np.ndarray,
    anchor: np.ndarray,
    mass: np.ndarray,
    accel: np.ndarray,
    dt: float,
    *,
    K: np.ndarray | None = None,
    W: np.ndarray | None = None,
    damping: np.ndarray | float = 0.0,
    integrator: str = "implicit",
    unilateral: bool = True,
    group: np.ndarray | None = None,
    normal_of: np.ndarray | None = None,
    always_damped: np.ndarray | None = None,
) -> ContactStep:
    """:func:`hailstorm.runtime.storm.hail.contact_step` (same arguments, same result), in numpy.

    With ``K`` alone, ``W = spd_inverse(K)``; with ``W`` alone, ``K = spd_inverse(W)``;
    the capacitance of an active subset ``a`` is ``spd_inverse(W[a, a])``.
    """
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    a = np.asarray(anchor, dtype=np.float64)
    m = np.asarray(mass, dtype=np.float64)
    g = np.asarray(accel, dtype=np.float64)
    n = q.size
    C = np.asarray(damping, dtype=np.float64)
    if C.ndim < 2:  # a diagonal dashpot
        C = np.diag(np.broadcast_to(C, (n,)))
    if K is None and W is None:
        raise ValueError("give the capacitance K or the contact compliance W")
    K = spd_inverse(W) if K is None else np.asarray(K, dtype=np.float64)
    W = spd_inverse(K) if W is None else np.asarray(W, dtype=np.float64)
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS)}, got {integrator!r}")
    group = np.arange(n) if group is None else np.asarray(group)
    wts = np.ones(n) if normal_of is None else np.asarray(normal_of, dtype=np.float64)
    if integrator == "exact":
        return exact_step_ref(q, v, a, m, g, float(dt), K, W, C, unilateral, group, wts, always_damped)
    # the dashpot acts in compression only (normal velocity of the contact < 0)
    vn_g = np.zeros(group.max() + 1 if n else 0)
    np.add.at(vn_g, group, wts * v)
    on = vn_g[group] < 0.0
    C = C * (on[:, None] & on[None, :])
    active = np.ones(n, dtype=bool)
    ubar = q - a
    while True:
        idx = np.flatnonzero(active)
        Ka = spd_inverse(W[np.ix_(idx, idx)]) if idx.size < n else K
        v_new = v + dt * g  # free motion of released components
        if idx.size:
            ma, ua, va, ga, ca = m[idx], ubar[idx], v[idx], g[idx], C[np.ix_(idx, idx)]
            if integrator == "implicit":
                A = dt * dt * Ka + dt * ca
                A[np.diag_indices_from(A)] += ma
                rhs = ma * va + dt * (ma * ga - Ka @ ua)
                v_new[idx] = np.linalg.solve(A, rhs)
            else:
                f = -(Ka @ ua) - ca @ va
                v_new[idx] = va + dt * (ga + f / ma)
        force = np.zeros(n)
        force[idx] = m[idx] * ((v_new[idx] - v[idx]) / dt - g[idx])
        if not unilateral or idx.size == 0:
            break
        # normal force per contact group (positive = pushes the stone out)
        fn = np.zeros(group.max() + 1)
        np.add.at(fn, group, wts * force)
        pulling = active & (fn[group] < 0.0)
        if not pulling.any():
            break
        active &= ~pulling
    q_new = q + dt * v_new
    seat = np.zeros(n)
    idx = np.flatnonzero(active)
    if idx.size:
        Ka = spd_inverse(W[np.ix_(idx, idx)]) if idx.size < n else K
        seat[idx] = Ka @ (q_new[idx] - a[idx])
    force[~active] = 0.0
    return ContactStep(q=q_new, v=v_new, active=active, force=force, seat_force=seat, peak_seat_force=seat.copy(),
                       peak_ubar=q_new - a)


# --------------------------------------------------------------------------
# the exact (modal) integrator
# --------------------------------------------------------------------------
_GRID = 32  # samples per bracket when locating an event
_REFINE = 2  # bracket refinements: event time to dt / 32**(_REFINE + 1)
_MAX_SEGMENTS = 12


class _Modal:
    """Closed-form solution of ``M y'' + C y' + K y = 0``, ``z = (y, y')``."""

    __slots__ = ("lam", "V", "Vi", "A", "n", "real")

    def __init__(self, K: np.ndarray, m: np.ndarray, c: np.ndarray) -> None:
        n = m.size
        A = np.zeros((2 * n, 2 * n))
        A[:n, n:] = np.eye(n)
        A[n:, :n] = -K / m[:, None]
        A[n:, n:] = -c / m[:, None]  # (n, n) dashpot
        self.n, self.A = n, A
        lam, V = np.linalg.eig(A)
        self.lam, self.V = lam, V
        try:
            Vi = np.linalg.inv(V)
            ok = np.isfinite(Vi).all() and np.abs(V).max() * np.abs(Vi).max() < 1e7
        except np.linalg.LinAlgError:
            ok = False
        self.Vi = Vi if ok else None  # None: (nearly) defective, use expm

    def at(self, z0: np.ndarray, t: np.ndarray) -> np.ndarray:
        """States (2n, len(t)) at times ``t`` from ``z0``."""
        if self.Vi is not None:
            c = self.Vi @ z0
            return (self.V @ (np.exp(np.multiply.outer(self.lam, t)) * c[:, None])).real
        from scipy.linalg import expm

        return np.stack([expm(self.A * ti) @ z0 for ti in np.atleast_1d(t)], axis=1)


def exact_step_ref(q, v, a, m, g, dt, K, W, C, unilateral, group, wts, always_damped) -> ContactStep:
    """The exact integrator's step (:func:`hailstorm.runtime.compiled.exact_step`), the plain way:
    ``K``, ``W`` the full set's capacitance and compliance, ``C`` the (n, n) dashpot."""
    n = q.size
    if n == 1 and group[0] == 0 and wts[0] == 1.0:
        k = float(K[0, 0])
        al = bool(always_damped[0]) if always_damped is not None else False
        qn, vn, act, ok, umin, umax = scalar_exact_py(float(q[0]), float(v[0]), float(a[0]), float(m[0]),
                                                    float(g[0]), dt, k, float(np.asarray(C)[0, 0]), unilateral, al)
        if ok:
            force = m * ((vn - v) / dt - g) if act else np.zeros(1)
            seat = np.array([k * (qn - a[0])]) if act else np.zeros(1)
            peak = np.array([k * (umin if -umin >= umax else umax)])
            return ContactStep(q=np.array([qn]), v=np.array([vn]), active=np.array([act]), force=force,
                               seat_force=seat, peak_seat_force=peak, peak_ubar=np.array([umin]))
    ng = int(group.max()) + 1 if n else 0
    K_full = K
    Cn = np.asarray(C, dtype=np.float64).copy()  # nominal dashpot (m, m)

    def dashpot(idx: np.ndarray) -> np.ndarray:  # of the components idx: on while compressing (or always)
        on = (damp_g[group] | always)[idx]
        return Cn[np.ix_(idx, idx)] * (on[:, None] & on[None, :])
    always = np.zeros(n, bool) if always_damped is None else np.asarray(always_damped, bool)
    v0 = v
    q, v = q.copy(), v.copy()
    active = np.ones(n, dtype=bool)

    ident = ng == n and np.array_equal(group, np.arange(n)) and np.all(wts == 1.0)

    def gsum(x: np.ndarray) -> np.ndarray:  # (n, ...) -> (ng, ...) normal sums per group
        if ident:
            return x
        out = np.zeros((ng,) + x.shape[1:])
        np.add.at(out, group, wts.reshape((-1,) + (1,) * (x.ndim - 1)) * x)
        return out

    def vn_of(vv):
        return gsum(vv)

    # dashpot on at the start where the contact is compressing (or always for resting ones)
    damp_g = vn_of(v) < 0.0
    t = 0.0
    Ka = K_full
    # peaks inside the step, per contact group: the largest |elastic seat force| (squared) and the
    # most negative normal q - a, with the components at those instants, over the closed-form
    # states the event search evaluates (its samples and the located events)
    pk2 = np.zeros(ng)
    pk_f = np.zeros(n)
    dmin = np.full(ng, np.inf)
    dmin_u = q - a

    def track(comp: np.ndarray, Ka_: np.ndarray, ub: np.ndarray) -> None:
        """Update the peaks from states of the active components ``comp`` (ub: their q - a, (na, T))."""
        F = Ka_ @ ub
        gc = group[comp]
        mag2 = np.zeros((ng, ub.shape[1]))
        np.add.at(mag2, gc, F * F)
        un = np.full((ng, ub.shape[1]), np.inf)
        un[gc] = 0.0
        np.add.at(un, gc, wts[comp][:, None] * ub)
        cb = np.argmax(mag2, axis=1)
        best = mag2[np.arange(ng), cb]
        up = best > pk2
        if up.any():
            pk2[up] = best[up]
            sel = up[gc]
            pk_f[comp[sel]] = F[sel, cb[gc[sel]]]
        cd = np.argmin(un, axis=1)
        deep = un[np.arange(ng), cd]
        dn = deep < dmin
        if dn.any():
            dmin[dn] = deep[dn]
            sel = dn[gc]
            dmin_u[comp[sel]] = ub[sel, cd[gc[sel]]]
    for _seg in range(_MAX_SEGMENTS):
        # unilateral: release contacts that pull now and do not approach (active-set iteration)
        while True:
            idx = np.flatnonzero(active)
            if idx.size < n:
                Ka = spd_inverse(W[np.ix_(idx, idx)])
            else:
                Ka = K_full[np.ix_(idx, idx)]
            if not unilateral or idx.size == 0:
                break
            ce = dashpot(idx)
            f = np.zeros(n)
            f[idx] = -(Ka @ (q[idx] - a[idx])) - ce @ v[idx]
            fn = gsum(f)
            vn = vn_of(v)
            pull = (fn < 0.0) & (vn >= 0.0) & np.bincount(group, active, minlength=ng).astype(bool)
            if not pull.any():
                break
            active &= ~pull[group]
        if _seg == 0 and active.any():
            ia = np.flatnonzero(active)
            track(ia, Ka, (q[ia] - a[ia])[:, None])
        h = dt - t
        if h <= 1e-12 * dt:
            break
        idx = np.flatnonzero(active)
        free = np.flatnonzero(~active)
        if idx.size == 0:
            q[free] += h * v[free] + 0.5 * h * h * g[free]
            v[free] += h * g[free]
            t = dt
            break
        ma, ga, aa = m[idx], g[idx], a[idx]
        ce = dashpot(idx)
        q_eq = aa + equilibrium_ref(Ka, ma * ga)
        modal = _Modal(Ka, ma, ce)
        z0 = np.concatenate([q[idx] - q_eq, v[idx]])
        na = idx.size
        gi = group[idx]
        wi = wts[idx]
        # event functions on the group level, evaluated on times tau (columns)
        sw_on = np.zeros(ng, bool)
        sw_on[gi] = True

        switchable = sw_on & np.bincount(gi, (np.diag(Cn)[idx] > 0) & ~always[idx], minlength=ng).astype(bool)
        off_mask = (switchable & damp_g)[:, None]
        on_mask = (switchable & ~damp_g)[:, None]
        ident_a = ident and na == n
        off_eq = (q_eq - aa)[:, None]

        def gsum_a(x: np.ndarray) -> np.ndarray:
            if ident_a:
                return x
            out = np.zeros((ng, x.shape[1]))
            np.add.at(out, gi, wi[:, None] * x)
            return out

        def events(tau: np.ndarray):
            Z = modal.at(z0, tau)
            y, vv = Z[:na], Z[na:]
            vng = gsum_a(vv)
            fng = gsum_a(-(Ka @ (y + off_eq)) - ce @ vv)
            ev = np.zeros((ng, tau.size), bool)
            ev |= off_mask & (vng >= 0.0)  # maximum compression: dashpot off
            ev |= on_mask & (vng < 0.0)  # compresses again: dashpot on
            if unilateral:
                ev |= sw_on[:, None] & (fng < 0.0) & (vng >= 0.0)  # released
            return Z, ev

        lo, hi = 0.0, h
        tau = h * np.arange(1, _GRID + 1) / _GRID
        Z, ev = events(tau)
        anyev = ev.any(axis=0)
        if not anyev.any():
            t_e, ze, evg = h, Z[:, -1], None
            track(idx, Ka, Z[:na] + off_eq)
        else:
            j = int(np.argmax(anyev))
            lo, hi = (tau[j - 1] if j else 0.0), tau[j]
            ze, evg = Z[:, j], ev[:, j]
            track(idx, Ka, Z[:na, :j + 1] + off_eq)  # the states up to the event (after it: another pattern)
            for _ in range(_REFINE):
                tau = lo + (hi - lo) * np.arange(1, _GRID + 1) / _GRID
                Z, ev = events(tau)
                anyev = ev.any(axis=0)
                j = int(np.argmax(anyev))  # the bracket's right end has an event
                lo, hi = (tau[j - 1] if j else lo), tau[j]
                ze, evg = Z[:, j], ev[:, j]
                track(idx, Ka, Z[:na, :j + 1] + off_eq)
            t_e = hi
        # advance to t_e
        q[idx] = ze[:na] + q_eq
        v[idx] = ze[na:]
        if free.size:
            q[free] += t_e * v[free] + 0.5 * t_e * t_e * g[free]
            v[free] += t_e * g[free]
        t += t_e
        if evg is None:
            break
        vng = vn_of(v)
        ea = evg & sw_on
        f = np.zeros(n)
        f[idx] = -(Ka @ (q[idx] - aa)) - ce @ v[idx]
        fng = gsum(f)
        rel = ea & (fng < 0.0) & (vng >= 0.0) if unilateral else np.zeros(ng, bool)
        damp_g = np.where(ea & ~rel, vng < 0.0, damp_g)
        if rel.any():
            active &= ~rel[group]
    else:
        # too many events in one step: finish it with the pattern frozen (rare)
        h = dt - t
        if h > 0:
            idx = np.flatnonzero(active)
            free = np.flatnonzero(~active)
            if idx.size:
                # (the last segment may have released contacts: the capacitance of those left)
                Ka = spd_inverse(W[np.ix_(idx, idx)]) if idx.size < n else K_full[np.ix_(idx, idx)]
                ce = dashpot(idx)
                q_eq = a[idx] + equilibrium_ref(Ka, m[idx] * g[idx])
                ze = _Modal(Ka, m[idx], ce).at(np.concatenate([q[idx] - q_eq, v[idx]]), np.array([h]))[:, 0]
                q[idx], v[idx] = ze[:idx.size] + q_eq, ze[idx.size:]
                track(idx, Ka, (q[idx] - a[idx])[:, None])
            q[free] += h * v[free] + 0.5 * h * h * g[free]
            v[free] += h * g[free]
    force = np.where(active, m * ((v - v0) / dt - g), 0.0)
    seat = np.zeros(n)
    idx = np.flatnonzero(active)
    if idx.size:
        if Ka.shape[0] != idx.size:  # released at the last event
            Ka = spd_inverse(W[np.ix_(idx, idx)]) if idx.size < n else K_full[np.ix_(idx, idx)]
        seat[idx] = Ka @ (q[idx] - a[idx])
    untouched = ~np.isfinite(dmin)[group]
    dmin_u[untouched] = (q - a)[untouched]
    return ContactStep(q=q, v=v, active=active, force=force, seat_force=seat, peak_seat_force=pk_f,
                       peak_ubar=dmin_u)
