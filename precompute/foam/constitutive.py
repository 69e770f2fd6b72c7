"""The foam's energy, first Piola stress and its tangent at a batch of deformation gradients.

Written on ``C = F^T F`` (:class:`~hailstorm.precompute.foam.material.Hyperfoam`'s energy is
``tr f(C) + U(J)`` with ``f(c) = sum 2 mu_i / a_i^2 c^(a_i / 2)``), so that

    ``S = 2 f'(C) + g(J) C^-1``,  ``g(J) = J U'(J) = -sum 2 mu_i / a_i J^(-a_i b_i)``,  ``P = F S``,

and the tangent ``dP = dF S + F dS[dF^T F + F^T dF]`` is the Daleckii-Krein derivative of the
matrix function ``f'(C)`` in ``C``'s eigenbasis: the divided differences of ``c^q`` are taken in
``ln c`` (``exp((q - 1) m) q shc(q d) / shc(d)``, ``shc(x) = sinh(x) / x``), exact and smooth
through repeated eigenvalues, where the principal-stretch formulas divide by zero. Exact
(not finite-differenced): Newton converges quadratically.
"""

from __future__ import annotations

import numpy as np

from hailstorm.precompute.foam.ogden import OgdenTerms, term_energy

__all__ = ["energy_density", "first_piola", "piola_tangent"]


def _T(X: np.ndarray) -> np.ndarray:
    return np.swapaxes(X, -1, -2)


def _shc(x: np.ndarray) -> np.ndarray:
    """``sinh(x) / x`` (1 at 0)."""
    small = np.abs(x) < 1e-4
    xs = np.where(small, 1.0, x)
    return np.where(small, 1.0 + x * x / 6.0, np.sinh(xs) / xs)


def _spectral(F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues ``c`` (..., 3) and vectors ``Q`` (..., 3, 3) of ``C = F^T F``, and ``ln J``."""
    C = _T(F) @ F
    c, Q = np.linalg.eigh(C)
    with np.errstate(invalid="ignore", divide="ignore"):
        lnJ = np.log(np.linalg.det(F))
    return c, Q, lnJ


def _stress_parts(foam: OgdenTerms, c: np.ndarray, lnJ: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``2 f'(c_a)`` (..., 3), ``g(J)`` and ``J g'(J)`` (...)."""
    two_fp = np.zeros_like(c)
    g = np.zeros_like(lnJ)
    Jgp = np.zeros_like(lnJ)
    lnc = np.log(c)
    for m, a, b in zip(foam.mu, foam.alpha, foam.beta):
        two_fp += 2.0 * m / a * np.exp((0.5 * a - 1.0) * lnc)
        Jab = np.exp(-a * b * lnJ)
        g -= 2.0 * m / a * Jab
        Jgp += 2.0 * m * b * Jab
    return two_fp, g, Jgp


def energy_density(foam: OgdenTerms, F: np.ndarray) -> np.ndarray:
    """``W(F)`` [J/m^3], (...); ``inf`` where ``det F <= 0`` (a line search's barrier)."""
    c, _, lnJ = _spectral(np.asarray(F, dtype=np.float64))
    out = np.zeros_like(lnJ)
    with np.errstate(all="ignore"):
        lnl = 0.5 * np.log(np.maximum(c, 1e-300))
        for m, a, b in zip(foam.mu, foam.alpha, foam.beta):
            out += 2.0 * m / a**2 * term_energy(lnl, lnJ, a, b)
    return np.where(np.isfinite(lnJ) & np.isfinite(out), out, np.inf)


def first_piola(foam: OgdenTerms, F: np.ndarray) -> np.ndarray:
    """``P = F S`` [Pa], (..., 3, 3); needs ``det F > 0``."""
    F = np.asarray(F, dtype=np.float64)
    c, Q, lnJ = _spectral(F)
    two_fp, g, _ = _stress_parts(foam, c, lnJ)
    S = (Q * (two_fp + g[..., None] / c)[..., None, :]) @ _T(Q)
    return F @ S


def _divided(foam: OgdenTerms, c: np.ndarray) -> np.ndarray:
    """``2 (f'(c_a) - f'(c_b)) / (c_a - c_b)`` (``2 f''(c_a)`` on the diagonal), (..., 3, 3)."""
    x = np.log(c)
    mid = 0.5 * (x[..., :, None] + x[..., None, :])
    half = 0.5 * (x[..., :, None] - x[..., None, :])
    out = np.zeros(c.shape + (3,))
    for m, a in zip(foam.mu, foam.alpha):
        q = 0.5 * a - 1.0
        out += 2.0 * m / a * q * np.exp((q - 1.0) * mid) * _shc(q * half) / _shc(half)
    return out


def piola_tangent(foam: OgdenTerms, F: np.ndarray, dF: np.ndarray) -> np.ndarray:
    """``dP[dF]`` for each direction: ``F`` (..., 3, 3), ``dF`` (k, ..., 3, 3) -> (k, ..., 3, 3) [Pa]."""
    F = np.asarray(F, dtype=np.float64)
    c, Q, lnJ = _spectral(F)
    two_fp, g, Jgp = _stress_parts(foam, c, lnJ)
    S = (Q * (two_fp + g[..., None] / c)[..., None, :]) @ _T(Q)
    D = _divided(foam, c)
    inv_cc = 1.0 / (c[..., :, None] * c[..., None, :])
    out = []
    for d in np.asarray(dF, dtype=np.float64):
        dC = _T(d) @ F
        H = _T(Q) @ (dC + _T(dC)) @ Q
        tr = (np.diagonal(H, axis1=-2, axis2=-1) / c).sum(axis=-1)
        dSp = (D - g[..., None, None] * inv_cc) * H
        dSp = dSp + (0.5 * Jgp * tr)[..., None, None] * np.eye(3) / c[..., None, :]
        dS = Q @ dSp @ _T(Q)
        out.append(d @ S + F @ dS)
    return np.stack(out)
