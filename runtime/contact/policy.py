"""The contact core's numerical policy: its constants, named once, and its one SPD factorisation.

Every solve of a contact compliance ``W`` (the contact API's
:class:`~hailstorm.runtime.contact.contact_capacitance.Capacitance`, its one-call
compiled point-contact solve, the storm's contact set) follows one rule:
Cholesky when ``W`` is safely positive definite, the pseudo-inverse when it is
singular or ill conditioned (coincident contacts), and a contact whose weight
lies on clamped vertices is rigid (excluded, never inverted). The thresholds of
that rule are here; set them on this module.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

__all__ = [
    "BARY_NEG_TOL",
    "BARY_SUM_TOL",
    "COND_LIMIT",
    "EMBED_BLOCKS_FROM",
    "PINV_RCOND",
    "POINT_FAST_MAX",
    "RIGID_WEIGHT",
    "SPDFactor",
    "SUBSET_REUSE_FROM",
    "is_rigid",
    "spd_inverse",
]

#: Above this (lower-bound) condition estimate of W, use the pseudo-inverse.
COND_LIMIT: float = 1e10
#: Relative eigenvalue cut-off of the pseudo-inverse.
PINV_RCOND: float = 1e-10
#: A contact is rigid (a hard wall) when the weight it puts on free (unclamped)
#: vertices is at most this: its rows and columns of W are zero.
RIGID_WEIGHT: float = 1e-12
#: Barycentric coordinates must sum to one within this and be >= -BARY_NEG_TOL.
BARY_SUM_TOL: float = 1e-6
BARY_NEG_TOL: float = 1e-9
#: Up to this many bilateral point contacts, ``solve_contacts`` takes the
#: one-call compiled solve (:func:`hailstorm.runtime.compiled.point_solve.point_contacts`);
#: above it the block kernels, which win from s = 64-80 on (measured on the default seat).
#: The one-call path is kept because at s <= 10 the general path is 4-8x slower (0.16-0.33
#: against 0.02-0.04 ms per fresh solve; ``tests/benchmarks/bench_contacts.py`` prints the
#: general path's phases beside the one-call total for s <= POINT_FAST_MAX).
POINT_FAST_MAX: int = 64
#: From this size of D_VV on, :meth:`Capacitance.add` grows it by block copies.
EMBED_BLOCKS_FROM: int = 300
#: From this many active constrained components on, an active-set re-solve with a few
#: contacts released reuses the first factor (a Schur complement) instead of a fresh
#: factorisation of ``W[a, a]``; below it the fresh factor is the cheaper (measured on the
#: default seat: 89 active components re-factorised 1.8 ms, reused 2.6 ms per solve; 267:
#: 7.0 ms re-factorised, 4.3 ms reused).
SUBSET_REUSE_FROM: int = 150


def is_rigid(fixed: np.ndarray, verts: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Contacts whose weight lies entirely on clamped vertices (at most :data:`RIGID_WEIGHT` elsewhere).

    Parameters
    ----------
    fixed : (n,) bool ndarray
        Clamped surface vertices.
    verts, w : (s, P) int / float ndarrays
        Each contact's weighted vertices and weights.

    Returns
    -------
    (s,) bool ndarray
    """
    free_w = np.where(fixed[verts], 0.0, np.abs(w)).sum(axis=1)
    return free_w <= RIGID_WEIGHT


_potrf, _potrs, _potri = sla.lapack.get_lapack_funcs(("potrf", "potrs", "potri"), dtype=np.float64)
(_trsv,) = sla.blas.get_blas_funcs(("trsv",), dtype=np.float64)


class SPDFactor:
    """Factorisation of a symmetric positive semi-definite W; never a singular solve.

    Cholesky if W is well conditioned (the condition estimate
    ``(max L_ii / min L_ii)^2`` from the diagonal of the factor is below
    :data:`COND_LIMIT`), else the rank-revealing pseudo-inverse (symmetric
    eigendecomposition, eigenvalues below :data:`PINV_RCOND` times the
    largest dropped): the minimum-norm forces, which split the force of
    coincident contacts equally and stay finite.

    The well-conditioned case costs one LAPACK ``potrf`` (on a copy of W) and
    nothing O(m^2) besides: the condition test reads the factor's diagonal, a
    non-finite W shows there too (a NaN or infinity in the upper triangle
    reaches the diagonal of its column), and :meth:`solve` of one right-hand
    side is two BLAS triangular solves (``trsv``: a third of ``potrs``'s time at
    m = 300). The eigendecomposition runs only for an ill-conditioned W.

    Parameters
    ----------
    W : (m, m) float ndarray
        Symmetric (it is symmetrised here unless ``symmetric``).
    symmetric : bool
        ``W`` is exactly symmetric already (the compiled kernels symmetrise
        it): skip the symmetrisation (which would not change it).

    Attributes
    ----------
    m : int
        Size.
    exact : bool
        True for the Cholesky factor, False for the pseudo-inverse.
    """

    def __init__(self, W: np.ndarray, *, symmetric: bool = False):
        m = W.shape[0]
        self.m = m
        self.exact = True
        self._cho: np.ndarray | None = None
        self._pinv: np.ndarray | None = None
        if m == 0:
            return
        Ws = W if symmetric else 0.5 * (W + W.T)
        # upper factor only (potrs, trsv and potri read no other entry: no clean-up pass), of
        # Ws.T, which is Ws (symmetric) and Fortran-ordered: LAPACK's copy is a plain memcpy,
        # not a transposing one
        c, info = _potrf(Ws.T, lower=0, clean=0, overwrite_a=0)
        if info == 0:
            d = np.abs(np.diagonal(c))
            dmin = d.min()
            if dmin > 0 and (d.max() / dmin) ** 2 < COND_LIMIT:  # False for a NaN: W not finite
                self._cho = c
                return
        self.exact = False
        lam, Q = np.linalg.eigh(Ws)
        keep = lam > PINV_RCOND * max(float(lam.max()), 0.0)
        Qk = Q[:, keep]
        K = (Qk / lam[keep]) @ Qk.T
        self._pinv = 0.5 * (K + K.T)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``W^-1 rhs`` (the pseudo-inverse's product if not :attr:`exact`)."""
        if self.m == 0:
            return np.zeros_like(rhs)
        if self._cho is not None:
            if rhs.ndim == 1:  # U^T U x = rhs: two triangular solves
                return _trsv(self._cho, _trsv(self._cho, rhs, trans=1), trans=0)
            x, info = _potrs(self._cho, rhs, lower=0)
            if info != 0:  # pragma: no cover - only on invalid arguments
                raise np.linalg.LinAlgError(f"LAPACK potrs failed (info={info})")
            return x
        assert self._pinv is not None
        return self._pinv @ rhs

    def inverse(self) -> np.ndarray:
        """The symmetric ``K = W^-1`` (or the pseudo-inverse), a new array."""
        if self.m == 0:
            return np.zeros((0, 0))
        if self._cho is not None:
            K, info = _potri(self._cho, lower=0)
            if info != 0:  # pragma: no cover
                raise np.linalg.LinAlgError(f"LAPACK potri failed (info={info})")
            return np.triu(K) + np.triu(K, 1).T
        assert self._pinv is not None
        return self._pinv.copy()


def spd_inverse(W: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive semi-definite matrix under the contact core's one policy.

    The Cholesky inverse when ``W`` is well conditioned (condition estimate below
    :data:`COND_LIMIT`), else the pseudo-inverse (eigenvalues below
    :data:`PINV_RCOND` times the largest dropped): :class:`SPDFactor`. For
    contacts that (nearly) coincide this is the min-norm split of their common
    force: finite and symmetric.

    Parameters
    ----------
    W : (m, m) ndarray
        A contact compliance (symmetrised here).

    Returns
    -------
    (m, m) ndarray
        Symmetric ``K``, the capacitance.
    """
    return SPDFactor(np.asarray(W, dtype=np.float64)).inverse()
