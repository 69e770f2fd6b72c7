"""The exact contact integrator's step: the damped linear dynamics of a contact set in closed
form over the step, split at the instants its dashpot pattern or its active set changes.

:func:`exact_step` is the one implementation of the ``"exact"`` integrator of
:func:`hailstorm.runtime.storm.hail.contact_step` and of the storm's contact step. One
frictionless contact takes the scalar closed form (:mod:`hailstorm.runtime.compiled.modal`); a
set goes through its modes, or where the modal basis is (nearly) defective through the
matrix exponential (:mod:`hailstorm.runtime.compiled.expm`). The tests hold it to the numpy
statement of the same algorithm (``tests/reference/contact_step_ref.py``), to
:func:`scipy.linalg.expm` of the state matrix and to the analytic bounce of one contact.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.contacts import inv_spd, submatrix
from hailstorm.runtime.compiled.expm import expm
from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.modal import scalar_exact_py

__all__ = ["exact_step"]


#: the closed-form single contact of the exact integrator: the one definition in :mod:`hailstorm.runtime.compiled.modal`, compiled
_scalar_exact = kernel(scalar_exact_py)


@kernel
def _gsum(x, group, wts, ng, ident):  # pragma: no cover (compiled)
    """Normal sums per contact group of per-component rows ``x`` (n, T) -> (ng, T)."""
    if ident:
        return x.copy()
    out = np.zeros((ng, x.shape[1]))
    for i in range(x.shape[0]):  # (element by element: a broadcast += compiles numba's shape-error path, ~1.5 s)
        gi, wi = group[i], wts[i]
        for c in range(x.shape[1]):
            out[gi, c] += wi * x[i, c]
    return out


@kernel
def _dashpot(idx, Cn, damp_g, group, always):  # pragma: no cover (compiled)
    """Dashpot (a, a) of the components ``idx``: on while their contact compresses (or always)."""
    na = idx.size
    on = np.empty(na, np.bool_)
    for r in range(na):
        i = idx[r]
        on[r] = damp_g[group[i]] or always[i]
    ce = np.zeros((na, na))
    for r in range(na):
        if on[r]:
            for c in range(na):
                if on[c]:
                    ce[r, c] = Cn[idx[r], idx[c]]
    return ce


@kernel
def _advance(q, v, g, idx, ze, q_eq, free, h):  # pragma: no cover (compiled)
    """Components ``idx`` to the modal state ``ze`` (about ``q_eq``); ``free`` ones fly for ``h``."""
    na = idx.size
    for r in range(na):
        q[idx[r]] = ze[r] + q_eq[r]
        v[idx[r]] = ze[na + r]
    for i in free:
        q[i] += h * v[i] + 0.5 * h * h * g[i]
        v[i] += h * g[i]


@kernel
def _state_matrix(Ka, ma, ce):  # pragma: no cover (compiled)
    """``A`` of ``z' = A z``, ``z = (y, y')``, for ``M y'' + C y' + K y = 0``."""
    n = ma.size
    A = np.zeros((2 * n, 2 * n))
    for i in range(n):
        A[i, n + i] = 1.0
        for j in range(n):
            A[n + i, j] = -Ka[i, j] / ma[i]
        for j in range(n):
            A[n + i, n + j] = -ce[i, j] / ma[i]
    return A


@kernel
def _modal(A):  # pragma: no cover (compiled)
    """Eigen-decomposition ``A = V diag(lam) Vi``: (lam, V, Vi, ok); ``ok`` False for a
    (nearly) defective system (critically damped modes: ``cond(V)`` too large), which
    the exact step then advances with :func:`hailstorm.runtime.compiled.expm.expm`."""
    lam, V = np.linalg.eig(A.astype(np.complex128))
    try:
        Vi = np.linalg.inv(V)
    except Exception:
        return lam, V, V, False
    ok = np.all(np.isfinite(Vi.real)) and np.all(np.isfinite(Vi.imag)) and np.abs(V).max() * np.abs(Vi).max() < 1e7
    return lam, V, Vi, ok


@kernel
def _expm_states(A, z, d, count):  # pragma: no cover (compiled)
    """States (2n, count) at ``d, 2 d, ..., count d`` from ``z``: ``E z, E^2 z, ...`` with
    ``E = expm(A d)`` (a defective modal basis). The velocities are scaled by the set's
    stiffest frequency ``sigma`` first (``A`` similar to ``[[0, sigma I], [-M^-1 K / sigma,
    -M^-1 C]]``, whose blocks are of one size), so that the exponential's normwise
    accuracy holds for positions and velocities alike."""
    n = A.shape[0] // 2
    top = 0.0
    for i in range(n):
        for j in range(n):
            top = max(top, abs(A[n + i, j]))
    sig = math.sqrt(top) if top > 0.0 else 1.0
    As = A * d
    for i in range(n):
        for j in range(n):
            As[i, n + j] *= sig
            As[n + i, j] /= sig
    E = expm(As)
    zk = z.copy()
    for i in range(n):
        zk[n + i] /= sig
    Z = np.empty((2 * n, count))
    for k in range(count):
        zk = E @ zk
        Z[:, k] = zk
    for i in range(n):
        for k in range(count):
            Z[n + i, k] *= sig
    return Z


@kernel
def _modal_at(lam, V, Vi, z0, tau):  # pragma: no cover (compiled)
    """States (2n, len(tau)) at times ``tau`` from ``z0``."""
    c = Vi @ z0.astype(np.complex128)
    E = np.empty((lam.size, tau.size), np.complex128)
    for i in range(lam.size):
        for j in range(tau.size):
            E[i, j] = np.exp(lam[i] * tau[j]) * c[i]
    return (V @ E).real


@kernel
def _track(idx, Ka, ub, ncol, group, wts, ng, pk2, pk_f, dmin, dmin_u):  # pragma: no cover (compiled)
    """Update the step's peaks from the first
    ``ncol`` states of the active components ``idx`` (``ub``: their q - a, (na, T)):
    per contact group the largest |elastic seat force| and the most negative normal q - a."""
    na = idx.size
    F = Ka @ np.ascontiguousarray(ub[:, :ncol])
    mag2 = np.zeros(ng)
    un = np.zeros(ng)
    seen = np.zeros(ng, np.bool_)
    for r in range(na):
        seen[group[idx[r]]] = True
    for col in range(ncol):
        for gg in range(ng):
            mag2[gg] = 0.0
            un[gg] = 0.0
        for r in range(na):
            gg = group[idx[r]]
            mag2[gg] += F[r, col] ** 2
            un[gg] += wts[idx[r]] * ub[r, col]
        for gg in range(ng):
            if mag2[gg] > pk2[gg]:
                pk2[gg] = mag2[gg]
                for r in range(na):
                    if group[idx[r]] == gg:
                        pk_f[idx[r]] = F[r, col]
        for gg in range(ng):
            if seen[gg] and un[gg] < dmin[gg]:
                dmin[gg] = un[gg]
                for r in range(na):
                    if group[idx[r]] == gg:
                        dmin_u[idx[r]] = ub[r, col]


@kernel
def exact_step(q, v, a, m, g, dt, K, W, Cn, unilateral, group, wts, always, cond_limit,
               rcond):  # pragma: no cover (compiled)
    """The exact integrator's step of a contact set (see :func:`hailstorm.runtime.storm.hail.contact_step`):
    the damped linear dynamics in closed form, split at the instants the dashpot pattern
    or the active set changes (located on the trajectory: a grid of 32 samples, refined
    twice). One frictionless contact takes the scalar closed form (where it applies: not
    overdamped); a set goes through its modes, or where the modal basis is (nearly)
    defective (critically damped or repeated modes) through the matrix exponential
    (:func:`~hailstorm.runtime.compiled.expm.expm`: one ``expm(A d)`` per grid of
    spacing ``d``, and its powers). Every case is covered.

    ``K`` the capacitance of the full set, ``W`` its compliance (the capacitance of an
    active subset ``a`` is ``inv(W[a, a])``), ``Cn`` the (n, n) dashpot, ``cond_limit``,
    ``rcond`` the policy of :func:`inv_spd`.

    Returns ``(q, v, active, force, seat_force, peak_seat_force, peak_ubar)``
    (see :class:`hailstorm.runtime.storm.hail.ContactStep`).

    One kernel over two hundred lines, on purpose: split into its steps (the active set at a
    segment's start, the next event, the pattern after it, the frozen finish, the result) as
    separate kernels it compiled in 30.6 s of CPU instead of 23.8 s on a first run
    (``tests/benchmarks/compile_time.py``, 2026-12-06, load 0.8), the same arithmetic; the
    first run's compile is what issue #44 asks to shorten. Its steps are marked by comments.
    """
    GRID = 32
    REFINE = 2
    MAX_SEGMENTS = 12
    n = q.size
    ng = np.int64(0)  # (not the literal 0: a literal argument is a second specialisation of _gsum, _track)
    for i in range(n):
        ng = max(ng, group[i] + 1)
    v0 = v.copy()
    q = q.copy()
    v = v.copy()
    active = np.ones(n, np.bool_)
    if n == 1 and group[0] == 0 and wts[0] == 1.0:
        k = K[0, 0]
        qn, vn, act, ok, umin, umax = _scalar_exact(q[0], v[0], a[0], m[0], g[0], dt, k, Cn[0, 0], unilateral,
                                                    always[0])
        if ok:
            q[0] = qn
            v[0] = vn
            active[0] = act
            force = np.zeros(1)
            seat = np.zeros(1)
            if act:
                force[0] = m[0] * ((vn - v0[0]) / dt - g[0])
                seat[0] = k * (qn - a[0])
            peak = np.empty(1)
            peak[0] = k * (umin if -umin >= umax else umax)
            pub = np.empty(1)
            pub[0] = umin
            return q, v, active, force, seat, peak, pub
    # (kernels called with one type each: a literal 1 or a strided view as an argument
    # would compile a second specialisation of _track / _advance / _gsum on a first run)
    one = np.int64(1)
    ngrid = np.int64(GRID)  # (not the literal: one specialisation of _expm_states)
    ident = ng == n
    for i in range(n):
        if group[i] != i or wts[i] != 1.0:
            ident = False
    damp_g = _gsum(v.reshape(n, 1), group, wts, ng, ident)[:, 0] < 0.0
    t = 0.0
    Ka = K
    pk2 = np.zeros(ng)
    pk_f = np.zeros(n)
    dmin = np.full(ng, np.inf)
    dmin_u = q - a
    for _seg in range(MAX_SEGMENTS):
        # unilateral: release contacts that pull now and do not approach (active-set iteration)
        while True:
            idx = np.flatnonzero(active)
            Ka = inv_spd(submatrix(W, idx), cond_limit, rcond) if idx.size < n else K
            if not unilateral or idx.size == 0:
                break
            f = np.zeros(n)
            fa = -(Ka @ (q[idx] - a[idx]))
            ce = _dashpot(idx, Cn, damp_g, group, always)
            fd = ce @ v[idx]
            for r in range(idx.size):
                f[idx[r]] = fa[r] - fd[r]
            fn = _gsum(f.reshape(n, 1), group, wts, ng, ident)[:, 0]
            vn = _gsum(v.reshape(n, 1), group, wts, ng, ident)[:, 0]
            gact = np.zeros(ng, np.bool_)
            for i in range(n):
                if active[i]:
                    gact[group[i]] = True
            pull = (fn < 0.0) & (vn >= 0.0) & gact
            if not pull.any():
                break
            for i in range(n):
                if pull[group[i]]:
                    active[i] = False
        if _seg == 0:
            ia = np.flatnonzero(active)
            if ia.size:
                _track(ia, Ka, (q[ia] - a[ia]).reshape(ia.size, 1), one, group, wts, ng, pk2, pk_f, dmin, dmin_u)
        h = dt - t
        if h <= 1e-12 * dt:
            break
        idx = np.flatnonzero(active)
        free = np.flatnonzero(~active)
        if idx.size == 0:
            for i in free:
                q[i] += h * v[i] + 0.5 * h * h * g[i]
                v[i] += h * g[i]
            t = dt
            break
        na = idx.size
        ma = m[idx]
        ga = g[idx]
        aa = a[idx]
        ce = _dashpot(idx, Cn, damp_g, group, always)
        q_eq = aa + submatrix(W, idx) @ (ma * ga)  # the static equilibrium: Ka^-1 (m g) = W[a, a] m g
        A = _state_matrix(Ka, ma, ce)
        lam, V, Vi, ok = _modal(A)
        z0 = np.concatenate((q[idx] - q_eq, v[idx]))
        zlo = z0  # (defective basis: the state at the bracket's left end)
        gi = group[idx]
        wi = wts[idx]
        ident_a = ident and na == n
        sw_on = np.zeros(ng, np.bool_)
        has_sw = np.zeros(ng, np.bool_)
        for r in range(na):
            sw_on[gi[r]] = True
            i = idx[r]
            if Cn[i, i] > 0.0 and not always[i]:
                has_sw[gi[r]] = True
        switchable = sw_on & has_sw
        off_mask = switchable & damp_g
        on_mask = switchable & ~damp_g
        off_eq = q_eq - aa
        lo = 0.0
        hi = h
        tau = h * np.arange(1, GRID + 1) / GRID
        t_e = h
        ze = np.empty(2 * na)
        evg = np.zeros(ng, np.bool_)
        found = False
        for ref in range(REFINE + 1):
            if ok:
                Z = _modal_at(lam, V, Vi, z0, tau)
            else:
                Z = _expm_states(A, zlo, (hi - lo) / GRID, ngrid)
            y = Z[:na]
            vv = Z[na:]
            vng = _gsum(np.ascontiguousarray(vv), gi, wi, ng, ident_a)
            fl = -(Ka @ (y + off_eq.reshape(na, 1))) - ce @ np.ascontiguousarray(vv)
            fng = _gsum(fl, gi, wi, ng, ident_a)
            j = -1
            for col in range(tau.size):
                for gg in range(ng):
                    e = (off_mask[gg] and vng[gg, col] >= 0.0) or (on_mask[gg] and vng[gg, col] < 0.0) or (
                        unilateral and sw_on[gg] and fng[gg, col] < 0.0 and vng[gg, col] >= 0.0)
                    if e:
                        j = col
                        break
                if j >= 0:
                    break
            if ref == 0 and j < 0:
                ze[:] = Z[:, -1]
                _track(idx, Ka, y + off_eq.reshape(na, 1), tau.size, group, wts, ng, pk2, pk_f, dmin, dmin_u)
                break
            if j < 0:  # (the bracket's right end had an event; rounding aside, it still does)
                j = 0
            # the states up to the event (after it: another pattern)
            _track(idx, Ka, y + off_eq.reshape(na, 1), j + 1, group, wts, ng, pk2, pk_f, dmin, dmin_u)
            found = True
            if j:
                zlo = np.ascontiguousarray(Z[:, j - 1])
            lo, hi = (tau[j - 1] if j else lo), tau[j]
            ze[:] = Z[:, j]
            for gg in range(ng):
                evg[gg] = (off_mask[gg] and vng[gg, j] >= 0.0) or (on_mask[gg] and vng[gg, j] < 0.0) or (
                    unilateral and sw_on[gg] and fng[gg, j] < 0.0 and vng[gg, j] >= 0.0)
            t_e = hi
            if ref < REFINE:
                tau = lo + (hi - lo) * np.arange(1, GRID + 1) / GRID
        _advance(q, v, g, idx, ze, q_eq, free, t_e)
        t += t_e
        if not found:
            break
        vng1 = _gsum(v.reshape(n, 1), group, wts, ng, ident)[:, 0]
        f = np.zeros(n)
        fa = -(Ka @ (q[idx] - aa)) - ce @ v[idx]
        for r in range(na):
            f[idx[r]] = fa[r]
        fng1 = _gsum(f.reshape(n, 1), group, wts, ng, ident)[:, 0]
        for gg in range(ng):
            ea = evg[gg] and sw_on[gg]
            rel = unilateral and ea and fng1[gg] < 0.0 and vng1[gg] >= 0.0
            if ea and not rel:
                damp_g[gg] = vng1[gg] < 0.0
            if rel:
                for i in range(n):
                    if group[i] == gg:
                        active[i] = False
    else:
        # too many events in one step: finish it with the pattern frozen (rare)
        h = dt - t
        if h > 0:
            idx = np.flatnonzero(active)
            free = np.flatnonzero(~active)
            ze = np.zeros(0)
            q_eq = np.zeros(0)
            if idx.size:
                # (the last segment may have released contacts: the capacitance of those left)
                Ka = inv_spd(submatrix(W, idx), cond_limit, rcond) if idx.size < n else K
                ce = _dashpot(idx, Cn, damp_g, group, always)
                q_eq = a[idx] + submatrix(W, idx) @ (m[idx] * g[idx])
                A = _state_matrix(Ka, m[idx], ce)
                lam, V, Vi, ok = _modal(A)
                z0 = np.concatenate((q[idx] - q_eq, v[idx]))
                if ok:
                    ze = np.ascontiguousarray(_modal_at(lam, V, Vi, z0, np.array([h]))[:, 0])
                else:
                    ze = np.ascontiguousarray(_expm_states(A, z0, h, one)[:, 0])
            _advance(q, v, g, idx, ze, q_eq, free, h)
            if idx.size:
                _track(idx, Ka, (q[idx] - a[idx]).reshape(idx.size, 1), one, group, wts, ng, pk2, pk_f, dmin, dmin_u)
    force = np.zeros(n)
    seat = np.zeros(n)
    idx = np.flatnonzero(active)
    for i in idx:
        force[i] = m[i] * ((v[i] - v0[i]) / dt - g[i])
    if idx.size:
        if Ka.shape[0] != idx.size:  # released at the last event
            Ka = inv_spd(submatrix(W, idx), cond_limit, rcond) if idx.size < n else K
        sa = Ka @ (q[idx] - a[idx])
        for r in range(idx.size):
            seat[idx[r]] = sa[r]
    for i in range(n):
        if not np.isfinite(dmin[group[i]]):
            dmin_u[i] = q[i] - a[i]
    return q, v, active, force, seat, pk_f, dmin_u
