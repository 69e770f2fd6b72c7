"""The active set of a unilateral contact solve: its result and the convex QP it falls back to.

A set of frictionless unilateral contacts on the capacitance's ``W`` is a linear
complementarity problem: block pivoting (in
:meth:`hailstorm.runtime.contact.contact_capacitance.Capacitance.solve`) solves it in a few
rounds, and where it cycles or ``W`` is singular, :func:`nonnegative_qp` (a projected Newton
method on ``min 1/2 x^T W x + q^T x, x >= 0``) does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ACTIVE_SET_TOL", "BLOCK_PIVOT_ROUNDS", "NEWTON_SHIFT", "QP_SHIFT", "ActiveSet", "nonnegative_qp"]

#: The active set releases a contact whose normal force pulls by more than this
#: fraction of the largest, and re-activates one the seat penetrates by more
#: than this fraction of the largest normal displacement.
ACTIVE_SET_TOL: float = 1e-10


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
