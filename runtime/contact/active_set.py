"""The active set of a unilateral contact solve: its result, block pivoting, and the convex QP it falls back to.

A set of frictionless unilateral contacts on the capacitance's ``W`` is a linear
complementarity problem: block pivoting (:func:`unilateral_solve`, which
:meth:`hailstorm.runtime.contact.contact_capacitance.Capacitance.solve` runs) solves it in a few
rounds, and where it cycles or ``W`` is singular, :func:`nonnegative_qp` (a projected Newton
method on ``min 1/2 x^T W x + q^T x, x >= 0``) does. Each round's re-solve with some contacts
released reuses the capacitance's factor where that is cheaper (a Schur complement).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hailstorm.runtime.contact.policy import SUBSET_REUSE_FROM, SPDFactor

__all__ = ["ACTIVE_SET_TOL", "BLOCK_PIVOT_ROUNDS", "NEWTON_SHIFT", "QP_SHIFT", "ActiveSet", "ContactSetSolver",
           "nonnegative_qp", "unilateral_solve"]

#: The active set releases a contact whose normal force pulls by more than this
#: fraction of the largest, and re-activates one the seat penetrates by more
#: than this fraction of the largest normal displacement.
ACTIVE_SET_TOL: float = 1e-10


class ContactSetSolver(Protocol):
    """What the unilateral solve reads of a contact set
    (:class:`hailstorm.runtime.contact.contact_capacitance.Capacitance`; a protocol, so that this
    module does not import the class built on it)."""

    W: np.ndarray
    rigid: np.ndarray
    normals: np.ndarray
    exact: bool

    @property
    def s(self) -> int: ...
    @property
    def per_contact(self) -> int: ...
    @property
    def live_dofs(self) -> np.ndarray: ...
    def solve_live(self, c: np.ndarray) -> np.ndarray: ...
    def live_columns(self, rows: np.ndarray) -> np.ndarray: ...
    def multiplier_forces(self, lam: np.ndarray) -> np.ndarray: ...


@dataclass
class ActiveSet:
    """Result of :meth:`hailstorm.runtime.contact.contact_capacitance.Capacitance.solve`.

    Attributes
    ----------
    forces : (s, 3) float ndarray
        Forces on the seat [N] (zero at released and rigid contacts).
    active : (s,) bool ndarray
        Contacts that carry force.
    iterations : int
        Active-set iterations (1 without unilateral contact).
    multipliers : (m,) float ndarray
        The constraint multipliers (sticky: ``forces.ravel()``; frictionless:
        the signed normal forces), zero at released and rigid contacts.
    """

    forces: np.ndarray
    active: np.ndarray
    iterations: int
    multipliers: np.ndarray


#: block-pivoting rounds of a frictionless unilateral solve before :func:`nonnegative_qp` takes
#: over (it also takes over as soon as a set repeats, and at once when ``W`` is singular to
#: working precision: block pivoting's subproblems are then solved by pseudo-inverse, an
#: eigendecomposition per round, and need not converge)
BLOCK_PIVOT_ROUNDS: int = 10
#: the compliance added to every contact (relative to the mean of W's diagonal) when the
#: frictionless unilateral QP is solved on a singular ``W`` (the minimiser is then unique; the
#: set it finds is re-solved exactly)
QP_SHIFT: float = 1e-8
#: the shift of the unit-diagonal free block in :func:`nonnegative_qp`'s Newton step (so that
#: a singular ``W`` still factors by Cholesky: a positive definite scaling of the step, which
#: keeps the method convergent)
NEWTON_SHIFT: float = 1e-10


def _newton_step(A: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``-(A + mu I)^-1 g`` for a symmetric positive semidefinite ``A`` with unit diagonal, by
    Cholesky; ``mu`` is :data:`NEWTON_SHIFT`, raised a hundredfold while the factor fails."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve

    mu = NEWTON_SHIFT
    eye = np.eye(A.shape[0])
    for _ in range(8):
        try:
            return -cho_solve(cho_factor(A + mu * eye, lower=True, check_finite=False), g, check_finite=False)
        except LinAlgError:
            mu *= 100.0
    return -g  # not reached for a semidefinite A: the gradient step


def _armijo_arc(Wt: np.ndarray, q: np.ndarray, y: np.ndarray, g: np.ndarray, d: np.ndarray,
                free: np.ndarray) -> np.ndarray:
    """Bertsekas' Armijo rule along the projection arc ``max(y + a d, 0)``, ``a = 1, 1/2, ...``."""
    def value(z: np.ndarray) -> float:
        return float(0.5 * z @ (Wt @ z) + q @ z)

    q0, a = value(y), 1.0
    for _ in range(80):
        z = np.maximum(y + a * d, 0.0)
        drop = -a * float(g[free] @ d[free]) + float(g[~free] @ (y[~free] - z[~free]))
        if q0 - value(z) >= 1e-4 * drop:
            return z
        a *= 0.5
    return y  # no decrease left at rounding level


def nonnegative_qp(W: np.ndarray, q: np.ndarray, x0: np.ndarray | None = None, *, tol: float = ACTIVE_SET_TOL,
                   max_iter: int = 200) -> tuple[np.ndarray, int]:
    """Solve ``min 1/2 x^T W x + q^T x`` subject to ``x >= 0`` (the LCP ``x >= 0``,
    ``W x + q >= 0``, ``x . (W x + q) = 0``) for a symmetric positive (semi)definite ``W``.

    Bertsekas' projected Newton method (SIAM J. Control Optim. 20, 1982) on the
    diagonally scaled problem (unit diagonal): a Newton step on the free
    components, a gradient step on the ones held at the bound, the Armijo rule
    along the projection arc. Every iteration decreases the convex objective, and
    the method converges to the minimiser for any start (the cited theorem); the
    active set is identified in finitely many steps, after which a full Newton
    step is exact. No cycling, unlike block pivoting on a matrix that is not an
    M-matrix.

    Parameters
    ----------
    W : (n, n) ndarray
        Symmetric positive semidefinite with a positive diagonal.
    q : (n,) ndarray
    x0 : (n,) ndarray, optional
        Start (projected onto ``x >= 0``); default 0.
    tol : float
        Stop when ``|min(W_ii x_i, g_i)| <= tol * max(|q|, |W x|)`` for every ``i``
        (``g = W x + q``): complementarity in the units of ``q``.
    max_iter : int
        Bound on the iterations (a safeguard, not a part of the method).

    Returns
    -------
    x : (n,) ndarray
    iterations : int

    Raises
    ------
    ValueError
        ``max_iter`` below 1, or a diagonal entry of ``W`` that is not positive.
    RuntimeError
        Not converged within ``max_iter`` iterations (rounding: ``W`` singular to
        working precision).
    """
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    W = np.asarray(W, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    n = q.size
    diag = np.diag(W).copy()
    if n and not (diag > 0).all():
        raise ValueError("nonnegative_qp needs a positive diagonal of W")
    sc = 1.0 / np.sqrt(diag) if n else diag
    Wt = W * sc[:, None] * sc[None, :]
    qt = q * sc
    y = np.zeros(n) if x0 is None else np.maximum(np.asarray(x0, dtype=np.float64) / sc, 0.0)
    for it in range(1, max_iter + 1):
        g = Wt @ y + qt
        r = np.minimum(y, g)  # the natural residual (scaled: units of q * sc)
        scale = max(float(np.abs(qt).max(initial=0.0)), float(np.abs(Wt @ y).max(initial=0.0)),
                    np.finfo(float).tiny)
        if float(np.abs(r).max(initial=0.0)) <= tol * scale:
            return y * sc, it
        eps = min(float(np.abs(r).max()), float(np.abs(y).max(initial=0.0)) + scale)
        free = ~((y <= eps) & (g > 0))
        d = -g.copy()
        if free.any():
            F = np.flatnonzero(free)
            d[F] = _newton_step(Wt[np.ix_(F, F)], g[F])
        z = _armijo_arc(Wt, qt, y, g, d, free)
        if np.array_equal(z, y):  # stalled at rounding level: the gradient step alone
            z = _armijo_arc(Wt, qt, y, g, -g, np.zeros(n, bool))
            if np.array_equal(z, y):
                raise RuntimeError(f"nonnegative_qp: no progress at iteration {it} (W singular to working precision)")
        y = z
    raise RuntimeError(f"nonnegative_qp did not converge in {max_iter} iterations")


def _subset_multipliers(cap: ContactSetSolver, c: np.ndarray, act: np.ndarray) -> np.ndarray:
    """Multipliers (m,) with only the (non-rigid) contacts ``act`` constrained: ``W[a, a] x = c[a]``.

    While few live components are released (``r``), the factor of ``W[live, live]``
    serves: with ``K = W^-1`` over the live components, ``W_aa^-1 = K_aa - K_ar
    K_rr^-1 K_ra`` (the inverse of a principal block by its Schur complement), so
    ``x = y_a - K_ar K_rr^-1 y_r`` for ``y = K [c_a; 0]``: ``|r| + 1`` solves with the
    kept factor (or columns of an explicit ``K``) and an ``|r| x |r|`` factor, no
    ``O(|a|^3)`` re-factorisation. ``W_aa`` is a principal block of an SPD ``W``,
    no worse conditioned. Many released, few active (below
    :data:`~hailstorm.runtime.contact.policy.SUBSET_REUSE_FROM`), a pseudo-inverse,
    or an ill-conditioned ``K_rr``: a fresh factorisation of ``W[a, a]`` (the one
    policy, :class:`SPDFactor`).
    """
    p = cap.per_contact
    dofs = (p * np.flatnonzero(act)[:, None] + np.arange(p)).ravel()
    lam = np.zeros(cap.W.shape[0])
    if dofs.size == 0:
        return lam
    live = cap.live_dofs
    na, nl = dofs.size, live.size
    nr = nl - na
    # reuse when its solves (~2 nl^2 flops per column, 3x potrf's rate) cost less than the factor
    if cap.exact and 0 < nr and na >= SUBSET_REUSE_FROM and 6 * (nr + 1) * nl * nl + nr ** 3 < na ** 3:
        keep = np.zeros(nl, bool)
        keep[np.searchsorted(live, dofs)] = True  # act's components among the live ones
        r = np.flatnonzero(~keep)
        z = np.zeros(nl)
        z[keep] = c[dofs]
        y = cap.solve_live(z)
        Kr = cap.live_columns(r)
        Frr = SPDFactor(Kr[r], symmetric=False)
        if Frr.exact:
            x = y - Kr @ Frr.solve(y[r])
            lam[dofs] = x[keep]
            return lam
    W_aa = cap.W.take(dofs, axis=0).take(dofs, axis=1)
    lam[dofs] = SPDFactor(W_aa, symmetric=True).solve(c[dofs])
    return lam


def _unilateral_qp(cap: ContactSetSolver, c: np.ndarray, lam: np.ndarray, limit: int,
                   cn: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The frictionless unilateral solve as the convex QP :func:`nonnegative_qp` over
    the live contacts (``x = -lambda``: ``min 1/2 x^T W x + c^T x``, ``x >= 0``), from
    the block-pivoting iterate; then the set it finds re-solved exactly
    (:func:`_subset_multipliers`, as block pivoting ends) when that meets the same
    tolerances, else the QP's own multipliers. Returns ``(lam, active, iterations)``."""
    live = np.flatnonzero(~cap.rigid)
    W = cap.W[np.ix_(live, live)]
    x0 = np.maximum(-lam[live], 0.0)
    if not cap.exact and live.size:  # singular (more contacts than the seat's vertices can tell
        # apart): a contact compliance of QP_SHIFT of the mean one makes the minimiser unique; the
        # pseudo-inverse's multipliers are no useful start
        W = W + QP_SHIFT * float(np.diag(W).mean()) * np.eye(live.size)
        x0 = None
    x, iters = nonnegative_qp(W, c[live], x0, tol=ACTIVE_SET_TOL, max_iter=limit)
    active = np.zeros(cap.s, bool)
    active[live[x > 0]] = True
    exact = _subset_multipliers(cap, c, active)
    un2 = cap.W @ exact
    fscale = max(float(np.abs(exact).max(initial=0.0)), np.finfo(float).tiny)
    uscale = max(float(np.abs(cn).max(initial=0.0)), float(np.abs(un2).max(initial=0.0)), np.finfo(float).tiny)
    ok = not (active & (exact > ACTIVE_SET_TOL * fscale)).any() and \
        not (~active & ~cap.rigid & (un2 - cn > ACTIVE_SET_TOL * uscale)).any()
    if ok:
        return exact, active, iters
    lam = np.zeros(cap.s)
    lam[live] = -x
    return lam, active, iters


def unilateral_solve(cap: ContactSetSolver, ubar: np.ndarray, c: np.ndarray, lam: np.ndarray,
                     max_iter: int | None) -> tuple[np.ndarray, np.ndarray, int]:
    """The active set of unilateral contacts on a capacitance: contacts may only push.

    A contact whose force would pull (``f . n > 0``) is released and the rest
    re-solved; a released contact is re-activated if the seat would penetrate the
    prescribed position (``(u - ubar) . n > 0``). Block pivoting; frictionless, once
    a set repeats, after :data:`BLOCK_PIVOT_ROUNDS` rounds, or at once for a ``W``
    singular to working precision (then with a contact compliance of
    :data:`QP_SHIFT`), the convex QP's projected Newton method (:func:`nonnegative_qp`);
    sticky, one flip per iteration once a set repeats (a sticky contact is released
    as a whole).

    Parameters
    ----------
    cap : ContactSetSolver
        The contact set (:class:`~hailstorm.runtime.contact.contact_capacitance.Capacitance`).
        The contacts (their normals are needed).
    ubar : (s, 3) float ndarray
        Prescribed contact-point displacements [m], checked.
    c : (m,) float ndarray
        ``ubar`` as constrained components.
    lam : (m,) float ndarray
        The bilateral multipliers of ``c`` (every live contact active): the first round's.
    max_iter : int or None
        Bound on the rounds (default ``2 s + 10``).

    Returns
    -------
    lam : (m,) float ndarray
        The multipliers (not yet zeroed at released contacts).
    active : (s,) bool ndarray
        The contacts that carry force.
    iterations : int
        Rounds of block pivoting, plus the QP's iterations if it took over.

    Raises
    ------
    ValueError
        The contacts have no normals.
    RuntimeError
        The active set did not settle within ``max_iter`` rounds.
    """
    s = cap.s
    rigid = cap.rigid
    active = ~rigid
    n = cap.normals
    if s and not np.any(n, axis=1).all():
        raise ValueError("unilateral contact needs the contact normals")
    p = cap.per_contact
    cn = np.einsum("ki,ki->k", ubar, n)
    seen: set[bytes] = set()
    limit = 2 * s + 10 if max_iter is None else int(max_iter)
    single = False
    for it in range(1, limit + 1):
        if it > 1:
            lam = _subset_multipliers(cap, c, active)
        fn = np.einsum("ki,ki->k", cap.multiplier_forces(lam), n)
        wl = cap.W @ lam  # constrained components of the contact displacement
        un = np.einsum("ki,ki->k", wl.reshape(s, 3), n) if p == 3 else wl
        fscale = max(float(np.abs(fn).max(initial=0.0)), np.finfo(float).tiny)
        uscale = max(float(np.abs(cn).max(initial=0.0)), float(np.abs(un).max(initial=0.0)),
                     np.finfo(float).tiny)
        pull = active & (fn > ACTIVE_SET_TOL * fscale)
        pen = ~active & ~rigid & (un - cn > ACTIVE_SET_TOL * uscale)
        viol = np.flatnonzero(pull | pen)
        if viol.size == 0:
            break
        key = active.tobytes()
        if p == 1 and (key in seen or it >= BLOCK_PIVOT_ROUNDS or not cap.exact):
            # frictionless: the convex QP's solver, which cannot cycle, from here
            lam, active, extra = _unilateral_qp(cap, c, lam, limit, cn)
            it += extra
            break
        if key in seen:
            single = True  # block pivoting cycled: one flip per iteration
        seen.add(key)
        if single:
            viol = viol[-1:]
        active = active.copy()
        active[viol] = ~active[viol]
    else:
        raise RuntimeError(f"unilateral contact: active set did not settle in {limit} iterations")
    return lam, active, it
